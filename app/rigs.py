"""Which hardware to build, as a small picklable description, and the one function that builds it.

The controller process receives a :class:`RigSpec` (not a built rig: devices hold OS handles that do
not cross a process boundary) and calls :func:`build_rig` on its own side. What the composition root needs
to know of a simulated rig before it runs (its autopilot plan) is taken from its phantom here too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from control.autopilot import AutopilotError, AutopilotPlan, plan_from_surface
from control.config import ControlConfig
from hardware.array_calibration import ArrayCalibration, ArrayCalibrationError, CalibratedSensor
from hardware.interfaces import TactileConstraints
from hardware.rig import Rig
from hardware.settings import ConfigError
from session.array_calibration import describe_array

Progress = Callable[[float, str], None]  # (fraction done, what is being done)

# Who moves the simulated rig's master side: the scripted operator of Section IV-A (``palpation-console
# simulate``, demos), or nobody, so X_d comes from the console's jog and autopilot (the interactive console).
SIM_MASTERS = ("scripted", "none")


@dataclass(frozen=True)
class RigSpec:
    backend: str = "sim"
    phantom: str = "flat"  # simulated rigs: a phantom name from tissue/phantoms or a path to a TOML file
    sim: dict[str, Any] = field(default_factory=dict)  # simulated rigs: SimSettings overrides
    seed: int = 0
    master: str = "scripted"  # simulated rigs: one of SIM_MASTERS
    hardware: dict[str, Any] = field(default_factory=dict)  # real rigs: the config's [hardware] table
    calibration: str = ""  # the tactile array's calibration file (hardware/array_calibration.py), if any

    def __post_init__(self):
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2**63:
            raise ConfigError("rig.seed", f"must be a whole number from 0 to 2**63 - 1, got {self.seed!r}")
        if self.master not in SIM_MASTERS:
            raise ConfigError("rig.master", f"unknown master {self.master!r} (known: {', '.join(SIM_MASTERS)})")


def _build_sim(spec: RigSpec, progress: Progress | None = None) -> Rig:
    # Imported here so a process driving real hardware never loads the simulator.
    from hardware.sim.rig import build_sim_rig

    rig = build_sim_rig(spec.phantom, settings=dict(spec.sim), seed=spec.seed, progress=progress)
    if spec.master == "none":
        rig.master = None
    rig.description["master"] = spec.master
    return rig


def _build_udp(spec: RigSpec, progress: Progress | None = None) -> Rig:
    # Opening the devices is the slow part and happens later, in the controller process: nothing to report.
    from hardware.udp.rig import build_rig as build_hardware_rig

    return build_hardware_rig(spec)


def _crtk_rig():
    """hardware.crtk.rig, or a ConfigError saying how to get what it needs (Cyclone DDS is an extra)."""
    try:
        from hardware.crtk import rig
    except ModuleNotFoundError as err:
        if not (err.name or "").startswith("cyclonedds"):
            raise
        raise ConfigError("rig.backend", "the CRTK backend speaks DDS through Cyclone DDS, which is not installed: "
                                         "pip install 'palpation-console[crtk]'") from None
    return rig


def arm_with_sim_array(spec: RigSpec) -> bool:
    """The CRTK rig whose tactile array is the simulated one on the arm (``[hardware.sensor] kind = "sim"``)."""
    sensor = spec.hardware.get("sensor") if isinstance(spec.hardware, dict) else None
    return spec.backend == "crtk" and isinstance(sensor, dict) and sensor.get("kind") == "sim"


def _build_crtk(spec: RigSpec, progress: Progress | None = None) -> Rig:
    # The arm is enabled and homed when the rig opens, in the controller process: nothing to report here.
    def sim_array(arm):
        from app.crtk_sim import sim_array  # only this rig loads the simulator

        return sim_array(spec.phantom, spec.sim, spec.seed, arm)

    rig = _crtk_rig().build_rig(spec, sim_array=sim_array)
    if arm_with_sim_array(spec):
        from tissue.phantom import load_phantom

        rig.ground_truth = load_phantom(spec.phantom).ground_truth()
    return rig


def bus_publisher(spec: RigSpec):
    """The :class:`app.ros_bus.BusPublisher` of a CRTK rig that publishes (``[hardware.bus] publish``), or None."""
    if spec.backend != "crtk":
        return None
    settings = _crtk_rig().CrtkHardwareSettings.from_mapping(spec.hardware, "hardware.")
    if not settings.bus.publish:
        return None
    from app.ros_bus import BusPublisher

    return BusPublisher(settings.slave.domain)


BACKENDS: dict[str, Callable[..., Rig]] = {"sim": _build_sim, "udp": _build_udp,  # (spec, progress=None) -> Rig
                                           "crtk": _build_crtk}


def check_hardware(backend: str, table: dict[str, Any], prefix: str = "hardware.") -> None:
    """ConfigError naming the key when ``table`` (the config's [hardware]) is not one ``backend`` could build from;
    a rig other than the CRTK one is checked against the UDP rig's tables, so a typo there is found whichever
    backend runs."""
    if backend == "crtk":
        _crtk_rig().CrtkHardwareSettings.from_mapping(table, prefix)
    else:
        from hardware.udp.rig import HardwareSettings

        HardwareSettings.from_mapping(table, prefix)


def prepare_rig(spec: RigSpec, progress: Progress | None = None) -> None:
    """Do a rig's slow one-off work before the controller process starts, so that process starts in
    milliseconds: for the simulated rig, precompute (or load from the disk cache) the tissue model."""
    if spec.backend == "sim" or arm_with_sim_array(spec):
        from hardware.sim.rig import build_tissue

        build_tissue(spec.phantom, dict(spec.sim), progress)


def build_rig(spec: RigSpec, progress: Progress | None = None) -> Rig:
    """Build (but do not open) the rig ``spec`` describes; ``progress`` hears about slow one-off work."""
    builder = BACKENDS.get(spec.backend)
    if builder is None:
        raise ConfigError("rig.backend", f"unknown backend {spec.backend!r} (known: {', '.join(sorted(BACKENDS))})")
    rig = builder(spec, progress=progress)
    if spec.calibration:
        calibration = load_calibration(spec.calibration)
        array = describe_array(rig.description)
        # a simulated array is known exactly by its seed and model: another's pattern would add its 7 % to
        # this one's instead of taking it out (a real array's description names a port, not the array)
        if spec.backend == "sim" and calibration.array.startswith("simulated") and calibration.array != array:
            raise ConfigError("rig.calibration", f"{spec.calibration} was made for the {calibration.array}, this "
                                                 f"rig has the {array}: calibrate this one (palpation-console "
                                                 f"calibrate) or leave the calibration out")
        rig.sensor = CalibratedSensor(rig.sensor, calibration)
        rig.description["calibration"] = {"file": spec.calibration, "summary": calibration.summary()}
    return rig


def load_calibration(path: str) -> ArrayCalibration:
    """The calibration file ``[rig] calibration`` names, or a ConfigError saying why it cannot serve."""
    try:
        return ArrayCalibration.load(path)
    except ArrayCalibrationError as err:
        raise ConfigError("rig.calibration", str(err)) from None


def plan_for_rig(spec: RigSpec, config: ControlConfig,
                 sensor: TactileConstraints | None = None) -> AutopilotPlan | None:
    """The autopilot's plan for a simulated tissue's phantom (the simulated rig's, or the simulated array's on a
    CRTK arm), with the simulated operator's clearance and travel height; None for other rigs (no phantom file
    to take the areas from)."""
    if spec.backend != "sim" and not arm_with_sim_array(spec):
        return None
    from hardware.sim.settings import SimSettings
    from tissue.phantom import load_phantom

    operator = SimSettings.from_mapping(dict(spec.sim)).operator
    try:
        return plan_from_surface(load_phantom(spec.phantom), sensor or TactileConstraints(),
                                 clearance_m=operator.clearance_m, travel_z_m=operator.travel_height_m,
                                 jog_speed_m_s=config.master.jog_speed_m_s)
    except AutopilotError as err:
        raise ConfigError("sim.operator.travel_height_m", str(err)) from None
