"""Synthetic session data with the real row layouts, for benchmarks and tests that need volume or control.

The numbers follow simple physics, not noise: the TSI presses a linear-elastic layer of thickness
``thickness_m`` and modulus ``youngs_pa`` (Eq. 1 read backwards: p = E dL / L0), stiffer by
``tumour_factor`` within ``tumour_radius_m`` of each tumour, so stitching and detection find what was put
in. Sessions recorded from the simulator (:mod:`app.session.simulated`) are the realistic alternative.
"""

from __future__ import annotations

import math

import numpy as np

from control.messages import LevelRecord
from control.telemetry import COLS, FRAME_DTYPE, ROWS, TICK_DTYPE
from hardware.interfaces import Phase, TactileConstraints


def tick_rows(start_tick: int, n: int, period_s: float = 1e-3) -> np.ndarray:
    """``n`` consecutive TICK_DTYPE rows from tick ``start_tick``: a 10 s cycle of approach and force ramp."""
    rows = np.zeros(n, TICK_DTYPE)
    k = np.arange(start_tick, start_tick + n)
    t = k * period_s
    cycle = (t % 10.0) / 10.0
    pressing = cycle > 0.4
    rows["tick"] = k
    rows["t_s"] = t
    rows["compute_s"] = 30e-6
    rows["io_s"] = 20e-6
    rows["phase"] = np.where(pressing, Phase.SETTLING, Phase.APPROACH)
    rows["sz"] = np.where(pressing, 0, 1)
    rows["region"] = (t // 10.0).astype(np.int16)
    rows["level"] = np.where(pressing, ((cycle - 0.4) / 0.6 * 7).astype(np.int16), -1)
    rows["n_levels"] = 7
    force = np.where(pressing, 1.0 + np.floor((cycle - 0.4) / 0.6 * 7), 0.0)
    rows["force_desired_N"] = force
    rows["force_measured_N"] = force * (1.0 + 0.01 * np.sin(2 * math.pi * 7.0 * t))
    rows["rmse_N"] = np.where(pressing, 0.02, np.nan)
    z = np.where(pressing, 0.025 - force * 1.3e-3, 0.03)
    for field in ("x_ref_m", "x_des_m", "x_slave_m"):
        rows[field][:, 0] = 0.004 + 0.008 * rows["region"]
        rows[field][:, 1] = 0.015
        rows[field][:, 2] = z
    rows["indentation_m"] = np.where(pressing, force * 1.3e-3, np.nan)
    rows["sensor_seq"] = k // 10
    rows["sensor_age_s"] = (k % 10) * period_s
    rows["master_age_s"] = 0.0
    rows["slave_age_s"] = 0.0
    return rows


def frame_rows(start_seq: int, n: int, frame_period_s: float = 0.01, seed: int = 0) -> np.ndarray:
    """``n`` FRAME_DTYPE rows from sensor frame ``start_seq`` (one every ``frame_period_s``)."""
    rng = np.random.default_rng(seed + start_seq)
    rows = np.zeros(n, FRAME_DTYPE)
    seq = np.arange(start_seq, start_seq + n)
    rows["sensor_seq"] = seq
    rows["t_s"] = seq * frame_period_s
    rows["tick"] = np.round(rows["t_s"] / 1e-3).astype(np.int64)
    rows["tsi_position_m"] = (0.036, 0.015, 0.02)
    pressure = 2000.0 + 50.0 * rng.standard_normal((n, ROWS, COLS))
    rows["pressure_pa"] = pressure.astype(np.float32)
    rows["dL_m"] = np.float32(2e-3)
    rows["stiffness_pa"] = (pressure * 0.025 / 2e-3).astype(np.float32)
    return rows


def level_record(region: int, level: int, force_N: float, position_xy_m: tuple[float, float], *,
                 tumours_xy_m: tuple[tuple[float, float], ...] = (), thickness_m: float = 0.025,
                 youngs_pa: float = 20e3, tumour_factor: float = 1.5, tumour_radius_m: float = 4e-3,
                 t_s: float = 0.0, noise: float = 0.0, seed: int = 0, frame_noise_pa: float = 50.0,
                 window_frames: int = 30, sensor: TactileConstraints | None = None) -> LevelRecord:
    """The level a flat TSI records at ``force_N`` over a layer with stiffer spots at ``tumours_xy_m``.

    Every element is indented by the same dL (a level face on a flat surface); it is found so that the
    element forces add up to ``force_N``. ``noise`` is a relative scatter of the modulus from element to
    element (fixed by ``seed``); ``frame_noise_pa`` is the scatter the record says its frames had over
    ``window_frames`` frames.
    """
    sensor = sensor or TactileConstraints()
    area = sensor.element_area_m2
    offsets = sensor.element_offsets_m()
    x = position_xy_m[0] + offsets[..., 0]
    y = position_xy_m[1] + offsets[..., 1]
    modulus = np.full(sensor.shape, youngs_pa)
    for tx, ty in tumours_xy_m:
        modulus = np.where(np.hypot(x - tx, y - ty) <= tumour_radius_m, youngs_pa * tumour_factor, modulus)
    if noise:
        modulus = modulus * (1.0 + noise * np.random.default_rng(seed).standard_normal(sensor.shape))
    # F = sum(E * A * dL / L0)  =>  dL = F * L0 / (A * sum(E))
    dL = force_N * thickness_m / (area * modulus.sum())
    pressure = modulus * dL / thickness_m
    z = thickness_m - dL
    return LevelRecord(
        region=region, level=level, t_s=t_s, force_desired_N=force_N, force_measured_N=float(pressure.sum() * area),
        rmse_N=0.01, settle_time_s=0.6, tsi_position_m=(position_xy_m[0], position_xy_m[1], z), indentation_m=dL,
        pressure_pa=pressure, pressure_std_pa=np.full(sensor.shape, frame_noise_pa), window_frames=window_frames,
        element_force_N=pressure * area, onset_height_m=np.full(sensor.shape, thickness_m),
        L0_m=np.full(sensor.shape, thickness_m), dL_m=np.full(sensor.shape, dL),
        stiffness_pa=pressure * area * thickness_m / (area * dL))
