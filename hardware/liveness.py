"""Whether a tactile array is still reading the world: the checks the console's loop and the slave both run
on their own copy of the array's frames (a lying device is the normal case).

* :class:`RepeatWatch`: a frame identical, element by element, to the one before says nothing new. Every real
  array has noise, so an array that repeats itself is frozen, or dead and streaming a constant (zeros); its
  frames are not fresh, and it goes stale on the ordinary timeout.
* :class:`TravelWatch`: pressing on, the probe may go only so far deeper without the force it reads rising. An
  array that is dead, repeats a frame, or whose reading drifts down reads no more force however deep the
  probe goes, while whatever pushes to reach a force pushes on.
"""

from __future__ import annotations

import math

import numpy as np


class RepeatWatch:
    """``fresh_t_s``: the sampling instant of the newest frame that differed from the one before it (-inf
    before any); ``repeats``: how many frames in a row since have repeated it."""

    def __init__(self, shape: tuple[int, int]):
        self._previous = np.full(shape, np.nan)
        self.repeats = 0
        self.fresh_t_s = -math.inf

    def push(self, pressure_pa: np.ndarray, t_s: float) -> bool:
        """Note a new frame; True when it says something new."""
        if np.array_equal(pressure_pa, self._previous):  # NaN never equals: a NaN frame is news, and implausible
            self.repeats += 1
            return False
        self.repeats = 0
        self.fresh_t_s = t_s
        self._previous[...] = pressure_pa
        return True


class TravelWatch:
    """How far the probe has gone below the height at which the force it reads last rose as tissue would: by
    ``rise_N``, and once it reads ``engaged_N`` by at least ``softest_N_m`` times the travel since. (A reading
    that creeps up by a few mN while the probe sinks a millimetre is not tissue pushing back: the fault
    campaign's drifting array did that, and a watch content with any rise of 5 mN let the probe go on. Before
    the face bears on the tissue, a first touch on a ridge rises by less: the paper's uneven phantom did.)"""

    def __init__(self, rise_N: float, softest_N_m: float = 0.0, engaged_N: float = 0.0):
        self.rise_N = rise_N
        self.softest_N_m = softest_N_m
        self.engaged_N = engaged_N
        self.peak_N = math.nan  # the force read where it last rose so, and where it was read
        self.peak_z_m = math.nan

    def reset(self) -> None:
        self.peak_N = self.peak_z_m = math.nan

    def push(self, force_N: float, z_m: float) -> None:
        """A frame's force and the face's height when it was sampled."""
        travel = max(self.peak_z_m - z_m, 0.0) if self.peak_N >= self.engaged_N else 0.0
        if not force_N <= self.peak_N + self.rise_N + self.softest_N_m * travel:  # (NaN before the first)
            self.peak_N, self.peak_z_m = force_N, z_m

    def travel_m(self, z_now_m: float) -> float:
        """How far ``z_now_m`` lies below the last rise (NaN before the first frame)."""
        return self.peak_z_m - z_now_m
