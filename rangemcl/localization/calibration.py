"""Online calibration of the odometry: its translation scale and the gyro's yaw-rate bias.

Wheel odometry is a few per cent off (tyre pressure, wear, load) and a gyro drifts. The filter predicts
with the odometry, so a 3 % scale error makes every prediction 3 % short or long and the estimate lags by
decimetres. :class:`OdometryCalibrator` is a slow estimator on the filter's own corrections:

* between two updates of a converged filter it compares the **raw** odometry's motion ``o`` (translation
  and yaw, in the pose of the earlier update) with the estimate's motion ``e`` over the same interval;
* the scale is a ratio of distances, ``s = Σ λ (e · ô) / Σ λ |o|``: the estimate's progress along the
  odometry's direction over the odometry's distance (reversing counts alike: both point backwards);
* the bias is ``b = Σ λ (o_yaw − e_yaw) / Σ λ Δt``: the gyro's excess turn per second;
* ``λ`` forgets exponentially, per metre driven for the scale (``window_m``) and per second for the bias
  (``window_s``); both start from the configured values with the weight of ``prior_m`` metres and
  ``prior_s`` seconds, which is forgotten alike.

The estimate's error at any update is a few centimetres and is nearly the same at the next update, so in
the sums it telescopes: over a window of 100 m the scale is known to about the estimate's error over
100 m. A car standing still adds nothing to the scale (``|o|`` = 0) and only time to the bias, where the
gyro's drift while standing is exactly what is measured; turning on the spot adds only to the bias. An
interval whose motion disagrees with the current calibration by more than ``outlier_m`` or
``outlier_deg`` (a recovery, a convergence, a refinement's jump) is left out.

:meth:`correct` applies the current estimates to an odometry increment. Pure Python and numpy.
"""

from __future__ import annotations

import math

import numpy as np

from rangemcl.se2 import se2_between, wrap_angle


class OdometryCalibrator:
    """Running estimates of the odometry's translation scale and the gyro's bias (module docstring).

    Args:
        scale: the configured translation scale (the start; multiplies the odometry's translations).
        gyro_bias_rad_s: the configured gyro bias (the start; subtracted times the elapsed time).
        estimate_scale, estimate_bias: which of the two are estimated (else they stay as configured).
        window_m: the scale's memory: weights fall by ``1/e`` per this many metres driven.
        window_s: the bias's memory, in seconds.
        prior_m, prior_s: the weight of the configured values, as metres and seconds of evidence.
        outlier_m, outlier_deg: intervals disagreeing by more than this are left out.
        min_scale, max_scale: the scale estimate is kept within these.
    """

    def __init__(
        self,
        *,
        scale: float,
        gyro_bias_rad_s: float,
        estimate_scale: bool,
        estimate_bias: bool,
        window_m: float,
        window_s: float,
        prior_m: float,
        prior_s: float,
        outlier_m: float,
        outlier_deg: float,
        min_scale: float,
        max_scale: float,
    ):
        self.scale0 = float(scale)
        self.bias0 = float(gyro_bias_rad_s)
        self.estimate_scale = bool(estimate_scale)
        self.estimate_bias = bool(estimate_bias)
        self.window_m = float(window_m)
        self.window_s = float(window_s)
        self.prior_m = float(prior_m)
        self.prior_s = float(prior_s)
        self.outlier_m = float(outlier_m)
        self.outlier = math.radians(outlier_deg)
        self.min_scale = float(min_scale)
        self.max_scale = float(max_scale)
        self.reset()

    def reset(self) -> None:
        """Back to the configured values."""
        self.scale = self.scale0
        self.gyro_bias = self.bias0
        self._s_num = self.scale0 * self.prior_m
        self._s_den = self.prior_m
        self._b_num = self.bias0 * self.prior_s
        self._b_den = self.prior_s
        self.distance_m = 0.0  # driven while observed
        self.observed = 0
        self.rejected = 0

    def correct(self, delta, dt_s: float | None) -> np.ndarray:
        """An odometry increment ``(dx, dy, dyaw)`` over ``dt_s`` seconds, calibrated."""
        d = np.asarray(delta, np.float64).reshape(3)
        out = np.array([d[0] * self.scale, d[1] * self.scale, d[2]])
        if dt_s is not None and math.isfinite(dt_s):
            out[2] = d[2] - self.gyro_bias * dt_s
        return out

    def observe(self, raw_motion, dt_s: float | None, estimate_before, estimate_after) -> bool:
        """One interval between two updates of a converged filter: the raw odometry's motion (in the
        earlier pose) over ``dt_s`` seconds, and the filter's estimates at both ends. False when left out
        as an outlier."""
        o = np.asarray(raw_motion, np.float64).reshape(3)
        e = se2_between(np.asarray(estimate_before, np.float64), np.asarray(estimate_after, np.float64))
        dist = math.hypot(o[0], o[1])
        dt = float(dt_s) if dt_s is not None and math.isfinite(dt_s) and dt_s > 0 else 0.0
        predicted = self.correct(o, dt if dt > 0 else None)
        if (
            math.hypot(e[0] - predicted[0], e[1] - predicted[1]) > self.outlier_m
            or abs(wrap_angle(e[2] - predicted[2])) > self.outlier
        ):
            self.rejected += 1
            return False
        if self.estimate_scale and dist > 1e-6:
            lam = math.exp(-dist / self.window_m)
            progress = (e[0] * o[0] + e[1] * o[1]) / dist
            self._s_num = lam * self._s_num + progress
            self._s_den = lam * self._s_den + dist
            self.scale = float(np.clip(self._s_num / self._s_den, self.min_scale, self.max_scale))
        if self.estimate_bias and dt > 0:
            lam = math.exp(-dt / self.window_s)
            self._b_num = lam * self._b_num + wrap_angle(o[2] - e[2])
            self._b_den = lam * self._b_den + dt
            self.gyro_bias = self._b_num / self._b_den
        self.distance_m += dist
        self.observed += 1
        return True


class ParticleCalibration:
    """The odometry's scale and the gyro's bias as extra state of a converged filter's particles: the
    alternative to :class:`OdometryCalibrator`'s slow estimator (``motion.calibration: particles``).

    * When the filter converges (or starts tracking), every particle draws its own scale and bias around
      the running estimate (``sigma_scale``, ``sigma_bias_rad_s``);
    * each prediction moves a particle with its own calibration: its distance times its scale, its turn
      less its bias times the elapsed time; the states take a random walk (``walk_scale`` per
      √metre driven, ``walk_bias_rad_s`` per √second) so that resampling does not collapse them;
    * the weighting selects the particles whose calibration predicts the scan, resampling carries their
      states along, and the estimate is the states' weighted mean.

    While the filter searches (not converged) every particle moves with the running estimate, as with
    the slow estimator. Same reading interface as :class:`OdometryCalibrator` (``scale``, ``gyro_bias``,
    ``correct``, ``observe``, ``distance_m``, ``observed``, ``rejected``).
    """

    def __init__(
        self,
        *,
        scale: float,
        gyro_bias_rad_s: float,
        estimate_scale: bool,
        estimate_bias: bool,
        sigma_scale: float,
        sigma_bias_rad_s: float,
        walk_scale: float,
        walk_bias_rad_s: float,
        min_scale: float,
        max_scale: float,
    ):
        self.scale0 = float(scale)
        self.bias0 = float(gyro_bias_rad_s)
        self.estimate_scale = bool(estimate_scale)
        self.estimate_bias = bool(estimate_bias)
        self.sigma_scale = float(sigma_scale) if self.estimate_scale else 0.0
        self.sigma_bias = float(sigma_bias_rad_s) if self.estimate_bias else 0.0
        self.walk_scale = float(walk_scale) if self.estimate_scale else 0.0
        self.walk_bias = float(walk_bias_rad_s) if self.estimate_bias else 0.0
        self.min_scale = float(min_scale)
        self.max_scale = float(max_scale)
        self.reset()

    def reset(self) -> None:
        """Back to the configured values, no particle state."""
        self.scale = self.scale0
        self.gyro_bias = self.bias0
        self.state: np.ndarray | None = None  # (N, 2) scale, bias (rad/s) per particle while converged
        self.distance_m = 0.0
        self.observed = 0
        self.rejected = 0

    def correct(self, delta, dt_s: float | None) -> np.ndarray:
        """An odometry increment calibrated with the running estimate (the filter's own prediction of its
        estimate, and every particle's while it searches)."""
        d = np.asarray(delta, np.float64).reshape(3)
        out = np.array([d[0] * self.scale, d[1] * self.scale, d[2]])
        if dt_s is not None and math.isfinite(dt_s):
            out[2] = d[2] - self.gyro_bias * dt_s
        return out

    def observe(self, raw_motion, dt_s, estimate_before, estimate_after) -> bool:
        """The evidence is in the particles' weights: only the distance is counted."""
        o = np.asarray(raw_motion, np.float64).reshape(3)
        self.distance_m += math.hypot(o[0], o[1])
        self.observed += 1
        return True

    def start(self, n: int, rng: np.random.Generator) -> None:
        """``n`` particle states drawn around the running estimate (at a convergence or tracking start)."""
        s = self.scale + rng.normal(0.0, 1.0, n) * self.sigma_scale
        b = self.gyro_bias + rng.normal(0.0, 1.0, n) * self.sigma_bias
        self.state = np.column_stack([np.clip(s, self.min_scale, self.max_scale), b])

    def stop(self) -> None:
        """The filter searches again: the states go, the running estimate stays."""
        self.state = None

    def resampled(self, index: np.ndarray) -> None:
        if self.state is not None:
            self.state = self.state[index]

    def increments(self, increment, dt_s: float, moved_m: float, rng: np.random.Generator):
        """Per-particle ``(rot1, trans, rot2)`` from the increment calibrated with the running estimate
        (``correct``): each particle's own scale and bias replace the running ones; then the states' random
        walk over ``moved_m`` metres and ``dt_s`` seconds."""
        rot1, trans, rot2 = increment
        s, b = self.state[:, 0], self.state[:, 1]
        trans_i = trans * s / self.scale if self.scale > 0 else np.full(len(s), trans)
        dt = dt_s if dt_s is not None and math.isfinite(dt_s) and dt_s > 0 else 0.0
        rot2_i = rot2 - (b - self.gyro_bias) * dt
        n = len(s)
        if self.walk_scale > 0 and moved_m > 0:
            s = s + rng.normal(0.0, 1.0, n) * self.walk_scale * math.sqrt(moved_m)
        if self.walk_bias > 0 and dt > 0:
            b = b + rng.normal(0.0, 1.0, n) * self.walk_bias * math.sqrt(dt)
        self.state = np.column_stack([np.clip(s, self.min_scale, self.max_scale), b])
        return rot1, trans_i, rot2_i

    def weighted(self, weights: np.ndarray) -> None:
        """The running estimate from the particles' weights (after an update)."""
        if self.state is None or len(weights) != len(self.state):
            return
        w = np.asarray(weights, np.float64)
        if self.estimate_scale:
            self.scale = float(np.sum(w * self.state[:, 0]))
        if self.estimate_bias:
            self.gyro_bias = float(np.sum(w * self.state[:, 1]))
