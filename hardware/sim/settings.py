"""Settings of the simulated rig, validated on construction.

``SimSettings.from_mapping`` takes the ``[sim]`` table of a config file (sections ``sensor``, ``robot``,
``operator`` and the world's integration keys) and refuses unknown keys and bad values with
:class:`control.config.ConfigError`, whose message names the full key (``sim.sensor.noise_std_pa``), so
the console reports simulator settings exactly like control settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from hardware.settings import ConfigError, Settings, bounded, non_negative, positive, vec3
from tissue.face import COVER_SPREAD_M, MAX_COVER_SPREAD_M
from tissue.mechanics.model import MAX_TILT_RAD, RIG_FINITE_STRAIN

Vec3 = tuple[float, float, float]


TISSUE_MODELS = ("continuum", "winkler")

# The simulated array's presets. "ideal": white noise, a 3 % gain spread, creep and hysteresis, and nothing
# else. "realistic": the errors measured on a real capacitive array pressing silicone (the public CySkin
# robotic-palpation recordings, 16-bit, 20 Hz: Scimeca et al., Autonomous Robots 2020), which act like an
# offset of the indentation rather than noise: pressing the same spot again moved the reading 3-11 % of full
# scale at 2-5 mm, about 0.4 mm of indentation (split here, our assumption, between the face and its
# elements); the first press after a pause read high by the equivalent of 0.6-0.8 mm (the 10 s recovery is
# our assumption); element gains spread 6-8 % as a fixed pattern; rest offsets moved about 2 % of full scale
# between days.
SENSOR_MODELS: dict[str, dict] = {
    "ideal": {},
    "realistic": {"gain_spread": 0.07, "press_offset_m": 0.3e-3, "press_offset_element_m": 0.25e-3,
                  "first_press_m": 0.7e-3, "first_press_recovery_s": 10.0, "session_offset_fraction": 0.02},
}


@dataclass(frozen=True)
class SensorSimSettings(Settings):
    """The capacitive tactile array and its electronics.

    ``seed`` fixes the sensor as manufactured (per-element gains and zero offsets: the same physical
    array in every run); the noise of a run comes from the rig's seed. Where each default comes from, and
    which are our assumptions: docs/phantoms.md, section 2, assumption 12.
    """

    full_scale_pa: float = 100e3  # the ADC saturates here (above the element's zero offset)
    frame_rate_hz: float = 100.0
    latency_s: float = 0.010  # from the sampling instant to the frame being readable by the host
    noise_std_pa: float = 50.0  # white, per element and frame
    quantisation_pa: float = 100e3 / 4096  # a 12-bit converter over full scale; 0 = none
    gain_spread: float = 0.03  # relative standard deviation of the per-element sensitivity
    zero_offset_pa: float = 1000.0  # mean unloaded reading before tare (capacitive baseline)
    zero_offset_spread_pa: float = 200.0  # its standard deviation across elements
    creep_fraction: float = 0.03  # final relative rise of the reading under a constant load
    creep_time_constant_s: float = 2.0
    # The widest gap between the reading on unloading and on loading over a cycle from zero to full scale and
    # back, as a fraction of full scale (how datasheets state it). No datasheet of the paper's array that we
    # could reach gives it; a review of tactile sensing for minimally invasive surgery rates capacitive
    # sensors' hysteresis "high" beside optical and piezoelectric ones (Frontiers in Robotics and AI
    # 8:705662, 2022, Table 2), so the default is a pessimistic 5 %, not zero.
    hysteresis_fraction: float = 0.05
    cover_spread_m: float = COVER_SPREAD_M  # the elastomer cover spreads load sideways by about its thickness
    # The cover the array is specified with, which its sessions record and the analysis uses: a real array's
    # cover is what it is, and the analysis knows only what its maker states (the study's realistic world
    # makes it thicker than stated)
    stated_cover_spread_m: float = COVER_SPREAD_M
    # What a real array does besides white noise (docs/phantoms.md, section 2): none of it by default ("ideal"),
    # the measured figures with ``model = "realistic"`` (SENSOR_MODELS). Each press of an element reads as if
    # the face stood deeper by an offset drawn for that press, common to the face and the element's own
    # (standard deviations), and a press after a rest reads deeper still, fully after a long rest.
    press_offset_m: float = 0.0
    press_offset_element_m: float = 0.0
    first_press_m: float = 0.0
    first_press_recovery_s: float = 10.0
    # how far each element's rest reading has moved since the array was made, drawn for each session (uniform
    # within this share of full scale either way): the tare takes it out, a calibration from another day not
    session_offset_fraction: float = 0.0
    model: str = "ideal"  # the preset the other keys started from (SENSOR_MODELS)
    seed: int = 0

    @classmethod
    def from_mapping(cls, data, prefix: str = ""):
        """A ``model`` key starts from that preset (SENSOR_MODELS); the table's other keys override it."""
        if isinstance(data, dict) and "model" in data:
            preset = SENSOR_MODELS.get(data["model"]) if isinstance(data["model"], str) else None
            if preset is None:
                raise ConfigError(f"{prefix}model", f"must be one of {', '.join(SENSOR_MODELS)}, got {data['model']!r}")
            data = {**preset, **data}
        return super().from_mapping(data, prefix)

    def __post_init__(self):
        for name in ("full_scale_pa", "frame_rate_hz", "creep_time_constant_s"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        for name in ("latency_s", "noise_std_pa", "quantisation_pa", "gain_spread", "zero_offset_pa",
                     "zero_offset_spread_pa", "creep_fraction", "hysteresis_fraction", "cover_spread_m",
                     "stated_cover_spread_m", "press_offset_m", "press_offset_element_m", "first_press_m",
                     "session_offset_fraction"):
            object.__setattr__(self, name, non_negative(name, getattr(self, name)))
        object.__setattr__(self, "first_press_recovery_s", positive("first_press_recovery_s",
                                                                    self.first_press_recovery_s))
        for name in ("press_offset_m", "press_offset_element_m", "first_press_m"):
            bounded(name, getattr(self, name), hi=3e-3,
                    why="an offset that large is a loose array, not a reading error")
        bounded("first_press_recovery_s", self.first_press_recovery_s, hi=3600.0, why="an hour's rest is a long one")
        bounded("session_offset_fraction", self.session_offset_fraction, hi=0.2, why="a tare refuses more")
        if self.model not in SENSOR_MODELS:
            raise ConfigError("model", f"must be one of {', '.join(SENSOR_MODELS)}, got {self.model!r}")
        bounded("frame_rate_hz", self.frame_rate_hz, hi=1000.0, why="no faster than the 1 kHz loop")
        bounded("latency_s", self.latency_s, hi=0.5, why="a slower sensor cannot be used for force control")
        bounded("gain_spread", self.gain_spread, hi=0.3, why="beyond that the array is broken, not spread")
        bounded("creep_fraction", self.creep_fraction, hi=0.5, why="capacitive arrays creep by a few %")
        bounded("hysteresis_fraction", self.hysteresis_fraction, hi=0.25,
                why="beyond that the reading is not a pressure")
        for name in ("cover_spread_m", "stated_cover_spread_m"):
            bounded(name, getattr(self, name), hi=MAX_COVER_SPREAD_M,
                    why="a cover thicker than an element blurs beyond it")
        bounded("quantisation_pa", self.quantisation_pa, hi=self.full_scale_pa / 16,
                why="at least 4 bits over full scale")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError("seed", f"must be a non-negative integer, got {self.seed!r}")


@dataclass(frozen=True)
class RobotSimSettings(Settings):
    """The slave robot as its inner Cartesian position loop presents it.

    The loop is a cascade (position P feeding a velocity loop) with natural frequency ``bandwidth_hz``
    and damping ratio ``damping_ratio`` for small motions; larger ones are shaped by the speed and
    acceleration limits. The reference is clamped into the workspace (the controller's soft limits).
    """

    bandwidth_hz: float = 20.0
    damping_ratio: float = 0.7
    max_speed_m_s: float = 0.25
    max_accel_m_s2: float = 5.0
    rate_hz: float = 1000.0  # joint-encoder readings per second
    home_m: Vec3 = (0.036, 0.015, 0.060)
    workspace_min_m: Vec3 = (-0.05, -0.05, 0.0)
    workspace_max_m: Vec3 = (0.15, 0.10, 0.12)

    def __post_init__(self):
        for name in ("bandwidth_hz", "damping_ratio", "max_speed_m_s", "max_accel_m_s2", "rate_hz"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        bounded("damping_ratio", self.damping_ratio, hi=2.0, why="an inner loop is not tuned that sluggish")
        # (1e300 Hz was accepted, and the integration raised a traceback)
        bounded("bandwidth_hz", self.bandwidth_hz, 0.5, 200.0, "a robot arm's Cartesian position loop")
        bounded("max_speed_m_s", self.max_speed_m_s, hi=2.0, why="a palpation robot near tissue")
        bounded("max_accel_m_s2", self.max_accel_m_s2, hi=100.0, why="a robot arm's, not a shaker's")
        bounded("rate_hz", self.rate_hz, hi=10e3, why="encoder readings are polled by a 1 kHz loop")
        lo = vec3("workspace_min_m", self.workspace_min_m)
        hi = vec3("workspace_max_m", self.workspace_max_m)
        home = vec3("home_m", self.home_m)
        for i, axis in enumerate("xyz"):
            if hi[i] <= lo[i]:
                raise ConfigError("workspace_max_m",
                                  f"{axis} upper bound {hi[i]:g} m must exceed lower bound {lo[i]:g} m")
            if not lo[i] <= home[i] <= hi[i]:
                raise ConfigError("home_m",
                                  f"{axis} = {home[i]:g} m lies outside the workspace [{lo[i]:g}, {hi[i]:g}] m")
        object.__setattr__(self, "workspace_min_m", lo)
        object.__setattr__(self, "workspace_max_m", hi)
        object.__setattr__(self, "home_m", home)


@dataclass(frozen=True)
class OperatorSimSettings(Settings):
    """The scripted operator of Section IV-A: heights are above the table, speeds are peak speeds."""

    # above the highest surface point under the TSI before switching S_z off: within the blind seek's depth
    # (control.safety.blind_seek_depth_m, 2.4 mm at the default ceiling and stiffest tissue), less room for a
    # surface higher than the phantom's nominal one
    clearance_m: float = 0.0015
    travel_height_m: float = 0.045  # for moves between areas
    lateral_speed_m_s: float = 0.02
    vertical_speed_m_s: float = 0.015
    dwell_above_s: float = 0.3  # steadying above the area before switching S_z off
    dwell_after_s: float = 0.2  # noticing the "region done" flag before switching S_z back on
    region_timeout_s: float = 120.0  # gives up on an area the loop never finishes
    rate_hz: float = 1000.0

    def __post_init__(self):
        for name in ("clearance_m", "travel_height_m", "lateral_speed_m_s", "vertical_speed_m_s",
                     "region_timeout_s", "rate_hz"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        for name in ("dwell_above_s", "dwell_after_s"):
            object.__setattr__(self, name, non_negative(name, getattr(self, name)))
        bounded("rate_hz", self.rate_hz, hi=10e3, why="positions are polled by a 1 kHz loop")


@dataclass(frozen=True)
class SimSettings(Settings):
    """Everything the simulated rig is built from, plus how its shared world is integrated."""

    sensor: SensorSimSettings = field(default_factory=SensorSimSettings)
    robot: RobotSimSettings = field(default_factory=RobotSimSettings)
    operator: OperatorSimSettings = field(default_factory=OperatorSimSettings)
    substep_s: float = 1e-3  # the world's time grid (the robot sub-steps within it when its limits act)
    max_catchup_s: float = 0.1  # longest host stall integrated step by step; the rest is skipped
    tissue: str = "continuum"  # continuum (finite elements, tissue/mechanics) | winkler (spring baseline)
    finite_strain: bool = RIG_FINITE_STRAIN  # continuum: the reduced finite-strain model (tissue/mechanics/model.py)
    # continuum: the probe's face tilted about y and x, in degrees (a face that rises along x, along y); the
    # analysis assumes a level face, so this is one of the realistic world's conditions it does not know
    probe_tilt_deg: tuple[float, float] = (0.0, 0.0)

    _nested: ClassVar[dict[str, type[Settings]]] = {
        "sensor": SensorSimSettings,
        "robot": RobotSimSettings,
        "operator": OperatorSimSettings,
    }

    def __post_init__(self):
        for name, kind in self._nested.items():
            if not isinstance(getattr(self, name), kind):
                raise ConfigError(name, f"must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")
        substep = positive("substep_s", self.substep_s)
        # 1e-300 s never got through a second of the world
        bounded("substep_s", substep, 1e-5, 1e-3, "the world is integrated at 1 to 100 kHz")
        if self.tissue not in TISSUE_MODELS:
            raise ConfigError("tissue", f"unknown tissue model {self.tissue!r} (known: {', '.join(TISSUE_MODELS)})")
        if not isinstance(self.finite_strain, bool):
            raise ConfigError("finite_strain", f"must be true or false, got {self.finite_strain!r}")
        catchup = positive("max_catchup_s", self.max_catchup_s)
        if catchup < substep:
            raise ConfigError("max_catchup_s", f"must be at least one substep ({substep:g} s)")
        tilt = self.probe_tilt_deg
        if (not isinstance(tilt, (list, tuple)) or len(tilt) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in tilt)):
            raise ConfigError("probe_tilt_deg", f"must be two numbers of degrees, got {tilt!r}")
        for value in tilt:
            bounded("probe_tilt_deg", value, -math.degrees(MAX_TILT_RAD), math.degrees(MAX_TILT_RAD),
                    why="a face tilted further no longer presses with its whole area")
        object.__setattr__(self, "probe_tilt_deg", (float(tilt[0]), float(tilt[1])))
        object.__setattr__(self, "substep_s", substep)
        object.__setattr__(self, "max_catchup_s", catchup)
