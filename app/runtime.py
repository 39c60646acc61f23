"""The one tick every driver runs: poll the rig, step the loop, apply its reference to the hardware.

The real-time controller process, the fast-forward driver and the tests all call :func:`make_loop` and
:func:`run_tick`, so whatever a test proves about a tick holds for the robot too.
"""

from __future__ import annotations

import time
from collections.abc import Iterable

from control.config import ControlConfig
from control.loop import ControlLoop, StepResult
from control.messages import Command, CommandApplied, CommandRefused
from hardware.interfaces import DeviceError
from hardware.rig import Rig


def make_loop(config: ControlConfig, rig: Rig) -> ControlLoop:
    return ControlLoop(config, rig.sensor.constraints, has_master=rig.master is not None)


def run_tick(loop: ControlLoop, rig: Rig, now_s: float, commands: Iterable[Command] = ()) -> StepResult:
    """One control period at host time ``now_s``.

    Writes into the tick row how long the loop computed (``compute_s``) and how long the devices took
    (``io_s``: polling them and applying the step's output). They are kept apart because on the
    simulated rig ``io_s`` is mostly the simulation of the world, work a real robot and sensor do on
    their own hardware, while on a real rig it is reading and writing buffers.
    """
    perf = time.perf_counter
    t0 = perf()
    rig.poll(now_s)
    master = rig.master
    t1 = perf()
    result = loop.step(
        now_s,
        rig.sensor.latest(),
        rig.slave.latest(),
        master.latest() if master is not None else None,
        commands,
    )
    t2 = perf()
    if result.hold:
        rig.slave.hold(now_s)
    else:
        rig.slave.command(result.position_ref_m, result.velocity_ref_m_s, now_s)
    if result.tare is not None:
        try:
            rig.sensor.tare()
        except DeviceError as err:
            result.events.append(CommandRefused(now_s, result.tare, str(err)))
        else:
            result.events.append(CommandApplied(now_s, result.tare, "Tactile sensor tared: the current reading is "
                                                                    "the new zero."))
    if master is not None and result.feedback is not None:
        master.feedback(result.feedback)
    row = loop.tick
    row["compute_s"] = t2 - t1
    row["io_s"] = (t1 - t0) + (perf() - t2)
    return result
