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
* ``filter``: the core (``MonteCarloLocalizer.step``) that composes them;
* ``settings`` and ``factory``: the YAML settings (every default) and the factories that build the filter
  and its parts from them (``rangemcl.mcl`` re-exports both).

They import numpy, scipy, Warp and rangemcl's numeric core (``se2``, ``raycast``, ``particles``); the
command-line pipeline (``rangemcl.localize``) builds on them.
"""
