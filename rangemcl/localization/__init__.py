"""The localizer's stages, one module each (docs/architecture.md, "Where each piece lives"):

* ``scan_prep``: the scan's rays for one update (sampling, de-skew, levelling);
* ``renderer``: every particle's view of the map for those rays, reduced to residuals (one Warp kernel);
* ``models``: the observation models that turn them into likelihoods (paper Eq. 5 and three baselines);
* ``spread``: the drivable area where global localization spreads its particles;
* ``place_prior``: map-rendered profiles matched against the scan at every yaw;
* ``hypotheses``: clusters, their evidence and the sequential convergence test;
* ``lost``: the evidence watch and the second opinion of a converged filter;
* ``refine`` and ``calibration``: scan-to-mesh refinement of a converged pose, and the odometry's online
  calibration;
* ``filter``: the core (``MonteCarloLocalizer.step``) that composes them, with its three phases beside
  it: ``search`` (the global search while not converged: the prior's draws, the polish of the hypotheses,
  the convergence test), ``tracking`` (a converged filter's refinement, odometry calibration and
  resampling) and ``recovery`` (the lost watch, the second opinion and the re-spread);
* ``particles``: the odometry motion model and resampling;
* ``settings`` and ``factory``: the YAML settings (every default) and the factories that build the filter
  and its parts from them;
* ``pipeline``: a run over a recording (``rangemcl localize``): load, filter every frame, write the
  trajectory, metrics, summary and plots.

They import numpy, scipy, Warp and rangemcl's foundation, sensing core and maps; only ``pipeline`` reads
recordings and writes results. The package's own names (``from rangemcl.localization import
LocalizerSettings, build_localizer``) are the localizer's public face; they are imported when first used.
"""

_PUBLIC = {
    "build_localizer": "factory",
    "map_place_prior": "factory",
    "prepare_rays": "factory",
    "ray_selector": "factory",
    "scan_refiner": "factory",
    "MonteCarloLocalizer": "filter",
    "StepInfo": "filter",
    "DrivableArea": "spread",
    "drivable_cells": "spread",
    "LocalizerSettings": "settings",
    "ParticleSettings": "settings",
    "MotionSettings": "settings",
    "ObservationSettings": "settings",
    "ConvergenceSettings": "settings",
    "RecoverySettings": "settings",
    "RefineSettings": "settings",
    "InitSettings": "settings",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    """The public names, from their modules, on first use (importing the package stays cheap)."""
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'rangemcl.localization' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"rangemcl.localization.{module}"), name)
