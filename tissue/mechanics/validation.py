"""The finite-element model of a wide homogeneous layer under a rigid rectangular punch.

This is the configuration the analytic reference (:mod:`.reference`) describes: a layer of uniform
thickness, bonded to a rigid base, laterally unbounded, indented by a rigid frictionless punch in
full contact. The FE model uses the same elements, grading and condensation as the phantom model;
it is made "unbounded" by extending the block ``margin`` layer thicknesses beyond the punch with
geometrically growing cells (a bonded layer's response decays exponentially with distance over a
few thicknesses), and only a quarter of it is meshed, with symmetry planes through the punch centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tissue.mechanics.fem import HexGrid, condensed_surface_stiffness, graded_levels, table_dofs


def graded_line(fine_to_m: float, spacing_m: float, extent_m: float, growth: float = 1.3) -> np.ndarray:
    """Nodes from 0: uniform ``spacing_m`` up to ``fine_to_m``, then cells growing by ``growth``."""
    n = int(round(fine_to_m / spacing_m))
    pts = list(np.arange(n + 1) * spacing_m)
    step = spacing_m
    while pts[-1] < extent_m - 1e-12:
        step *= growth
        pts.append(min(pts[-1] + step, extent_m))
    if len(pts) >= 3 and pts[-1] - pts[-2] < 0.3 * (pts[-2] - pts[-3]):
        pts.pop(-2)  # no sliver at the far end
    return np.array(pts)


@dataclass(frozen=True)
class LayerPunchResult:
    stiffness_N_m: float
    nodes_under_punch: int
    elements: int
    all_compressive: bool  # every node pushes on the punch, so full contact is the consistent state


def layer_punch_fe_stiffness(size_x_m: float, size_y_m: float, young_pa: float, nu: float, thickness_m: float,
                             spacing_m: float, layers: int, top_layer_m: float, margin: float = 3.0,
                             growth: float = 1.3) -> LayerPunchResult:
    """Punch stiffness of the FE layer (quarter model, symmetry planes x = 0 and y = 0)."""
    half_x, half_y = size_x_m / 2.0, size_y_m / 2.0
    x = graded_line(half_x, spacing_m, half_x + margin * thickness_m, growth)
    y = graded_line(half_y, spacing_m, half_y + margin * thickness_m, growth)
    levels = graded_levels(layers, min(top_layer_m / thickness_m, 1.0 / layers))
    grid = HexGrid(x, y, levels, np.full((len(x), len(y)), thickness_m))
    fixed = table_dofs(grid)
    nx1, ny1, nz1 = grid.node_shape
    i, j, k = np.meshgrid(np.arange(nx1), np.arange(ny1), np.arange(nz1), indexing="ij")
    nodes = grid.node_index(i, j, k)
    fixed[3 * nodes[0].ravel() + 0] = True  # symmetry plane x = 0: no displacement across it
    fixed[3 * nodes[:, 0].ravel() + 1] = True  # symmetry plane y = 0
    under = (x[:, None] <= half_x + 1e-12) & (y[None, :] <= half_y + 1e-12)

    def material(points):
        return np.full(points.shape[:-1], young_pa), np.full(points.shape[:-1], nu)

    ij, stiffness = condensed_surface_stiffness(grid, material, mask=under, fixed=fixed)
    forces = stiffness.sum(axis=1)  # unit indentation of every node under the punch
    # The quarter carries a quarter of the load (nodes on a symmetry plane already carry only the
    # part of their patch inside it).
    return LayerPunchResult(4.0 * float(forces.sum()), len(forces), int(np.prod(grid.shape)),
                            bool(forces.min() > 0.0))
