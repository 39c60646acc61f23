"""Continuum mechanics of the tissue phantom: what the simulated TSI feels (docs/phantoms.md).

* :mod:`.fem` - linear-elastic hexahedral FE (locking-free Q1/P0), condensed onto the top surface;
* :mod:`.contact` - exact frictionless unilateral contact path of a level rigid face;
* :mod:`.model` - :class:`ContinuumTissue`, the precomputed, cached, per-tick model the rig uses;
* :mod:`.finite_strain` - the face pressed into a block at finite strain, the reference of the model's
  finite-strain factors;
* :mod:`.reference`, :mod:`.validation` - the analytic layer solution and the FE model it checks;
* :mod:`.study` - the paper's palpation protocol run on a tissue model, for reports;
* :mod:`.cache`, :mod:`.progress` - on-disk cache and progress reporting.
"""

from tissue.mechanics.model import ContinuumTissue, MeshSettings
from tissue.mechanics.progress import TextProgressBar

__all__ = ["ContinuumTissue", "MeshSettings", "TextProgressBar"]
