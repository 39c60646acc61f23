"""The probe's own pattern taken out: each element's contrast against homogeneous tissue, and its uncertainty.

How (written down once, here):

* **Expected pressure.** For the record r of an area at force level k, element e of homogeneous tissue would
  read ``expected[r, e] = scale[r] * baseline[k, e] * share[r, e]``:

  - ``share`` is the physics: the element forces a homogeneous block gives under the face at that pose and
    force (edge rows high, inner rows low, soft near a free end, and, for the stiffness map, the contact the
    level actually had on its measured surface), normalised to a mean of one. It comes from the
    composition root (``session.physics``), which knows the continuum mechanics; without it the share is one
    everywhere (the face's pattern is then left to the baseline alone).
  - ``baseline`` is what the physics does not know and every area shares: the array's own element-to-element
    sensitivity, its compliant cover, the pattern's systematic error. In order of preference it comes from
    a **reference palpation** of tumour-free tissue (:class:`Reference`, recorded once and reused), or it
    is **estimated from the session** itself: for each element, the median over the other areas
    palpated at that level (an area never vouches for itself) of measured / (scale * share), each area
    weighted by how sure its share is, which tolerates a minority of areas with tumours. An element fewer
    than ``MIN_VOUCHING`` other areas are sure of (a bump under most of them) takes the median of its part
    of the face, and that part's spread as its uncertainty. With physics it stays within
    ``BASELINE_RANGE`` of its part of the face's level (the edge rows', the inside's), and that level
    within ``PART_RANGE`` of one; without, it is the whole pattern of the face (and a tumour that lies
    under the same elements of most areas is taken for part of it: say so, use physics).
  - ``scale`` is the record's own level (the tissue's modulus there, the force actually reached): the
    median over its elements of measured / (baseline * share), robust to the elements over a tumour.

* **Contrast** = measured / expected - 1 (0: as homogeneous tissue; +0.2: 20 % harder than expected).

* **Uncertainty** of a contrast (relative, one standard deviation), the root sum of squares of:

  - the sensor's noise on the level's mean: the element's scatter over its settled window
    (``pressure_std_pa``) over the square root of the frames averaged (``window_frames``);
  - the scatter of healthy tissue: the robust spread of the contrasts at that level (1.4826 times their
    median absolute value), over the whole face and, where larger, over the part of the face the element
    is in (its inside, edge rows, side columns, corners: the physics is surer of some than of others),
    never less than ``accuracy``, the repeatability one element's reading can have from one loading to the
    next; with a reference, the reference's own scatter is added, and without, the baseline's own
    uncertainty where too few areas vouched for it;
  - the geometry: how well the share is known where the surface had to be rebuilt (``share_sigma``), of
    which the part shared between elements is kept apart (``Contrast.modes``) for the detection.

* The **stiffness map** (Eq. 1, E = F L0 / (A dL)) is compared with the stiffness homogeneous tissue of the
  same measured geometry would show by Eq. 1: both use the element's own L0 and dL, so its contrast is
  measured force / expected force with the share of the measured surface. The **force map** is compared
  with the face pressing a flat surface: the raw tactile map with the probe's pattern taken out, which is
  what the paper's force map shows (a thicker or raised part reads as harder).
"""

from __future__ import annotations

import json
import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from session.stitch import level_groups

MAPS = ("stiffness", "force")
ACCURACY = 0.02  # see DetectParams.accuracy
MIN_VOUCHING = 3  # records an element's session baseline needs (the median of three outvotes one tumour)
# An element's baseline is its sensitivity relative to the array's and the physics' systematic error there,
# which calibration and the model keep within this of its part of the face's level (:func:`_face_parts`):
# a larger departure is a tumour the areas share (the paper's three tumours lie under the same elements of
# three areas), not the array.
BASELINE_RANGE = 0.15
# The physics' systematic error is mostly a part's (the edge rows stiffen faster than the inside at finite
# strain, by about a tenth at 5 N): a part's level may leave one by up to about three times that.
PART_RANGE = 0.3
# A part needs this many elements for a level of its own: the side columns and the corners (four elements
# each, where the tissue's free sides make the physics least sure) stay about one, or a tumour near the
# side, lifting one of the four, moved their level and was found 2-3 mm off or missed.
MIN_PART_LEVEL = 10
REFERENCE_FORMAT = "palpation-console-reference"
# A saved reference holds two numbers per element and force level, about 25 bytes each: 0.6 MB for the 4 x 15
# array at the most levels a ramp has (200). A larger file is not one and is not read, so that loading what a
# path names costs at most this much text and about half as much again parsed (a fraction of a second).
MAX_REFERENCE_BYTES = 4 * 2**20


class FlatFieldError(ValueError):
    """A reference that cannot be used (a damaged file, another array, no level); the message says why."""


@dataclass(frozen=True)
class Reference:
    """A reference palpation of tumour-free tissue: for each force level, each element's baseline (its
    reading over what the physics expects there, the median over the reference's areas) and its relative
    scatter between those areas. Saved as JSON (:meth:`save`), reused for later sessions (:meth:`load`)."""

    forces_N: tuple[float, ...]
    baseline: np.ndarray  # (levels, rows, cols), median 1 over the elements of each level
    scatter: np.ndarray  # (levels, rows, cols) relative
    areas: int
    description: str
    physics: bool = False  # the baseline is over the physics' share; else it is the face's whole pattern

    def check_usable(self, with_physics: bool) -> None:
        """Raises FlatFieldError if this reference needs the finite-element physics and it is not there (one
        made without physics holds the face's whole pattern and serves either way)."""
        if self.physics and not with_physics:
            raise FlatFieldError("this reference palpation was made over the finite-element physics' pattern: "
                                 "use it with that physics, or save one without physics (the console's File "
                                 "menu, or stitch --physics none --save-reference)")

    def at(self, force_N: float) -> tuple[np.ndarray, np.ndarray]:
        """(baseline, scatter) at the reference level nearest ``force_N``."""
        k = int(np.argmin(np.abs(np.asarray(self.forces_N) - force_N)))
        return self.baseline[k], self.scatter[k]

    def to_json(self) -> dict:
        return {"format": REFERENCE_FORMAT, "version": 1, "description": self.description, "areas": self.areas,
                "physics": self.physics,
                "forces_N": list(self.forces_N),
                "baseline": np.where(np.isfinite(self.baseline), self.baseline, -1.0).tolist(),
                "scatter": np.where(np.isfinite(self.scatter), self.scatter, -1.0).tolist()}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1), encoding="utf-8")

    @classmethod
    def from_json(cls, data, shape: tuple[int, int], where: str = "reference") -> Reference:
        if not isinstance(data, dict) or data.get("format") != REFERENCE_FORMAT:
            raise FlatFieldError(f"{where}: not a Palpation Console reference palpation")
        try:
            forces = tuple(float(f) for f in data["forces_N"])
            baseline = np.asarray(data["baseline"], dtype=float)
            scatter = np.asarray(data["scatter"], dtype=float)
            areas = int(data.get("areas", 0))
            description = str(data.get("description", ""))
            # files written before the key existed came from ``stitch``, whose default has physics
            physics = data.get("physics", True)
            if not isinstance(physics, bool):
                raise ValueError(f"physics must be true or false, not {physics!r}")
        except (KeyError, TypeError, ValueError) as err:
            raise FlatFieldError(f"{where}: damaged ({err})") from None
        if not forces or baseline.shape != (len(forces), *shape) or scatter.shape != baseline.shape:
            raise FlatFieldError(f"{where}: made for another array (levels x elements {baseline.shape}, this "
                                 f"array has {shape})")
        if not all(math.isfinite(f) and f > 0 for f in forces):
            raise FlatFieldError(f"{where}: force levels must be finite and positive")
        baseline = np.where(baseline > 0, baseline, np.nan)
        scatter = np.where(scatter >= 0, scatter, np.nan)
        return cls(forces, baseline, scatter, areas, description, physics)

    @classmethod
    def load(cls, path: str | Path, shape: tuple[int, int]) -> Reference:
        try:
            # opened without blocking, so that a FIFO with no writer is refused instead of waited on
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
            if not stat.S_ISREG(os.fstat(fd).st_mode):  # a folder, a FIFO, a device (/dev/zero never ends)
                os.close(fd)
                raise FlatFieldError(f"{path}: not a regular file: not a reference palpation")
            with open(fd, "rb") as f:
                raw = f.read(MAX_REFERENCE_BYTES + 1)
            if len(raw) > MAX_REFERENCE_BYTES:
                raise FlatFieldError(f"{path}: larger than {MAX_REFERENCE_BYTES >> 20} MB: not a reference palpation "
                                     "(one is well under 1 MB)")
            data = json.loads(raw.decode("utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise FlatFieldError(f"{path}: cannot read the reference palpation ({err})") from None
        return cls.from_json(data, shape, str(path))

    @classmethod
    def from_levels(cls, levels: np.ndarray, share: np.ndarray, share_sigma: np.ndarray,
                    description: str, physics: bool = True, quantity: str = "pressure_pa") -> Reference:
        """The reference a palpation of tumour-free tissue gives (its level records and their physics;
        ``physics`` False: the share is one everywhere and the baseline is the face's whole pattern).
        ``quantity``: the level field whose pattern it holds (the stiffness map's, ``stiffness_pa``, differs
        from the pressure's where the surface is uneven)."""
        forces, baselines, scatters = [], [], []
        measured = _measured(levels, quantity)
        for force, records in level_groups(levels):
            base, scale, _ = _session_baseline(measured[records], share[records], share_sigma[records], physics)
            rel = measured[records] / (scale[:, None, None] * base * share[records]) - 1.0
            forces.append(force)
            baselines.append(base)
            scatters.append(1.4826 * np.nanmedian(np.abs(rel), axis=0) if len(records) > 1
                            else np.full(base.shape, np.nan))
        if not forces:
            raise FlatFieldError("the reference palpation recorded no level")
        areas = len(np.unique(levels["region"]))
        return cls(tuple(forces), np.array(baselines), np.array(scatters), areas, description, physics)


@dataclass
class Contrast:
    """One map's contrast for every level record: (n, rows, cols) arrays, NaN where an element has none."""

    map: str  # "stiffness" or "force"
    contrast: np.ndarray
    sigma: np.ndarray  # relative uncertainty (one standard deviation)
    expected_pa: np.ndarray  # what homogeneous tissue would have read
    source: str  # "reference" | "session"
    description: str  # how the expected pattern was obtained, in words
    share: np.ndarray  # the physics it was made with (see :func:`contrast`)
    share_sigma: np.ndarray
    physics: bool  # whether ``share`` came from physics (else it is one everywhere)
    # (n, modes, rows, cols) the share's uncertainties shared between elements, one standard deviation each
    # (``sigma`` holds them too); None: every element's uncertainty is its own
    modes: np.ndarray | None = None

    @property
    def z(self) -> np.ndarray:
        """Contrast over its uncertainty."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.contrast / self.sigma


def _measured(levels: np.ndarray, quantity: str = "pressure_pa") -> np.ndarray:
    """Each element's mean pressure (or other ``quantity``) where it was in contact (its Eq. 1 inputs exist),
    NaN elsewhere."""
    values = levels[quantity]
    return np.where(np.isfinite(levels["dL_m"]) & (levels["pressure_pa"] > 0) & (values > 0), values, np.nan)


def _weighted_median(values: np.ndarray, weights: np.ndarray, axis: int = 0) -> np.ndarray:
    """Median along ``axis`` with weights (NaN values and zero weights ignored)."""
    v = np.moveaxis(values, axis, 0)
    w = np.moveaxis(np.where(np.isfinite(values), weights, 0.0), axis, 0)
    order = np.argsort(np.where(np.isfinite(v), v, np.inf), axis=0)
    v = np.take_along_axis(v, order, 0)
    w = np.take_along_axis(w, order, 0)
    cum = np.cumsum(w, axis=0)
    total = cum[-1]
    idx = np.argmax(cum >= 0.5 * total, axis=0)
    out = np.take_along_axis(v, idx[None], 0)[0]
    return np.where(total > 0, out, np.nan)


def _trusted(share_sigma: np.ndarray) -> np.ndarray:
    """The element-records whose physics is about as sure as is usual at this level: a bump's flank in some
    areas must not set the baseline, nor the scatter of healthy tissue, of the flat ones."""
    sigma = np.nan_to_num(share_sigma, nan=np.inf)
    typical = float(np.median(sigma[np.isfinite(sigma)])) if np.isfinite(sigma).any() else 0.0
    return sigma <= max(2.0 * typical, ACCURACY)


def _session_baseline(measured: np.ndarray, share: np.ndarray, share_sigma: np.ndarray, bounded: bool = True,
                      iterations: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(baseline per element, scale per record, the baseline's uncertainty per element) estimated from the
    records of one level together. An element counts towards its baseline only in the records that trust
    their physics there (:func:`_trusted`), and needs ``MIN_VOUCHING`` of them, so that one area with a
    tumour cannot be taken for the baseline. An element too few records vouch for is given what the
    vouched elements of its part of the face (:func:`_face_parts`) have, their median, and their spread as
    its uncertainty (zero where vouched): the physics' systematic error is mostly a part's (at finite strain
    the edge rows stiffen faster than the inside, by about a tenth at 5 N), and an element left at one
    there read 8 % harder than healthy tissue in three areas in a row. ``bounded``: the physics gave the
    face's pattern, and the baseline only corrects it (:func:`_within_parts`)."""
    ratio = measured / share
    trusted = _trusted(share_sigma) & np.isfinite(ratio)
    sigma = np.nan_to_num(share_sigma, nan=np.inf)
    enough = trusted.sum(axis=0) >= MIN_VOUCHING
    weight = np.where(trusted & enough[None], 1.0 / (ACCURACY ** 2 + sigma ** 2), 0.0)
    base = np.ones(measured.shape[1:])
    spread = np.zeros(base.shape)
    scale = np.ones(len(measured))
    for _ in range(iterations):
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.nanmedian((ratio / base).reshape(len(measured), -1), axis=1)
            base = _weighted_median(ratio / scale[:, None, None], weight, axis=0)
        vouched = enough & np.isfinite(base)
        base = np.where(vouched, base, 1.0)
        base = base / np.median(base[vouched]) if vouched.any() else base
        base, spread = _unvouched(base, vouched, BASELINE_RANGE if bounded else 1.0)
        if bounded:
            base = _within_parts(base)
    return base, scale, spread


def _within_parts(base: np.ndarray) -> np.ndarray:
    """``base`` with each element within ``BASELINE_RANGE`` of its part of the face's median, and that
    median within ``PART_RANGE`` of one (of one itself, in a part of fewer than ``MIN_PART_LEVEL``
    elements). Bounded about one everywhere, an edge row's element whose sensitivity was a few percent
    above its row's, on a level where the physics missed the row by a tenth, read 6-10 % harder than
    healthy tissue in every area (a false tumour on a held-out phantom of the study)."""
    parts = _face_parts(base.shape)
    out = base.copy()
    for part in np.unique(parts):
        here = parts == part
        centre = 1.0
        if here.sum() >= MIN_PART_LEVEL:
            centre = float(np.clip(np.median(base[here]), 1.0 / (1.0 + PART_RANGE), 1.0 + PART_RANGE))
        out[here] = np.clip(base[here], centre / (1.0 + BASELINE_RANGE), centre * (1.0 + BASELINE_RANGE))
    return out


def _robust_spread(deviations: np.ndarray, floor: float) -> float:
    """The standard deviation the median absolute deviation implies (NaNs ignored), never below ``floor``."""
    return max(floor, 1.4826 * float(np.nanmedian(np.abs(deviations))))


# a part of the face needs this many vouched elements to stand for its others (a median and a spread)
MIN_PART_VOUCHED = 4


def _unvouched(base: np.ndarray, vouched: np.ndarray, unknown: float) -> tuple[np.ndarray, np.ndarray]:
    """(baseline, its uncertainty) with each unvouched element given the median and the robust spread of the
    vouched elements of its part of the face, or of the whole face where its part has too few, or one
    and ``unknown`` where the face has too few."""
    if vouched.all():
        return base, np.zeros(base.shape)
    parts = _face_parts(base.shape)
    out, spread = base.copy(), np.zeros(base.shape)
    for part in np.unique(parts):
        missing = (parts == part) & ~vouched
        if not missing.any():
            continue
        known = base[(parts == part) & vouched]
        if len(known) < MIN_PART_VOUCHED:
            known = base[vouched]
        if len(known) < MIN_PART_VOUCHED:
            out[missing], spread[missing] = 1.0, unknown
            continue
        centre = float(np.median(known))
        out[missing] = centre
        spread[missing] = _robust_spread(known - centre, ACCURACY)
    return out, spread


def _baseline_without_each(measured: np.ndarray, share: np.ndarray, share_sigma: np.ndarray, bounded: bool,
                           voters: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(baseline per record and element, scale per record, the baseline's uncertainty per record and
    element), each record's baseline estimated from the other records of its level that may vote
    (``voters``, all if None): a record must not vouch for itself (the median of five would then return
    one of its own readings exactly, and the scatter of healthy tissue measured on those residuals would
    come out too small), nor can a tumour under it lift its own baseline."""
    n = len(measured)
    voters = np.ones(n, bool) if voters is None else voters
    if voters.sum() <= MIN_VOUCHING:  # too few others to vouch: everything is left to the shared estimate
        base, scale, spread = _session_baseline(measured[voters], share[voters], share_sigma[voters], bounded)
        if not voters.all():
            with np.errstate(invalid="ignore", divide="ignore"):
                scale = np.nanmedian((measured / (share * base)).reshape(n, -1), axis=1)
        return np.broadcast_to(base, measured.shape).copy(), scale, np.broadcast_to(spread, measured.shape).copy()
    bases = np.empty(measured.shape)
    spreads = np.empty(measured.shape)
    scales = np.empty(n)
    for i in range(n):
        others = voters & (np.arange(n) != i)
        base, _, spread = _session_baseline(measured[others], share[others], share_sigma[others], bounded)
        with np.errstate(invalid="ignore", divide="ignore"):
            scales[i] = np.nanmedian(measured[i] / (share[i] * base))
        bases[i], spreads[i] = base, spread
    return bases, scales, spreads


# A record whose contrasts' mean square over its face, in their standard deviations, passes this is not
# homogeneous tissue, nor does one that passes three times its level's median: it does not vote on its
# level's baseline. Measured on simulated sessions: healthy areas give 0.1-1.4; areas on a bump 1.2-4 (the
# physics' error there is shared by the other areas on the bump, whose votes correct it: setting them aside
# at 2 raised bump tops as tumours on the paper's uneven phantom); areas over a tumour or beside a large
# one 5-400.
DEPARTURE_LIMIT = 8.0


def _departures(rel: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Each record's mean square contrast over its face, in standard deviations (NaN: no element)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        z2 = (rel / sigma) ** 2
    counted = np.isfinite(z2).sum(axis=(1, 2))
    return np.where(counted > 0, np.nansum(z2, axis=(1, 2)) / np.maximum(counted, 1), np.nan)


def _voters(departure: np.ndarray) -> np.ndarray:
    """The records that may vote on their level's baseline: all but those that depart from homogeneous
    tissue (``DEPARTURE_LIMIT``), keeping at least ``MIN_VOUCHING`` + 1, the least departing."""
    d = np.nan_to_num(departure, nan=np.inf)
    typical = float(np.median(d)) if len(d) else 0.0
    voters = ~((d > DEPARTURE_LIMIT) & (d > 3.0 * typical))
    keep = min(len(d), MIN_VOUCHING + 1)
    if voters.sum() < keep:
        voters = np.zeros(len(d), bool)
        voters[np.argsort(d, kind="stable")[:keep]] = True
    return voters


def _face_parts(shape: tuple[int, int]) -> np.ndarray:
    """Each element's part of the face: 0 inside, 1 the two edge rows across the face's length, 2 the two
    side columns along it, 3 the four corners."""
    rows, cols = shape
    parts = np.zeros(shape, dtype=int)
    parts[[0, rows - 1], :] = 1
    parts[:, [0, cols - 1]] = 2
    parts[np.ix_([0, rows - 1], [0, cols - 1])] = 3
    return parts


# A robust spread from fewer contrasts than this is itself uncertain by more than about a fifth: a part of
# the face with fewer takes the whole face's.
MIN_PART_CONTRASTS = 16


def _healthy_scatter(rel: np.ndarray, accuracy: float) -> np.ndarray:
    """(rows, cols) the scatter of healthy tissue at one level: the robust spread of the level's contrasts
    ``rel`` (records, rows, cols) over the whole face, or over the element's part of it (:func:`_face_parts`)
    where that is larger. The physics is least sure where the face ends: in the simulated sessions the side
    columns, where the face meets the tissue's free sides, scatter two to three times as much as the rest,
    and one spread for the whole face let them raise spots at several times the stated false-alarm rate."""
    if not np.isfinite(rel).any():
        return np.full(rel.shape[1:], accuracy)
    whole = _robust_spread(rel, accuracy)
    parts = _face_parts(rel.shape[1:])
    out = np.full(rel.shape[1:], whole)
    for part in np.unique(parts):
        values = rel[:, parts == part]
        if np.isfinite(values).sum() >= MIN_PART_CONTRASTS:
            # Never below the whole face's: a part that scattered less over a handful of areas is no surer
            # for it (the paper's flat phantom: its side columns' own spread, 0.02, let the load a shallow
            # tumour moves onto them, +0.1, read as two more tumours).
            out[parts == part] = max(whole, _robust_spread(values, accuracy))
    return out


def contrast(levels: np.ndarray, map_name: str, share: np.ndarray | None = None,
             share_sigma: np.ndarray | None = None, reference: Reference | None = None,
             accuracy: float = ACCURACY, description: str = "", share_modes: np.ndarray | None = None
             ) -> Contrast:
    """The ``map_name`` contrast of every level record (see the module docstring). ``share``/``share_sigma``:
    the physics (None: one everywhere, exactly known), and ``share_modes`` the part of ``share_sigma``
    shared between elements (None: none); ``reference``: the baseline to use instead of the
    session's own estimate: one made without physics holds the face's whole pattern, so it stands in for
    the physics too; one made over the physics' share needs the same physics here (raises FlatFieldError)."""
    if map_name not in MAPS:
        raise ValueError(f"unknown map {map_name!r} (known: {', '.join(MAPS)})")
    if reference is not None:
        reference.check_usable(with_physics=share is not None)
    if reference is not None and not reference.physics:
        share = share_sigma = share_modes = None
        description = ""
    measured = _measured(levels)
    shape = measured.shape
    physics = share is not None
    share = np.ones(shape) if share is None else np.where(np.isfinite(measured), share, np.nan)
    share_sigma = np.zeros(shape) if share_sigma is None else share_sigma
    noise = levels["pressure_std_pa"] / np.sqrt(np.maximum(levels["window_frames"], 1))[:, None, None]
    expected = np.full(shape, np.nan)
    sigma = np.full(shape, np.nan)
    set_aside = set()
    for force, records in level_groups(levels):
        m, s, g = measured[records], share[records], share_sigma[records]
        with np.errstate(invalid="ignore", divide="ignore"):
            sensor = np.nan_to_num(noise[records] / m, nan=0.0)
        voters = None
        # Twice without a reference: the median over areas outvotes one area over a tumour, not three (a
        # large or deep tumour changes the load of the whole face in the areas either side of it too, and
        # their median then paints its mirror image on every healthy area); the second time the areas whose
        # contrast departs from homogeneous tissue do not vote.
        for _ in range(2):
            if reference is not None:
                base, ref_scatter = reference.at(force)
                with np.errstate(invalid="ignore", divide="ignore"):
                    scale = np.nanmedian((m / (s * base)).reshape(len(records), -1), axis=1)
            else:
                base, scale, ref_scatter = _baseline_without_each(m, s, g, physics, voters)
            exp = scale[:, None, None] * base * s
            with np.errstate(invalid="ignore", divide="ignore"):
                rel = np.where(_trusted(g), m / exp - 1.0, np.nan)
            healthy = _healthy_scatter(rel, accuracy)
            sig = np.sqrt(sensor ** 2 + healthy ** 2 + np.nan_to_num(ref_scatter, nan=0.0) ** 2 + g ** 2)
            if reference is not None or voters is not None:
                break
            voters = _voters(_departures(rel, sig))
            if voters.all():
                break
            set_aside.update(int(r) for r in levels["region"][records[~voters]])
        expected[records] = exp
        sigma[records] = sig
    with np.errstate(invalid="ignore", divide="ignore"):
        values = measured / expected - 1.0
    values = np.where(np.isfinite(values) & np.isfinite(sigma), values, np.nan)
    if reference is not None:
        source, how = "reference", f"reference palpation ({reference.description})"
    else:
        source, how = "session", f"estimated from this session's {len(np.unique(levels['region']))} areas"
        if set_aside:
            how += (f" ({len(set_aside)} of them not homogeneous tissue at some level and left out of "
                    "its estimate there)")
    what = f"{description}; baseline {how}" if description else f"no physics; baseline {how}"
    modes = None if share_modes is None else np.where(np.isfinite(values)[:, None], share_modes, 0.0)
    return Contrast(map_name, values, np.where(np.isfinite(values), sigma, np.nan), expected, source, what, share,
                    share_sigma, physics, modes)
