"""The continuum tissue model the simulated rig presses on: precomputed once per phantom, cheap per tick.

Precomputation (once per phantom content, then cached on disk):

1. Mesh the phantom (:func:`phantom_grid`): a hexahedral block on the table, node lines every
   ``spacing_m`` in the plane (so every 2 mm sensor element spans whole cells), graded layers through
   the depth, each node column stretched to the surface height above it; the inclusions are assigned
   per Gauss point.
2. Condense it onto the vertical displacements of the whole top surface (:mod:`.fem`), and invert to
   the surface compliance ``C``.
3. For every TSI pose on a lattice (x every ``spacing_m`` along the whole phantom, y within
   ``drift_y_m`` of its mid-line), follow the exact contact path of the face descending onto the
   nodes under it (:mod:`.contact`) and integrate the nodal forces over each 2 x 2 mm element. The
   result is, per pose, a short table of depths at which a node touches down or lifts off and the
   element forces and their slopes there; between those depths the response is exactly linear.

Per tick, :meth:`ContinuumTissue.element_forces_N` looks up the four lattice poses around (x, y),
evaluates each one's piecewise-linear table at the face height z, and blends them bilinearly. At the
lattice poses the answer is the full linear-elastic contact solution; between them (the lattice is
1 mm) it is interpolated. A TSI further than ``drift_y_m`` off the phantom's mid-line is evaluated at
the nearest tabulated y offset (the TSI covers the phantom's whole width, so palpation never needs
more); along x every position on or beside the phantom is tabulated.

Finite strain (``MeshSettings(finite_strain=True)``, off by default here, on in the simulated rig): the
linear model is exact only for small strains, and 10 mm into 25 mm is not. It is a reduced nonlinear
model, two factors on each element's linear force, both functions of the element's own nominal strain
``s`` (its indentation since its contact onset over its onset height):

* the **homogeneous** factor ``1 + a s + b s^2``, per element: :mod:`.finite_strain` solves the face
  pressed into the phantom's homogeneous base block at finite strain (its hyperelastic law, side condition
  and friction at the face; with friction the factor is ``1 + c + a s + b s^2``, a gripped layer being
  stiffer than the frictionless linear model from the first touch) once per phantom, up to ``FIT_STRAIN``,
  and fits each element's nonlinear/linear force. The face's own pattern changes with it: its edge rows
  stiffen faster than its inner rows, the elements at the phantom's free sides slower. Past ``FIT_STRAIN``
  the pattern is held and only the total keeps stiffening along its own fitted curve;
* the **inclusion** factor: as the layer compresses, the tissue over a stiff inclusion thins, so the
  inclusion shows more the harder the face presses. A second set of linear tables has every inclusion
  where a layer compressed by ``COMPRESSED_STRAIN`` carries it (:func:`compressed_material`); an
  element's force ratio between the two sets at the same pose and height, ``r``, gives the factor
  ``1 + (r - 1) min(s, COMPRESSED_STRAIN) / COMPRESSED_STRAIN``: linear in the strain up to the state
  tabulated, held beyond it.

Against a full nonlinear solve of the flat phantom with one tumour under the face (``bench.rig_bench``,
docs/phantoms.md) it follows each element's force within a few per cent where the uniform correction it
replaces was off by up to a third, and it captures most, not all, of the tumour's growing contrast.
"""

from __future__ import annotations

import bisect
import dataclasses
import hashlib
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from tissue.face import Face
from tissue.mechanics import cache as cache_mod
from tissue.mechanics.contact import contact_path, tributary_weights
from tissue.mechanics.fem import (
    HexGrid,
    MaterialFn,
    SchurStore,
    condensed_surface_stiffness,
    graded_levels,
    table_dofs,
    wall_dofs,
)
from tissue.mechanics.progress import Progress, stage
from tissue.mechanics.workers import Job, usable_cores
from tissue.mechanics.workers import run as run_jobs
from tissue.phantom import Phantom

log = logging.getLogger(__name__)
# The simulated rig presses its tissue at finite strain unless its settings say otherwise; a recorded
# session that does not say is read as the rig's default.
RIG_FINITE_STRAIN = True
# A face tilted further than this no longer presses with its whole area at palpation depths (5 degrees over
# the TSI's 30 mm is 2.6 mm of height)
MAX_TILT_RAD = math.radians(5.0)


@dataclass(frozen=True)
class MeshSettings:
    """Discretisation of the continuum model (part of the cache key)."""

    spacing_m: float = 1e-3  # in-plane node spacing; must divide the sensor pitch
    layers: int = 11  # element layers from the table to the surface
    top_layer_m: float = 0.5e-3  # thickness of the top layer where the surface is at the base thickness
    drift_y_m: float = 1e-3  # y offsets of the TSI from the phantom's mid-line that are tabulated
    finite_strain: bool = False  # the reduced finite-strain model on top of the linear tables (see above)
    # Not a discretisation, but it shapes every table: the face tilted about its centre, by these angles
    # about y (its height rising along x) and about x (rising along y). A probe mounted by hand is off by a
    # degree or so; the analysis assumes a level face.
    tilt_rad: tuple[float, float] = (0.0, 0.0)

    def validate(self, sensor: Face) -> None:
        ratio = sensor.pitch_m / self.spacing_m
        if self.spacing_m <= 0 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(f"MeshSettings.spacing_m: {self.spacing_m:g} m must divide the sensor pitch "
                             f"{sensor.pitch_m:g} m a whole number of times")
        if self.layers < 2:
            raise ValueError(f"MeshSettings.layers: need at least 2, got {self.layers}")
        if self.top_layer_m <= 0:
            raise ValueError(f"MeshSettings.top_layer_m: must be > 0, got {self.top_layer_m:g}")
        if self.drift_y_m < 0:
            raise ValueError(f"MeshSettings.drift_y_m: must be >= 0, got {self.drift_y_m:g}")
        if not all(math.isfinite(a) and abs(a) <= MAX_TILT_RAD for a in self.tilt_rad):
            raise ValueError(f"MeshSettings.tilt_rad: each within +-{MAX_TILT_RAD:g} rad, got {self.tilt_rad}")


def _line(length_m: float, spacing_m: float) -> np.ndarray:
    n = int(math.floor(length_m / spacing_m + 1e-9))
    pts = np.round(np.arange(n + 1) * spacing_m, 12)
    if length_m - pts[-1] > 1e-9:
        pts = np.append(pts, length_m)
    return pts


def phantom_grid(phantom: Phantom, settings: MeshSettings) -> HexGrid:
    """The hexahedral mesh of a phantom (see the module docstring)."""
    x = _line(phantom.length_m, settings.spacing_m)
    y = _line(phantom.width_m, settings.spacing_m)
    gx, gy = np.meshgrid(x, y, indexing="ij")
    height = phantom.surface_height_m(gx, gy)
    if np.any(height <= 0):
        raise ValueError(f"phantom {phantom.name!r}: the surface height must be positive everywhere")
    top_fraction = min(settings.top_layer_m / phantom.thickness_m, 1.0 / settings.layers)
    return HexGrid(x, y, graded_levels(settings.layers, top_fraction), height)


def phantom_material(phantom: Phantom):
    """(E, nu) at points: the tissue's, or an inclusion's modulus inside its sphere."""

    def material(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        young = np.full(points.shape[:-1], phantom.youngs_modulus_pa)
        for inc in phantom.inclusions:
            d2 = ((points[..., 0] - inc.x_m) ** 2 + (points[..., 1] - inc.y_m) ** 2
                  + (points[..., 2] - inc.z_m) ** 2)
            young = np.where(d2 <= inc.radius_m**2, inc.youngs_modulus_pa, young)
        return young, np.full(points.shape[:-1], phantom.poisson_ratio)

    return material


def surface_compliance(phantom: Phantom, settings: MeshSettings | None = None,
                       keep: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                       progress: Progress | None = None, sides: str = "free", store: SchurStore | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(C, node (x, y)): the surface compliance of ``phantom``'s block bonded to its table (vertical
    displacement per vertical force between its top nodes, every other top node free of load) and where
    those nodes are, x-major as C takes them; ``keep(x, y)`` says which top nodes to keep (default: all);
    ``sides``: "free", or "mould" (its four lateral faces on frictionless walls, as ``precompute`` holds a
    phantom whose ``sides`` say so); ``store``: boxes of the condensation kept between calls
    (:class:`tissue.mechanics.fem.SchurStore`)."""
    grid = phantom_grid(phantom, settings or MeshSettings())
    mask = None if keep is None else keep(*np.meshgrid(grid.x_m, grid.y_m, indexing="ij"))
    fixed = table_dofs(grid) | wall_dofs(grid) if sides == "mould" else None
    ij, stiffness = condensed_surface_stiffness(grid, phantom_material(phantom), mask=mask, progress=progress,
                                                fixed=fixed, store=store)
    return _spd_inverse(stiffness), np.stack([grid.x_m[ij[:, 0]], grid.y_m[ij[:, 1]]], axis=1)


def cache_key(phantom: Phantom, settings: MeshSettings, sensor: Face, what: str = "tables") -> str:
    """Key of the contact tables (``what="tables"``, or ``"tables-compressed"`` with the inclusions moved),
    or of the finite-strain stiffening (``"stiffening"``, which depends on the phantom only)."""
    mesh = asdict(settings)
    mesh.pop("finite_strain")  # applied on top of the tables, not part of them
    if not any(mesh["tilt_rad"]):
        mesh.pop("tilt_rad")  # a level face keeps the keys it had before tilt was a setting
    blob = json.dumps({
        "what": what,
        "phantom": phantom.content_hash(),
        "mesh": mesh if what.startswith("tables") else None,
        "sensor": [sensor.rows, sensor.cols, sensor.pitch_m],
    }, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:24]


@dataclass(frozen=True)
class _Lattice:
    x0_m: float
    y0_m: float
    step_m: float
    nx: int
    ny: int

    def centre(self, ix: int, iy: int) -> tuple[float, float]:
        return self.x0_m + ix * self.step_m, self.y0_m + iy * self.step_m


def _lattice(phantom: Phantom, settings: MeshSettings, sensor: Face) -> _Lattice:
    step = settings.spacing_m
    half_x = sensor.size_m[0] / 2.0
    first = math.floor((-half_x) / step + 1e-9) + 1
    last = math.ceil((phantom.length_m + half_x) / step - 1e-9) - 1
    mid = round(phantom.width_m / 2.0 / step)
    span = int(math.floor(settings.drift_y_m / step + 1e-9))
    return _Lattice(first * step, (mid - span) * step, step, last - first + 1, 2 * span + 1)


def precompute(phantom: Phantom, settings: MeshSettings, sensor: Face,
               progress: Progress | None = None, material: MaterialFn | None = None) -> dict[str, np.ndarray]:
    """Every table the per-tick model needs, as plain arrays (what the cache stores); ``material``
    defaults to the phantom's own."""
    settings.validate(sensor)
    started = time.perf_counter()
    if progress:
        progress(0.0, "meshing the phantom")
    grid = phantom_grid(phantom, settings)
    fixed = table_dofs(grid) | wall_dofs(grid) if phantom.sides == "mould" else None
    ij, stiffness = condensed_surface_stiffness(grid, material or phantom_material(phantom), fixed=fixed,
                                                progress=stage(progress, 0.0, 0.8))
    if progress:
        progress(0.8, "inverting the surface stiffness")
    compliance = _spd_inverse(stiffness)
    del stiffness
    xs, ys = grid.x_m[ij[:, 0]], grid.y_m[ij[:, 1]]
    hs = grid.height_m[ij[:, 0], ij[:, 1]]
    extent = (0.0, phantom.length_m, 0.0, phantom.width_m)
    lat = _lattice(phantom, settings, sensor)
    size_x, size_y = sensor.size_m
    eps = 1e-9
    t_all, f_all, g_all, onsets, offsets = [], [], [], [], [0]
    report = stage(progress, 0.85, 0.99)
    for ix in range(lat.nx):
        for iy in range(lat.ny):
            cx, cy = lat.centre(ix, iy)
            lo = (cx - size_x / 2.0, cy - size_y / 2.0)
            under = np.flatnonzero((xs >= lo[0] - eps) & (xs <= lo[0] + size_x + eps)
                                   & (ys >= lo[1] - eps) & (ys <= lo[1] + size_y + eps))
            weights = tributary_weights(xs[under], ys[under], extent, lo, sensor.pitch_m, sensor.shape)
            carried = weights.sum(axis=0) > 0
            under, weights = under[carried], weights[:, carried]
            # a node meets the tilted face when the face's centre is this far above the node's own height
            level = hs[under] - (xs[under] - cx) * math.tan(settings.tilt_rad[0]) \
                - (ys[under] - cy) * math.tan(settings.tilt_rad[1])
            path = contact_path(compliance[np.ix_(under, under)], level).mapped(weights)
            t_all.append(path.t)
            f_all.append(path.f0)
            g_all.append(path.df)
            onsets.append(_onsets(path.t, path.f0, path.df, sensor.rows * sensor.cols))
            offsets.append(offsets[-1] + len(path.t))
        if report:
            report((ix + 1) / lat.nx, "tabulating contact along the phantom")
    n_el = sensor.rows * sensor.cols
    return {
        "lattice": np.array([lat.x0_m, lat.y0_m, lat.step_m, lat.nx, lat.ny], dtype=float),
        "onset_z": np.array(onsets).reshape(-1, n_el),
        "offsets": np.array(offsets, dtype=np.int64),
        "t": np.concatenate(t_all) if t_all else np.zeros(0),
        "f0": np.concatenate([f.reshape(-1, n_el) for f in f_all]),
        "df": np.concatenate([g.reshape(-1, n_el) for g in g_all]),
        "mesh_shape": np.array(grid.shape, dtype=np.int64),
        "precompute_s": np.array(time.perf_counter() - started),
    }


def _onsets(t: np.ndarray, f0: np.ndarray, df: np.ndarray, n_el: int) -> np.ndarray:
    """Face height at which each element first carries force along one pose's path (NaN: never)."""
    out = np.full(n_el, np.nan)
    if len(t) == 0:
        return out
    loaded = (f0 > 1e-12 * np.abs(f0).max(initial=0.0)) | (df > 1e-12 * np.abs(df).max(initial=0.0))
    first = np.argmax(loaded, axis=0)
    hit = loaded[first, np.arange(n_el)]
    out[hit] = -t[first[hit]]
    return out


# As deep as the full solve is checked against a finer mesh and the rig's model against it (8 mm into the
# flat phantom's 25 mm, bench/rig_bench.py); fitted to 20 %, the pattern held beyond was 14 % off per
# element at 8 mm.
FIT_STRAIN = 0.32


def _stiffening(phantom: Phantom, sensor: Face, progress: Progress | None) -> dict[str, np.ndarray]:
    """Nonlinear/linear force of each element, ``1 + a s + b s^2`` in the nominal strain s (``1 + c + a s +
    b s^2`` with friction at the face), fitted up to
    ``FIT_STRAIN`` and extrapolated beyond, for the face pressed into the middle of the phantom's
    homogeneous base block; and the same fit for the total force."""
    from tissue.mechanics.finite_strain import homogeneous, punch

    # A 2 mm mesh: per element it agrees with a 1 mm mesh within 2.8 % (rms 1.4 %) up to 20 % strain and
    # 2.7 % (2.0 %) at 32 % (finite_strain: the face's corner held out of the tissue). Five steps, as the
    # fit had to 20 %: the solve is elastic, so larger steps give the same points, and eight of them made a
    # new phantom's first palpation wait 8-14 s longer.
    solution = punch(phantom.length_m, phantom.width_m, phantom.thickness_m,
                     homogeneous(phantom.youngs_modulus_pa, phantom.poisson_ratio), face_m=sensor.size_m,
                     pitch_m=sensor.pitch_m, max_indentation_m=FIT_STRAIN * phantom.thickness_m,
                     step_m=FIT_STRAIN / 5 * phantom.thickness_m, spacing_m=2e-3, y_spacing_m=sensor.pitch_m, layers=6,
                     sides=phantom.sides, law=phantom.material, friction=phantom.face_friction, progress=progress)
    if len(solution.indentation_m) < 3:
        raise RuntimeError("the finite-strain solution did not get past its second step")
    # A solve that stops short is fitted as far as it got and held beyond (FiniteStrain.scale): a quadratic
    # through three points within 4 % strain, extrapolated to 32 %, once took a block's force to 0.28 of
    # its linear value.
    s = solution.indentation_m[1:] / phantom.thickness_m
    # A face that grips the tissue is stiffer than a frictionless one from the first touch (flat phantom at
    # 6 % strain: 1.04 frictionless, 1.06-1.10 with mu 0.2-1), so with friction the fit starts from its own
    # value at rest; without, the two models are one at rest by construction and the fit stays as it was.
    gripped = phantom.face_friction > 0
    basis = np.stack(([np.ones_like(s)] if gripped else []) + [s, s * s], axis=1)
    linear = solution.linear_N()[1:].reshape(len(s), -1)
    nonlinear = solution.nonlinear_N[1:].reshape(len(s), -1)
    loaded = linear[-1] > 0
    excess = np.divide(nonlinear, linear, out=np.ones_like(linear), where=linear > 0) - 1.0
    per_element, *_ = np.linalg.lstsq(basis, excess[:, loaded], rcond=None)
    coeffs = np.zeros((basis.shape[1], linear.shape[1]))  # elements off the phantom carry nothing to scale
    coeffs[:, loaded] = per_element
    total, *_ = np.linalg.lstsq(basis, solution.curve().ratio()[1:] - 1.0, rcond=None)
    # (FIT_STRAIN t) / t is FIT_STRAIN only to rounding (0.31999999999999995 for t = 12.9 mm), and a rebuilt
    # block whose solve got all the way was described as "solved to 32 % of 32 % and held beyond"
    reached = FIT_STRAIN if s[-1] >= FIT_STRAIN * (1.0 - 1e-9) else float(s[-1])
    fit = {"element_ab": coeffs[-2:], "total_ab": total[-2:], "fit_strain": np.array(reached)}
    if gripped:
        fit.update(element_at_rest=coeffs[0], total_at_rest=total[0])
    return fit


# The strain at which the inclusions are tabulated where the compressed layer has carried them (see
# ``compressed_material``); the change of each element's force between rest and it is interpolated
# linearly in the element's strain, and held beyond it.
COMPRESSED_STRAIN = 0.3


def compressed_material(phantom: Phantom, strain: float) -> MaterialFn:
    """The phantom's material with each inclusion where the layer compressed by ``strain`` carries it.

    Under the face the tissue shortens by about the same strain everywhere in a column while a stiff
    inclusion keeps its size: its centre, at height z, sinks to z (1 - s) in a layer now L (1 - s)
    thick, so the tissue over it thins from h to h (1 - s) - R s. The linear model with the inclusion
    that much nearer the surface is what the tissue over it feels once compressed (the thinning is what
    makes a deep tumour show as the probe presses harder); the inclusion is never moved out of the
    surface.
    """
    moved = []
    for inc in phantom.inclusions:
        depth = phantom.inclusion_depth_m(inc)
        new_depth = max(depth * (1.0 - strain) - inc.radius_m * strain, 0.0)
        moved.append(dataclasses.replace(inc, z_m=inc.z_m + depth - new_depth))
    return phantom_material(dataclasses.replace(phantom, inclusions=tuple(moved)))


@dataclass(frozen=True, eq=False)
class FiniteStrain:
    """The reduced model's homogeneous finite-strain factor (module docstring) of one block."""

    element_ab: np.ndarray  # (2, elements): each element's (a, b)
    total_ab: tuple[float, float]  # the total force's (a, b)
    fit_strain: float = FIT_STRAIN  # as far as the solve got, and the fit goes
    # with a face that grips the tissue, each element's and the total's excess at rest (c: c + a s + b s^2)
    element_at_rest: np.ndarray | float = 0.0
    total_at_rest: float = 0.0

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> FiniteStrain:
        return cls(np.asarray(arrays["element_ab"], dtype=float), tuple(float(v) for v in arrays["total_ab"]),
                   float(arrays["fit_strain"]), np.asarray(arrays.get("element_at_rest", 0.0), dtype=float),
                   float(arrays.get("total_at_rest", 0.0)))

    def scale(self, strain: np.ndarray) -> np.ndarray:
        """Each element's nonlinear over linear force at its nominal strain (flat, one per element)."""
        # Past the strains solved, the pattern is held where it was solved and only the total keeps
        # stiffening along the fitted curve: extrapolating each element's own curve would grow the
        # face's edge peaks without anything to check them against. The total never softens out there: a
        # homogeneous layer only stiffens as it is pressed, so a fit that bends down is held at its top.
        held = np.minimum(strain, self.fit_strain)
        a, b = self.element_ab
        out = 1.0 + self.element_at_rest + held * (a + b * held)
        if strain.max() > self.fit_strain:
            a_total, b_total = self.total_ab
            top = -a_total / (2.0 * b_total) if b_total < 0 else np.inf
            beyond = np.minimum(strain, max(top, self.fit_strain))
            c = self.total_at_rest
            out *= (1.0 + c + beyond * (a_total + b_total * beyond)) / (1.0 + c + held * (a_total + b_total * held))
        return out


def compressed_precompute(phantom: Phantom, settings: MeshSettings, sensor: Face,
                          progress: Progress | None = None) -> dict[str, np.ndarray]:
    """:func:`precompute` with every inclusion where the layer compressed by ``COMPRESSED_STRAIN`` carries it."""
    return precompute(phantom, settings, sensor, progress, compressed_material(phantom, COMPRESSED_STRAIN))


def homogeneous_stiffening(phantom: Phantom, sensor: Face | None = None,
                           cache_dir: str | Path | None = None, progress: Progress | None = None) -> FiniteStrain:
    """The finite-strain factor of ``phantom``'s homogeneous base block (its inclusions play no part), from
    the cache if there, else solved (a few seconds) and cached."""
    folder = Path(cache_dir) if cache_dir is not None else cache_mod.default_cache_dir()
    return FiniteStrain.from_arrays(_stiffening_cached(phantom, sensor or Face(), folder, progress))


def _stiffening_cached(phantom: Phantom, sensor: Face, folder: Path,
                       progress: Progress | None) -> dict[str, np.ndarray]:
    return cached(folder, _stiffening_key(phantom, sensor), lambda: _stiffening(phantom, sensor, progress),
                  _check_stiffening)


def _stiffening_key(phantom: Phantom, sensor: Face) -> str:
    # the key leaves the mesh out (cache_key): the finite-strain solve has its own
    return cache_key(phantom, MeshSettings(), sensor, "stiffening")


def _check_stiffening(arrays: dict[str, np.ndarray]) -> None:
    if (np.asarray(arrays["element_ab"]).ndim != 2 or len(arrays["element_ab"]) != 2
            or np.asarray(arrays["total_ab"]).shape != (2,) or not 0 < float(arrays["fit_strain"]) <= FIT_STRAIN
            or np.shape(arrays.get("element_at_rest", np.zeros(np.shape(arrays["element_ab"])[1:])))
            != np.shape(arrays["element_ab"])[1:] or np.shape(arrays.get("total_at_rest", 0.0)) != ()):
        raise ValueError("inconsistent cache entry")


def cached(folder: Path, key: str, compute, check) -> dict[str, np.ndarray]:
    """The arrays under ``key``: from the cache if they load and pass ``check``, else computed and stored.

    An unwritable cache is logged and otherwise ignored: the model still works, it is just recomputed
    next time."""
    arrays = _load_checked(folder, key, check)
    if arrays is None:
        arrays = compute()
        _store(folder, key, arrays)
    return arrays


def cached_together(folder: Path, pieces: list[tuple[str, Callable[[dict], None], Job]], workers: int | None,
                    progress: Progress | None = None) -> list[dict[str, np.ndarray]]:
    """Each ``(key, check, job)``'s arrays as :func:`cached` gives them, the jobs of those not in the cache
    run side by side in up to ``workers`` processes (None: one per core)."""
    found = [_load_checked(folder, key, check) for key, check, _ in pieces]
    missing = [i for i, arrays in enumerate(found) if arrays is None]
    if missing:
        workers = usable_cores() if workers is None else workers
        computed = run_jobs([pieces[i][2] for i in missing], min(workers, len(missing)), progress)
        for i, arrays in zip(missing, computed):
            _store(folder, pieces[i][0], arrays)
            found[i] = arrays
    return found


def _load_checked(folder: Path, key: str, check) -> dict[str, np.ndarray] | None:
    path = cache_mod.cache_path(folder, key)
    arrays = cache_mod.load(path, key)
    if arrays is not None:
        try:
            check(arrays)
            return arrays
        except (KeyError, ValueError, TypeError):
            log.warning("ignoring inconsistent tissue cache %s; recomputing", path)
    return None


def _store(folder: Path, key: str, arrays: dict[str, np.ndarray]) -> None:
    path = cache_mod.cache_path(folder, key)
    try:
        cache_mod.store(path, key, arrays)
    except OSError as err:
        log.warning("could not write the tissue cache %s: %s", path, err)


def _spd_inverse(a: np.ndarray) -> np.ndarray:
    import scipy.linalg as sla

    chol, info = sla.lapack.dpotrf(np.asfortranarray(a), lower=1, overwrite_a=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError("the condensed surface stiffness is not positive definite")
    inv, info = sla.lapack.dpotri(chol, lower=1, overwrite_c=1)
    if info != 0:
        raise np.linalg.LinAlgError("could not invert the condensed surface stiffness")
    return np.tril(inv) + np.tril(inv, -1).T


class _Tables:
    """One set of contact tables: the linear element forces of the face at any pose and height."""

    def __init__(self, tables: dict[str, np.ndarray], n_el: int):
        x0, y0, step, nx, ny = (float(v) for v in tables["lattice"])
        self.x0, self.y0, self.step = x0, y0, step
        self.nx, self.ny = int(nx), int(ny)
        offsets = np.asarray(tables["offsets"], dtype=np.int64)
        t = np.asarray(tables["t"], dtype=float)
        f0 = np.asarray(tables["f0"], dtype=float)
        df = np.asarray(tables["df"], dtype=float)
        if (len(offsets) != self.nx * self.ny + 1 or offsets[0] != 0 or np.any(np.diff(offsets) < 0)
                or offsets[-1] != len(t) or f0.shape != (len(t), n_el) or df.shape != (len(t), n_el)):
            raise ValueError("inconsistent tissue tables")
        self.offsets = offsets.tolist()
        self.t = [t[a:b].tolist() for a, b in zip(self.offsets[:-1], self.offsets[1:])]
        self.f0, self.df = f0, df
        self.onset = np.asarray(tables["onset_z"], dtype=float)
        if self.onset.shape != (self.nx * self.ny, n_el):
            raise ValueError("inconsistent tissue tables")

    def blend(self, x_m: float, y_m: float) -> list[tuple[int, float]]:
        """The lattice poses around (x, y) and their bilinear weights."""
        fx = (x_m - self.x0) / self.step
        fy = min(max((y_m - self.y0) / self.step, 0.0), self.ny - 1.0)
        ix = math.floor(fx)
        iy = min(int(fy), self.ny - 2) if self.ny > 1 else 0
        wx = fx - ix
        wy = fy - iy if self.ny > 1 else 0.0
        out = []
        for px, w_x in ((ix, 1.0 - wx), (ix + 1, wx)):
            if w_x <= 0.0 or px < 0 or px >= self.nx:
                continue
            for py, w_y in ((iy, 1.0 - wy), (iy + 1, wy)):
                if w_y > 0.0:
                    out.append((px * self.ny + py, w_x * w_y))
        return out

    def forces(self, blend: list[tuple[int, float]], z_m: float) -> tuple[np.ndarray | None, list[int]]:
        """Element forces (flat; None where the face touches nothing) and the poses that touch."""
        t = -z_m
        rows, weights, steps, poses = [], [], [], []
        for pose, weight in blend:
            tb = self.t[pose]
            k = bisect.bisect_right(tb, t) - 1
            if k >= 0:
                rows.append(self.offsets[pose] + k)
                weights.append(weight)
                steps.append(t - tb[k])
                poses.append(pose)
        if not rows:
            return None, poses
        w = np.array(weights)
        return np.maximum(w @ self.f0[rows] + (w * np.array(steps)) @ self.df[rows], 0.0), poses


class ContinuumTissue:
    """Continuum phantom on a rigid table under a rigid TSI face, level unless ``MeshSettings.tilt_rad``.

    Implements :class:`hardware.sim.tissue.TissueModel`. Build it with :meth:`load`.
    """

    def __init__(self, phantom: Phantom, sensor: Face, tables: dict[str, np.ndarray],
                 stiffening: dict[str, np.ndarray] | None = None,
                 compressed: dict[str, np.ndarray] | None = None):
        self.phantom = phantom
        self.sensor = sensor
        n_el = sensor.rows * sensor.cols
        self._tables = _Tables(tables, n_el)
        self._compressed = None if compressed is None else _Tables(compressed, n_el)
        if compressed is not None and not np.array_equal(tables["lattice"], compressed["lattice"]):
            raise ValueError("inconsistent tissue tables")
        if stiffening is not None and np.asarray(stiffening["element_ab"]).shape != (2, n_el):
            raise ValueError("inconsistent cache entry")
        # the finite-strain factor, or None for the purely linear model
        self.finite_strain = None if stiffening is None else FiniteStrain.from_arrays(stiffening)
        self.precompute_s = float(tables["precompute_s"]) + (0.0 if compressed is None
                                                             else float(compressed["precompute_s"]))
        self.mesh_shape = tuple(int(v) for v in tables["mesh_shape"])
        self._shape = sensor.shape

    @property
    def stiffening(self) -> tuple[float, float] | None:
        """(a, b) of the total force's finite-strain factor 1 + c + a s + b s^2 (for reports; c, non-zero only
        with friction at the face, is ``finite_strain.total_at_rest``), or None."""
        return None if self.finite_strain is None else self.finite_strain.total_ab

    @classmethod
    def load(cls, phantom: Phantom, cache_dir: str | Path | None = None, progress: Progress | None = None,
             settings: MeshSettings | None = None, sensor: Face | None = None,
             workers: int | None = None) -> "ContinuumTissue":
        """The model of ``phantom``: from the cache if a trustworthy entry exists, else computed and cached.

        ``cache_dir`` defaults to ``$PALPATION_CACHE_DIR`` or the user cache directory. An unwritable
        cache is logged and otherwise ignored: the model still works, it is just recomputed next time.
        The pieces not in the cache are computed side by side in up to ``workers`` processes (default:
        one per core; 1 computes them here, for a caller whose own processes already fill the cores).
        """
        settings = settings or MeshSettings()
        sensor = sensor or Face()
        settings.validate(sensor)
        folder = Path(cache_dir) if cache_dir is not None else cache_mod.default_cache_dir()
        n_el = sensor.rows * sensor.cols

        def check(arrays):
            _Tables(arrays, n_el)

        # longest first: the finite-strain fit takes a third of either table's time, so it follows the first
        pieces = {"tables": (cache_key(phantom, settings, sensor), check,
                             Job("tables at rest", f"{__name__}:precompute", (phantom, settings, sensor), 0.45))}
        if settings.finite_strain and phantom.inclusions:
            pieces["compressed"] = (
                cache_key(phantom, settings, sensor, f"tables-compressed-{COMPRESSED_STRAIN:g}"), check,
                Job("compressed tables", f"{__name__}:compressed_precompute",
                    (phantom, settings, sensor), 0.35))
        if settings.finite_strain:
            pieces["stiffening"] = (_stiffening_key(phantom, sensor), _check_stiffening,
                                    Job("finite-strain fit", f"{__name__}:_stiffening", (phantom, sensor), 0.2))
        arrays = cached_together(folder, list(pieces.values()), workers, progress)
        found = dict(zip(pieces, arrays))
        if progress:
            progress(1.0, f"tissue model of {phantom.name!r} ready")
        return cls(phantom, sensor, found["tables"], found.get("stiffening"), found.get("compressed"))

    def element_forces_N(self, x_m: float, y_m: float, z_m: float) -> np.ndarray:
        """Normal force on each TSI element, (rows, cols), for the face centred at (x, y) at height z."""
        blend = self._tables.blend(x_m, y_m)
        forces, poses = self._tables.forces(blend, z_m)
        if forces is None:
            return np.zeros(self._shape)
        if self.finite_strain is not None:
            onset = np.fmax.reduce(self._tables.onset[poses], axis=0)  # neighbouring poses' onsets barely differ
            strain = np.divide(onset - z_m, onset, out=np.zeros_like(forces), where=forces > 0)
            scale = self.finite_strain.scale(strain)
            if self._compressed is not None:
                moved, _ = self._compressed.forces(blend, z_m)
                if moved is not None:
                    ratio = np.divide(moved, forces, out=np.ones_like(forces), where=(moved > 0) & (forces > 0))
                    scale *= 1.0 + (ratio - 1.0) * (np.minimum(strain, COMPRESSED_STRAIN) / COMPRESSED_STRAIN)
            forces = forces * scale
        return forces.reshape(self._shape)

    def total_force_N(self, x_m: float, y_m: float, z_m: float) -> float:
        return float(self.element_forces_N(x_m, y_m, z_m).sum())

    def ground_truth(self) -> list[dict[str, float]]:
        """The phantom's inclusions (position, depth below the local surface, diameter, modulus)."""
        return self.phantom.ground_truth()
