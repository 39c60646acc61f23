"""Winkler (local spring) tissue: the baseline the continuum model is measured against.

Each TSI element presses on its own vertical column of tissue, from the table up to the phantom's surface
under the element's centre, and the columns do not interact. A column of length ``L0`` compressed by
``dL`` pushes back with ``F = A * dL / C``, where ``C = sum(L_i / E_i)`` is its compliance per unit area:
the soft tissue and, where the column passes through a spherical inclusion, the chord through the sphere
at the inclusion's modulus, in series. Without inclusions this is Eq. 1 read backwards,
``F = E * A * dL / L0``. Contact is unilateral (a column never pulls on the TSI), and an element over a
lower part of an uneven surface, or off the phantom, simply does not touch.

What it gets wrong, on purpose: real tissue is a continuum. Pressing a rigid 8 x 30 mm face into a
25 mm layer drags the surrounding material down with it, so the real punch needs 2-3 times the force
this model predicts for the same indentation (for the flat phantom, 2.4 times by the elastic half-space
solution for a rigid disc of the same area, more on a layer bonded to the table); the pressure peaks at
the face's edges instead of being uniform; and an inclusion is felt only by the elements right above it,
at any depth, rather than as a broad bump that fades with depth. Those are the effects the continuum
model exists for; this model is the cheap, transparent reference and a fast tissue for tests.

A consequence to keep in mind: on the flat phantom (20 kPa, 25 mm) the whole face gives only
``E * A / L0 = 192 N/m``, so reaching the paper's 7 N takes 36 mm, more than the tissue is thick; ramps
on this tissue must stop at about 3 N (16 mm indentation).

Simplifications: each element is represented by the column under its centre; strains are small (the
column's compliance is that of its undeformed length); overlapping inclusions are not expected (their
chords are summed and capped at the column length).
"""

from __future__ import annotations

import numpy as np

from tissue.face import Face
from tissue.phantom import Phantom


class WinklerTissue:
    def __init__(self, phantom: Phantom, sensor: Face | None = None):
        self.phantom = phantom
        sensor = sensor if sensor is not None else Face()
        self.shape = sensor.shape
        self._offsets = sensor.element_offsets_m()
        self._area_m2 = sensor.element_area_m2

    def column(self, x_m: float, y_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(surface height L0, compliance per unit area C in m/Pa) of each element's column, TSI at (x, y)."""
        ex = x_m + self._offsets[..., 0]
        ey = y_m + self._offsets[..., 1]
        top = self.phantom.surface_height_m(ex, ey)
        soft = top.copy()
        compliance = np.zeros_like(top)
        for inc in self.phantom.inclusions:
            half = np.sqrt(np.clip(inc.radius_m**2 - (ex - inc.x_m) ** 2 - (ey - inc.y_m) ** 2, 0.0, None))
            chord = np.clip(np.minimum(inc.z_m + half, top) - np.maximum(inc.z_m - half, 0.0), 0.0, None)
            chord = np.minimum(chord, soft)
            compliance += chord / inc.youngs_modulus_pa
            soft -= chord
        compliance += soft / self.phantom.youngs_modulus_pa
        return top, compliance

    def element_forces_N(self, x_m: float, y_m: float, z_m: float) -> np.ndarray:
        top, compliance = self.column(x_m, y_m)
        dL = np.clip(top - z_m, 0.0, top)
        forces = np.zeros(self.shape)
        touching = dL > 0.0
        forces[touching] = self._area_m2 * dL[touching] / compliance[touching]
        return forces
