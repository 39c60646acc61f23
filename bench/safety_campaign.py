"""The fault campaign: seeded, randomized runs of the real loop off the happy path, checked against the truth.

Each run draws, from its own seed, a plant, a configuration the validation accepts and a schedule of
trouble, then runs the 1 kHz loop through it and checks on every tick what must hold whatever happens:

* the true force (what the tissue pushes back with, not what the sensor says) stays below the force
  ceiling plus a stated margin: the force the tissue adds while the probe travels at the velocity limit
  for as long as a frame may be overdue before the loop stops descending (three frame periods,
  control/loop.py), plus 0.5 N;
* the true indentation stays below the indentation ceiling plus the indentation the run started with
  plus the same travel and 0.5 mm;
* no reference leaves the loop farther than ``v_max * max(dt, period)`` (+1 um rounding) from the last
  one sent, and none is non-finite;
* after a stop-where-it-is fault the robot comes to rest within its braking plan (the simulated robot
  brakes at 0.6 of its acceleration limit) plus 0.1 mm.

Two kinds of run:

* ``plant``: the loop on the exact layer plant (:mod:`hardware.sim.plant`), stiff (200 kPa) or soft (15 kPa),
  starting above or already in the tissue, a master whose position jumps by up to 50 mm, random S_z
  toggles, ramps and impedance gains, tare attempts, e-stops and clears, a sensor that goes silent or
  sends NaN, huge, negative or saturated frames, and a robot that goes silent.
* ``rig``: the fast-forward simulated rig (robot dynamics, finite-element tissue, the sensor's noise and
  creep), driven by jogs, S_z toggles, tare attempts, e-stops and a sensor unplugged for a while.

Beside the runs, :func:`fuzz` feeds every reader of outside input mutated copies of good input (flipped,
inserted and deleted bytes, truncations, numbers swapped for absurd ones): UDP packets, the serial frame
stream, phantom and configuration files, and a recorded session. A crash is any exception other than the
reader's own one-line error type.

``python -m bench.safety_campaign`` runs a campaign; the bench (``make bench``) writes
``build/bench/safety.json``; a short campaign runs in ``make test``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.fastforward import FastForward
from hardware.sim.plant import ELEMENT_AREA_M2, LayerPlant
from control.config import ControlConfig, ImpedanceGains, RampSettings
from control.loop import OVERDUE_FRAME_PERIODS, ControlLoop
from control.messages import ClearFault, EStop, FaultRaised, Jog, Notice, SetGains, SetRamp, SetSz, Tare
from control.safety import RETRACT_FAULTS
from hardware.interfaces import MasterState, TactileConstraints, TactileFrame
from hardware.settings import ConfigError
from hardware.sim.rig import build_sim_rig

BRAKE_FRACTION = 0.6  # the simulated robot's braking plan (hardware/sim/world.py)
STOP_MARGIN_M = 0.1e-3
FORCE_MARGIN_N = 0.5
STEP_TOLERANCE_M = 1e-6
STIFF_PA, SOFT_PA = 200e3, 15e3


@dataclass
class RunResult:
    kind: str
    seed: int
    ticks: int = 0
    violations: list[str] = field(default_factory=list)
    faults: int = 0
    stops: int = 0
    stop_distance_max_mm: float = 0.0  # how far the robot went after a stop was ordered
    stop_beyond_plan_max_mm: float = -math.inf  # that distance less the braking plan (negative: inside it)
    max_force_over_ceiling_N: float = -math.inf
    gains_refused: int = 0


class _Checker:
    """The invariants, tick by tick."""

    def __init__(self, result: RunResult, config: ControlConfig):
        self.r = result
        self.config = config
        self.sent = None

    def reference(self, step_result, dt: float) -> None:
        if step_result.hold:
            self.sent = None
            return
        x = step_result.position_ref_m
        if not all(math.isfinite(v) for v in x):
            self.violate(f"a non-finite reference was sent: {x}")
            return
        if self.sent is not None:
            allowed = self.config.safety.velocity_limit_m_s * max(dt, self.config.period_s) + STEP_TOLERANCE_M
            step = math.dist(x, self.sent)
            if step > allowed:
                self.violate(f"a reference stepped {step * 1e3:.3f} mm (allowed {allowed * 1e3:.3f} mm)")
        self.sent = x

    def force(self, true_N: float, margin_N: float) -> None:
        ceiling = self.config.safety.force_ceiling_N
        self.r.max_force_over_ceiling_N = max(self.r.max_force_over_ceiling_N, true_N - ceiling)
        if true_N > ceiling + margin_N:
            self.violate(f"true force {true_N:.2f} N above the {ceiling:g} N ceiling + {margin_N:.2f} N")

    def indentation(self, true_m: float, allowed_m: float) -> None:
        if true_m > allowed_m:
            self.violate(f"true indentation {true_m * 1e3:.2f} mm above {allowed_m * 1e3:.2f} mm")

    def violate(self, what: str) -> None:
        if len(self.r.violations) < 5:
            self.r.violations.append(f"{self.r.kind} seed {self.r.seed}, tick {self.r.ticks}: {what}")


def random_config(rng: np.random.Generator, result: RunResult) -> ControlConfig:
    """A configuration the validation accepts: gains, ramp and ceilings drawn wide, refused ones redrawn."""
    while True:
        gains = _draw_gains(rng)
        ceiling = float(rng.uniform(4.0, 20.0))
        f_max = float(rng.uniform(1.5, ceiling))
        table = {"gains": gains,
                 "ramp": {"force_min_N": 1.0, "force_max_N": f_max, "force_step_N": float(rng.uniform(0.5, 3.0)),
                          "min_settle_s": 0.2, "settle_window_s": 0.1, "level_timeout_s": 1.0},
                 "safety": {"force_ceiling_N": ceiling,
                            "indentation_ceiling_m": float(rng.uniform(0.004, 0.02)),
                            "velocity_limit_m_s": float(rng.uniform(0.03, 0.2))},
                 "contact": {"retract_speed_m_s": 0.02}}
        if table["ramp"]["force_step_N"] > f_max - 1.0:
            table["ramp"]["force_step_N"] = max(f_max - 1.0, 0.1)
        try:
            return ControlConfig.from_mapping(table)
        except ConfigError:
            result.gains_refused += 1


def _draw_gains(rng: np.random.Generator) -> dict:
    """M, B and K per axis, log-uniform over ranges wider than any lab would use."""
    def draw(lo: float, hi: float) -> list[float]:
        return [float(v) for v in np.exp(rng.uniform(math.log(lo), math.log(hi), 3))]

    return {"mass_kg": draw(0.02, 5.0), "damping_N_s_m": draw(2.0, 3000.0), "stiffness_N_m": draw(10.0, 5000.0)}


def _random_gains(rng: np.random.Generator) -> ImpedanceGains | None:
    try:
        return ImpedanceGains.from_mapping(_draw_gains(rng))
    except ConfigError:
        return None


def plant_run(seed: int, seconds: float = 2.0) -> RunResult:
    rng = np.random.default_rng(seed)
    stiff = bool(rng.integers(2))
    result = RunResult("plant-stiff" if stiff else "plant-soft", seed)
    config = random_config(rng, result)
    surface = 0.025
    start_depth = float(rng.uniform(-0.008, 0.003))  # < 0: above the surface
    plant = LayerPlant(surface_m=surface, modulus_pa=STIFF_PA if stiff else SOFT_PA,
                       start_m=(0.03, 0.015, surface - start_depth), noise_pa=float(rng.uniform(0.0, 100.0)),
                       full_scale_pa=100e3)
    plant.rng = np.random.default_rng(seed + 1)
    loop = ControlLoop(config, TactileConstraints(), has_master=True)
    check = _Checker(result, config)
    k_layer = float(plant.modulus.sum()) * ELEMENT_AREA_M2 / surface
    lag_s = OVERDUE_FRAME_PERIODS * plant.frame_period_s
    v_lim = config.safety.velocity_limit_m_s
    force_margin = FORCE_MARGIN_N + k_layer * v_lim * lag_s
    allowed_depth = config.safety.indentation_ceiling_m + max(start_depth, 0.0) + v_lim * lag_s + 0.5e-3

    master = list(plant.x)
    switch = True
    n = int(seconds * config.rate_hz)
    period = config.period_s
    # the trouble, as (tick, what) drawn up front so a run is its seed
    trouble = sorted((int(rng.integers(1, n)), int(rng.integers(13))) for _ in range(int(rng.integers(4, 16))))
    sensor_silent_until = slave_silent_until = -1
    push_until, push_m_s = -1, 0.0
    corrupt_until, corruption = -1, 0
    for k in range(n):
        now = k * period
        commands = []
        while trouble and trouble[0][0] == k:
            what = trouble.pop(0)[1]
            if what == 0:
                switch = not switch
            elif what == 1:
                jump = rng.uniform(-0.05, 0.05, 3)
                master = [master[i] + float(jump[i]) for i in range(3)]
            elif what == 2:
                commands.append(Tare())
            elif what == 3:
                commands.append(EStop("campaign"))
                result.stops += 1
            elif what == 4:
                commands.append(ClearFault())
            elif what == 5:
                sensor_silent_until = k + int(rng.integers(20, 300))
            elif what == 6:
                slave_silent_until = k + int(rng.integers(5, 100))
            elif what in (7, 8):
                corrupt_until, corruption = k + int(rng.integers(10, 60)), int(rng.integers(4))
            elif what == 9:
                gains = _random_gains(rng)
                if gains is not None:
                    commands.append(SetGains(gains))
            elif what == 10:
                commands.append(SetRamp(RampSettings(force_min_N=1.0, force_max_N=config.ramp.force_max_N,
                                                     force_step_N=config.ramp.force_step_N, min_settle_s=0.2,
                                                     settle_window_s=0.1, level_timeout_s=1.0)))
            elif what == 11:
                commands.append(SetSz(position_control=bool(rng.integers(2))))
            else:  # the operator pushes the master down, steadily, within the velocity limit
                push_until, push_m_s = k + int(rng.integers(200, 2000)), float(rng.uniform(0.005, v_lim))
        if k < push_until:
            master[2] -= push_m_s * period
        plant.sensor_alive = k >= sensor_silent_until
        plant.slave_alive = k >= slave_silent_until
        plant.poll(now)
        frame = plant.frame
        if frame is not None and k < corrupt_until and plant.sensor_alive:
            frame = _corrupt(frame, corruption)
        m = MasterState(k, now, tuple(master), switch)
        step = loop.step(now, frame, plant.slave(now), m, commands)
        result.faults += sum(1 for e in step.events if isinstance(e, FaultRaised))
        check.reference(step, period)
        plant.apply(step)
        check.force(plant.true_force_N(), force_margin)
        check.indentation(surface - plant.x[2], allowed_depth)
        result.ticks += 1
    return result


def _corrupt(frame: TactileFrame, how: int) -> TactileFrame:
    """An implausible frame: NaN, a huge reading, a huge negative one, or a saturated array."""
    p = frame.pressure_pa.copy()
    saturated = None
    if how == 0:
        p[1, 3] = np.nan
    elif how == 1:
        p[:] = 1e9
    elif how == 2:
        p[:] = -1e6
    else:
        saturated = np.ones(p.shape, bool)
        p[:] = 100e3
    return TactileFrame(frame.seq, frame.t_s, p, saturated)


def rig_run(seed: int, phantom: str, sim: dict, tissue, seconds: float = 3.0) -> RunResult:
    """The fast-forward simulated rig, driven by jogs, S_z toggles, tare attempts, e-stops and an unplug."""
    rng = np.random.default_rng(seed)
    result = RunResult("rig", seed)
    config = random_config(rng, result)
    # the jog may go as fast as the limit allows, so a stop has something to brake; half the runs keep the
    # default gains, with which the robot follows the jog briskly (drawn gains may follow it very slowly)
    config = config.replace(master=config.master.replace(jog_speed_m_s=config.safety.velocity_limit_m_s))
    if rng.integers(2):
        config = config.replace(gains=ControlConfig().gains)
    rig = build_sim_rig(phantom, settings=dict(sim), tissue=tissue, seed=seed)
    rig.master = None  # X_d from the jog: the campaign is the operator
    robot = rig.slave.world.settings.robot
    # start over the phantom, from 8 mm above its surface to 3 mm in
    body = rig.slave.world.robot
    x0, y0 = robot.home_m[0], robot.home_m[1]
    z0 = float(rig.slave.world.phantom.surface_height_m(x0, y0)) - float(rng.uniform(-0.008, 0.003))
    body.position = [x0, y0, z0]
    body.set_reference((x0, y0, z0), (0.0, 0.0, 0.0))
    with FastForward(config, rig) as ff:
        loop = ff.loop
        check = _Checker(result, config)
        tissue_model = rig.slave.world.tissue
        v_lim = config.safety.velocity_limit_m_s
        lag = OVERDUE_FRAME_PERIODS / rig.sensor.constraints.frame_rate_hz
        n = int(seconds * config.rate_hz)
        trouble = sorted((int(rng.integers(1, n)), int(rng.integers(6))) for _ in range(int(rng.integers(4, 12))))
        replug_at = -1
        stop_speed = None
        for k in range(n):
            while trouble and trouble[0][0] == k:
                what = trouble.pop(0)[1]
                if what == 0:
                    # down more often than up: the operator pressing the probe in by hand
                    ff.send(Jog((float(rng.uniform(-0.02, 0.02)), float(rng.uniform(-0.02, 0.02)),
                                 float(rng.uniform(-0.04, 0.01)))))
                elif what == 1:
                    ff.send(SetSz(position_control=bool(rng.integers(2))))
                elif what == 2:
                    ff.send(Tare())
                elif what == 3:
                    ff.send(EStop("campaign"))
                elif what == 4:
                    ff.send(ClearFault())
                elif rig.sensor.connected:
                    rig.sensor.simulate_unplug()
                    replug_at = k + int(rng.integers(30, 300))
            if k == replug_at:
                rig.sensor.open()
            ff.step()
            step = ff.last_result
            for e in step.events:
                if isinstance(e, FaultRaised):
                    result.faults += 1
                    if e.kind not in RETRACT_FAULTS:  # a stop where it is: its braking plan from this speed
                        result.stops += 1
                        v = rig.slave.world.robot.velocity
                        stop_speed = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
            check.reference(step, config.period_s)
            x, y, z = rig.slave.world.state_at(ff.now_s)[0]
            true_force = float(np.sum(tissue_model.element_forces_N(x, y, z)))
            check.force(true_force, FORCE_MARGIN_N + _rig_stiffness(true_force) * v_lim * lag)
            if stop_speed is not None and any(isinstance(e, Notice) and "came to rest" in e.message
                                              for e in step.events):
                plan = stop_speed**2 / (2 * BRAKE_FRACTION * robot.max_accel_m_s2)
                over = loop.stop_distance_m - plan
                result.stop_distance_max_mm = max(result.stop_distance_max_mm, loop.stop_distance_m * 1e3)
                result.stop_beyond_plan_max_mm = max(result.stop_beyond_plan_max_mm, over * 1e3)
                if over > STOP_MARGIN_M:
                    check.violate(f"stopped {loop.stop_distance_m * 1e3:.2f} mm after the e-stop, "
                                   f"braking plan {plan * 1e3:.2f} mm")
                stop_speed = None
            result.ticks += 1
    return result


def _rig_stiffness(force_N: float) -> float:
    """A bound on the phantom's contact stiffness at this force, N/m: silicone under the 8 x 30 mm face
    stiffens with load; 2000 N/m plus 500 per N covers the paper's phantoms up to the ceiling."""
    return 2000.0 + 500.0 * max(force_N, 0.0)


def campaign(plant_runs: int, rig_runs: int, seed: int = 0, phantom: str = "flat", sim: dict | None = None,
             first: int = 0) -> dict:
    """Run the campaign (plant runs ``first`` .. ``first + plant_runs - 1`` of this ``seed``, then the rig
    runs); the summary, whose JSON keys are stable, with the first violations found."""
    started = time.monotonic()
    base = seed * 1_000_003
    results = [plant_run(base + first + i) for i in range(plant_runs)]
    if rig_runs:
        sim = sim or {}
        tissue = build_sim_rig(phantom, settings=dict(sim)).slave.world.tissue  # built or cached once for all
        results += [rig_run(base + 500_000 + i, phantom, sim, tissue) for i in range(rig_runs)]
    violations = [v for r in results for v in r.violations]
    stopped = [r for r in results if r.kind == "rig" and r.stops]
    return {
        "runs": len(results),
        "plant_runs": plant_runs,
        "rig_runs": rig_runs,
        "ticks": sum(r.ticks for r in results),
        "faults_raised": sum(r.faults for r in results),
        "stops": sum(r.stops for r in results),
        "violations": sum(1 for r in results if r.violations),
        "violation_examples": violations[:10],
        "estop_overshoot_max_mm": max((r.stop_distance_max_mm for r in stopped), default=0.0),
        "stop_beyond_braking_plan_max_mm": max((r.stop_beyond_plan_max_mm for r in stopped), default=None),
        "force_over_ceiling_max_N": max((r.max_force_over_ceiling_N for r in results), default=None),
        "gain_sets_refused": sum(r.gains_refused for r in results),
        "seconds": time.monotonic() - started,
    }


def merge(parts: list[dict]) -> dict:
    """One summary of several campaigns (run in separate processes)."""
    def top(key):
        values = [p[key] for p in parts if p[key] is not None and p["runs"]]
        return max(values) if values else None

    out = {key: sum(p[key] for p in parts) for key in ("runs", "plant_runs", "rig_runs", "ticks", "faults_raised",
                                                        "stops", "violations", "gain_sets_refused")}
    out["violation_examples"] = [v for p in parts for v in p["violation_examples"]][:10]
    out["estop_overshoot_max_mm"] = top("estop_overshoot_max_mm") or 0.0
    out["stop_beyond_braking_plan_max_mm"] = top("stop_beyond_braking_plan_max_mm")
    out["force_over_ceiling_max_N"] = top("force_over_ceiling_max_N")
    return out


# ---- fuzzing the readers of outside input -----------------------------------------------------------------

ABSURD = (b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"1e-300", b"0", b"-1", b"99999999999999999999", b'"12"',
          b"[]", b"{}", b"true")


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One to four random edits of ``data``."""
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        how = int(rng.integers(6))
        at = int(rng.integers(len(out))) if out else 0
        if how == 0 and out:
            out[at] ^= 1 << int(rng.integers(8))
        elif how == 1:
            out[at:at] = bytes(rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8))
        elif how == 2:
            del out[at:at + int(rng.integers(1, 64))]
        elif how == 3:
            del out[at:]
        elif how == 4 and out:  # a number swapped for an absurd one (text formats)
            digits = [i for i in range(len(out)) if chr(out[i]).isdigit()]
            if digits:
                i = digits[int(rng.integers(len(digits)))]
                j = i
                while j < len(out) and (chr(out[j]).isdigit() or out[j] in b".e-"):
                    j += 1
                out[i:j] = ABSURD[int(rng.integers(len(ABSURD)))]
        else:
            out[at:at] = out[max(0, at - 64):at]
    return bytes(out)


def _fuzz_udp(rng, n: int) -> tuple[int, list[str]]:
    from hardware.udp import protocol as P

    good = [P.pack_command(1, 2, 0.5, P.Command(P.Mode.TRACK, (0.03, 0.01, 0.05), (0.0, 0.0, -0.01))),
            P.pack_state(1, 2, 0.5, P.State(P.Status.NONE, 3, 0.4, (0.03, 0.01, 0.05), (0, 0, 0), 1.0, 2, 0.3, 0.4)),
            P.pack_tactile(1, 2, 0.5, P.Tactile(3, 0.4, np.full((4, 15), 1e3))), P.pack_ping(1, 2, 0.5)]
    crashes = []
    for _ in range(n):
        data = mutate(good[int(rng.integers(len(good)))], rng)
        try:
            P.unpack(data)
        except P.PacketError:
            pass
        except Exception as err:  # noqa: BLE001 - a crash is what the fuzz counts
            crashes.append(f"udp packet {data[:32].hex()}...: {type(err).__name__}: {err}")
    return n, crashes


def _fuzz_serial(rng, n: int) -> tuple[int, list[str]]:
    from hardware.serial_tactile.driver import FrameParser, encode_frame

    frames = b"".join(encode_frame(k, 1000 * k, np.full((4, 15), 100 + k, dtype=np.uint16)) for k in range(8))
    crashes = []
    for _ in range(n):
        data = mutate(frames, rng)
        try:
            list(FrameParser(4, 15).feed(data))
        except Exception as err:  # noqa: BLE001
            crashes.append(f"serial stream: {type(err).__name__}: {err}")
    return n, crashes


def _fuzz_file(rng, n: int, good: bytes, suffix: str, read, allowed, folder: Path, what: str) -> tuple[int, list[str]]:
    crashes = []
    path = folder / f"fuzz{suffix}"
    for _ in range(n):
        path.write_bytes(mutate(good, rng))
        try:
            read(path)
        except allowed:
            pass
        except Exception as err:  # noqa: BLE001
            crashes.append(f"{what}: {type(err).__name__}: {str(err)[:200]}")
    return n, crashes


def fuzz(n_per_reader: int, seed: int, folder: Path, session: Path | None = None) -> dict:
    """Feed each reader ``n_per_reader`` mutated inputs; the counts and the crashes."""
    from app.config import DEFAULT_CONFIG, load_config
    from tissue.phantom import PHANTOM_DIR, PhantomError, load_phantom
    from session.reader import SessionFileError, open_session

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    parts = [_fuzz_udp(rng, n_per_reader), _fuzz_serial(rng, n_per_reader),
             _fuzz_file(rng, n_per_reader, (PHANTOM_DIR / "uneven.toml").read_bytes(), ".toml", load_phantom,
                        PhantomError, folder, "phantom file"),
             _fuzz_file(rng, n_per_reader, DEFAULT_CONFIG.read_bytes(), ".toml", load_config, ConfigError, folder,
                        "config file")]
    if session is not None:
        def read_session(path):
            with open_session(path) as s:
                s.overview()
                s.regions()
                s.event_dicts()
                s.frames(0, 100)

        parts.append(_fuzz_file(rng, n_per_reader, session.read_bytes(), ".h5", read_session, SessionFileError,
                                folder, "session file"))
    crashes = [c for _, found in parts for c in found]
    return {"fuzz_inputs": sum(n for n, _ in parts), "fuzz_crashes": len(crashes), "fuzz_crash_examples": crashes[:10]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.safety_campaign", description=__doc__.splitlines()[0])
    parser.add_argument("--plant-runs", type=int, default=200)
    parser.add_argument("--rig-runs", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the summary here")
    args = parser.parse_args(argv)
    summary = campaign(args.plant_runs, args.rig_runs, args.seed)
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 1 if summary["violations"] else 0


if __name__ == "__main__":
    sys.exit(main())
