"""Suite-wide guards: headless Qt, sandboxed settings and caches, nothing left running after a test."""

import contextlib
import multiprocessing
import os
import threading
from pathlib import Path

import pytest

try:
    import fcntl
except ImportError:  # Windows: each worker computes the model itself
    fcntl = None

from app import process

# The suite starts processes as the console does: the same numpy settings, before any test module loads numpy.
process.keep_numpy_off_huge_pages()
process.limit_blas_threads()

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

# hardware.crtk.dds pins every participant the project makes to loopback; this pins any other, in the suite
# and in every process it starts (the fake arm), so nothing a test runs multicasts on the machine's network.
try:
    from hardware.crtk.dds import loopback_config
except ImportError:  # without Cyclone DDS (the crtk extra) nothing here speaks DDS
    pass
else:
    os.environ["CYCLONEDDS_URI"] = loopback_config(None)

# Tissue models are precomputed once per machine (seconds to a minute per phantom) and shared by every
# test run; spawned controller processes inherit the variable.
TEST_CACHE = Path(__file__).resolve().parents[1] / "build" / "test-cache"
os.environ["PALPATION_CACHE_DIR"] = str(TEST_CACHE)


@pytest.fixture(scope="session", autouse=True)
def _default_tissue_model():
    """Precompute the default phantom's tissue model up front, not inside some test's signal timeout. Under
    pytest-xdist each worker asks for it at once; the lock lets one compute it and the others read it from
    the cache (on a fresh clone two workers solving it side by side took 25 s each, one alone 15 s)."""
    from app.rigs import RigSpec, prepare_rig

    TEST_CACHE.mkdir(parents=True, exist_ok=True)
    with open(TEST_CACHE / "default-model.lock", "w") as lock:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)
        prepare_rig(RigSpec())


@contextlib.contextmanager
def sandboxed(base: Path):
    """The console's data and settings folders under ``base`` while inside."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PALPATION_DATA_DIR", str(base / "data"))
        patch.setenv("XDG_CONFIG_HOME", str(base / "config"))
        yield


@contextlib.contextmanager
def nothing_left_running():
    """Fails, and stops what was left, if a process or a thread started inside is still running at the end."""
    threads_before = {t.ident for t in threading.enumerate()}
    yield
    children = multiprocessing.active_children()
    for child in children:
        child.kill()
        child.join(5)
    assert not children, f"left processes running: {children}"
    leftover = [t for t in threading.enumerate() if t.ident not in threads_before and t.is_alive()
                and not t.daemon]
    assert not leftover, f"left threads running: {leftover}"


@pytest.fixture(autouse=True)
def _sandbox(tmp_path_factory):
    with sandboxed(tmp_path_factory.mktemp("sandbox")):
        yield


@pytest.fixture(autouse=True)
def _nothing_left_running():
    with nothing_left_running():
        yield


@pytest.fixture
def bus():
    """An emulated USB bus: the tactile array, a SpaceMouse, a keyboard and a SpaceMouse the user may not open."""
    from hardware.usb.emulator import EmulatedBackend, EmulatedDevice, InterfaceSpec, SpaceMouseDevice, UsbTactileDevice

    keyboard = EmulatedDevice(0x046D, 0xC31C, [InterfaceSpec(0, 3)], manufacturer="Logitech", product="Keyboard")
    locked = EmulatedDevice(0x256F, 0xC635, [InterfaceSpec(0, 3)], manufacturer="3Dconnexion", product="SpaceMouse")
    locked.access_denied = True
    return EmulatedBackend(UsbTactileDevice(), SpaceMouseDevice(product_id=0xC62E), keyboard, locked)
