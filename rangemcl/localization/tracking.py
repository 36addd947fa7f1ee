"""The converged filter's tracking (:class:`Tracking`): what a filter that has found its place does beyond
predicting and weighing.

* **Refinement**: each update's rays are aligned to the mesh from the estimate
  (:mod:`rangemcl.localization.refine`) and the cloud moves by the correction when it lies within the
  cloud's own spread (else it is refused and counted).
* **Odometry calibration** (:mod:`rangemcl.localization.calibration`): every odometry increment is
  corrected with the running calibration (while searching too); the raw odometry between two converged
  updates, against the estimate's motion over the same interval, estimates the odometry's scale and the
  gyro's bias, or, with the particle calibration, each particle carries its own scale and bias, drawn
  when tracking starts, carried along by the resampling and weighted with the particles.
* **Resampling once converged**: low-variance resampling, roughened with the tracking's jitter.

Its state (the refiner, the calibrator, their counts and the calibration's current interval) is its own,
so it is a part that :class:`rangemcl.localization.filter.MonteCarloLocalizer` composes
(``MonteCarloLocalizer.tracking``) rather than more methods of the filter: each call is handed the cloud,
the estimate and the generator it needs, and returns the cloud and the estimate it moved.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from rangemcl.localization.calibration import OdometryCalibrator, ParticleCalibration
from rangemcl.localization.particles import resample_roughened
from rangemcl.localization.refine import ScanRefiner
from rangemcl.localization.scan_prep import ScanRays
from rangemcl.se2 import se2_compose, wrap_angle


class Tracking:
    """Refinement, odometry calibration and resampling of a converged filter (module docstring).

    Args:
        refiner: scan-to-mesh refinement of the converged pose; None: none (the paper's filter).
        calibrator: the odometry's calibration (applied to every increment; estimated online where it is
            set to); None: the odometry as it comes.
        refine_gate_m, refine_gate_deg: a refinement is taken when its correction is within this much
            beyond twice the cloud's own spread (x and y together, and yaw).
        refine_all_heights_updates: the updates after a search's convergence (or a start at an approximate
            pose) that refine with every hit, the lowest metres included.
        calibration_settle_updates: the updates after a convergence left out of the calibration (while the
            cloud settles on its place).
        sensor_height_m: the sensor's height above the ground.
        jitter_xy_m, jitter_yaw_deg: the roughening after each resampling.
    """

    def __init__(
        self,
        *,
        refiner: ScanRefiner | None,
        calibrator: OdometryCalibrator | ParticleCalibration | None,
        refine_gate_m: float,
        refine_gate_deg: float,
        refine_all_heights_updates: int,
        calibration_settle_updates: int,
        sensor_height_m: float,
        jitter_xy_m: float,
        jitter_yaw_deg: float,
    ):
        self.refiner = refiner
        self.calibrator = calibrator
        self.refine_gate = (float(refine_gate_m), math.radians(refine_gate_deg))
        self.refine_all_heights_updates = int(refine_all_heights_updates)
        self.calibration_settle_updates = int(calibration_settle_updates)
        self.sensor_height_m = float(sensor_height_m)
        self.jitter = (float(jitter_xy_m), float(jitter_yaw_deg))
        self.refinements = 0  # refinements taken ...
        self.refused_refinements = 0  # ... and refused (outside the cloud's spread)
        self._since_search = -1  # updates since the search declared convergence (-1: tracking start)
        self._calib_ref: np.ndarray | None = None  # estimate at the last converged update
        self._settled = 0  # updates since the last convergence (or tracking start)
        self._raw_since_ref = np.zeros(3)  # raw odometry since then (in that pose) ...
        self._dt_since_ref = 0.0  # ... and the time it took (NaN: a frame without a time)
        self._dt_pending = 0.0  # seconds of the odometry not yet applied to the particles

    @property
    def particle_calibration(self) -> bool:
        """The calibration is carried by the particles (:class:`ParticleCalibration`)."""
        return isinstance(self.calibrator, ParticleCalibration)

    # --- the odometry, every frame ------------------------------------------------------------------------

    def odometry(self, delta: np.ndarray, dt_s: float | None) -> np.ndarray:
        """A frame's raw odometry increment over ``dt_s`` seconds (None: unknown), kept for the
        calibration's interval; returns it corrected with the running calibration."""
        self._raw_since_ref = se2_compose(self._raw_since_ref, delta)
        self._dt_since_ref += dt_s if dt_s is not None else math.nan
        self._dt_pending += dt_s if dt_s is not None else math.nan
        if self.calibrator is not None:
            delta = self.calibrator.correct(delta, dt_s)
        return delta

    def increments(self, increment, moved_m: float, rng: np.random.Generator):
        """The prediction's ``(rot1, trans, rot2)``: per particle, with each one's own scale and bias,
        while the particles carry calibration states (their random walk over ``moved_m`` metres and the
        seconds since the last prediction drawn from ``rng``); else as given."""
        if self.particle_calibration and self.calibrator.state is not None:
            increment = self.calibrator.increments(increment, self._dt_pending, moved_m, rng)
        self._dt_pending = 0.0
        return increment

    # --- starting and stopping ----------------------------------------------------------------------------

    def start(self, n: int, rng: np.random.Generator, *, settle: bool) -> None:
        """Tracking starts with ``n`` particles (a search's convergence, or a start at a pose): the particle
        calibration draws their states; ``settle``: the first ``refine_all_heights_updates`` refine with
        every hit (the place may still be off by decimetres)."""
        self._since_search = 0 if settle else -1
        if self.particle_calibration:
            self.calibrator.start(n, rng)

    def stop(self) -> None:
        """The filter searches again: the particle calibration's states go (its running estimate stays)."""
        if self.particle_calibration:
            self.calibrator.stop()

    def new_interval(self) -> None:
        """A new cloud: the calibration's interval starts again."""
        self._calib_ref = None
        self._raw_since_ref = np.zeros(3)
        self._dt_since_ref = 0.0

    # --- a converged update -------------------------------------------------------------------------------

    def resample(
        self, particles: np.ndarray, weights: np.ndarray, rng: np.random.Generator, n: int
    ) -> np.ndarray:
        """``n`` particles resampled and roughened with the tracking's jitter; the particle calibration's
        states follow their particles."""
        parts, idx = resample_roughened(particles, weights, rng, n, *self.jitter)
        if self.particle_calibration:
            self.calibrator.resampled(idx)
        return parts

    def update(
        self,
        rays: ScanRays,
        particles: np.ndarray,
        weights: np.ndarray,
        estimate: np.ndarray,
        sensor_z: Callable[[np.ndarray], np.ndarray],
        *,
        refine: bool,
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """After a converged update's weighing (and resampling): the particle calibration's running estimate
        from the weights, then, with ``refine`` (the lost watch has no doubt), the refinement
        (:meth:`refine`). Returns the cloud and the estimate (moved by a refinement taken) and the
        refinement's :class:`~rangemcl.localization.filter.StepInfo` fields."""
        if self.particle_calibration:
            self.calibrator.weighted(weights)
        out = {}
        if refine and self.refiner is not None:
            particles, estimate, out = self.refine(rays, particles, weights, estimate, sensor_z)
        if self._since_search >= 0:
            self._since_search += 1
        return particles, estimate, out

    def refine(
        self,
        rays: ScanRays,
        particles: np.ndarray,
        weights: np.ndarray,
        estimate: np.ndarray,
        sensor_z: Callable[[np.ndarray], np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """Align the update's rays to the mesh from the estimate (:mod:`rangemcl.localization.refine`);
        take the correction (the whole cloud moves by it) when it lies within the cloud's own spread.
        ``sensor_z``: the sensor's world z over ``(x, y)`` rows. Returns the cloud and the estimate (moved
        when taken, else as given) and the fields ``refined`` and ``refine_shift_m``."""
        est = estimate
        z = float(sensor_z(est[None, :2])[0])
        # just after a search declared convergence the cloud's place along a street may still be off by
        # decimetres that the facades do not constrain: the lowest metres (kerbs, parked cars) take part
        all_heights = 0 <= self._since_search < self.refine_all_heights_updates
        ref = self.refiner.refine(
            rays.directions,
            rays.ranges,
            est,
            z,
            ground_z=None if all_heights else z - self.sensor_height_m,
        )
        if ref is None:
            return particles, estimate, {}
        w = weights
        spread_xy = math.sqrt(
            float(np.sum(w * ((particles[:, 0] - est[0]) ** 2 + (particles[:, 1] - est[1]) ** 2)))
        )
        spread_yaw = math.sqrt(float(np.sum(w * wrap_angle(particles[:, 2] - est[2]) ** 2)))
        shift = math.hypot(ref.correction[0], ref.correction[1])
        if (
            shift > self.refine_gate[0] + 2.0 * spread_xy
            or abs(ref.correction[2]) > self.refine_gate[1] + 2.0 * spread_yaw
        ):
            self.refused_refinements += 1
            return particles, estimate, dict(refined=-1, refine_shift_m=shift)
        moved = particles + ref.correction
        moved[:, 2] = wrap_angle(moved[:, 2])
        self.refinements += 1
        return moved, ref.pose.copy(), dict(refined=1, refine_shift_m=shift)

    def calibrate(self, converged: bool, recovered: bool, converged_now: bool, estimate: np.ndarray) -> None:
        """After a weighted update: the interval since the last converged update feeds the odometry's
        calibration (:mod:`rangemcl.localization.calibration`); a search, a recovery or a convergence
        starts a new interval instead, and the first ``calibration_settle_updates`` after a convergence
        (while the cloud settles on its place) are left out."""
        if self.calibrator is None:
            return
        steady = converged and not recovered and not converged_now
        self._settled = self._settled + 1 if steady else 0
        if steady and self._calib_ref is not None and self._settled > self.calibration_settle_updates:
            dt = self._dt_since_ref if math.isfinite(self._dt_since_ref) else None
            self.calibrator.observe(self._raw_since_ref, dt, self._calib_ref, estimate)
        self._calib_ref = estimate.copy() if converged and not recovered else None
        self._raw_since_ref = np.zeros(3)
        self._dt_since_ref = 0.0

    def readings(self) -> dict:
        """The calibration's current values as :class:`~rangemcl.localization.filter.StepInfo` fields."""
        if self.calibrator is None:
            return {}
        return dict(
            odometry_scale=self.calibrator.scale,
            gyro_bias_deg_s=math.degrees(self.calibrator.gyro_bias),
        )
