"""Test plants for the loop alone: a robot that tracks X_r exactly over a flat elastic layer.

Each element's pressure is E * dL / L0 (a local linear layer), the array delivers frames every
``frame_period_s``, ``latency_s`` late, optionally clipped at a full scale (saturation flagged). The
plant knows the truth the loop cannot see (:meth:`LayerPlant.true_force_N`), which is what the fault
campaign (:mod:`bench.safety_campaign`) and the control tests check the loop against. The simulated rig
(hardware/sim) is the physics-based plant; this one is exact and fast.
"""

from __future__ import annotations

import numpy as np

from hardware.interfaces import SlaveState, TactileConstraints, TactileFrame

SHAPE = TactileConstraints().shape
ELEMENT_AREA_M2 = TactileConstraints().element_area_m2


class LayerPlant:
    def __init__(self, surface_m=0.025, modulus_pa=60e3, frame_period_s=0.01, latency_s=0.005,
                 start_m=(0.03, 0.015, 0.032), stiff_mask=None, stiff_factor=1.0, noise_pa=50.0,
                 full_scale_pa=None):
        self.surface_m = surface_m
        self.modulus = np.full(SHAPE, modulus_pa)
        if stiff_mask is not None:
            self.modulus[stiff_mask] *= stiff_factor
        self.frame_period_s = frame_period_s
        self.latency_s = latency_s
        self.x = list(start_m)
        self.v = [0.0, 0.0, 0.0]
        self.history: list[tuple[float, float]] = []
        self.frame: TactileFrame | None = None
        self.seq = 0
        self.next_frame_t = 0.0
        self.sensor_alive = True
        self.slave_alive = True
        self.extra_force_pa = 0.0
        # white noise per element and frame, as the simulated array's default (hardware/sim/settings.py): an
        # array without noise repeats its frames exactly, which the loop takes for a frozen array
        self.noise_pa = noise_pa
        self.full_scale_pa = full_scale_pa  # None: an array that never saturates
        self.rng = np.random.default_rng(1)

    def pressure_at(self, z: float) -> np.ndarray:
        d = max(self.surface_m - z, 0.0)
        noise = self.rng.normal(0.0, self.noise_pa, SHAPE) if np.any(self.noise_pa) else 0.0
        return self.modulus * d / self.surface_m + self.extra_force_pa + noise

    def poll(self, now: float) -> None:
        self.history.append((now, self.x[2]))
        if self.sensor_alive and now >= self.next_frame_t:
            t_sample = now - self.latency_s
            z = np.interp(t_sample, [h[0] for h in self.history[-50:]], [h[1] for h in self.history[-50:]])
            self.seq += 1
            p = self.pressure_at(float(z))
            saturated = None
            if self.full_scale_pa is not None:
                saturated = p >= self.full_scale_pa
                p = np.minimum(p, self.full_scale_pa)
            self.frame = TactileFrame(self.seq, t_sample, p, saturated)
            self.next_frame_t = now + self.frame_period_s
        self._slave = SlaveState(int(now * 1e6), now, tuple(self.x), tuple(self.v))

    def true_force_N(self) -> float:
        """The force the layer pushes back with where the probe is now (no noise, no sensor)."""
        d = max(self.surface_m - self.x[2], 0.0)
        return float((self.modulus * d / self.surface_m).sum()) * ELEMENT_AREA_M2

    def slave(self, now: float) -> SlaveState | None:
        return self._slave if self.slave_alive else None

    def apply(self, result) -> None:
        if not result.hold:
            self.x = list(result.position_ref_m)
            self.v = list(result.velocity_ref_m_s)
