"""Old import paths of the localizer's settings and factory (kept working): the settings live in
:mod:`rangemcl.localization.settings`, the factories in :mod:`rangemcl.localization.factory`, the filter
core in :mod:`rangemcl.localization.filter`, the SE(2) helpers in :mod:`rangemcl.se2`.
"""

from __future__ import annotations

from rangemcl.localization.factory import (
    build_localizer,
    map_place_prior,
    prepare_rays,
    ray_selector,
    scan_refiner,
)
from rangemcl.localization.filter import MonteCarloLocalizer, StepInfo
from rangemcl.localization.settings import (
    ConvergenceSettings,
    InitSettings,
    LocalizerSettings,
    MotionSettings,
    ObservationSettings,
    ParticleSettings,
    RecoverySettings,
    RefineSettings,
)
from rangemcl.localization.spread import DrivableArea, drivable_cells
from rangemcl.se2 import rotation_roll_pitch, se2_between, se2_compose, wrap_angle

__all__ = [
    "ConvergenceSettings",
    "DrivableArea",
    "InitSettings",
    "LocalizerSettings",
    "MonteCarloLocalizer",
    "MotionSettings",
    "ObservationSettings",
    "ParticleSettings",
    "RecoverySettings",
    "RefineSettings",
    "StepInfo",
    "build_localizer",
    "drivable_cells",
    "map_place_prior",
    "prepare_rays",
    "ray_selector",
    "rotation_roll_pitch",
    "scan_refiner",
    "se2_between",
    "se2_compose",
    "wrap_angle",
]
