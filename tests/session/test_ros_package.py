"""The ROS 2 message package the repository ships (ros/palpation_console_msgs, issue 51): its ``.msg`` files are
what the console's bags and bus say its messages are, and rosidl reads them and builds them with what they use."""

from __future__ import annotations

import re
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

# rosidl_adapter's own parser of .msg files, the one `colcon build` runs, as mcap_ros2 carries it
from mcap_ros2._vendor.rosidl_adapter.parser import BaseType, parse_message_file, validate_field_types

from session.mcap_export import DEFINITIONS, TOPICS, schema_text

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "ros" / "palpation_console_msgs"
NAME = "palpation_console_msgs"
OURS = sorted(type_name.split("/")[1] for type_name in DEFINITIONS if type_name.startswith(f"{NAME}/"))
SCHEMA_RULE = f"\n{'=' * 80}\n"  # between a bag schema's own definition and those of the types it uses


def test_the_msg_files_are_what_the_bags_and_the_bus_say_the_messages_are():
    shipped = {path.stem: path.read_bytes() for path in (PACKAGE / "msg").iterdir()}
    # the definition a bag's schema opens with, byte for byte
    assert shipped == {name: schema_text(f"{NAME}/{name}").split(SCHEMA_RULE)[0].encode("utf-8") for name in OURS}
    # and nothing published or exported lacks its file
    assert {type_name.split("/")[1] for _, type_name in TOPICS if type_name.startswith(f"{NAME}/")} == set(OURS)


def test_rosidl_reads_every_message_and_the_package_builds_each_with_what_it_uses():
    used: set[str] = set()
    for name in OURS:
        spec = parse_message_file(NAME, str(PACKAGE / "msg" / f"{name}.msg"))
        used |= {field.type.pkg_name for field in spec.fields if not field.type.is_primitive_type()}
    assert used == {"std_msgs", "geometry_msgs"}
    standard = [BaseType(type_name) for type_name in DEFINITIONS if not type_name.startswith(f"{NAME}/")]
    for name in OURS:
        validate_field_types(parse_message_file(NAME, str(PACKAGE / "msg" / f"{name}.msg")), standard)

    cmake = (PACKAGE / "CMakeLists.txt").read_text()
    generate = re.search(r"rosidl_generate_interfaces\(\$\{PROJECT_NAME\}(.*?)\)", cmake, re.S).group(1).split()
    assert generate == [f'"msg/{name}.msg"' for name in OURS] + ["DEPENDENCIES", *sorted(used)]
    assert f"project({NAME})" in cmake
    assert all(f"find_package({package} REQUIRED)" in cmake for package in used)

    package = ET.parse(PACKAGE / "package.xml").getroot()
    assert package.get("format") == "3" and package.findtext("name") == NAME
    assert {e.text for e in package.iter("depend")} == used
    assert [e.text for e in package.iter("buildtool_depend")] == ["ament_cmake", "rosidl_default_generators"]
    assert [e.text for e in package.iter("exec_depend")] == ["rosidl_default_runtime"]
    assert package.findtext("member_of_group") == "rosidl_interface_packages"
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert (package.findtext("version"), package.findtext("license")) == (project["version"], project["license"])
