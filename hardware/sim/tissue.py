"""What the simulated rig needs from a tissue model: per-element contact forces under a rigid TSI."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from tissue.phantom import Phantom


class TissueModel(Protocol):
    phantom: Phantom

    def element_forces_N(self, x_m: float, y_m: float, z_m: float) -> np.ndarray:
        """Normal contact force on each TSI element, shape (4, 15), >= 0, for a rigid, level TSI face
        centred at (x_m, y_m) at height z_m above the table (rows along x, columns along y)."""
        ...
