"""How deep a tumour lies, from how it showed: the model-based depth with its 90 % interval.

The paper reads a tumour's depth off the TSI indentation at the first level where it shows (the rule in
:mod:`session.detect`). This module gives the second estimate issue 11 asks for: invert what the tumour
did to the elements with a forward model of the probe on a layer with a spherical inclusion.

**The forward model** is the project's own continuum mechanics (:mod:`tissue.mechanics`: finite
elements of a block bonded to its table, condensed onto its surface). A library (:func:`build_library`,
``make depth-library``, shipped in ``session/depth_library.npz``) holds, for a flat homogeneous block
40 mm long and as wide as the TSI is long, the nodal forces under the rigid face pressed evenly into it,
without and with one spherical inclusion under the middle of the TSI, for every combination of

* layer thickness 20 and 32 mm (interpolated between, held outside),
* depth of the sphere's top 0-12 mm, diameter 5-12 mm, modulus ratio 3-12 (:class:`LibraryGrid`): a tumour
  lies 1-12 mm deep at rest (``LEAST_DEPTH_M``), and the press carries a shallow one nearer the surface,
* the face's centre 0-4 mm along x from the tumour (an area's strip is 8 mm: every tumour lies within 4 mm
  of the centre of the area that covers it).

A second library (``depth_library_mould.npz``) holds the same layer with its lateral faces on a mould's
frictionless walls: the layer is as wide as the TSI is long, as the study's phantoms are and a phantom in its
casting tray is, and the walls hold the tissue a sphere would push aside, so a deep sphere shows far less
between them (8 mm deep, 10.25 mm across, 12 times stiffer: +0.18 against +0.31 under a free face's middle),
which the free layer's library read as a sphere 0.3-1.7 mm deeper. The analysis takes the library of the
sides its flat field's tissue has (:meth:`DepthModel.with_sides`; free where no model of the tissue says).
Linear elasticity makes the pattern independent of the tissue's modulus, so one solve per combination
serves every tissue. How far the face is pressed matters at finite strain: the tissue over a tumour thins.
The estimate takes that from the project's reduced finite-strain model, the simulated rig's
(tissue.mechanics.model; against a full nonlinear solve it explains most, not all, of how a
tumour's contrast grows with the press, so on real tissue the estimate can still read somewhat shallow):
a layer compressed by S = ``COMPRESSED_STRAIN`` carries a sphere of diameter a whose top lies d deep at
rest to d (1 - S) - a S / 2 (never out of the surface), and a level pressed to the nominal strain s sees
the contrast at rest and that one's mixed in proportion min(s, S) / S. How fast the press grows the
contrast that way is the reduced model's law's, and tissue has its own: on sessions forged from an
independent small-strain model the estimate read 1.0-2.9 mm deep, and in the validation study's realistic
world (a Yeoh law) tumours 3 and 8 mm deep read 1.4 and 2.9 mm shallow, their intervals short of the truth.
So what the press adds to the contrast at rest is scaled by a factor spread evenly over 1 - ``law_spread``
to 1 + ``law_spread`` (``DepthParams``; ``law_steps`` of them, 0.5 to 1.5 by default) and marginalised with a
uniform prior. Over the validation study's phantoms (seed 20261125) that spread took the intervals' coverage
from 13 to 15 of 15 tumours in the ideal world and from 8 to 9 of 10 in the realistic one with the array
calibrated, their median width from 2.8 to 3.2 and from 3.3 to 3.8 mm; a spread of 1 (small strain to twice
the growth) widened them to 4.0 and 4.2 mm and covered no more. What a tumour does to the rest of the face
(:meth:`DepthModel.signature`, which detection uses) is the reduced model's law's alone.

**The inversion** (:meth:`DepthModel.estimate`) takes the tumour's contrast in every area whose face
centre lay within 4 mm of it, averaged (inverse variance) over the levels that pressed every element near
it in ``STRAIN_BINS`` groups (the levels pressed least and those pressed most), and compares each with the
model's contrast of the same elements, averaged over the same levels with the same weights, each level's
as its strain (the near elements' median dL over the layer's thickness) mixes the states at rest and
compressed: the library's forces at the
tumour's offset from the face and along the array (shifted to its position, the rest of the face as in
homogeneous tissue), seen through the sensor's cover, each element's force over the homogeneous block's,
over the median of that ratio (the flat-field's own scale). The misfit counts each element's measured
uncertainty, a model error of the predicted contrast (``DepthParams.model_error``), and a floor; those
two are one and the same error in every group, so each group counts them as many times over as there are
groups. Most of an element's measured error is one and the same at every level of its area too: a real
array's offset is of the press, drawn when the element is loaded and kept through the ramp, and the rebuilt
tissue's error is of the place. How much, the session says (:func:`level_correlation`: the correlation of a
healthy element's contrast from one level to the next, 0.79 and 0.93 on the first sessions of the ideal and
the realistic world of the validation study); that share is not averaged away over the levels of a group,
and is one error across the area's groups (:func:`_level_mean`). Counted as independent, as it was before,
a real array's errors over a deep tumour's few elements read as its signature: on a held-out seed of the
realistic world tumours 6-9 mm deep read 2.8 mm shallow on average and the intervals covered 64 % of all
the truths; with the shared error, 1.1 mm and 91 % (docs/validation.md). Part of the model's error is one
scale on everything it predicts for the tumour (``DepthParams.scale_error``), shared by all its elements,
groups and areas. Both are relative to what the sphere that best explains the tumour predicts (found in a
first pass), the same for every sphere compared.
Elements on a side of the tissue (the outermost column of the palpated extent across the array, where
the tissue is taken to end, as the flat field takes it) are left out of it: the library's mid-array
signature shifted sideways knows no free side, which a stiff sphere near it unloads the more the face
presses (the simulated sessions of the validation study read -0.15 to -0.2 there, as their tissue model
does, where the shifted signature says +0.1 to +0.15), and fitting those elements drew tumours near a
side to a smaller, shallower sphere (3.3 mm deep read as 1.35 mm, 5.1 mm as 2.5 mm, their intervals
missing the truth).
Depth, diameter and modulus ratio are given a prior (uniform in depth over 1-12 mm and in diameter over
5-12 mm, log-uniform in ratio over 3-12, the sphere inside the layer with 1 mm to spare), the posterior is
evaluated on a grid (the library interpolated), and diameter and ratio are marginalised out: the estimate
is the posterior median of the depth, the interval its 5th to 95th percentiles. A tumour the library
cannot explain (a depth outside it, or thickness or array it was not built for) gets no estimate (NaN)
rather than a wrong one.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import time
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from session.detect import DepthParams
from tissue.mechanics.finite_strain import SIDES

if TYPE_CHECKING:
    from tissue.mechanics.fem import SchurStore

# shipped as package data beside this module, in a checkout and in an installed wheel alike: the layer's sides
# free, and held in a mould
LIBRARY_PATH = Path(str(resources.files(__package__).joinpath("depth_library.npz")))
LIBRARY_PATHS = {"free": LIBRARY_PATH,
                 "mould": Path(str(resources.files(__package__).joinpath("depth_library_mould.npz")))}
GAP_M = 0.5e-3  # how far beyond the library's farthest face offset a tumour is still read at it
SNAP_M = 0.25e-3  # spheres (and layers, and places across) within this of each other are one solve
# A solve stands in for a sphere whose contrast the library predicts within this share of the model's error of
# the solved one's, at most TWIN_Y_M across from it (DepthModel._twin); what they differ by is added to the
# signature's uncertainty, in quadrature with the model's error: at most 12 % wider (sqrt(1 + 0.5^2)).
TWIN_SHARE = 0.5
TWIN_Y_M = 1e-3
SIGNATURE_REACH_M = 12e-3  # a face whose centre lies farther along x from a sphere is taken not to feel it
LIBRARY_FORMAT = "palpation-console-depth-library"
LIBRARY_VERSION = 1
NU = 0.49  # as session.physics: nearly incompressible tissue and silicone
CLEARANCE_M = 1e-3  # tissue kept between the sphere and the table
STRAIN_BINS = 2  # the levels of an area are compared with the model in this many groups, by how far they pressed
# The shallowest a tumour's top is taken to lie at rest (the prior's, the validation study's). The library
# reaches shallower: a level pressed to 30 % strain carries a tumour 2 mm deep at rest to 0.5 mm, and a
# library that stopped at 1 mm under-predicted what it showed there, which read tumours 2-3 mm deep about
# a millimetre too shallow, their intervals short of the truth.
LEAST_DEPTH_M = 1e-3
HEALTHY_Z = 3.0  # an element this many standard deviations from homogeneous tissue is not counted as healthy
# The most of an element's error its levels are taken to share: the validation study's sessions read 0.79-0.93,
# and a session with few healthy elements to tell it from is not taken to leave its levels no error of their own.
MAX_LEVEL_CORRELATION = 0.95
REDUCED_LAW = np.array([1.0])  # the reduced finite-strain model's own law, as the simulated rig's
# called before each finite-element solve the cache does not hold, with what is solved in words: the analysis's
# progress, which may raise to stop the analysis there
Solving = Callable[[str], None]


@dataclass(frozen=True)
class LibraryGrid:
    """The configurations the library holds (lengths in m). The ranges are the validation study's
    distribution (app.study.StudyDistribution), which is what the console is meant to find."""

    thickness_m: tuple[float, ...] = (0.020, 0.032)
    # finer near the surface, where a sphere's contrast grows ever faster as it rises and its footprint
    # sharpens with its diameter: interpolated linearly between 1 and 2.5 mm, a 2 mm deep sphere read 1.1 mm
    depth_m: tuple[float, ...] = (0.0, 0.5e-3, 1e-3, 1.5e-3, 2e-3, 2.5e-3, 3.25e-3, 4e-3, 5e-3, 6e-3, 8e-3, 10e-3,
                                  12e-3)
    diameter_m: tuple[float, ...] = (5e-3, 6.75e-3, 8.5e-3, 10.25e-3, 12e-3)
    modulus_ratio: tuple[float, ...] = (3.0, 6.0, 12.0)
    offset_x_m: tuple[float, ...] = (0.0, 1e-3, 2e-3, 3e-3, 4e-3)
    length_m: float = 0.040
    rows: int = 4  # the TSI: rows along x, cols along y, pitch
    cols: int = 15
    pitch_m: float = 2e-3
    grid_m: float = 1e-3  # the mesh's node spacing (MeshSettings' default)

    @property
    def width_m(self) -> float:
        return self.cols * self.pitch_m

    @property
    def face_shape(self) -> tuple[int, int, int]:
        """(offsets, nodes along x, along y) of the face's nodal forces a solve gives: the face covers the
        layer's width."""
        return (len(self.offset_x_m), int(round(self.rows * self.pitch_m / self.grid_m)) + 1,
                int(round(self.width_m / self.grid_m)) + 1)

    @property
    def tumour_xy_m(self) -> tuple[float, float]:
        """Where the library's tumour sits: a node line, with room for every face offset on one side."""
        return round(self.length_m / 2 - 2e-3, 9), self.width_m / 2


def _block_solve(grid: LibraryGrid, thickness_m: float, inclusion: tuple[float, float, float] | None,
                 tumour_y_m: float | None = None, store: SchurStore | None = None, sides: str = "free") -> np.ndarray:
    """(offsets, face nodes along x, along y): the face's nodal forces at a unit indentation (per unit
    modulus) for each face offset; ``inclusion`` = (depth of its top, diameter, modulus ratio), at
    ``tumour_y_m`` across the block (default: the library's, mid-array); ``store`` keeps the finite elements'
    boxes for the next solve (most of a block is the same whatever its sphere); ``sides``: the block's lateral
    faces free, or held by a mould's frictionless walls (the layer is as wide as the face is long: its walls
    are where a phantom in its casting tray has them)."""
    from session.physics import SurfaceBlock
    from tissue.mechanics.model import MeshSettings, surface_compliance
    from tissue.phantom import Inclusion

    nx = int(round(grid.length_m / grid.grid_m)) + 1
    _, face_nodes, ny = grid.face_shape
    inclusions = ()
    if inclusion is not None:
        depth, diameter, ratio = inclusion
        x, y = grid.tumour_xy_m
        y = y if tumour_y_m is None else tumour_y_m
        inclusions = (Inclusion(x, y, thickness_m - depth - diameter / 2, diameter, ratio),)
    block = SurfaceBlock(np.full((nx, ny), thickness_m), grid.length_m, grid.width_m, 1.0, NU, inclusions)
    half = grid.rows * grid.pitch_m / 2
    tx = grid.tumour_xy_m[0]
    # every face position the offsets need, condensed at once: the other retained nodes carry no load
    compliance, nodes = surface_compliance(
        block, MeshSettings(spacing_m=grid.grid_m),
        keep=lambda x, _: (x >= tx - half - 1e-9) & (x <= tx + max(grid.offset_x_m) + half + 1e-9), store=store,
        sides=sides)
    out = np.empty(grid.face_shape)
    for k, off in enumerate(grid.offset_x_m):
        under = np.flatnonzero(np.abs(nodes[:, 0] - (tx + off)) <= half + 1e-9)
        forces = np.linalg.solve(compliance[np.ix_(under, under)], np.ones(len(under)))
        out[k] = forces.reshape(face_nodes, ny)  # the nodes come x-major: rows of x, columns of y
    return out


# bump when _block_solve changes what it returns: the cache's code digest covers the mechanics, not this module
SOLVE_VERSION = 1


def _kept_block_solve(grid: LibraryGrid, thickness_m: float, inclusion: tuple[float, float, float] | None,
                      tumour_y_m: float | None = None, solving: Solving | None = None,
                      store: SchurStore | None = None, sides: str = "free") -> np.ndarray:
    """:func:`_block_solve`, kept in the tissue model's cache: a session analysed again (a study re-analysed
    with other options, ``stitch`` run twice) asks for the same spheres, about 8 s of solves a case.
    ``solving(what)`` is called before a solve the cache does not hold (not for one it loads)."""
    from tissue.mechanics.cache import default_cache_dir
    from tissue.mechanics.model import cached

    # a free layer's key as it was before a mould's solves were asked for: the caches' free solves stay good
    described = json.dumps({"version": SOLVE_VERSION, "grid": asdict(grid), "thickness_m": thickness_m,
                            "inclusion": inclusion, "tumour_y_m": tumour_y_m,
                            **({} if sides == "free" else {"sides": sides})}, sort_keys=True)

    def check(arrays):
        if np.shape(arrays["forces"]) != grid.face_shape:
            raise ValueError("inconsistent cache entry")

    def solve():
        if solving is not None:
            solving("block without a sphere" if inclusion is None else f"sphere {inclusion[0] * 1e3:.1f} mm deep")
        return {"forces": _block_solve(grid, thickness_m, inclusion, tumour_y_m, store, sides)}

    return cached(default_cache_dir(), "depth-" + hashlib.sha256(described.encode()).hexdigest()[:24], solve,
                  check)["forces"]


def build_library(path: Path = LIBRARY_PATH, grid: LibraryGrid = LibraryGrid(),
                  progress: Callable[[str], None] | None = None, sides: str = "free") -> Path:
    """Solve every configuration of ``grid`` with the layer's ``sides`` free or in a mould and write the library
    to ``path`` (a few minutes of one core per thickness); configurations whose sphere would not fit in the
    layer are NaN."""
    from tissue.mechanics.fem import SchurStore

    store = SchurStore()  # each sphere's block shares every box its sphere is not in with the one before
    shape = (len(grid.thickness_m), len(grid.depth_m), len(grid.diameter_m), len(grid.modulus_ratio))
    face = grid.face_shape
    homogeneous = np.empty((len(grid.thickness_m), *face))
    inclusion = np.full((*shape, *face), np.nan)
    started = time.perf_counter()
    for t, h in enumerate(grid.thickness_m):
        homogeneous[t] = _block_solve(grid, h, None, store=store, sides=sides)
        for index in np.ndindex(shape[1:]):
            d, a, r = (grid.depth_m[index[0]], grid.diameter_m[index[1]], grid.modulus_ratio[index[2]])
            if h - d - a < CLEARANCE_M:
                continue
            inclusion[(t, *index)] = _block_solve(grid, h, (d, a, r), store=store, sides=sides)
            if progress is not None:
                progress(f"h {h * 1e3:.0f} mm, depth {d * 1e3:g} mm, diameter {a * 1e3:g} mm, ratio {r:g} "
                         f"({time.perf_counter() - started:.0f} s)")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path, format=np.array(LIBRARY_FORMAT), version=np.array(LIBRARY_VERSION), sides=np.array(sides),
        thickness_m=np.array(grid.thickness_m), depth_m=np.array(grid.depth_m),
        diameter_m=np.array(grid.diameter_m), modulus_ratio=np.array(grid.modulus_ratio),
        offset_x_m=np.array(grid.offset_x_m), geometry=np.array([grid.length_m, grid.rows, grid.cols,
                                                                  grid.pitch_m, grid.grid_m]),
        homogeneous=homogeneous.astype(np.float32), inclusion=inclusion.astype(np.float32))
    return path


class DepthModelError(ValueError):
    """The library cannot be used (missing, damaged, another array); the message says why in one line."""


@dataclass(frozen=True)
class _Library:
    thickness_m: np.ndarray
    depth_m: np.ndarray
    diameter_m: np.ndarray
    modulus_ratio: np.ndarray
    offset_x_m: np.ndarray
    rows: int
    cols: int
    pitch_m: float
    grid_m: float
    homogeneous: np.ndarray  # (thickness, offset, face nodes x, face nodes y)
    inclusion: np.ndarray  # (thickness, depth, diameter, ratio, offset, face nodes x, face nodes y)
    sides: str = "free"  # the layer's lateral faces (a library that does not say was built with them free)


def load_library(path: Path = LIBRARY_PATH) -> _Library:
    """The library at ``path``, checked; raises :class:`DepthModelError`."""
    try:
        # our own handle: np.load leaves its own open when the file is not an archive
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise DepthModelError(f"depth model library {path}: cannot be read ({err})") from None
    if str(arrays.get("format", "")) != LIBRARY_FORMAT or int(arrays.get("version", -1)) != LIBRARY_VERSION:
        raise DepthModelError(f"depth model library {path}: not a version {LIBRARY_VERSION} {LIBRARY_FORMAT} file")
    try:
        length, rows, cols, pitch, grid = (float(v) for v in arrays["geometry"])
        axes = [np.asarray(arrays[k], float) for k in ("thickness_m", "depth_m", "diameter_m", "modulus_ratio",
                                                         "offset_x_m")]
        face = (int(round(rows * pitch / grid)) + 1, int(round(cols * pitch / grid)) + 1)
        homogeneous = np.asarray(arrays["homogeneous"], float)
        inclusion = np.asarray(arrays["inclusion"], float)
        sides = str(arrays.get("sides", "free"))
    except (KeyError, ValueError, TypeError) as err:
        raise DepthModelError(f"depth model library {path}: incomplete ({err})") from None
    if (homogeneous.shape != (len(axes[0]), len(axes[4]), *face)
            or inclusion.shape != (*(len(a) for a in axes[:4]), len(axes[4]), *face)
            or any(len(a) < 2 or np.any(np.diff(a) <= 0) for a in axes[:4])
            or not np.all(np.isfinite(homogeneous)) or not np.all(homogeneous > 0)):
        raise DepthModelError(f"depth model library {path}: its arrays do not fit its axes")
    if sides not in SIDES:
        raise DepthModelError(f"depth model library {path}: built for sides {sides!r}, not one of {', '.join(SIDES)}")
    return _Library(*axes, int(rows), int(cols), pitch, grid, homogeneous, inclusion, sides)


def _lerp_axis(values: np.ndarray, axis: np.ndarray, at: np.ndarray, dim: int) -> np.ndarray:
    """``values`` interpolated linearly along dimension ``dim`` (tabulated at ``axis``) to points ``at``."""
    k = np.clip(np.searchsorted(axis, at) - 1, 0, len(axis) - 2)
    w = np.clip((at - axis[k]) / (axis[k + 1] - axis[k]), 0.0, 1.0)
    lo, hi = np.take(values, k, axis=dim), np.take(values, k + 1, axis=dim)
    shape = [1] * values.ndim
    shape[dim] = len(at)
    return lo * (1 - w.reshape(shape)) + hi * w.reshape(shape)


class DepthModel:
    """The inversion of one session's tumours (module docstring): the library, and what the session says of
    its array (pitch, shape, the cover that spreads each element's load) and its table."""

    contrast_floor = 0.02  # absolute, per element
    reach_m = 6e-3  # elements nearer the tumour than this carry its signature
    depth_step_m = 0.25e-3
    fine_diameters = 8
    fine_ratios = 7
    law_steps = 5  # the laws marginalised, evenly spread (DepthParams.law_spread)

    def __init__(self, library: _Library, shape: tuple[int, int], pitch_m: float, table_height_m: float,
                 cover: Callable[[np.ndarray], np.ndarray] | None = None, params: DepthParams = DepthParams(),
                 sides: str = "free"):
        if (library.rows, library.cols) != tuple(shape) or abs(library.pitch_m - pitch_m) > 1e-9:
            raise DepthModelError(f"the depth model was built for a {library.rows} x {library.cols} array at "
                                  f"{library.pitch_m * 1e3:g} mm, this session's is {shape[0]} x {shape[1]} at "
                                  f"{pitch_m * 1e3:g} mm")
        from tissue.mechanics.contact import tributary_weights
        from tissue.mechanics.fem import SchurStore
        from tissue.mechanics.model import COMPRESSED_STRAIN

        self.library = library
        self.sides = sides  # the layer's lateral faces, free or in a mould: the library's and every solve's
        self._libraries = {sides: library}  # what with_sides takes; the others loaded when first asked for
        self.shape = tuple(shape)
        self.pitch_m = pitch_m
        self.table_height_m = table_height_m
        self.cover = cover
        self._set(params)
        # the finite-element solves of :meth:`signature`, shared with every copy :meth:`with_params` makes
        self._solves: dict = {}
        self._patterns: dict = {}  # what the library predicts of each sphere asked for (:meth:`_twin`)
        self._homogeneous: dict = {}
        # the boxes of those solves' finite elements, kept for the next (most of a block is the same whatever
        # its sphere): each sphere after the first solved about 30 % sooner, for up to the store's budget of
        # memory (256 MB) held as long as the model is
        self._store = SchurStore()
        nx, ny = library.homogeneous.shape[-2:]
        xs, ys = np.meshgrid(np.arange(nx) * library.grid_m, np.arange(ny) * library.grid_m, indexing="ij")
        self._weights = tributary_weights(xs.ravel(), ys.ravel(), (0.0, xs.max(), 0.0, ys.max()), (0.0, 0.0),
                                          pitch_m, self.shape)
        lib = library
        self.depths = np.arange(lib.depth_m[0], lib.depth_m[-1] + 1e-9, self.depth_step_m)
        self.least_depth_m = max(LEAST_DEPTH_M, float(lib.depth_m[0]))
        self.compressed_strain = COMPRESSED_STRAIN
        self.diameters = np.linspace(lib.diameter_m[0], lib.diameter_m[-1], self.fine_diameters)
        self.ratios = np.exp(np.linspace(math.log(lib.modulus_ratio[0]), math.log(lib.modulus_ratio[-1]),
                                         self.fine_ratios))

    def with_params(self, params: DepthParams) -> DepthModel:
        """This model with ``params`` (the library and the solves made so far shared)."""
        out = copy.copy(self)
        out._set(params)
        return out

    def with_sides(self, sides: str) -> DepthModel:
        """This model for tissue whose sides are ``sides`` (:data:`SIDES`): itself where they are its own, else
        one on that library, with solves of its own (a mould's walls change every sphere's contrast: one 8 mm
        deep, 10.25 mm across and 12 times stiffer, at +0.31 under a free face's middle, makes +0.18 between a
        mould's walls, which the free layer reads as a sphere 1.4 mm deeper). Raises :class:`DepthModelError`
        where that library cannot be used."""
        if sides == self.sides:
            return self
        if sides not in LIBRARY_PATHS:
            raise DepthModelError(f"no depth model library for sides {sides!r} (known: {', '.join(SIDES)})")
        if sides not in self._libraries:
            self._libraries[sides] = load_library(LIBRARY_PATHS[sides])
        library = self._libraries[sides]
        if library.sides != sides:
            raise DepthModelError(f"depth model library {LIBRARY_PATHS[sides]}: built for sides {library.sides!r}, "
                                  f"not {sides!r}")
        out = DepthModel(library, self.shape, self.pitch_m, self.table_height_m, self.cover, self.params, sides)
        out._libraries = self._libraries
        return out

    def _set(self, params: DepthParams) -> None:
        self.params = params
        self.model_error = params.model_error
        self.scale_error = params.scale_error
        # each law as how fast it grows a tumour's contrast with the press, over the reduced model's
        self.law_factors = 1.0 + params.law_spread * np.linspace(-1.0, 1.0, self.law_steps if params.law_spread else 1)

    @classmethod
    def for_session(cls, session, path: Path = LIBRARY_PATH) -> DepthModel:
        return cls._described(session, tuple(session.levels.dtype["pressure_pa"].shape), session.pitch_m, path)

    @classmethod
    def for_info(cls, info, path: Path = LIBRARY_PATH) -> DepthModel:
        """For the session being recorded (a :class:`session.info.SessionInfo`): the live console's findings."""
        calibration = info.calibration
        return cls._described(info, (int(calibration["rows"]), int(calibration["cols"])),
                              float(calibration["pitch_m"]), path)

    @classmethod
    def _described(cls, described, shape: tuple[int, int], pitch_m: float, path: Path) -> DepthModel:
        from session.physics import cover_for

        model = cls(load_library(path), shape, pitch_m, float(described.calibration.get("table_height_m", 0.0)),
                    cover_for(described, shape, pitch_m))
        # the other sides' libraries read now: a damaged one is told before the analysis, not half-way through it
        model._libraries.update({sides: load_library(other) for sides, other in LIBRARY_PATHS.items()
                                 if sides != model.sides})
        return model

    # ---- the forward model ----

    def _elements(self, nodal: np.ndarray) -> np.ndarray:
        forces = np.einsum("en,...n->...e", self._weights, nodal.reshape(*nodal.shape[:-2], -1))
        forces = forces.reshape(*nodal.shape[:-2], *self.shape)
        return forces if self.cover is None else self.cover(forces)

    def predict(self, thickness_m: float, offset_x_m: float, tumour_y_m: float) -> np.ndarray:
        """(depth, diameter, ratio, rows, cols) contrast on the library's axes for a tumour ``offset_x_m``
        before the face's centre along x (face centre minus tumour) and ``tumour_y_m`` from the face's first
        column edge; NaN where the library holds no solve."""
        lib = self.library
        t = np.clip(np.searchsorted(lib.thickness_m, thickness_m) - 1, 0, len(lib.thickness_m) - 2)
        w = float(np.clip((thickness_m - lib.thickness_m[t]) / (lib.thickness_m[t + 1] - lib.thickness_m[t]), 0, 1))
        out = []
        for tk, wk in ((t, 1.0 - w), (t + 1, w)):
            out.append((self._predict_at(tk, abs(offset_x_m), tumour_y_m), wk))
        (a, wa), (b, wb) = out
        # a sphere that fits only the thicker layer is taken from it alone
        blended = np.where(np.isfinite(a) & np.isfinite(b), wa * a + wb * b, np.where(np.isfinite(a), a, b))
        return blended[..., ::-1, :] if offset_x_m < 0 else blended

    def _predict_at(self, t: int, offset_m: float, tumour_y_m: float) -> np.ndarray:
        lib = self.library
        hom = _lerp_axis(lib.homogeneous[t], lib.offset_x_m, np.array([offset_m]), 0)[0]
        inc = _lerp_axis(lib.inclusion[t], lib.offset_x_m, np.array([offset_m]), 3)[:, :, :, 0]
        ratio = inc / hom
        # the library's tumour lies mid-array; move its disturbance to where this one is, node by node
        shift = (tumour_y_m - lib.cols * lib.pitch_m / 2) / lib.grid_m
        lo = int(math.floor(shift))
        frac = shift - lo
        moved = (1 - frac) * _shift_y(ratio, lo) + frac * _shift_y(ratio, lo + 1)
        q = self._elements(hom * moved) / self._elements(hom)
        scale = np.median(q.reshape(*q.shape[:-2], -1), axis=-1)[..., None, None]  # NaN where no solve
        return q / scale - 1.0

    def _fine(self, coarse: np.ndarray, depths=None, diameters=None, ratios=None) -> np.ndarray:
        """``coarse`` (on the library's depth, diameter and ratio axes) at the given ones (default: the fine
        grid's)."""
        lib = self.library
        fine = _lerp_axis(coarse, lib.depth_m, self.depths if depths is None else np.asarray(depths), 0)
        fine = _lerp_axis(fine, lib.diameter_m, self.diameters if diameters is None else np.asarray(diameters), 1)
        return _lerp_axis(fine, np.log(lib.modulus_ratio),
                          np.log(self.ratios if ratios is None else np.asarray(ratios)), 2)

    def _moved_m(self, depth_m, diameter_m: float):
        """Where the layer compressed by ``COMPRESSED_STRAIN`` carries the top of a sphere ``depth_m`` deep at
        rest (tissue.mechanics.model.compressed_material), within the library."""
        strain = self.compressed_strain
        return np.clip(np.asarray(depth_m) * (1.0 - strain) - 0.5 * diameter_m * strain, self.depths[0],
                       self.depths[-1])

    def _mix(self, strain):
        """How much of the compressed state's contrast a level pressed to the nominal ``strain`` sees."""
        return np.clip(strain, 0.0, self.compressed_strain) / self.compressed_strain

    def _pressed(self, fine: np.ndarray, strain: np.ndarray, weights: np.ndarray, laws: np.ndarray) -> np.ndarray:
        """The contrast ``fine`` (depth, diameter, ratio, elements) as the levels pressed to ``strain`` saw
        it (the module docstring), averaged with the levels' ``weights`` (level, element), for each of
        ``law_factors``: (law, depth, diameter, ratio, elements)."""
        mix = self._mix(np.asarray(strain))[:, None]
        total, compressed = weights.sum(axis=0), (mix * weights).sum(axis=0)
        grown = np.empty_like(fine)  # what the press adds to the contrast at rest, at the reduced model's law
        for j, diameter in enumerate(self.diameters):
            at = (self._moved_m(self.depths, diameter) - self.depths[0]) / self.depth_step_m
            lo = np.minimum(np.floor(at).astype(int), len(self.depths) - 2)
            frac = (at - lo)[:, None, None]
            moved = (1.0 - frac) * fine[lo, j] + frac * fine[lo + 1, j]
            grown[:, j] = compressed * (moved - fine[:, j])
        return (total * fine)[None] + laws[:, None, None, None, None] * grown[None]

    # ---- the inversion ----

    def estimate(self, tumour, levels: np.ndarray, contrast) -> tuple[float, float, float]:
        """(depth, 5th percentile, 95th percentile) of the tumour's depth in m (module docstring); NaNs when
        no area pressed it near enough its face's centre or the library cannot explain what it showed."""
        posterior = self._posterior(tumour, levels, contrast, self.law_factors)
        if posterior is None:
            return math.nan, math.nan, math.nan
        log_post, _ = posterior
        post = np.exp(log_post - log_post.max()).sum(axis=(0, 2, 3))
        cdf = np.cumsum(post) / post.sum()
        # each grid depth stands for the bin around it: read the percentiles off the bins' edges
        edges = np.concatenate([[self.depths[0] - self.depth_step_m / 2], self.depths + self.depth_step_m / 2])
        cdf = np.concatenate([[0.0], cdf])
        low, median, high = np.interp([0.05, 0.5, 0.95], cdf, edges)
        return float(median), float(max(low, self.least_depth_m)), float(min(high, self.depths[-1]))

    def _posterior(self, tumour, levels: np.ndarray, contrast, laws: np.ndarray) -> tuple[np.ndarray, float] | None:
        """(log posterior on the fine (depth, diameter, ratio) grid, -inf where the sphere does not fit;
        the layer's thickness in m), or None when nothing can be said."""
        from tissue.face import element_offsets_m

        offsets = element_offsets_m(self.shape[0], self.shape[1], self.pitch_m)
        across = levels["tsi_position_m"][:, 1:2] + offsets[0, :, 1][None, :]  # every element centre, across
        sides = (float(across.min()), float(across.max()))
        terms = []
        thickness = []
        rho = level_correlation(levels, contrast)
        for region in np.unique(levels["region"]):
            rows = np.flatnonzero(levels["region"] == region)
            centre = levels["tsi_position_m"][rows[-1]]
            off_x = float(centre[0]) - tumour.x_m
            y_from_edge = tumour.y_m - (float(centre[1]) - self.shape[1] * self.pitch_m / 2)
            # Areas laid to cover a tissue leave gaps of a few tenths of a millimetre between them: a tumour
            # fitted in one is read as lying at the library's farthest offset, the face's edge.
            if (abs(off_x) > self.library.offset_x_m[-1] + GAP_M
                    or not 0.0 <= y_from_edge <= self.shape[1] * self.pitch_m):
                continue
            off_x = float(np.clip(off_x, -self.library.offset_x_m[-1], self.library.offset_x_m[-1]))
            element_y = offsets[..., 1] + float(centre[1])
            near = ((np.hypot(offsets[..., 0] + float(centre[0]) - tumour.x_m, element_y - tumour.y_m) <= self.reach_m)
                    & (element_y > sides[0] + self.pitch_m / 2) & (element_y < sides[1] - self.pitch_m / 2))
            c, s = contrast.contrast[rows][:, near], contrast.sigma[rows][:, near]
            whole = np.flatnonzero(np.all(np.isfinite(c) & np.isfinite(s) & (s > 0), axis=1))
            onset = levels["onset_height_m"][rows[-1]][near] - self.table_height_m
            if not len(whole) or not np.isfinite(onset).any():
                continue
            h = float(np.nanmedian(onset))
            thickness.append(h)
            strain = np.zeros(len(rows))  # a level that did not press every element near it plays no part
            strain[whole] = np.nan_to_num(np.nanmedian(levels["dL_m"][rows[whole]][:, near], axis=1) / h)
            fine = self._fine(self.predict(h, off_x, y_from_edge))[..., near]
            # The levels pressed least and most, each averaged: how a tumour's contrast grows with the press
            # tells its depth apart from its size and stiffness, which one average of every level blurs (a
            # sphere 2 mm deep read 1.7 mm, 1.4-1.9). The model's error is one and the same in each, so each
            # counts it that many times over, and together they are as sure of it as one average is.
            by_strain = whole[np.argsort(strain[whole], kind="stable")]
            bins = [b for b in np.array_split(by_strain, STRAIN_BINS) if len(b)]
            area = []
            for b in bins:
                measured, own, shared, weights = _level_mean(c[b], s[b], rho)
                area.append((measured, own, shared, self._pressed(fine, strain[b], weights, laws)))
            terms.append(area)
        if not terms:
            return None
        h = float(np.median(thickness))
        d, a = np.meshgrid(self.depths, self.diameters, indexing="ij")
        sphere_fits = ((h - d - a >= CLEARANCE_M) & (d >= self.least_depth_m - 1e-12))[None, :, :, None]
        # The model's error is relative to the contrast it predicts. Taken from each sphere's own
        # prediction, it favoured the spheres that predict less than was measured (a wider allowance for
        # their own misfit: at 25 % error the best sphere predicted 6 % less), that is, deeper ones. It is
        # taken from the sphere that best explains the tumour that way, the same for every sphere compared.
        log_like = self._own_log_like(terms)
        fits = sphere_fits & np.isfinite(log_like)
        if not fits.any():
            return None
        mode = np.unravel_index(int(np.argmax(np.where(fits, log_like, -np.inf))), log_like.shape)
        log_like = self._log_like(terms, mode)
        fits = sphere_fits & np.isfinite(log_like)
        if not fits.any():
            return None
        return np.where(fits, log_like, -np.inf), h

    def _own_log_like(self, terms) -> np.ndarray:
        """The log likelihood on the fine grid of the areas' level groups ``terms``, the model's error relative
        to each sphere's own prediction: independent per element and group, but for the part of the measured
        error an element's levels share (:func:`_level_mean`), one per element across its area's groups."""
        out = 0.0
        for area in terms:
            groups = len(area)
            quad = logdet = along = shared2 = 0.0
            for measured, own, shared, predicted in area:
                variance = self._variance(own, groups, predicted)
                residual = measured - predicted
                quad = quad + residual**2 / variance
                along = along + shared * residual / variance
                shared2 = shared2 + shared**2 / variance
                logdet = logdet + np.log(variance)
            out = out - 0.5 * np.sum(quad - along**2 / (1.0 + shared2) + logdet + np.log1p(shared2), axis=-1)
        return out

    def _variance(self, own: np.ndarray, groups: int, predicted: np.ndarray) -> np.ndarray:
        """Each element's variance in one of ``groups`` level groups that is its own: the measured error its
        levels do not share, and the model's error relative to ``predicted`` and its floor, counted once per
        group (module docstring)."""
        return own**2 + groups * ((self.model_error * predicted) ** 2 + self.contrast_floor**2)

    def _log_like(self, terms, mode: tuple[int, ...]) -> np.ndarray:
        """The log likelihood on the fine grid (up to a constant) of the areas' level groups ``terms``, the
        model's errors relative to what the sphere at ``mode`` predicts (p). The covariance is D, diagonal
        (:meth:`_variance`), plus each element's shared measured error u u^T across its area's groups
        (:func:`_level_mean`), plus ``scale_error`` on p shared by all, s^2 p p^T. The first two, B, invert
        element by element and the last on top of them, each by Sherman-Morrison:
        r^T B^-1 r - s^2 (p^T B^-1 r)^2 / (1 + s^2 p^T B^-1 p)."""
        chi2 = along = norm = 0.0
        for area in terms:
            groups = len(area)
            rr = pr = pp = ur = up = uu = 0.0
            for measured, own, shared, predicted in area:
                p = predicted[mode]
                variance = self._variance(own, groups, p)
                residual = measured - predicted
                rr = rr + residual**2 / variance
                pr = pr + p * residual / variance
                pp = pp + p**2 / variance
                ur = ur + shared * residual / variance
                up = up + shared * p / variance
                uu = uu + shared**2 / variance
            chi2 = chi2 + np.sum(rr - ur**2 / (1.0 + uu), axis=-1)
            along = along + np.sum(pr - up * ur / (1.0 + uu), axis=-1)
            norm += float(np.sum(pp - up**2 / (1.0 + uu)))
        s2 = self.scale_error**2
        return -0.5 * (chi2 - s2 * along**2 / (1.0 + s2 * norm))

    # ---- what a tumour does to the rest of the face ----

    def signature(self, tumour, levels: np.ndarray, contrast, records: np.ndarray, solving: Solving | None = None
                  ) -> tuple[np.ndarray, np.ndarray] | None:
        """(contrast, its uncertainty), each (len(records), rows, cols): what the sphere that best explains
        the tumour (the posterior's mode) does to every element of each of ``records``' faces, solved where
        it lies across the tissue (the library's mid-array signature shifted sideways knows no side: a
        stiff sphere 11 mm from one side of the tissue raises the far side's elements by +0.05 and lowers
        the near side's by 0.09, which the shifted signature puts at 0), as each record's strain mixes
        its states at rest and compressed (the module docstring), through the sensor's cover; the
        uncertainty is the model's relative error, and what a twin that stands in for a sphere differs from it
        by (:meth:`_twin`), in quadrature. None when the tumour has no fit; zero, fit or none, for a
        face beyond ``SIGNATURE_REACH_M``. A finite-element solve of the block per depth and offset, cached;
        ``solving(what)`` before each one the cache does not hold."""
        if all(abs(float(levels["tsi_position_m"][r][0]) - tumour.x_m) > SIGNATURE_REACH_M for r in records):
            return np.zeros((len(records), *self.shape)), np.zeros((len(records), *self.shape))
        posterior = self._posterior(tumour, levels, contrast, REDUCED_LAW)
        if posterior is None:
            return None
        log_post, h = posterior
        _, i, j, k = np.unravel_index(int(np.argmax(log_post)), log_post.shape)
        depth, diameter, ratio = float(self.depths[i]), float(self.diameters[j]), float(self.ratios[k])
        out = np.zeros((len(records), *self.shape))
        error = np.zeros(len(records))
        for n, r in enumerate(records):
            centre = levels["tsi_position_m"][r]
            off_x = float(centre[0]) - tumour.x_m
            y_from_edge = tumour.y_m - (float(centre[1]) - self.shape[1] * self.pitch_m / 2)
            mix = float(self._mix(np.nan_to_num(np.nanmedian(levels["dL_m"][r]) / h)))
            moved = float(self._moved_m(depth, diameter))
            (at_rest, off_rest), (compressed, off_compressed) = (
                self._solved(h, d, diameter, ratio, off_x, y_from_edge, solving) for d in (depth, moved))
            out[n] = (1.0 - mix) * at_rest + mix * compressed
            error[n] = max(off_rest, off_compressed)
        return out, np.hypot(self.model_error, error)[:, None, None] * np.abs(out)

    def _solved(self, thickness_m: float, depth_m: float, diameter_m: float, ratio: float, offset_x_m: float,
                tumour_y_m: float, solving: Solving | None = None) -> tuple[np.ndarray, float]:
        """The contrast one sphere makes on a face ``offset_x_m`` from it (face centre minus tumour) whose
        first column's edge lies ``tumour_y_m`` from it across, the layer as wide as the face is long (none
        beyond ``SIGNATURE_REACH_M``), and how far off it may be relative to its largest value where a
        twin's solve stands in for it (:meth:`_twin`; 0 for its own)."""
        from dataclasses import replace

        if abs(offset_x_m) > SIGNATURE_REACH_M:
            return np.zeros(self.shape), 0.0
        key = tuple(round(v / SNAP_M) for v in (thickness_m, depth_m, diameter_m, tumour_y_m)) + (round(ratio, 1),)
        cache = self._solves
        if key not in cache:
            t, d, a, y = (v * SNAP_M for v in key[:4])
            a = min(a, max(t - d - CLEARANCE_M, 0.5e-3))
            y = min(max(y, a / 2), self.shape[1] * self.pitch_m - a / 2)
            pattern = self._library_pattern(t, d, a, key[4], y)
            twin = self._twin(key, pattern)
            if twin is not None:
                cache[key] = (cache[twin[0]][0], twin[1])
            else:
                # every whole-millimetre offset at once: the face's edges stay on the mesh's node lines
                grid = replace(LibraryGrid(), offset_x_m=tuple(np.arange(0.0, SIGNATURE_REACH_M + 1e-9, 1e-3)))
                q = self._elements(_kept_block_solve(grid, t, (d, a, ratio), tumour_y_m=y, solving=solving,
                                                     store=self._store, sides=self.sides)
                                   ) / self._elements(self._homogeneous_solve(t, grid, solving))
                cache[key] = (q / np.median(q.reshape(len(q), -1), axis=1)[:, None, None] - 1.0, 0.0)
                if np.all(np.isfinite(pattern)):
                    self._patterns[key] = pattern
        solved, error = cache[key]
        out = _lerp_axis(solved, np.arange(len(solved)) * 1e-3, np.array([abs(offset_x_m)]), 0)[0]
        return (out[::-1] if offset_x_m < 0 else out), error

    def _library_pattern(self, thickness_m: float, depth_m: float, diameter_m: float, ratio: float,
                         tumour_y_m: float) -> np.ndarray:
        """(library offsets, rows, cols): the contrast the library predicts of one sphere on the faces it
        holds, NaN where it holds none."""
        return np.array([self._fine(self.predict(thickness_m, off, tumour_y_m), [depth_m], [diameter_m],
                                    [ratio])[0, 0, 0] for off in self.library.offset_x_m])

    def _twin(self, key: tuple, pattern: np.ndarray) -> tuple[tuple, float] | None:
        """(its key, how far apart they are relative to the largest of ``pattern``) of the sphere solved
        already whose contrast the library predicts nearest ``key``'s (``pattern``), if within ``TWIN_SHARE``
        of the model's error at every element, on a layer within ``SNAP_M`` as thick and at most ``TWIN_Y_M``
        across from it: its solve stands in for this one's; else None. The posterior of a deep or wide
        tumour is a ridge along which depth, size and stiffness trade off, and its mode moves along it from
        one sweep of the fits to the next and from one map to the other: on s20261125-0008, two tumours asked
        for 42 spheres, of which 18 now stand in for one another (24 solves, was 42)."""
        if not np.all(np.isfinite(pattern)):
            return None
        scale = max(float(np.abs(pattern).max()), self.contrast_floor)
        near = [(float(np.abs(seen - pattern).max()) / scale, other) for other, seen in self._patterns.items()
                if abs(other[0] - key[0]) <= 1 and abs(other[3] - key[3]) * SNAP_M <= TWIN_Y_M + 1e-12]
        if not near:
            return None
        apart, other = min(near)
        return (other, apart) if apart <= TWIN_SHARE * self.model_error else None

    def _homogeneous_solve(self, thickness_m: float, grid: LibraryGrid, solving: Solving | None = None
                           ) -> np.ndarray:
        cache = self._homogeneous
        key = round(thickness_m, 6)
        if key not in cache:
            cache[key] = _kept_block_solve(grid, thickness_m, None, solving=solving, store=self._store,
                                           sides=self.sides)
        return cache[key]


def _shift_y(ratio: np.ndarray, nodes: int) -> np.ndarray:
    """``ratio`` moved ``nodes`` along its last axis, homogeneous (1) where it moved in from beyond."""
    out = np.ones_like(ratio)
    n = ratio.shape[-1]
    if abs(nodes) >= n:
        return out
    if nodes >= 0:
        out[..., nodes:] = ratio[..., :n - nodes]
    else:
        out[..., :n + nodes] = ratio[..., -nodes:]
    return out


def _level_mean(contrast: np.ndarray, sigma: np.ndarray, rho: float):
    """The inverse-variance mean over levels (first axis) of each element's contrast; the standard deviation
    of its error that is its own and the one it shares with the element's other levels, when a fraction
    ``rho`` of each level's variance is shared by all the area's levels (equicorrelated); and each level's
    weight per element."""
    precision = 1.0 / sigma**2
    weights = precision / precision.sum(axis=0)
    own = np.sqrt((1.0 - rho) * np.sum(weights**2 * sigma**2, axis=0))
    shared = math.sqrt(rho) * np.sum(weights * sigma, axis=0)
    return (contrast * weights).sum(axis=0), own, shared, weights


def level_correlation(levels: np.ndarray, contrast) -> float:
    """How much of a healthy element's error one level of an area shares with the next: the correlation of
    the standardised contrasts of the same element at consecutive levels of an area, over the session's
    elements that read as healthy tissue at both (|z| < ``HEALTHY_Z``), within [0, ``MAX_LEVEL_CORRELATION``];
    0, every level's error its own as before, with fewer than 30 such pairs to read it from. A real array's errors
    are mostly of the press, not of the frame (an element's offset is drawn when it is loaded and kept
    through the area's ramp), and the rebuilt tissue's errors are of the place: averaging levels does not
    average them away."""
    z = contrast.contrast / contrast.sigma
    first, second = [], []
    for region in np.unique(levels["region"]):
        rows = np.flatnonzero(levels["region"] == region)
        a, b = z[rows[:-1]].ravel(), z[rows[1:]].ravel()
        ok = np.isfinite(a) & np.isfinite(b) & (np.abs(a) < HEALTHY_Z) & (np.abs(b) < HEALTHY_Z)
        first.append(a[ok])
        second.append(b[ok])
    a, b = np.concatenate(first), np.concatenate(second)
    if len(a) < 30 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.clip(np.corrcoef(a, b)[0, 1], 0.0, MAX_LEVEL_CORRELATION))


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m session.depth",
                                     description="Rebuild the depth model's library of finite-element solves.")
    parser.add_argument("--sides", choices=SIDES, default="free",
                        help="the layer's lateral faces free (default) or held in a mould")
    parser.add_argument("--out", type=Path, help=f"where to write it (default {LIBRARY_PATH} for free sides, "
                                                 f"{LIBRARY_PATHS['mould']} for a mould)")
    args = parser.parse_args(argv)
    built = build_library(args.out or LIBRARY_PATHS[args.sides], progress=lambda line: print(line, flush=True),
                          sides=args.sides)
    print(f"wrote {built}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
