"""Phantoms nobody designed for: a seeded, documented distribution of silicone blocks with tumours.

The validation study palpates phantoms drawn here (:func:`draw_phantom`), so that its figures measure the
console on tissue it was not tuned to. Each draw is a phantom file's table, valid by construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from tissue.phantom import PhantomError, parse_phantom

# the paper's comparison of the two maps turns on the surface: on even thickness they see the same
# within-face pattern, where the thickness varies only Eq. 1 tells a tumour from thicker tissue
SURFACES = ("flat", "sloped", "bumpy")


@dataclass(frozen=True)
class StudyDistribution:
    """Where the study's phantoms come from (all ranges uniform unless said otherwise; lengths in m).

    The phantom is a silicone block on the table like the paper's, as wide as the TSI is long (the TSI
    spans it, as in Section IV-A), palpated in 8 mm strips along its length. Its surface is flat, sloped
    (a plane tilted along x and y) or bumpy (one or two half-cylinders along x over part of the length,
    like the paper's uneven phantom), each with the probability given. It holds 0 to 3 spherical tumours
    (each count equally likely) at a depth (surface to the sphere's top) of 1-12 mm, 5-12 mm across and
    3-12 times stiffer than the tissue (log-uniform), anywhere inside the block that keeps 1 mm of tissue
    between tumours and 2 mm above the table. The tissue's modulus is log-uniform around the paper's
    20 kPa. A draw that the phantom schema refuses is drawn again.
    """

    length_m: tuple[float, float] = (0.056, 0.088)
    width_m: float = 0.030
    thickness_m: tuple[float, float] = (0.020, 0.032)
    youngs_modulus_pa: tuple[float, float] = (15e3, 30e3)  # log-uniform
    poisson_ratio: float = 0.49
    surface_odds: tuple[float, float, float] = (0.4, 0.3, 0.3)  # flat, sloped, bumpy
    slope_x: tuple[float, float] = (-0.10, 0.10)  # rise per unit length along x
    slope_y: tuple[float, float] = (-0.05, 0.05)
    bump_radius_m: tuple[float, float] = (0.003, 0.006)
    tumours: tuple[int, int] = (0, 3)
    depth_m: tuple[float, float] = (1e-3, 12e-3)
    diameter_m: tuple[float, float] = (5e-3, 12e-3)
    modulus_ratio: tuple[float, float] = (3.0, 12.0)  # log-uniform
    min_gap_m: float = 1e-3  # tissue between two tumours
    table_clearance_m: float = 2e-3  # tissue under a tumour


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1]))))


def draw_phantom(rng: np.random.Generator, name: str, dist: StudyDistribution = StudyDistribution(),
                 attempts: int = 200) -> dict[str, Any]:
    """One phantom from ``dist`` as a phantom file's table (see docs/phantoms.md), valid by construction."""
    for _ in range(attempts):
        length = round(_uniform(rng, dist.length_m), 4)
        thickness = round(_uniform(rng, dist.thickness_m), 4)
        tissue_pa = round(_log_uniform(rng, dist.youngs_modulus_pa), -2)
        table: dict[str, Any] = {
            "name": name, "length_m": length, "width_m": dist.width_m, "thickness_m": thickness,
            "youngs_modulus_pa": tissue_pa, "poisson_ratio": dist.poisson_ratio,
        }
        kind = SURFACES[int(rng.choice(len(SURFACES), p=np.asarray(dist.surface_odds)))]
        if kind == "sloped":
            gx, gy = round(_uniform(rng, dist.slope_x), 3), round(_uniform(rng, dist.slope_y), 3)
            # tilted about the phantom's centre, so the base thickness is its mean height
            table["surface"] = [{"kind": "slope", "gradient": [gx, gy], "origin_m": [length / 2, dist.width_m / 2],
                                 "x_range_m": [0.0, length]}]
        elif kind == "bumpy":
            table["surface"] = []
            for _ in range(int(rng.integers(1, 3))):
                radius = round(_uniform(rng, dist.bump_radius_m), 4)
                start = round(float(rng.uniform(0.0, 0.5)) * length, 4)
                end = round(min(length, start + float(rng.uniform(0.3, 0.7)) * length), 4)
                centre = round(float(rng.choice([radius, dist.width_m - radius])), 4)
                table["surface"].append({"kind": "half_cylinder", "centre_y_m": centre, "radius_m": radius,
                                         "x_range_m": [start, end]})
        table["inclusions"] = []
        for _ in range(int(rng.integers(dist.tumours[0], dist.tumours[1] + 1))):
            diameter = round(_uniform(rng, dist.diameter_m), 4)
            radius = diameter / 2
            table["inclusions"].append({
                "centre_xy_m": [round(_uniform(rng, (radius, length - radius)), 4),
                                round(_uniform(rng, (radius, dist.width_m - radius)), 4)],
                "diameter_m": diameter,
                "youngs_modulus_pa": round(tissue_pa * _log_uniform(rng, dist.modulus_ratio), -2),
                "depth_m": round(_uniform(rng, dist.depth_m), 4),
            })
        data = {"phantom": table}
        try:
            phantom = parse_phantom(data, name)
        except PhantomError:
            continue
        if _room_around_tumours(phantom, dist):
            table["description"] = (f"study phantom, {kind} surface, {len(table['inclusions'])} tumour(s), "
                                    f"E = {tissue_pa / 1e3:.1f} kPa")
            return data
    raise RuntimeError(f"no valid phantom after {attempts} draws: the distribution leaves no room")


def _room_around_tumours(phantom, dist: StudyDistribution) -> bool:
    for i, a in enumerate(phantom.inclusions):
        if a.z_m - a.radius_m < dist.table_clearance_m:
            return False
        for b in phantom.inclusions[:i]:
            if math.dist((a.x_m, a.y_m, a.z_m), (b.x_m, b.y_m, b.z_m)) < a.radius_m + b.radius_m + dist.min_gap_m:
                return False
    return True


def surface_kind(phantom: dict[str, Any]) -> str:
    """Which of :data:`SURFACES` a phantom file's table has (a drawn phantom's features are all of one kind;
    micro-relief, :func:`draw_conditions`, is on every surface of the realistic world and does not count)."""
    features = [f for f in phantom["phantom"].get("surface", []) if f["kind"] != "relief"]
    if not features:
        return "flat"
    return "sloped" if features[0]["kind"] == "slope" else "bumpy"


@dataclass(frozen=True)
class RealisticConditions:
    """What the study's realistic world changes about a phantom and its palpation, none of which the analysis
    knows of or reads (ranges uniform; lengths in m, angles in degrees).

    * **Law**: Yeoh, ``W = C1 (I1-3) + C2 (I1-3)^2 + C3 (I1-3)^3``, with C2/C1 and C3/C1 spanning the two Yeoh
      fits for Ecoflex 00-30 that circulate in soft-robotics finite-element material libraries (C1 17 kPa,
      C2 -0.2 kPa, C3 0.023 kPa; and C1 8.4 kPa, C2 0.1 kPa, C3 0); the analysis assumes neo-Hookean.
    * **Sides**: in the casting mould with probability ``mould_odds`` (lateral faces held; 1.7x stiffer for the
      paper's flat phantom, docs/phantoms.md), else free on the table as the paper's; the analysis assumes free.
      The paper's own phantoms stay free: the paper says they lay on the table.
    * **Micro-relief** of a cast surface, rms and wavelength as given (the mesh's 1 mm nodes resolve 3 mm
      ripples); the analysis measures the surface from the contact onsets.
    * **Probe tilt** about both axes: a hand-mounted probe is off by a degree or so; the analysis assumes a
      level face.
    * **A thicker cover** than the array is specified with: its load spreads sideways by up to twice the
      stated 0.5 mm (``tissue.face.COVER_SPREAD_M``; assumed, we found no measurement of a capacitive
      array's cover to cite); the analysis uses the stated one, which the session's calibration records.
    * **Friction at the face** (Coulomb's mu, 0.2-1: the range issue 48 states; we found no measurement of
      silicone on a tactile array's cover to cite); the analysis assumes a frictionless face.
    """

    c2_over_c1: tuple[float, float] = (-0.0118, 0.0119)
    c3_over_c1: tuple[float, float] = (0.0, 0.00135)
    mould_odds: float = 0.3
    relief_rms_m: tuple[float, float] = (0.1e-3, 0.3e-3)
    relief_wavelength_m: tuple[float, float] = (3e-3, 8e-3)
    tilt_deg: tuple[float, float] = (-1.5, 1.5)
    cover_spread_m: tuple[float, float] = (0.5e-3, 1.0e-3)
    face_friction: tuple[float, float] = (0.2, 1.0)


def draw_conditions(rng: np.random.Generator, phantom: dict[str, Any], paper: bool = False,
                    dist: RealisticConditions = RealisticConditions()) -> tuple[dict[str, Any], dict[str, Any]]:
    """``phantom`` (a phantom file's content) under conditions drawn from ``dist``: the phantom file with its
    law, sides, friction at the face and micro-relief, and the conditions as plain values (``probe_tilt_deg``
    and ``cover_spread_m`` for the rig, the rest for the record)."""
    table = dict(phantom["phantom"])
    c3 = round(_uniform(rng, dist.c3_over_c1), 6)
    # a softening C2 needs C3 enough to keep the energy rising (tissue.phantom's check), as both fits have
    c2 = round(_uniform(rng, (max(dist.c2_over_c1[0], -0.99 * math.sqrt(3.0 * c3)), dist.c2_over_c1[1])), 5)
    sides = "free" if paper or rng.uniform() >= dist.mould_odds else "mould"
    rms = round(_uniform(rng, dist.relief_rms_m), 5)
    wavelength = round(_uniform(rng, dist.relief_wavelength_m), 4)
    relief_seed = int(rng.integers(2**31))
    tilt = [round(_uniform(rng, dist.tilt_deg), 2) for _ in range(2)]
    cover = round(_uniform(rng, dist.cover_spread_m), 6)  # drawn after the others: theirs stay as they were
    friction = round(_uniform(rng, dist.face_friction), 3)  # (and after the cover, for the same reason)
    table["material"] = {"law": "yeoh", "c2_over_c1": c2, "c3_over_c1": c3}
    table["sides"] = sides
    table["face_friction"] = friction
    table["surface"] = [*table.get("surface", []),
                        {"kind": "relief", "rms_m": rms, "wavelength_m": wavelength, "seed": relief_seed,
                         "x_range_m": [0.0, table["length_m"]]}]
    data = {**phantom, "phantom": table}
    parse_phantom(data, str(table.get("name", "<phantom>")))  # valid by construction; a bug if not
    return data, {"law": "yeoh", "c2_over_c1": c2, "c3_over_c1": c3, "sides": sides, "relief_rms_m": rms,
                  "relief_wavelength_m": wavelength, "probe_tilt_deg": tilt, "cover_spread_m": cover,
                  "face_friction": friction}
