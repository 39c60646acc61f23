"""Tissue phantom definitions: geometry, materials and embedded inclusions, loaded from TOML.

Schema (all lengths in m, moduli in Pa)::

    [phantom]
    name = "flat"
    description = "..."
    length_m = 0.072          # extent along x
    width_m = 0.030           # extent along y
    thickness_m = 0.025       # base surface height above the table
    youngs_modulus_pa = 20e3
    poisson_ratio = 0.49
    sides = "free"            # optional: "free" (default) or "mould" (lateral faces on frictionless walls)
    face_friction = 0.0       # optional: Coulomb's coefficient of the probe's face on the tissue (0: none)

    [phantom.material]        # optional: the law at finite strain; small strain is set by the modulus
    law = "neo_hookean"       # default; or "yeoh", W = C1 (I1-3) + C2 (I1-3)^2 + C3 (I1-3)^3, C1 = mu/2,
    # c2_over_c1 = -0.05      # with the ratios C2/C1 and C3/C1 (yeoh only, default 0)
    # c3_over_c1 = 0.01

    [[phantom.surface]]       # optional features added to the base height
    kind = "half_cylinder"    # axis along x, centred at y = centre_y_m; adds sqrt(r^2 - (y-c)^2)
    centre_y_m = 0.025
    radius_m = 0.005
    x_range_m = [0.0, 0.024]

    [[phantom.surface]]
    kind = "slope"            # adds gradient_x * (x - x0) + gradient_y * (y - y0) over x_range_m
    gradient = [0.05, 0.0]
    origin_m = [0.0, 0.0]
    x_range_m = [0.0, 0.072]

    [[phantom.surface]]
    kind = "relief"           # micro-relief: a smooth random height field of rms_m over x_range_m, made of
    rms_m = 0.2e-3            # ripples between wavelength_m and twice it, in all directions, fixed by seed
    wavelength_m = 0.004
    seed = 7
    x_range_m = [0.0, 0.072]

    [[phantom.inclusions]]    # spheres, inside the phantom and apart from each other
    centre_xy_m = [0.012, 0.015]
    diameter_m = 0.008
    youngs_modulus_pa = 160e3
    depth_m = 0.002           # from the local surface to the sphere's top ...
    # height_m = 0.020        # ... or the sphere centre's height above the table (exactly one of them)

    [[phantom.regions]]       # palpation areas (TSI centre x, y); default: 8 mm strips along x
    centre_xy_m = [0.004, 0.015]

A bad file raises :class:`PhantomError` whose message names the key and the problem. The schema, the
shipped phantoms and every assumption behind them are documented in docs/phantoms.md.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from tissue.files import UnreadableFile, read_toml

# shipped as package data beside this module, in a checkout and in an installed wheel alike
PHANTOM_DIR = Path(str(resources.files(__package__).joinpath("phantoms")))
MIN_SURFACE_HEIGHT_M = 1e-3  # a thinner layer is no phantom, and the mesh needs room
MAX_LENGTH_M, MAX_WIDTH_M, MAX_THICKNESS_M = 0.5, 0.3, 0.1  # the bench's phantom tray, with room to spare
MAX_COORDINATE_M = 1.0  # positions and sizes of features, m
MAX_GRADIENT = 10.0  # a slope steeper than 84 degrees is a wall
# A cast surface's micro-relief: ripples finer than the mesh's 1 mm nodes could not be represented, and a
# relief of millimetres is a feature of its own (half_cylinder, slope)
MAX_RELIEF_RMS_M, RELIEF_WAVELENGTH_M = 1e-3, (2e-3, 0.05)
RELIEF_WAVES = 12
MAX_MODULUS_PA = 1e9
MIN_MODULUS_PA = 100.0  # softer than any tissue or gel (1e-300 Pa was accepted, and the solver failed on it)
MIN_EXTENT_M = 4e-3  # two elements: a smaller block has nothing to palpate (1e-9 m was accepted)
# Each feature and inclusion is evaluated over the whole surface grid, each region palpated: 3,000 inclusions
# took 272 s and 4.8 GB to load, and 4,000 surface features kept the parser alone busy for a quarter of an hour
MAX_FEATURES, MAX_INCLUSIONS, MAX_REGIONS = 20, 20, 200
FACE_SAMPLE_M = 0.5e-3


SIDES = ("free", "mould")
LAWS = ("neo_hookean", "yeoh")
MAX_YEOH_RATIO = 100.0
# the realistic world draws 0.2-1 (tissue.generator); from about 1 on the face grips the tissue outright (a
# 24 x 30 x 10 mm block read the same with mu 1 and 2, to four digits at 10 % strain)
MAX_FACE_FRICTION = 2.0


class PhantomError(ValueError):
    def __init__(self, source: str, key: str, problem: str):
        super().__init__(f"{source}: {key}: {problem}")
        self.source, self.key, self.problem = source, key, problem


@dataclass(frozen=True)
class SurfaceFeature:
    kind: str  # "half_cylinder" | "slope" | "relief"
    x_range_m: tuple[float, float]
    centre_y_m: float = 0.0
    radius_m: float = 0.0
    gradient: tuple[float, float] = (0.0, 0.0)
    origin_m: tuple[float, float] = (0.0, 0.0)
    rms_m: float = 0.0
    wavelength_m: float = 0.0
    seed: int = 0

    def height_m(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        inside = (x >= self.x_range_m[0]) & (x <= self.x_range_m[1])
        if self.kind == "half_cylinder":
            d2 = self.radius_m**2 - (y - self.centre_y_m) ** 2
            h = np.sqrt(np.clip(d2, 0.0, None))
        elif self.kind == "relief":
            h = self._relief(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        else:
            h = self.gradient[0] * (x - self.origin_m[0]) + self.gradient[1] * (y - self.origin_m[1])
        return np.where(inside, h, 0.0)

    def _relief(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """A sum of plane waves of random direction, wavelength (within an octave) and phase: a field whose
        rms over a large area is ``rms_m``, the same for every reader of the same file."""
        rng = np.random.default_rng(self.seed)
        angle = rng.uniform(0.0, np.pi, RELIEF_WAVES)
        k = 2.0 * np.pi / (self.wavelength_m * rng.uniform(1.0, 2.0, RELIEF_WAVES))
        phase = rng.uniform(0.0, 2.0 * np.pi, RELIEF_WAVES)
        h = np.zeros(np.broadcast(x, y).shape)
        for a, kk, ph in zip(angle, k, phase, strict=True):
            h = h + np.cos(kk * (np.cos(a) * x + np.sin(a) * y) + ph)
        return self.rms_m * math.sqrt(2.0 / RELIEF_WAVES) * h


@dataclass(frozen=True)
class Inclusion:
    x_m: float
    y_m: float
    z_m: float  # centre height above the table
    diameter_m: float
    youngs_modulus_pa: float

    @property
    def radius_m(self) -> float:
        return self.diameter_m / 2.0


@dataclass(frozen=True)
class Hyperelastic:
    """The strain energy at finite strain, relative to the small-strain shear modulus mu (C1 = mu / 2)."""

    law: str = "neo_hookean"
    c2_over_c1: float = 0.0
    c3_over_c1: float = 0.0


@dataclass(frozen=True)
class Phantom:
    name: str
    description: str
    length_m: float
    width_m: float
    thickness_m: float
    youngs_modulus_pa: float
    poisson_ratio: float
    surface: tuple[SurfaceFeature, ...] = ()
    inclusions: tuple[Inclusion, ...] = ()
    regions: tuple[tuple[float, float], ...] = ()
    sides: str = "free"  # "mould": the lateral faces slide on frictionless walls (a phantom in its casting tray)
    material: Hyperelastic = Hyperelastic()
    face_friction: float = 0.0  # Coulomb's coefficient of the probe's face on the tissue
    source: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def surface_height_m(self, x, y) -> np.ndarray:
        """Surface height above the table at (x, y); 0 outside the phantom's footprint."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        h = np.full(np.broadcast(x, y).shape, self.thickness_m)
        for feature in self.surface:
            h = h + feature.height_m(x, y)
        outside = (x < 0) | (x > self.length_m) | (y < 0) | (y > self.width_m)
        return np.where(outside, 0.0, h)

    def highest_surface_m(self, x_m: float, y_m: float, face_size_m: tuple[float, float]) -> float:
        """The highest surface point under a face of ``face_size_m`` (along x, y) centred at (x, y): what an
        operator aims to clear before handing z to force control (sampled every 0.5 mm, the detail a
        camera shows)."""
        sx, sy = face_size_m
        gx = np.linspace(x_m - sx / 2, x_m + sx / 2, int(math.ceil(sx / FACE_SAMPLE_M)) + 1)
        gy = np.linspace(y_m - sy / 2, y_m + sy / 2, int(math.ceil(sy / FACE_SAMPLE_M)) + 1)
        return float(np.max(self.surface_height_m(*np.meshgrid(gx, gy, indexing="ij"))))

    def inclusion_depth_m(self, inc: Inclusion) -> float:
        """Depth of the inclusion's top below the surface directly above its centre."""
        return float(self.surface_height_m(inc.x_m, inc.y_m)) - (inc.z_m + inc.radius_m)

    def palpation_regions(self, tsi_length_x_m: float = 8e-3) -> tuple[tuple[float, float], ...]:
        """The listed regions, or strips as long as the TSI along x across the whole phantom."""
        if self.regions:
            return self.regions
        n = max(1, int(round(self.length_m / tsi_length_x_m)))
        pitch = self.length_m / n
        return tuple(((k + 0.5) * pitch, self.width_m / 2.0) for k in range(n))

    def content_hash(self) -> str:
        """Stable hash of everything that affects the mechanics (cache key): what the phantom is, not the file
        it came from. A phantom built in code has no file: hashed by its file, every block the analysis
        rebuilds shared one cached finite-strain solve, whichever a machine had made first."""
        content = {k: v for k, v in asdict(self).items() if k != "source"}
        if not self.face_friction:
            del content["face_friction"]  # a frictionless phantom keeps the hash it had before friction existed
        blob = json.dumps(content, sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def ground_truth(self) -> list[dict[str, float]]:
        return [
            {
                "x_m": inc.x_m,
                "y_m": inc.y_m,
                "z_m": inc.z_m,
                "depth_m": self.inclusion_depth_m(inc),
                "diameter_m": inc.diameter_m,
                "youngs_modulus_pa": inc.youngs_modulus_pa,
            }
            for inc in self.inclusions
        ]


def load_phantom(name_or_path: str | Path) -> Phantom:
    """Load a phantom by name (a file in tissue/phantoms) or by path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = PHANTOM_DIR / f"{name_or_path}.toml"
    src = str(path)
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in PHANTOM_DIR.glob("*.toml")))
        raise PhantomError(src, "file", f"no such phantom (shipped phantoms: {known})")
    try:
        data = read_toml(path, "phantom file")
    except UnreadableFile as err:
        raise PhantomError(src, "file", err.problem) from None
    return parse_phantom(data, src)


def parse_phantom(data: dict[str, Any], src: str = "<phantom>") -> Phantom:
    p = _Reader(src, data).table("phantom")
    # stated maxima, checked before anything is allocated: a bench phantom, whose model's mesh and surface
    # grid grow with its size (a 10 m phantom once asked for 12 GiB before failing)
    length = p.bounded("length_m", MAX_LENGTH_M, "a bench phantom", least=MIN_EXTENT_M)
    width = p.bounded("width_m", MAX_WIDTH_M, "a bench phantom", least=MIN_EXTENT_M)
    thickness = p.bounded("thickness_m", MAX_THICKNESS_M, "a palpated layer")
    nu = p.number("poisson_ratio")
    if not 0.0 <= nu < 0.5:
        p.fail("poisson_ratio", f"must be in [0, 0.5), got {nu:g} (use 0.49-0.499 for nearly incompressible)")
    surface = tuple(_feature(f) for f in p.list_of_tables("surface", MAX_FEATURES))
    friction = p.number("face_friction", default=0.0, bound=MAX_FACE_FRICTION)
    if friction < 0:
        p.fail("face_friction", f"must be >= 0 (0: frictionless), got {friction:g}")
    base = Phantom(
        name=p.string("name"),
        description=p.string("description", default=""),
        length_m=length,
        width_m=width,
        thickness_m=thickness,
        youngs_modulus_pa=p.bounded("youngs_modulus_pa", MAX_MODULUS_PA, "stiffer than bone is not tissue",
                                    least=MIN_MODULUS_PA),
        poisson_ratio=nu,
        surface=surface,
        sides=p.choice("sides", SIDES, default="free"),
        material=_material(p.optional_table("material")),
        face_friction=friction,
    )
    lowest = float(base.surface_height_m(*_footprint_grid(base)).min())
    if lowest < MIN_SURFACE_HEIGHT_M:
        p.fail("surface", f"the surface comes down to {lowest * 1e3:.2f} mm above the table; it must stay at "
                          f"least {MIN_SURFACE_HEIGHT_M * 1e3:g} mm above it everywhere")
    inclusions = []
    for r in p.list_of_tables("inclusions", MAX_INCLUSIONS):
        inc = _inclusion(r, base)
        for j, other in enumerate(inclusions):
            gap = math.dist((inc.x_m, inc.y_m, inc.z_m), (other.x_m, other.y_m, other.z_m))
            if gap < inc.radius_m + other.radius_m:
                r.fail("centre_xy_m", f"overlaps inclusions[{j}] (centres {gap * 1e3:.1f} mm apart)")
        inclusions.append(inc)
    inclusions = tuple(inclusions)
    regions = tuple(_region(r, base) for r in p.list_of_tables("regions", MAX_REGIONS))
    p.no_unknown({"name", "description", "length_m", "width_m", "thickness_m", "youngs_modulus_pa",
                  "poisson_ratio", "surface", "inclusions", "regions", "sides", "material", "face_friction"})
    return Phantom(**{**base.__dict__, "inclusions": inclusions, "regions": regions, "source": data})


def _footprint_grid(phantom: Phantom, step_m: float = 0.25e-3) -> tuple[np.ndarray, np.ndarray]:
    x = np.linspace(0.0, phantom.length_m, max(2, int(round(phantom.length_m / step_m)) + 1))
    y = np.linspace(0.0, phantom.width_m, max(2, int(round(phantom.width_m / step_m)) + 1))
    return np.meshgrid(x, y, indexing="ij")


def _material(r: "_Reader | None") -> Hyperelastic:
    if r is None:
        return Hyperelastic()
    law = r.choice("law", LAWS, default="neo_hookean")
    if law == "neo_hookean":
        r.no_unknown({"law"})
        return Hyperelastic()
    r.no_unknown({"law", "c2_over_c1", "c3_over_c1"})
    c2 = r.number("c2_over_c1", default=0.0, bound=MAX_YEOH_RATIO)
    c3 = r.number("c3_over_c1", default=0.0, bound=MAX_YEOH_RATIO)
    # dW/dI1 = C1 (1 + 2 c2 x + 3 c3 x^2) must stay positive for every x = I1 - 3 >= 0, or the material
    # would offer no resistance to some finite deformation
    if c3 < 0 or (c2 < 0 and (c3 == 0 or c2 * c2 >= 3.0 * c3)):
        r.fail("c2_over_c1", f"with c3_over_c1 = {c3:g}, the energy stops rising with I1 at some strain "
                             f"(need c3_over_c1 >= 0 and c2_over_c1^2 < 3 c3_over_c1 when c2_over_c1 < 0)")
    return Hyperelastic("yeoh", c2, c3)


def _feature(r: "_Reader") -> SurfaceFeature:
    kind = r.string("kind")
    x_range = r.pair("x_range_m", bound=MAX_COORDINATE_M)
    if x_range[1] <= x_range[0]:
        r.fail("x_range_m", "upper bound must exceed lower bound")
    if kind == "half_cylinder":
        r.no_unknown({"kind", "x_range_m", "centre_y_m", "radius_m"})
        return SurfaceFeature(kind, x_range, centre_y_m=r.number("centre_y_m", bound=MAX_COORDINATE_M),
                              radius_m=r.bounded("radius_m", MAX_COORDINATE_M, "a feature of a bench phantom"))
    if kind == "slope":
        r.no_unknown({"kind", "x_range_m", "gradient", "origin_m"})
        return SurfaceFeature(kind, x_range, gradient=r.pair("gradient", bound=MAX_GRADIENT),
                              origin_m=r.pair("origin_m", (0.0, 0.0), bound=MAX_COORDINATE_M))
    if kind == "relief":
        r.no_unknown({"kind", "x_range_m", "rms_m", "wavelength_m", "seed"})
        wavelength = r.bounded("wavelength_m", RELIEF_WAVELENGTH_M[1], "a ripple, not a slope",
                               least=RELIEF_WAVELENGTH_M[0])
        seed = r.data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
            r.fail("seed", f"must be a non-negative integer, got {seed!r}")
        return SurfaceFeature(kind, x_range, rms_m=r.bounded("rms_m", MAX_RELIEF_RMS_M, "micro-relief"),
                              wavelength_m=wavelength, seed=seed)
    r.fail("kind", f"unknown surface feature {kind!r} (known: half_cylinder, slope, relief)")
    raise AssertionError


def _inclusion(r: "_Reader", phantom: Phantom) -> Inclusion:
    r.no_unknown({"centre_xy_m", "diameter_m", "youngs_modulus_pa", "depth_m", "height_m"})
    x, y = r.pair("centre_xy_m")
    if not (0 <= x <= phantom.length_m and 0 <= y <= phantom.width_m):
        r.fail("centre_xy_m",
               f"({x:g}, {y:g}) m lies outside the phantom's {phantom.length_m:g} x {phantom.width_m:g} m")
    d = r.bounded("diameter_m", phantom.thickness_m, "it must fit in the layer")
    radius = d / 2
    if not (radius <= x <= phantom.length_m - radius and radius <= y <= phantom.width_m - radius):
        r.fail("centre_xy_m", f"a {d * 1e3:g} mm sphere at ({x * 1e3:g}, {y * 1e3:g}) mm pokes out of the "
                              f"phantom's sides")
    has_depth, has_height = "depth_m" in r.data, "height_m" in r.data
    if has_depth == has_height:
        r.fail("depth_m", "give exactly one of depth_m (below the local surface) or height_m (above the table)")
    surface = float(phantom.surface_height_m(x, y))
    z = (surface - r.bounded("depth_m", phantom.thickness_m, "inside the layer") - radius if has_depth
         else r.bounded("height_m", phantom.thickness_m, "inside the layer"))
    key = "depth_m" if has_depth else "height_m"
    if z - radius < 0:
        r.fail(key, f"the sphere (centre {z * 1e3:.1f} mm above the table, {d * 1e3:g} mm across) goes through "
                    f"the table")
    # The sphere must stay under the surface everywhere over it, not only at its centre.
    ang = np.linspace(0.0, 2.0 * np.pi, 33)
    rad = np.linspace(0.0, radius, 9)
    px = x + np.outer(rad, np.cos(ang))
    py = y + np.outer(rad, np.sin(ang))
    top = z + np.sqrt(np.clip(radius**2 - (px - x) ** 2 - (py - y) ** 2, 0.0, None))
    clearance = float((phantom.surface_height_m(px, py) - top).min())
    if clearance < 0:
        r.fail(key, f"the sphere (centre {z * 1e3:.1f} mm above the table, {d * 1e3:g} mm across) breaks "
                    f"through the surface by {-clearance * 1e3:.2f} mm")
    return Inclusion(x, y, z, d, r.bounded("youngs_modulus_pa", MAX_MODULUS_PA, "stiffer than bone is not tissue",
                                           least=MIN_MODULUS_PA))


def _region(r: "_Reader", phantom: Phantom) -> tuple[float, float]:
    r.no_unknown({"centre_xy_m"})
    x, y = r.pair("centre_xy_m")
    if not (0 <= x <= phantom.length_m and 0 <= y <= phantom.width_m):
        r.fail("centre_xy_m", f"({x:g}, {y:g}) m lies outside the phantom")
    return (x, y)


class _Reader:
    """Typed access to one TOML table, with errors that name the full key."""

    def __init__(self, src: str, data: Any, prefix: str = ""):
        self.src, self.data, self.prefix = src, data, prefix

    def fail(self, key: str, problem: str):
        raise PhantomError(self.src, self.prefix + key, problem)

    def table(self, key: str) -> "_Reader":
        value = self.data.get(key)
        if not isinstance(value, dict):
            self.fail(key, "missing table" if value is None else "must be a table")
        return _Reader(self.src, value, f"{self.prefix}{key}.")

    def optional_table(self, key: str) -> "_Reader | None":
        return self.table(key) if key in self.data else None

    def choice(self, key: str, options: tuple[str, ...], default: str) -> str:
        value = self.string(key, default)
        if value not in options:
            self.fail(key, f"must be one of {', '.join(options)}, got {value!r}")
        return value

    def list_of_tables(self, key: str, most: int) -> list["_Reader"]:
        value = self.data.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            self.fail(key, "must be an array of tables ([[...]])")
        if len(value) > most:
            self.fail(key, f"{len(value)} of them; a bench phantom has at most {most}")
        return [_Reader(self.src, v, f"{self.prefix}{key}[{i}].") for i, v in enumerate(value)]

    def string(self, key: str, default: str | None = None) -> str:
        value = self.data.get(key, default)
        if not isinstance(value, str):
            self.fail(key, "missing" if value is None else f"must be a string, got {value!r}")
        return value

    def number(self, key: str, default: float | None = None, bound: float = math.inf) -> float:
        value = self.data.get(key, default)
        if value is None:
            self.fail(key, "missing")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(key, f"must be a finite number, got {value!r}")
        if not abs(value) <= bound:
            self.fail(key, f"must be within +-{bound:g}, got {value:g}")
        return float(value)

    def bounded(self, key: str, top: float, why: str, least: float = 0.0) -> float:
        """A number in (0, top], and at least ``least``."""
        v = self.positive(key)
        if v > top:
            self.fail(key, f"must be at most {top:g} ({why}), got {v:g}")
        if v < least:
            self.fail(key, f"must be at least {least:g}, got {v:g}")
        return v

    def positive(self, key: str) -> float:
        v = self.number(key)
        if v <= 0:
            self.fail(key, f"must be > 0, got {v:g}")
        return v

    def pair(self, key: str, default: tuple[float, float] | None = None,
             bound: float = MAX_COORDINATE_M) -> tuple[float, float]:
        value = self.data.get(key, default)
        if value is None:
            self.fail(key, "missing")
        if (not isinstance(value, (list, tuple)) or len(value) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in value)):
            self.fail(key, f"must be two finite numbers, got {value!r}")
        if not all(abs(v) <= bound for v in value):
            self.fail(key, f"must be two numbers within +-{bound:g}, got {value!r}")
        return (float(value[0]), float(value[1]))

    def no_unknown(self, known: set[str]) -> None:
        for key in self.data:
            if key not in known:
                self.fail(key, f"unknown key (known: {', '.join(sorted(known))})")
