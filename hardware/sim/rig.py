"""Build the simulated rig: tactile sensor, slave robot and scripted operator sharing one world."""

from __future__ import annotations

import math
from typing import Any

from hardware.interfaces import TactileConstraints
from hardware.rig import Rig
from hardware.sim.operator import ScriptedOperator
from hardware.sim.robot import SimSlave
from hardware.sim.sensor import SimTactileSensor
from hardware.sim.settings import SimSettings
from hardware.sim.tissue import TissueModel
from hardware.sim.world import SimWorld
from tissue.mechanics import ContinuumTissue, MeshSettings
from tissue.mechanics.progress import Progress
from tissue.phantom import Phantom, load_phantom
from tissue.winkler import WinklerTissue


def _resolve(phantom: Phantom | str, settings: SimSettings | dict[str, Any] | None) -> tuple[Phantom, SimSettings]:
    if isinstance(phantom, str):
        phantom = load_phantom(phantom)
    elif not isinstance(phantom, Phantom):
        raise TypeError(f"phantom must be a Phantom or a phantom name, got {type(phantom).__name__}")
    if settings is None:
        settings = SimSettings()
    elif isinstance(settings, dict):
        settings = SimSettings.from_mapping(settings)
    elif not isinstance(settings, SimSettings):
        raise TypeError(f"settings must be SimSettings or a mapping, got {type(settings).__name__}")
    return phantom, settings


def build_tissue(
    phantom: Phantom | str,
    settings: SimSettings | dict[str, Any] | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
) -> TissueModel:
    """The tissue model ``settings.tissue`` names; the continuum model is precomputed on first use of a
    phantom (seconds to a minute, with ``progress`` reports, in up to ``workers`` processes: see
    :meth:`ContinuumTissue.load`) and loaded from the disk cache after that."""
    phantom, settings = _resolve(phantom, settings)
    sensor_geometry = TactileConstraints(full_scale_pa=settings.sensor.full_scale_pa,
                                         frame_rate_hz=settings.sensor.frame_rate_hz)
    if settings.tissue == "winkler":
        return WinklerTissue(phantom, sensor_geometry)
    return ContinuumTissue.load(phantom, progress=progress, sensor=sensor_geometry,
                                settings=MeshSettings(finite_strain=settings.finite_strain,
                                                      tilt_rad=tuple(math.radians(a) for a in settings.probe_tilt_deg)),
                                workers=workers)


def build_sim_rig(
    phantom: Phantom | str,
    settings: SimSettings | dict[str, Any] | None = None,
    tissue: TissueModel | None = None,
    seed: int = 0,
    progress: Progress | None = None,
) -> Rig:
    """The simulated rig for ``phantom`` (a loaded phantom or a shipped phantom's name / a TOML path).

    ``settings`` may be the ``[sim]`` table of a config file; ``tissue`` defaults to the model
    ``settings.tissue`` names (see :func:`build_tissue`); ``seed`` drives the run's sensor noise (the
    sensor as manufactured is fixed by ``settings.sensor.seed``). Raises
    :class:`~tissue.phantom.PhantomError` or :class:`~control.config.ConfigError` naming the bad
    key, or ValueError for a mismatched tissue.
    """
    phantom, settings = _resolve(phantom, settings)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    sensor_geometry = TactileConstraints(full_scale_pa=settings.sensor.full_scale_pa,
                                         frame_rate_hz=settings.sensor.frame_rate_hz)
    if tissue is None:
        tissue = build_tissue(phantom, settings, progress)
    elif tissue.phantom.content_hash() != phantom.content_hash():
        raise ValueError(f"the tissue model was built for phantom {tissue.phantom.name!r} "
                         f"({tissue.phantom.content_hash()}), not for {phantom.name!r} ({phantom.content_hash()})")

    world = SimWorld(phantom, tissue, settings)
    return Rig(
        sensor=SimTactileSensor(world, seed=seed),
        slave=SimSlave(world),
        master=ScriptedOperator(world, sensor_geometry),
        ground_truth=phantom.ground_truth(),
        description={
            "backend": "sim",
            "phantom": phantom.name,
            "phantom_hash": phantom.content_hash(),
            "tissue_model": type(tissue).__name__,
            "seed": seed,
            "settings": settings.to_mapping(),
        },
    )
