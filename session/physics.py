"""What homogeneous tissue would have pressed on each element: the physics behind the flat-field.

A rigid face does not load a homogeneous layer evenly: its edge rows carry two to three times what its inner
rows carry, the tissue is softer near a free end or side, and where only part of the face touches (an
uneven surface) the edge of the contact is loaded like an edge of the face. A tumour shows as what is left
once that expected pattern is divided out (:mod:`session.flatfield`).

The pattern comes from the project's continuum mechanics (:mod:`tissue.mechanics`: finite elements of
the block on its table, condensed onto its surface) for a block of homogeneous tissue rebuilt from the
session's own measurements, never from a phantom file, so a real session gets the same treatment:

* its extent is what was palpated (the areas of the paper's protocol cover the tissue, so the tissue ends
  where they end) and its thickness the median height at which the elements first touched, over the table;
* each recorded level is a rigid flat punch pressing that block uniformly over the elements that were in
  contact at that level (:meth:`HomogeneousTissue.pattern`): the force map is compared with the whole face
  pressing a flat surface (``measured_surface=False``, the face's own pattern), the stiffness map with the
  surface the level's onsets measured, which Eq. 1 then relates to each element's own indentation and
  thickness;
* its sides are free, or held by the frictionless walls of a mould, and the face frictionless or gripping
  it, whichever leaves the session's areas reading most alike (:func:`supported_sides`): a session does not
  record which, and the wrong one misplaces what lies near a side (held sides taken for free pulled a tumour
  4 mm from the side 2 mm towards it), and a face that grips free sides loads the array's end columns over
  them up to twice as much, more in the areas at the tissue's ends than the flat field's baseline can take
  in (false tumours where an end area meets a side: docs/validation.md, "Friction at the face");
* on the measured surface the tissue is pressed at finite strain: each element's force takes the reduced
  finite-strain model's factor (:class:`tissue.mechanics.model.FiniteStrain`, solved once for a
  homogeneous neo-Hookean block of the rebuilt extent and thickness) at its own nominal strain (the
  indentation over its surface's height above the table) over the factor at the record's typical strain.
  Tissue that stands higher under the face (a bump) is pressed further than the rest and carries more
  than linear elasticity gives it: without this, the tops of the bumps read as tumours. What finite strain
  does to the face's own pattern at the typical strain is the same in every area of a level, and the
  level's baseline carries it (as it does for the force map's flat surface, pressed alike everywhere).
  Not so the face's grip: its whole pattern, each element's gripped over its frictionless factor at its own
  strain, is taken on (:data:`GRIP_FRICTION`).

Forces are seen through the sensor's compliant cover when the session records one, and returned normalised
to their mean over the elements pressing: the flat-field fits its own scale per level. The block's modulus is
irrelevant to the pattern (linear elasticity scales with it, and the finite-strain factor is a ratio).
:meth:`HomogeneousTissue.from_phantom` gives, for a simulated session only, the pattern of its own phantom
without the tumours: the simulator's answer, for tests and comparison.
"""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from session.info import SessionInfo
from session.reader import Session
from tissue.face import COVER_SPREAD_M, cover_operators, cover_weight, element_offsets_m
from tissue.mechanics.finite_strain import SIDES
from tissue.mechanics.progress import stage

if TYPE_CHECKING:
    from tissue.mechanics.model import FiniteStrain

Progress = Callable[[float, str], None]
NU = 0.49  # nearly incompressible soft tissue and silicone (docs/phantoms.md)
MESH_VERSION = 2  # bump when the block's mesh changes: cached compliances are keyed by it
GRID_M = 1e-3  # the mesh's node spacing in the plane (MeshSettings' default)
# How far the tissue may go on beyond the palpated extent: areas laid to cover it end within about half an
# element's pitch of its end, and the mesh places an end on its node lines (GRID_M)
EXTENT_SLACK_M = 1e-3
# How far off the sink-in the surface's rebuild adds to the onsets is, one standard deviation relative to it,
# shared by the elements of an area (it comes from one contact): next to a ridge pressed 11 mm before the
# flat part beside it touched, the flanks' onsets came early (the cover spreads the crest's load onto them),
# the rebuild took them at their highest and added 1.6 times the sink-in the simulated tissue had, and the
# flat part read tilted, +0.2 to +0.35 at the face's far side (s2611-0007). Against the simulated truth, on
# 4,551 elements that touched by their own contact in 12 sloped and bumpy study sessions (s777, s4711), the
# rebuilt sink-in ran 22-37 % above the truth, scattered by 8-25 %: this is the typical error, not the worst.
SINK_IN_ERROR = 0.25
# The onsets' own scatter (0.1-0.3 mm) is smoothed out of the block's surface, but not a bump's step.
SMOOTHING_M = 0.5e-3
# A block's lateral faces are free (tissue on a table, as the paper's phantoms were palpated) or held by the
# frictionless walls of the mould it was cast in, and nothing a session records says which. Held, its ends and
# sides read stiffer than free ones: the validation study's realistic world holds 3 phantoms in 10 in their
# mould, and there a tumour 4 mm from a held side, under free sides, read 2.1 mm towards it (s20261125-0009).
# The choices are the continuum model's own (tissue.mechanics.finite_strain.SIDES).
# The rebuilt block's surface compliance is dense: 8,000 nodes (about 120 x 65 mm of palpated extent) is
# 0.5 GB, and memory and solve time grow with its square, so a larger extent is refused up front.
MAX_BLOCK_NODES = 8000


@dataclass(frozen=True, eq=False)
class SurfaceBlock:
    """A homogeneous block on the table, ``length_m`` along x and ``width_m`` along y from (0, 0), whose
    surface stands at ``heights_m`` (on a ``GRID_M`` grid from (0, 0) reaching at least that far, first index
    along x): what the continuum model needs of a phantom to mesh it."""

    heights_m: np.ndarray
    length_m: float
    width_m: float
    youngs_modulus_pa: float = 1.0
    poisson_ratio: float = NU
    inclusions: tuple = ()
    source: dict = field(default_factory=dict)

    @property
    def thickness_m(self) -> float:
        return float(np.median(self.heights_m))

    @property
    def name(self) -> str:
        return (f"{self.length_m * 1e3:.0f} x {self.width_m * 1e3:.0f} mm block, "
                f"{self.heights_m.min() * 1e3:.1f}-{self.heights_m.max() * 1e3:.1f} mm thick")

    def surface_height_m(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        h = self.heights_m
        fx = np.clip(x / GRID_M, 0.0, h.shape[0] - 1.0)
        fy = np.clip(y / GRID_M, 0.0, h.shape[1] - 1.0)
        i = np.minimum(np.floor(fx).astype(int), h.shape[0] - 2)
        j = np.minimum(np.floor(fy).astype(int), h.shape[1] - 2)
        wx, wy = fx - i, fy - j
        value = ((1 - wx) * (1 - wy) * h[i, j] + wx * (1 - wy) * h[i + 1, j] + (1 - wx) * wy * h[i, j + 1]
                 + wx * wy * h[i + 1, j + 1])
        outside = (x < -1e-9) | (x > self.length_m + 1e-9) | (y < -1e-9) | (y > self.width_m + 1e-9)
        return np.where(outside, 0.0, value)

    def content_hash(self) -> str:
        digest = hashlib.sha256(np.round(self.heights_m, 6).tobytes())
        digest.update(f"{self.length_m:.7f} {self.width_m:.7f} {self.poisson_ratio} {MESH_VERSION}".encode())
        return digest.hexdigest()[:16]


def measured_surface(levels: np.ndarray, pitch_m: float, table_height_m: float,
                     extent_m: tuple[float, float, float, float] | None = None) -> tuple[SurfaceBlock, tuple]:
    """(the block of the measured surface, (x0, y0) of its origin in the tissue frame): the
    onsets of every palpated area placed where its elements were, over the union of their footprints (and of
    ``extent_m``, (x0, x1, y0, y1), where the tissue is known to reach further), smoothed over about one
    element (an onset comes from noisy frames). Where an element never touched the surface is taken a
    millimetre below the lowest it was found under that area; between areas nobody measured, and beyond
    them, the nearest measurement stands."""
    from scipy import ndimage

    rows, cols = levels.dtype["onset_height_m"].shape
    offsets = element_offsets_m(rows, cols, pitch_m)
    centres = levels["tsi_position_m"][:, None, None, :2] + offsets[None]
    lo = centres.reshape(-1, 2).min(axis=0) - pitch_m / 2
    hi = centres.reshape(-1, 2).max(axis=0) + pitch_m / 2
    if extent_m is not None:
        lo = np.minimum(lo, (extent_m[0], extent_m[2]))
        hi = np.maximum(hi, (extent_m[1], extent_m[3]))
    nx = int(np.ceil((hi[0] - lo[0]) / GRID_M - 1e-6)) + 1
    ny = int(np.ceil((hi[1] - lo[1]) / GRID_M - 1e-6)) + 1
    if nx * ny > MAX_BLOCK_NODES:
        raise ValueError(f"the palpated areas span {(hi[0] - lo[0]) * 1e3:.0f} x {(hi[1] - lo[1]) * 1e3:.0f} mm, a "
                         f"block of {nx * ny:,} surface nodes; the rebuilt physics models at most "
                         f"{MAX_BLOCK_NODES:,} (about 120 x 65 mm): analyse with --physics none")
    gx = lo[0] + GRID_M * np.arange(nx)
    gy = lo[1] + GRID_M * np.arange(ny)
    total, count = np.zeros((nx, ny)), np.zeros((nx, ny))
    for region in np.unique(levels["region"]):
        i = np.flatnonzero(levels["region"] == region)[-1]  # its last level: onsets refined the longest
        onset = levels["onset_height_m"][i] - table_height_m
        if not np.isfinite(onset).any():
            continue
        onset = np.where(np.isfinite(onset), onset, np.nanmin(onset) - 1e-3)
        for a in range(rows):
            for b in range(cols):
                cx, cy = centres[i, a, b]
                cells = np.ix_(np.abs(gx - cx) <= pitch_m / 2 + 1e-9, np.abs(gy - cy) <= pitch_m / 2 + 1e-9)
                total[cells] += onset[a, b]
                count[cells] += 1
    if not count.any():
        raise ValueError("no element of this session ever touched the tissue: its surface is unknown")
    known = count > 0
    heights = total / np.maximum(count, 1)
    if not known.all():
        nearest = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
        heights = heights[tuple(nearest)]
    heights = ndimage.gaussian_filter(heights, SMOOTHING_M / GRID_M, mode="nearest")
    block = SurfaceBlock(np.clip(heights, 1e-3, None), float(hi[0] - lo[0]), float(hi[1] - lo[1]))
    return block, (float(lo[0]), float(lo[1]))


@dataclass(frozen=True)
class Pattern:
    """What homogeneous tissue presses on each element of each record, and how sure that is."""

    share: np.ndarray  # (n, rows, cols) element forces over their mean over the elements pressing; NaN: none
    sigma: np.ndarray  # (n, rows, cols) relative uncertainty of ``share`` from the rebuilt geometry (0: exact)
    # (n, modes, rows, cols): the parts of that uncertainty shared between elements, one standard deviation
    # each (a surface under one element a little higher loads it more and its neighbours less; the tissue
    # going on beyond the palpated extent unloads the elements near the end together); ``sigma`` holds them
    # too, with what is independent per element
    modes: np.ndarray | None = None


class HomogeneousTissue(ABC):
    """Element forces of a homogeneous block under the face at each recorded level (module docstring).

    ``description`` says which block, for the analysis report."""

    sides = "free"  # the block's lateral faces: free, or held in a mould (SIDES); the depth model reads by them

    def __init__(self, description: str, cover_spread_m: float, pitch_m: float, shape: tuple[int, int]):
        self.description = description
        self.cover_spread_m = cover_spread_m
        self.pitch_m = pitch_m
        self.shape = shape
        self._cover = _cover(cover_spread_m, shape, pitch_m)

    @classmethod
    def reconstructed(cls, session: Session, cache_dir=None, progress: Progress | None = None,
                      ends_known: bool = True) -> BlockResponse:
        """The block rebuilt from ``session`` (raises ValueError if no element ever touched), its sides free or
        held in a mould as the session's own tissue says (:func:`supported_sides`); without ``ends_known``, a
        session of part of a tissue, where it ends not known, and its sides taken to be free."""
        if not ends_known:
            return BlockResponse.from_levels(session.levels, session, cache_dir, progress, ends_known=False)
        # The grip shows at finite strain only, and free sides gripped read much as sides in a mould: each side
        # is solved at finite strain with the face frictionless and gripping, and the four compared.
        step = 1.0 / len(SIDES)
        candidates = []
        for k, sides in enumerate(SIDES):
            tissue = BlockResponse.from_levels(session.levels, session, cache_dir,
                                               stage(progress, k * step, (k + 0.6) * step), sides=sides)
            candidates += [tissue, tissue.gripped(cache_dir, stage(progress, (k + 0.6) * step, (k + 1) * step))]
        return supported_sides(session.levels, candidates)

    @classmethod
    def from_phantom(cls, session: Session, cache_dir=None, progress: Progress | None = None) -> PhantomResponse:
        """The simulated session's phantom without its tumours (raises ValueError for other sessions)."""
        return PhantomResponse.load(session, cache_dir, progress)

    @abstractmethod
    def pattern(self, levels: np.ndarray, measured_surface: bool = True, progress: Progress | None = None
                ) -> Pattern:
        """The pattern of each level record. ``measured_surface``: the surface under the face is the one
        the record's onsets measured, else a flat one pressed evenly by the whole face; ``progress(fraction,
        message)`` after each record."""

    def _finish(self, forces: np.ndarray) -> np.ndarray:
        if self._cover is not None:
            forces = self._cover[0] @ forces @ self._cover[1]
        pressing = forces > 1e-9 * max(float(forces.max()), 1e-300)
        if not pressing.any():
            return np.full(forces.shape, np.nan)
        return np.where(pressing, forces / forces[pressing].mean(), np.nan)


class BlockResponse(HomogeneousTissue):
    """The flat block of the palpated extent: its surface compliance, and punches on it."""

    def __init__(self, block: SurfaceBlock, origin_xy_m: tuple[float, float], compliance: np.ndarray,
                 nodes_xy_m: np.ndarray, cover_spread_m: float, pitch_m: float, shape: tuple[int, int],
                 finite_strain: FiniteStrain | None = None, table_height_m: float = 0.0,
                 ends_known: bool = True, sides: str = "free", grip: FiniteStrain | None = None):
        if sides not in SIDES:
            raise ValueError(f"sides must be one of {SIDES}, got {sides!r}")
        if grip is not None and finite_strain is None:
            raise ValueError("the face's grip is a finite-strain factor: the block needs its own")
        ends = "" if ends_known else "; where the tissue ends not known"
        held = "" if sides == "free" else ", its sides held in a mould"
        held += "" if grip is None else ", the face gripping it"
        super().__init__(f"homogeneous tissue rebuilt from the session (a {block.name}{held}: the palpated "
                         f"extent and the measured surface, finite elements{_finite(finite_strain)}{ends})",
                         cover_spread_m, pitch_m, shape)
        self.ends_known = ends_known
        self.sides = sides
        self.sides_why = ""  # how the sides were told from the session (supported_sides), for the description
        # the last pattern made of each kind: choosing the sides makes the one the analysis asks for next
        self._made: dict[bool, tuple[bytes, Pattern]] = {}
        self.block = block
        self.origin_xy_m = origin_xy_m
        self.finite_strain = finite_strain
        self.grip = grip  # the factor with the face gripping the block (GRIP_FRICTION), or None: frictionless
        self.table_height_m = table_height_m
        self._compliance = compliance
        self._nodes = nodes_xy_m
        self._faces: dict[tuple[int, int], _Face] = {}

    @classmethod
    def from_levels(cls, levels: np.ndarray, described: Session | SessionInfo, cache_dir=None,
                    progress: Progress | None = None,
                    extent_m: tuple[float, float, float, float] | None = None,
                    ends_known: bool = True, sides: str = "free", finite_strain: bool = True) -> BlockResponse:
        """The block rebuilt from ``levels`` of the session ``described`` (recorded, or being recorded: the
        live maps ask for the areas palpated so far), reaching over ``extent_m`` too where the tissue is known
        to: the live maps' last area is not at the tissue's end, and modelled as if it were, its far edge
        rows read as a tumour (the paper's flat phantom, 8 areas of 9: a spot at x = 64 mm, z 5.9). Without
        ``ends_known`` the block's ends are not taken to be the tissue's (:meth:`_extent_modes`): the live
        maps of a session whose tissue no plan describes, whose last area is where the operator has got to.
        ``sides``: the block's lateral faces free, or held by a mould's frictionless walls (:data:`SIDES`).
        Without ``finite_strain``, linear elasticity only (:meth:`at_finite_strain` adds it)."""
        if not len(levels):
            raise ValueError("the session recorded no level: there is no palpated area to model")
        shape = tuple(levels.dtype["pressure_pa"].shape)
        table = float(described.calibration.get("table_height_m", 0.0))
        pitch = float(described.calibration["pitch_m"])
        block, origin = measured_surface(levels, pitch, table, extent_m)
        compliance, nodes = _block_compliance(block, cache_dir, stage(progress, 0.0, 0.6 if finite_strain else 1.0),
                                              sides)
        tissue = cls(block, origin, compliance, nodes, _cover_of(described), pitch, shape, None, table, ends_known,
                     sides)
        return tissue.at_finite_strain(cache_dir, stage(progress, 0.6, 1.0)) if finite_strain else tissue

    def at_finite_strain(self, cache_dir=None, progress: Progress | None = None) -> BlockResponse:
        """This block pressed at finite strain: its finite-strain factor solved for its extent, thickness and
        sides (cached), what was said of its sides kept."""
        tissue = self._like(finite_strain=_block_stiffening(self.block, self.shape, self.pitch_m, cache_dir, progress,
                                                            self.sides))
        tissue.sides_why = self.sides_why
        tissue.description = tissue.description[:-1] + self.sides_why + ")"
        return tissue

    def gripped(self, cache_dir=None, progress: Progress | None = None) -> BlockResponse:
        """This block at finite strain with the face gripping it (:data:`GRIP_FRICTION`; its factor solved for
        the block's extent, thickness and sides, cached)."""
        finite = self.finite_strain or _block_stiffening(self.block, self.shape, self.pitch_m, cache_dir, None,
                                                          self.sides)
        return self._like(finite_strain=finite, grip=_block_stiffening(self.block, self.shape, self.pitch_m, cache_dir,
                                                                       progress, self.sides, GRIP_FRICTION))

    def _like(self, **changed) -> BlockResponse:
        """A block as this one but for ``changed`` of its constructor's arguments (what was said of its sides not
        carried)."""
        given = dict(block=self.block, origin_xy_m=self.origin_xy_m, compliance=self._compliance,
                     nodes_xy_m=self._nodes, cover_spread_m=self.cover_spread_m, pitch_m=self.pitch_m, shape=self.shape,
                     finite_strain=self.finite_strain, table_height_m=self.table_height_m, ends_known=self.ends_known,
                     sides=self.sides, grip=self.grip)
        return BlockResponse(**(given | changed))

    def on_surface_of(self, levels: np.ndarray, extent_m: tuple[float, float, float, float] | None = None
                      ) -> BlockResponse:
        """This block's finite elements (its surface compliance and finite-strain factor) under the surface that
        ``levels`` measured over the same extent: the contact is solved on the new surface, the tissue's
        response is the one meshed on this block's. Seconds instead of :meth:`from_levels`'s finite elements;
        an approximation where the surfaces differ (the live maps, app/live_physics.py, say how much). Raises
        ValueError where ``levels`` reach beyond this block's extent."""
        block, origin = measured_surface(levels, self.pitch_m, self.table_height_m, extent_m)
        if block.heights_m.shape != self.block.heights_m.shape or not np.allclose(origin, self.origin_xy_m,
                                                                                   atol=GRID_M / 10):
            raise ValueError(f"the areas reach beyond the {self.block.name} whose finite elements are known")
        tissue = self._like(block=block, origin_xy_m=origin)
        if block.content_hash() != self.block.content_hash():
            tissue.description = tissue.description[:-1] + f"; its finite elements meshed on the {self.block.name})"
        return tissue

    def pattern(self, levels: np.ndarray, measured_surface: bool = True, progress: Progress | None = None
                ) -> Pattern:
        asked = levels.tobytes()
        made = self._made.get(measured_surface)
        if made is None or made[0] != asked:
            made = self._made[measured_surface] = (asked, self._pattern(levels, measured_surface, progress))
        return made[1]

    def _pattern(self, levels: np.ndarray, measured_surface: bool, progress: Progress | None) -> Pattern:
        shape = levels["pressure_pa"].shape
        done = _records_done(progress, len(levels))
        if not measured_surface:
            flat = np.full(shape, np.nan)
            modes = [[] for _ in levels]
            for k, row in enumerate(levels):
                done(k)
                flat[k] = self._share(row, None)
                modes[k] = self._extent_modes(row, None, flat[k])
            return _pattern(flat, np.zeros(shape), modes)
        # An onset is where an element first touched: the highest point under it, or where a neighbour's load
        # leaking through the sensor's cover first reached the threshold. Where the surface falls away within
        # an element (a bump's flank, the edge of a gap) the truth lies between that and the lowest of its
        # neighbours' surfaces, and an onset step to a neighbour beyond the onsets' scatter says by how much
        # it may fall within the element (the only clue at the array's edge). The pattern is taken on the
        # surface half-way; each uncertain element's half-range is propagated through the contact to every
        # element's share (a raised element takes load off its neighbours), one mode of the uncertainty
        # shared between them, and the onsets' own scatter counts, per element, relative to how far each
        # element is pressed in.
        upper, sink_in = self._surfaces(levels)
        onset_noise = _onset_noise_m(levels)
        relief = _relief(levels, onset_noise)
        share = np.full(shape, np.nan)
        independent = np.full(shape, np.nan)
        modes = [[] for _ in levels]
        for k, row in enumerate(levels):
            done(k)
            region = int(row["region"])
            high = upper[region]
            low = np.minimum(_lower_envelope(high), high - relief[region])
            mid = 0.5 * (high + low)
            half = np.nan_to_num(0.5 * (high - low))
            base = self._share(row, mid)
            sunk = np.nan_to_num(sink_in[region])
            if np.abs(sunk).max() > 2.0 * onset_noise:
                modes[k].append(_change_of_pattern(self._share(row, mid - SINK_IN_ERROR * sunk), base))
            pressed = np.maximum(mid - float(row["tsi_position_m"][2]), 1e-4)
            for e in np.flatnonzero(half.ravel() > 2.0 * onset_noise):
                raised = mid.copy()
                raised.flat[e] += half.flat[e]
                modes[k].append(_change_of_pattern(self._share(row, raised), base))
            share[k] = base
            independent[k] = (onset_noise / pressed) ** 2
            modes[k] += self._extent_modes(row, mid, base)
        return _pattern(share, independent, modes)

    def _extent_modes(self, row, heights: np.ndarray | None, base: np.ndarray) -> list[np.ndarray]:
        """The share's relative changes from not knowing where the tissue ends. The block ends where the
        palpated areas end; the tissue may go on beyond that by up to ``EXTENT_SLACK_M``, and an element
        over a free end is loaded very differently from one a millimetre inside it (a face edge flush with
        the end rides on a free edge; one a little short of it presses a punch's edge into the tissue). Where
        the face reaches an end of the block, the change of every element's share if the tissue went on by
        that much (the face that far inside the block) is one standard deviation of that uncertainty.

        Where the ends are not known (``ends_known`` false), the tissue may as well go on by another area:
        the slack is the face's own length along that axis, and a face up to that far from an end feels it
        too (on the flat phantom's block of its first eight areas, the face an area short of the end changes
        by up to 12 % with it, the one two areas short by 2 %). Taken to end a millimetre beyond the face,
        the live maps' newest area read its far edge as a tumour after four of the flat phantom's first
        eight areas (z 6-10); taken to go on by 4 mm more on every side, as often (the free end's effect
        reaches further into 20 mm of tissue), and at the tissue's real end the face's other edge read as
        one. docs/validation.md, "Live findings on part of a tissue", says what this costs and gains on
        the validation study's phantoms."""
        modes = []
        rows, cols = self.shape
        reach = ((self.block.length_m, rows * self.pitch_m), (self.block.width_m, cols * self.pitch_m))
        lo = self._face_lo(row)
        for axis, (extent, span) in enumerate(reach):
            if self.ends_known:
                slack, within = EXTENT_SLACK_M, EXTENT_SLACK_M / 2
            else:
                slack, within = span, span + EXTENT_SLACK_M / 2
            near_end = lo[axis] * GRID_M
            far_end = extent - near_end - span
            for gap, inward in ((near_end, 1.0), (far_end, -1.0)):
                other = far_end if inward > 0 else near_end
                if gap > within or other < slack:  # not near this end, or no room to move
                    continue
                moved = row.copy()
                moved["tsi_position_m"][axis] += inward * slack
                modes.append(_change_of_pattern(self._share(moved, heights), base))
        return modes

    def _share(self, row, heights: np.ndarray | None) -> np.ndarray:
        """The normalised element forces of one record: the face on ``heights`` (undeformed surface height
        under each element; None: a flat surface pressed evenly)."""
        fx, fy = self._face_lo(row)
        ix, iy = int(np.floor(fx)), int(np.floor(fy))
        z = float(row["tsi_position_m"][2])
        forces = np.zeros(self.shape)
        # The mesh resolves a face whose edges lie on its node lines; a face between them is the blend of
        # the two neighbouring faces along each axis, as the simulator's model does.
        for px, wx in ((ix, 1.0 - (fx - ix)), (ix + 1, fx - ix)):
            for py, wy in ((iy, 1.0 - (fy - iy)), (iy + 1, fy - iy)):
                if wx * wy > 1e-9:
                    face = self._face(px, py)
                    # a flat surface pressed evenly: a unit indentation everywhere
                    gap = np.ones(len(face.nodes)) if heights is None else face.surface(heights) - z
                    forces += wx * wy * face.elements(face.contact(gap))
        if heights is not None and self.finite_strain is not None:
            # Each element stiffens with its own nominal strain: where the surface stands higher (a bump) it
            # is pressed further than the rest of the face and carries more than linear elasticity says. Only
            # that departure from the record's typical strain is modelled; how the face's own pattern changes
            # with the typical strain is shared by every area at a level, and the level's baseline measures it
            # better than this model predicts it (with the whole factor, a deep tumour's contrast on a flat
            # phantom came out 10 % below the simulator's own with/without ratio, against 2 % without). Not
            # so where a ridge holds part of a level's areas back; the whole factor, measured again for that
            # in both worlds, gained only in the world that shares this model (docs/validation.md, "The face's
            # pattern at finite strain, and the onsets beside a crest").
            with np.errstate(invalid="ignore", divide="ignore"):
                strain = (heights - z) / (heights - self.table_height_m)
            strain = np.clip(np.nan_to_num(strain, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None).ravel()
            pressed = forces.ravel() > 0
            if pressed.any():
                typical = np.full(strain.shape, float(np.median(strain[pressed])))
                factor = (self.grip or self.finite_strain).scale(strain) / self.finite_strain.scale(typical)
                forces = forces * factor.reshape(forces.shape)
        return self._finish(forces)

    def _face_lo(self, row) -> tuple[float, float]:
        """The face's lower corner in the block, in node spacings."""
        rows, cols = self.shape
        x0, y0 = self.origin_xy_m
        return ((float(row["tsi_position_m"][0]) - x0 - rows * self.pitch_m / 2) / GRID_M,
                (float(row["tsi_position_m"][1]) - y0 - cols * self.pitch_m / 2) / GRID_M)

    def _face(self, ix: int, iy: int) -> _Face:
        """The nodes under a face whose lower corner is node line (ix, iy), and how they map to its elements."""
        from tissue.mechanics.contact import tributary_weights

        face = self._faces.get((ix, iy))
        if face is None:
            rows, cols = self.shape
            lo = (ix * GRID_M, iy * GRID_M)
            nx, ny = self._nodes[:, 0], self._nodes[:, 1]
            eps = 1e-9
            under = np.flatnonzero((nx >= lo[0] - eps) & (nx <= lo[0] + rows * self.pitch_m + eps)
                                   & (ny >= lo[1] - eps) & (ny <= lo[1] + cols * self.pitch_m + eps))
            weights = tributary_weights(nx[under], ny[under], (0.0, self.block.length_m, 0.0, self.block.width_m),
                                        lo, self.pitch_m, self.shape)
            carried = weights.sum(axis=0) > 0
            under, weights = under[carried], weights[:, carried]
            # each node's position in element units from the first element's centre, kept on the array
            u = np.clip((nx[under] - lo[0]) / self.pitch_m - 0.5, 0.0, rows - 1.0)
            v = np.clip((ny[under] - lo[1]) / self.pitch_m - 0.5, 0.0, cols - 1.0)
            i0 = np.minimum(np.floor(u).astype(int), max(rows - 2, 0))
            j0 = np.minimum(np.floor(v).astype(int), max(cols - 2, 0))
            i1, j1 = np.minimum(i0 + 1, rows - 1), np.minimum(j0 + 1, cols - 1)
            fu, fv = u - i0, v - j0
            corners = np.stack([i0 * cols + j0, i1 * cols + j0, i0 * cols + j1, i1 * cols + j1], axis=1)
            corner_weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=1)
            face = self._faces[(ix, iy)] = _Face(under, weights, np.argmax(weights, axis=0), self.shape,
                                                 corners, corner_weights, self._compliance[np.ix_(under, under)])
        return face

    def _surfaces(self, levels: np.ndarray) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Each palpated area's undeformed surface height under each element, relative to the face, and the
        sink-in added to its onsets (both by region).

        An element's onset is where the face was when it first touched, but by then the elements already
        touching had pushed the surface around it down (sink-in), so the undeformed surface was higher by
        that much. Going through the elements in the order they touched, each one's sink-in at its onset is
        the homogeneous block's response to the contact already made: undeformed height = onset + sink-in.
        Elements that never touched lie below every face height recorded (NaN)."""
        surfaces, sink_in = {}, {}
        for region in np.unique(levels["region"]):
            rows_of = np.flatnonzero(levels["region"] == region)
            row = levels[rows_of[-1]]  # the last level's onsets: refined for as long as the area was pressed
            onset = np.where(np.isfinite(row["dL_m"]) | np.isfinite(row["onset_height_m"]),
                             row["onset_height_m"], np.nan).ravel()
            fx, fy = self._face_lo(row)
            face = self._face(int(round(fx)), int(round(fy)))
            heights = np.full(onset.shape, np.nan)
            for e in np.argsort(-np.where(np.isfinite(onset), onset, -np.inf)):
                if not np.isfinite(onset[e]):
                    break
                gap = heights[face.owner] - onset[e]
                f = face.contact(gap)
                mine = face.owner == e
                # the element touched first where its surface stood highest after sinking in, and the point
                # that sank least is the one whose height the onset can vouch for
                sink = float((face.compliance[mine] @ f).min()) if mine.any() else 0.0
                heights[e] = onset[e] + sink
            surfaces[int(region)] = heights.reshape(self.shape)
            sink_in[int(region)] = (heights - onset).reshape(self.shape)
        return surfaces, sink_in


def supported_sides(levels: np.ndarray, candidates: list[BlockResponse]) -> BlockResponse:
    """Of ``candidates``, blocks alike but for their sides and whether the face grips them, the one under which
    the areas of ``levels`` read most like homogeneous tissue: the least scatter of their stiffness contrast, in
    the mean over the force levels of its robust standard deviation (the flat field's own estimate of healthy
    tissue's scatter). A tumour raises it alike under every candidate; the sides' and the grip's pattern is at
    every area's ends of the face and at the tissue's ends. Its description says which was chosen, and the
    scatter under each."""
    from session.flatfield import _robust_spread, contrast
    from session.stitch import level_groups

    scatter = []
    for tissue in candidates:
        pattern = tissue.pattern(levels)
        seen = contrast(levels, "stiffness", pattern.share, pattern.sigma, share_modes=pattern.modes).contrast
        scatter.append(float(np.mean([_robust_spread(c, 0.0) for c in (seen[records] for _, records in
                                                                         level_groups(levels))
                                      if np.isfinite(c).any()])))
    best = int(np.argmin(scatter))
    chosen = candidates[best]

    def named(c: BlockResponse) -> str:
        return c.sides + ("" if c.grip is None else ", gripped")

    others = "; ".join(f"{named(c)} {s:.1%}" for k, (c, s) in enumerate(zip(candidates, scatter)) if k != best)
    chosen.sides_why = (f"; sides {named(chosen)}: the areas' stiffness contrast scatters {scatter[best]:.1%} so, "
                        f"{others}")
    chosen.description = chosen.description[:-1] + chosen.sides_why + ")"
    return chosen


def _records_done(progress: Progress | None, records: int) -> Callable[[int], None]:
    def done(k: int) -> None:
        if progress is not None:
            progress(k / records, f"the face's contact on record {k + 1} of {records}")

    return done


def _change_of_pattern(share: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Each element's relative change from ``base`` to ``share``, less the change of their median: the flat
    field fits each record's scale itself, so only a change of the pattern is an error (0 where either has
    none)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        change = share / base
        return np.nan_to_num(change / np.nanmedian(change) - 1.0)


def _pattern(share: np.ndarray, independent_variance: np.ndarray, modes: list[list[np.ndarray]]) -> Pattern:
    """A Pattern from each record's share, the variance independent per element, and its shared modes."""
    count = max((len(m) for m in modes), default=0)
    stacked = np.zeros((len(share), count) + share.shape[1:])
    for k, record in enumerate(modes):
        if record:
            stacked[k, :len(record)] = record
    inside = np.isfinite(share)
    stacked = np.where(inside[:, None], stacked, 0.0)
    sigma = np.sqrt(independent_variance + (stacked ** 2).sum(axis=1))
    return Pattern(share, np.where(inside, sigma, np.nan), stacked)


def _onset_noise_m(levels: np.ndarray) -> float:
    """How much the onsets scatter about the surface they measure: the robust spread of each element's
    onset about the mean of its neighbours, over every palpated area (relief a few elements wide cancels)."""
    from scipy import ndimage

    residuals = []
    kernel = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=float)
    for region in np.unique(levels["region"]):
        onset = levels["onset_height_m"][np.flatnonzero(levels["region"] == region)[-1]]
        known = np.isfinite(onset)
        if known.sum() < 5:
            continue
        total = ndimage.convolve(np.where(known, onset, 0.0), kernel, mode="constant")
        count = ndimage.convolve(known.astype(float), kernel, mode="constant")
        inner = known & (count >= 3)
        residuals.append((onset - total / np.maximum(count, 1))[inner])
    if not residuals:
        return 0.0
    r = np.concatenate(residuals)
    # the residual of one element against the mean of n ~ 4 neighbours has sd sigma * sqrt(1 + 1/4)
    return float(1.4826 * np.median(np.abs(r - np.median(r))) / np.sqrt(1.25))


def _relief(levels: np.ndarray, onset_noise_m: float) -> dict[int, np.ndarray]:
    """Per area, each element's largest onset step to a neighbour beyond what the onsets' scatter explains."""
    out = {}
    for region in np.unique(levels["region"]):
        onset = levels["onset_height_m"][np.flatnonzero(levels["region"] == region)[-1]]
        padded = np.pad(onset, 1, mode="constant", constant_values=np.nan)
        steps = np.stack([np.abs(onset - padded[:-2, 1:-1]), np.abs(onset - padded[2:, 1:-1]),
                          np.abs(onset - padded[1:-1, :-2]), np.abs(onset - padded[1:-1, 2:])])
        with np.errstate(invalid="ignore"):
            largest = np.nanmax(np.where(np.isfinite(steps), steps, -np.inf), axis=0)
        out[int(region)] = np.clip(np.where(np.isfinite(largest), largest, 0.0) - 2.0 * onset_noise_m, 0.0, None)
    return out


def _lower_envelope(heights: np.ndarray) -> np.ndarray:
    """Each element's height, or the lowest of its four neighbours' where lower. A neighbour that never
    touched counts as falling away by as much as the deepest drop measured under the face; one beyond the
    array's edge continues the slope from the element on the other side."""
    h = heights
    known = h[np.isfinite(h)]
    floor = float(known.min() - (known.max() - known.min()) - 1e-3) if len(known) else np.nan
    filled = np.where(np.isfinite(h), h, floor)
    padded = np.pad(filled, 1, mode="reflect", reflect_type="odd")  # odd reflection: 2 h_edge - h_inner
    low = np.minimum.reduce([filled, padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
    return np.where(np.isfinite(h), low, np.nan)


class _Face:
    """The block's nodes under one face position, how they map to its elements, and their contact."""

    def __init__(self, nodes: np.ndarray, weights: np.ndarray, owner: np.ndarray, shape: tuple[int, int],
                 corners: np.ndarray, corner_weights: np.ndarray, compliance: np.ndarray):
        self.nodes = nodes  # block nodes under the face
        self.weights = weights  # (elements, nodes): share of each node's force each element takes
        self.owner = owner  # the element taking most of each node's force
        self.shape = shape
        self.corners = corners  # (nodes, 4): the element centres around each node, as flat element indices
        self.corner_weights = corner_weights  # (nodes, 4): their bilinear weights at the node
        self.compliance = compliance  # (nodes, nodes): the block's surface compliance among them
        # Its inverse, once per face: a contact's nodes are most of the face's, and the inverse of the
        # compliance among them is this one's less a correction the size of the nodes left out (_forces).
        # The rebuilt physics solves thousands of contacts per session on some 30 faces; factorising each
        # contact's nodes afresh made the block rebuilt for a 9-area session take 18 s, against 4.6 s so.
        self.inverse = np.linalg.inv(compliance)

    def elements(self, nodal_forces: np.ndarray) -> np.ndarray:
        return (self.weights @ nodal_forces).reshape(self.shape)

    def surface(self, heights: np.ndarray) -> np.ndarray:
        """The surface at each node, interpolated between the element centres (an element's own height
        where a neighbour never touched: it is the only measurement there)."""
        h = heights.ravel()
        around = h[self.corners]
        value = (around * self.corner_weights).sum(axis=1)
        return np.where(np.isfinite(value), value, h[self.owner])

    def contact(self, gap_m: np.ndarray) -> np.ndarray:
        """Nodal forces of a rigid level face pressing these nodes of a linear-elastic block, where ``gap_m``
        is how far each node's undeformed surface rises above the face (NaN: never reaches it): frictionless
        and unilateral (f >= 0, each node pushed down at least its gap, exactly where it carries force), found
        by active sets."""
        gap = np.where(np.isfinite(gap_m), gap_m, -np.inf)
        active = gap > 0
        for _ in range(4 * len(self.nodes) + 4):
            f = self._forces(active, gap)
            pulling = active & (f < 0)
            if pulling.any():
                active &= ~pulling
                continue
            through = ~active & (self.compliance @ f < gap - 1e-12)
            if not through.any():
                return f
            active |= through
        raise RuntimeError("the contact of the face with the rebuilt surface did not settle")

    def _forces(self, active: np.ndarray, gap: np.ndarray) -> np.ndarray:
        """The forces that push the ``active`` nodes down by exactly their gap, the others carrying none:
        C_SS f_S = g_S. With G the inverse of the whole C, the inverse of C_SS is G_SS - G_SR G_RR^-1 G_RS
        (R the nodes left out), so where fewer nodes are left out than kept, only G_RR is solved."""
        f = np.zeros(len(self.nodes))
        kept = np.flatnonzero(active)
        if not len(kept):
            return f
        out = np.flatnonzero(~active)
        if len(out) >= len(kept):
            f[kept] = np.linalg.solve(self.compliance[np.ix_(kept, kept)], gap[kept])
            return f
        # G_SS g and G_RS g at once, from G times the gap with the left-out nodes' zeroed
        whole = self.inverse @ np.where(active, gap, 0.0)
        if len(out):
            whole -= self.inverse[:, out] @ np.linalg.solve(self.inverse[np.ix_(out, out)], whole[out])
        f[kept] = whole[kept]
        return f


class PhantomResponse(HomogeneousTissue):
    """A simulated session's own phantom without its tumours, at each level's pose and measured force, at
    finite strain if the rig that recorded it was."""

    def __init__(self, tissue, cover_spread_m: float, pitch_m: float, shape: tuple[int, int], description: str):
        super().__init__(description, cover_spread_m, pitch_m, shape)
        self.tissue = tissue
        self.sides = tissue.phantom.sides  # the phantom's own: free, or in its mould

    @classmethod
    def load(cls, session: Session, cache_dir=None, progress: Progress | None = None) -> PhantomResponse:
        from tissue.mechanics.model import RIG_FINITE_STRAIN, ContinuumTissue, MeshSettings
        from tissue.mechanics.study import without_inclusions
        from tissue.phantom import parse_phantom

        if not session.simulated or not session.phantom:
            raise ValueError("only a simulated session knows its phantom")
        phantom = without_inclusions(parse_phantom(session.phantom, str(session.path)))
        recorded = (session.config.get("sim") or {}).get("finite_strain")  # as the rig that recorded it was set
        finite = recorded if isinstance(recorded, bool) else RIG_FINITE_STRAIN
        tissue = ContinuumTissue.load(phantom, cache_dir=cache_dir, progress=progress,
                                      settings=MeshSettings(finite_strain=finite))
        shape = tuple(session.levels.dtype["pressure_pa"].shape)
        return cls(tissue, _cover_of(session), session.pitch_m, shape,
                   f"the simulated phantom {phantom.name!r} without its tumours (the simulator's own model)")

    def pattern(self, levels: np.ndarray, measured_surface: bool = True, progress: Progress | None = None
                ) -> Pattern:
        """The phantom's own surface whatever ``measured_surface`` says: this is the exact answer."""
        from tissue.mechanics.study import height_for_force

        out = np.full(levels["pressure_pa"].shape, np.nan)
        done = _records_done(progress, len(levels))
        for k, row in enumerate(levels):
            done(k)
            x, y = (float(v) for v in row["tsi_position_m"][:2])
            # where this tissue carries the measured force (NaN: not even down at the table; no pattern then)
            z = height_for_force(self.tissue, x, y, float(row["force_measured_N"]))
            if np.isfinite(z):
                out[k] = self._finish(self.tissue.element_forces_N(x, y, z))
        return Pattern(out, np.where(np.isfinite(out), 0.0, np.nan), np.zeros((len(out), 0) + out.shape[1:]))


def _block_compliance(block: SurfaceBlock, cache_dir=None, progress: Progress | None = None, sides: str = "free"
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(C, node (x, y)): the block's surface compliance and where its top nodes are
    (:func:`tissue.mechanics.model.surface_compliance`), its sides free or in a mould, computed once per block
    and cached."""
    from tissue.mechanics.cache import default_cache_dir
    from tissue.mechanics.model import cached, surface_compliance

    def solve():
        compliance, nodes = surface_compliance(block, progress=progress, sides=sides)
        return {"compliance": compliance, "nodes": nodes}

    def check(arrays):
        if np.shape(arrays["compliance"]) != (len(arrays["nodes"]),) * 2:
            raise ValueError("inconsistent cache entry")

    held = "" if sides == "free" else f"{sides}-"
    arrays = cached(cache_dir if cache_dir is not None else default_cache_dir(),
                    f"block-{held}{block.content_hash()}", solve, check)
    return arrays["compliance"], arrays["nodes"]


def _finite(finite_strain: FiniteStrain | None) -> str:
    from tissue.mechanics.model import FIT_STRAIN

    if finite_strain is None:
        return ""
    if finite_strain.fit_strain < FIT_STRAIN:
        return (f", finite strain solved to {finite_strain.fit_strain:.0%} of {FIT_STRAIN:.0%} and held "
                "beyond")
    return ", finite strain"


# The grip the analysis offers besides a frictionless face: a face that grips outright (a 24 x 30 x 10 mm block
# read the same with mu 1 and 2, to four digits at 10 % strain). What a face's friction is, no session says;
# between none and this, what the flat field's baseline takes in of every area's pattern is left to it.
GRIP_FRICTION = 1.0


def _block_stiffening(block: SurfaceBlock, shape: tuple[int, int], pitch_m: float, cache_dir=None,
                      progress: Progress | None = None, sides: str = "free", friction: float = 0.0) -> FiniteStrain:
    """The finite-strain factor of the face pressed into a homogeneous neo-Hookean block of the rebuilt
    extent and thickness (the tissue ends where the palpation ends), its sides free or in a mould, the face
    frictionless or with Coulomb's ``friction``, cached. A real tissue's law is not known to the analysis:
    neo-Hookean is the phantom's default (docs/phantoms.md)."""
    from hardware.interfaces import TactileConstraints
    from tissue.mechanics.model import homogeneous_stiffening
    from tissue.phantom import Phantom

    # The factor is a ratio of forces in the same material, so the modulus drops out; a soft silicone's
    # keeps the solver in the range it is tested in.
    homogeneous = Phantom("rebuilt", "the rebuilt block, homogeneous", block.length_m, block.width_m,
                          block.thickness_m, youngs_modulus_pa=20e3, poisson_ratio=block.poisson_ratio, sides=sides,
                          face_friction=friction)
    sensor = TactileConstraints(rows=shape[0], cols=shape[1], pitch_m=pitch_m)
    return homogeneous_stiffening(homogeneous, sensor, cache_dir, progress)


def _cover_of(session: Session | SessionInfo) -> float:
    """The sensor cover's lateral spread as the session's calibration states it (the array's specification,
    not a simulated array's actual cover); for a session recorded before calibrations stated it, its
    simulated array's setting, else none."""
    value = session.calibration.get("cover_spread_m")
    if value is None:
        value = ((session.config.get("sim") or {}).get("sensor") or {}).get("cover_spread_m")
        if value is None and session.simulated:
            value = COVER_SPREAD_M
    # a file's value that is no spread (text, NaN, negative) states none: it would blur every element into NaN
    usable = isinstance(value, (int, float)) and not isinstance(value, bool) and float(value) >= 0.0
    return float(value) if usable and np.isfinite(value) else 0.0


def cover_for(described: Session | SessionInfo, shape: tuple[int, int], pitch_m: float
              ) -> Callable[[np.ndarray], np.ndarray] | None:
    """The sensor cover's spread of element forces on a (rows, cols) array at ``pitch_m``, as a recorded
    session or one being recorded describes it (None: it records no cover)."""
    operators = _cover(_cover_of(described), shape, pitch_m)
    return None if operators is None else (lambda forces: operators[0] @ forces @ operators[1])


def _cover(spread_m: float, shape: tuple[int, int], pitch_m: float):
    if spread_m <= 0:
        return None
    return cover_operators(cover_weight(spread_m, pitch_m), shape)


PHYSICS = {
    "rebuilt": "homogeneous tissue rebuilt from the session's own measurements (any session)",
    "partial": "the same, for part of a tissue palpated: where the tissue ends not known, it may go on beyond the "
               "areas by another area",
    "phantom": "the simulated phantom without its tumours (simulated sessions only)",
    "none": "no physics: the face's pattern is left to the baseline alone",
}


def physics_for(session: Session, name: str = "rebuilt", cache_dir=None,
                progress: Progress | None = None) -> HomogeneousTissue | None:
    """The physics :data:`PHYSICS` names for ``session``; raises ValueError saying why it cannot be had."""
    if name == "none":
        return None
    if name in ("rebuilt", "partial"):
        return HomogeneousTissue.reconstructed(session, cache_dir, progress, ends_known=name == "rebuilt")
    if name == "phantom":
        return HomogeneousTissue.from_phantom(session, cache_dir, progress)
    raise ValueError(f"unknown physics {name!r}; choose from {', '.join(PHYSICS)}")
