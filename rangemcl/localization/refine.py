"""Scan-to-mesh refinement of a converged filter's pose.

A converged cloud of 100 particles places the car only as well as its particles happen to sit: with the
odometry 3 % off, every prediction lands 3 % of the step short or long and the weighting pulls the cloud
back only by resampling, so the estimate lags by decimetres. Here the scan itself is aligned to the map:

* the update's rays (levelled sensor frame, measured ranges) are cast through the map from the current
  pose with the same Warp caster (:meth:`rangemcl.raycast.RayCaster.cast`, face normals on);
* each ray that hits the map within ``max_residual_m`` of its measured range gives a point-to-plane
  residual ``e = n · (p − q)``, with ``p`` the measured point and ``q`` the map's surface point on the same
  ray (projective association, re-cast at every iteration);
* rays whose map hit lies lower than ``min_hit_height_m`` above the ground take no part when enough others
  do: parked cars and people change between the mapping drive and today's, and a parked car's front or
  back, often the only surface across a street, drags the pose along it (a sensor that sees only the
  lowest metres keeps every hit);
* Gauss-Newton on ``(x, y, yaw)`` (height, roll and pitch stay with the ground grid and the IMU), Huber
  weights, a few iterations;
* only the directions the scan constrains move: the normal equations are solved in the eigenbasis of
  their information matrix (yaw scaled by ``lever_m`` so that metres and radians compare), and a
  direction whose information is below ``min_information`` (a street of parallel walls along its axis) is
  left where the particles put it;
* a weakly constrained direction (information from ``min_information`` up to ``weak_information``) moves
  only by small steps (at most ``weak_step_m``; a larger step along it is left out, ``Refinement.held``):
  a sparse scan's few rays on one low surface across a street (a vehicle just in front of a mapped
  surface) can constrain a direction just above the floor and pull the pose decimetres along the street
  at each update, while the few-centimetre steps that a wheel error of a few per cent asks for along a
  corridor are still taken (raising ``min_information`` to the band's top instead would stop those
  too).

:class:`ScanRefiner` returns the refined pose with what it rests on; the filter decides whether to take it
(:meth:`rangemcl.localization.tracking.Tracking.refine`: a correction outside the cloud's own spread
is refused and counted). Pure numpy on top of the caster; deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rangemcl.se2 import wrap_angle


@dataclass
class Refinement:
    """The outcome of one :meth:`ScanRefiner.refine`."""

    pose: np.ndarray  # (3,) refined (x, y, yaw)
    correction: np.ndarray  # (3,) refined minus start: (dx, dy, dyaw), world frame
    inliers: int  # rays that took part at the last iteration
    inlier_share: float  # ... as a share of the rays given
    rms_m: float  # their point-to-plane RMS residual at the refined pose
    cost: float  # mean Huber cost over all rays given (a ray taking no part costs as at max_residual_m)
    start_cost: float  # ... at the start pose
    constrained: int  # directions (0..3) the scan constrains at the returned pose
    iterations: int  # Gauss-Newton steps that led to the returned pose (the best one visited)
    held: int = 0  # weakly constrained directions whose step was beyond ``weak_step_m`` and left out


class ScanRefiner:
    """Point-to-plane Gauss-Newton alignment of a scan's rays to the map mesh (module docstring).

    Args:
        caster: the :class:`~rangemcl.raycast.RayCaster` holding the map.
        iterations: at most this many Gauss-Newton steps (each re-casts the rays).
        max_residual_m: a ray takes part when its measured range is within this of the map's surface.
        huber_m: Huber threshold of the point-to-plane residual.
        min_inliers: fewer taking part: no refinement.
        min_information: a direction's information (sum of squared unit Jacobians) below this is not moved.
        lever_m: yaw is compared with translation at this distance (the scan's typical range).
        min_incidence: rays meeting their surface at ``|n · d|`` below this (grazing) take no part.
        min_hit_height_m: rays whose map hit lies lower than this above the ground under the sensor take
            no part (None: all heights): parked cars and people, which change between drives, are low.
            Where fewer than ``min_inliers`` rays hit higher (an 8-beam sensor looking down), all take part.
        weak_information: directions with information from ``min_information`` up to this are weakly
            constrained: their part of the correction is taken only when it is at most ``weak_step_m``,
            else left out (``held``); None: no such band (every direction above the floor moves freely).
        weak_step_m: see ``weak_information``.
    """

    def __init__(
        self,
        caster,
        *,
        iterations: int,
        max_residual_m: float,
        huber_m: float,
        min_inliers: int,
        min_information: float,
        lever_m: float,
        min_incidence: float,
        min_hit_height_m: float | None,
        weak_information: float | None,
        weak_step_m: float,
    ):
        self.caster = caster
        self.iterations = int(iterations)
        self.max_residual_m = float(max_residual_m)
        self.huber_m = float(huber_m)
        self.min_inliers = int(min_inliers)
        self.min_information = float(min_information)
        self.lever_m = float(lever_m)
        self.min_incidence = float(min_incidence)
        self.min_hit_height_m = None if min_hit_height_m is None else float(min_hit_height_m)
        self.weak_information = None if weak_information is None else float(weak_information)
        self.weak_step_m = float(weak_step_m)

    def _linearize(self, directions, ranges, pose, sensor_z, ground_z=None):
        """Residuals, Jacobians (yaw column scaled by 1/lever) and Huber weights of the rays that take
        part at ``pose``."""
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = np.empty_like(directions)
        d[:, 0] = c * directions[:, 0] - s * directions[:, 1]
        d[:, 1] = s * directions[:, 0] + c * directions[:, 1]
        d[:, 2] = directions[:, 2]
        origin = np.array([pose[0], pose[1], sensor_z])
        hits = self.caster.cast(origin, d, ranges + self.max_residual_m, normals=True)
        t = hits.ranges.astype(np.float64)
        n = hits.normals.astype(np.float64)
        along = ranges - t  # measured minus map, along the ray
        cos_i = np.einsum("ij,ij->i", n, d)
        ok = hits.hit & (np.abs(along) <= self.max_residual_m) & (np.abs(cos_i) >= self.min_incidence)
        if self.min_hit_height_m is not None and ground_z is not None:
            hit_z = sensor_z + np.where(ok, t, 0.0) * d[:, 2]  # misses have t = inf
            high = ok & (hit_z >= ground_z + self.min_hit_height_m)
            if high.sum() >= self.min_inliers:  # else (a sensor that sees only the lowest metres): all
                ok = high
        e = along[ok] * cos_i[ok]  # n · (p − q), p − q = (r − t) d
        n, dd, r = n[ok], d[ok], ranges[ok]
        px, py = r * dd[:, 0], r * dd[:, 1]  # measured point relative to the sensor, world axes
        jac = np.stack([n[:, 0], n[:, 1], (n[:, 1] * px - n[:, 0] * py) / self.lever_m], axis=1)
        a = np.abs(e)
        w = np.where(a <= self.huber_m, 1.0, self.huber_m / np.maximum(a, 1e-12))
        return e, jac, w

    def _cost(self, e: np.ndarray, rays: int) -> float:
        """Mean Huber cost over ``rays`` rays of which those with residuals ``e`` take part."""
        k = self.huber_m
        a = np.abs(e)
        rho = np.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k))
        worst = k * (self.max_residual_m - 0.5 * k)
        return float((rho.sum() + (rays - len(e)) * worst) / max(1, rays))

    def refine(
        self, directions, ranges, pose, sensor_z: float, ground_z: float | None = None
    ) -> Refinement | None:
        """Align the rays (``directions`` ``(R, 3)`` unit vectors in the levelled sensor frame, measured
        ``ranges`` ``(R,)``) to the map, starting at ``pose`` ``(x, y, yaw)`` with the sensor at world
        height ``sensor_z`` (the ground under it at ``ground_z``, for ``min_hit_height_m``). None when
        fewer than ``min_inliers`` rays take part."""
        directions = np.asarray(directions, np.float64).reshape(-1, 3)
        ranges = np.asarray(ranges, np.float64).reshape(-1)
        start = np.asarray(pose, np.float64).reshape(3)
        x = start.copy()
        start_cost = math.nan
        best = None  # (cost, pose, residuals, constrained, iteration): the best pose visited
        for it in range(1, self.iterations + 2):
            e, jac, w = self._linearize(directions, ranges, x, sensor_z, ground_z)
            if len(e) < self.min_inliers:
                break
            cost = self._cost(e, len(ranges))
            h = jac.T @ (w[:, None] * jac)
            g = jac.T @ (w * e)
            vals, vecs = np.linalg.eigh(h)
            if it == 1:  # the cost, and how the scan constrains each direction, where it starts
                start_cost, start_eigen = cost, (vals, vecs)
            keep = vals >= self.min_information
            constrained = int(keep.sum())
            if best is None or cost < best[0]:
                best = (cost, x.copy(), e, constrained, it - 1)
            if it > self.iterations or constrained == 0:
                break
            step = -(vecs[:, keep] @ ((vecs[:, keep].T @ g) / vals[keep]))
            step[2] /= self.lever_m
            x = x + step
            x[2] = wrap_angle(x[2])
            if math.hypot(step[0], step[1]) < 1e-4 and abs(step[2]) < 1e-5:
                break
        if best is None:
            return None
        cost, x, e, constrained, it = best
        corr = x - start
        corr[2] = wrap_angle(corr[2])
        held = 0
        if self.weak_information is not None and np.any(corr):
            corr, held = self._hold_weak_steps(*start_eigen, corr)
            if held:
                x = start + corr
                x[2] = wrap_angle(x[2])
                e, _jac, _w = self._linearize(directions, ranges, x, sensor_z, ground_z)
                cost = self._cost(e, len(ranges))
        return Refinement(
            pose=x,
            correction=corr,
            inliers=len(e),
            inlier_share=len(e) / max(1, len(ranges)),
            rms_m=float(np.sqrt(np.mean(e * e))),
            cost=cost,
            start_cost=start_cost,
            constrained=constrained,
            iterations=it,
            held=held,
        )

    def _hold_weak_steps(self, vals, vecs, corr):
        """``corr`` without its parts along the weakly constrained directions (eigenvalues ``vals``,
        eigenvectors ``vecs`` of the information at the start pose; from ``min_information`` up to
        ``weak_information``) that exceed ``weak_step_m``, and how many were left out."""
        scaled = corr.copy()
        scaled[2] *= self.lever_m
        along = vecs.T @ scaled
        hold = (vals < self.weak_information) & (np.abs(along) > self.weak_step_m)
        if not hold.any():
            return corr, 0
        along[hold] = 0.0
        out = vecs @ along
        out[2] /= self.lever_m
        return out, int(hold.sum())
