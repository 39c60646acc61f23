"""The ground floor: the tissue and the probe's face as the simulated rig and the analysis both see them.

Phantom definitions and their schema (:mod:`.phantom`, the shipped ones in ``phantoms/``), the seeded
distribution of phantoms nobody designed for (:mod:`.generator`), the continuum mechanics (:mod:`.mechanics`),
the Winkler columns (:mod:`.winkler`), and the face's geometry, the cover's spread and Eq. 1 (:mod:`.face`).
It imports nothing of the project's: everything else stands on it.
"""
