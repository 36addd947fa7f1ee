"""The lost watch and the recovery (:class:`RecoveryMixin`): how a converged filter notices that it has lost
its place, and starts again.

At each update of a converged filter the lost detector (:class:`rangemcl.localization.lost.LostDetector`)
watches the evidence (the best particle's inlier share, or its residual). On a suspicion, and through the
probation after a convergence, it asks for a second opinion: the place prior's best places for this scan
(and the last better place, moved with the odometry) are scored on the far rays against the filter's own
cloud, the best of them searched again with the search's polish grids
(:mod:`rangemcl.localization.search`), and, while the filter's own place still fits, a better place must
also explain the scans of the recent updates (the look at the past). When the detector declares the filter
lost, the particles are spread over the map again and the search starts over (a recovery).

A mixin of :class:`rangemcl.localization.filter.MonteCarloLocalizer` rather than a part it composes: the
second opinion scores the filter's cloud and estimate with its observation model, reads its place prior,
draws from its generator and looks with the search's grids, and a recovery spreads the filter again. What
it keeps of its own: the detector (``lost``, a part of its own), the recent updates for the look at the
past (``_recent``) and the count of recoveries (``recoveries``). What it reads of the filter: the cloud
(``particles``, ``last_estimate``), ``scorer``, ``sensor_z``, ``rng``, ``map``, ``prior_for`` and
``_elevations``, ``_motion``, ``_spread_count``, and the settings ``use_prior``, ``separation_m``,
``prior_yaw_sigma``, ``sensor_height_m`` and ``global_count``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from rangemcl.localization.lost import Opinion, Polish, candidate_particles, history_fit, second_opinion
from rangemcl.localization.scan_prep import ScanRays
from rangemcl.se2 import se2_compose, se2_inverse


class RecoveryMixin:
    """The lost watch, the second opinion and the recovery, a mixin of
    :class:`~rangemcl.localization.filter.MonteCarloLocalizer` (module docstring)."""

    @property
    def vetoed_alarms(self) -> int:
        """Lost suspicions that the second opinion vetoed (episodes)."""
        return self.lost.vetoed_alarms if self.lost is not None else 0

    def _remember(self, rays: ScanRays | None) -> None:
        """An update's rays (None: no scan) and the odometry since the update before, kept for the look at
        the past (when it is on)."""
        if self._recent is not None:
            self._recent.append((rays, self._motion.copy()))

    def _start_probation(self) -> None:
        if self.lost is not None:
            # the prior search carries its rivals through the probation instead of second opinions
            rivals = self.convergence == "prior" and self._rivals is not None
            self.lost.start_probation(with_opinions=not rivals)
            # the challenge is the particle search's (the prior search's newborns and rivals play its part)
            challenge = self.challenge_top > 0 and self.challenge_places > 0
            challenge = challenge and self.convergence == "hypotheses"
            self._challenges_left = self.lost.probation_updates if challenge else 0

    def _watch(
        self, rays: ScanRays, level: Callable[[], np.ndarray] | None, best: float, inliers: float
    ) -> dict:
        """The lost watch at a converged update: the detector's verdict on this update's evidence (``best``
        badness, the best particle's ``inliers``), asking for a second opinion on the scan that ``level()``
        gives (levelled on demand; None, or without the place prior: none). Lost: the particles are spread
        again (a recovery). Returns the :class:`~rangemcl.localization.filter.StepInfo` fields ``vetoed``
        and, after a recovery, ``recovered``."""
        if self._challenges_left > 0 and self.use_prior and level is not None:
            self._challenges_left -= 1
            own = self.particles[int(np.argmax(self.log_w))]
            better = self._challenge(level(), own, self.last_estimate, 0.0)
            if better is not None:
                self.recoveries += 1
                self._reopen(*better)
                return dict(vetoed=False, recovered=True)
        opinion = (
            (lambda rival, gain: self._second_opinion(rays, level(), rival, gain))
            if self.use_prior and level is not None
            else None
        )
        lost, vetoed = self.lost.update(best, inliers, opinion, self._motion)
        if not lost:
            return dict(vetoed=vetoed)
        self.recoveries += 1
        self.spread(max(self._spread_count, self.global_count))
        return dict(vetoed=vetoed, recovered=True)

    def _reopen(self, poses: np.ndarray, gap: np.ndarray) -> None:
        """The probation's challenge found places ``poses`` ``(K, 3)`` that explain the recent scans better
        than the converged cloud (by ``gap`` nats): the search takes up again, the cloud one hypothesis
        and each place another (``min_cluster_particles`` particles) with the weight its evidence gives it.
        Not a spread: what the scans have told is kept, and the sequential test decides again."""
        m = self.min_cluster_particles
        fresh = self._around_challengers(poses)
        own = np.log(np.maximum(self.weights, 1e-300))
        self.particles = np.vstack([self.particles, fresh])
        self.log_w = np.concatenate([own, np.repeat(np.asarray(gap, np.float64) - math.log(m), m)])
        self._challenges_left = 0
        self._leader = None
        self._unconverge()

    def _unconverge(self) -> None:
        """A convergence undone by its probation (the particle search's challenge, the prior search's
        rivals): the tracking stops, the sequential test and the lost watch start over."""
        self.converged = False
        self.tracking.stop()
        self.convergence_test.reset()
        self.lost.reset()

    def _second_opinion(
        self, rays: ScanRays, levelled: np.ndarray, rival: np.ndarray | None, inlier_gain: float
    ) -> Opinion | None:
        """:func:`rangemcl.localization.lost.second_opinion` on the prior's best places for this scan,
        with the rays measured at least ``opinion_min_range_m`` away (near objects, vehicles alongside
        above all, fit any wall); the filter's own cloud is scored on the same rays. ``None`` when the
        scan has too little in the prior's height band, or too few far rays, to compare. ``rival``: a
        place scored with them (the last better place moved with the odometry, or None); ``inlier_gain``:
        what a better place must gain (:class:`rangemcl.localization.lost.LostDetector`). Over a map
        within a budget (:meth:`rangemcl.maps.view.MapView.consult`) the places whose tiles are not
        held yet are asked for and left out of this opinion."""
        lost = self.lost
        sub = self._far_rays(rays)
        if sub is None:
            return None
        prior = self.prior_for(levelled)
        xy, yaw, _cost, known = prior.candidates(
            levelled, self.sensor_height_m, lost.opinion_top, self._elevations(prior, levelled)
        )
        if known < max(8, prior.params.bins // 20):
            return None
        consult = getattr(self.map, "consult", None)  # a map within a budget: only the places held
        if consult is not None:
            far_away = np.hypot(xy[:, 0] - self.last_estimate[0], xy[:, 1] - self.last_estimate[1])
            keep = far_away > self.separation_m - 0.5 * prior.params.cell_m
            xy, yaw = xy[keep], yaw[keep]
            held = consult(xy)
            xy, yaw = xy[held], yaw[held]
            if len(xy) == 0:  # none scoreable yet (their tiles are loading): no better place found
                return Opinion(False, self.last_estimate.copy(), math.inf, math.nan, 0)
        cand = candidate_particles(
            xy, yaw, lost.opinion_per_place, prior.params.cell_m, self.prior_yaw_sigma, self.rng
        )
        centres = np.repeat(np.column_stack([xy, yaw]), len(cand) // max(len(xy), 1), axis=0)
        polish = Polish(lost.polish_places, lost.polish_per_place, *lost.polish_sigma, self.rng)
        if rival is not None and polish.places > 0:  # the last better place, moved with the odometry
            near_rival = np.vstack([rival[None], polish.around(rival[None])])
            cand = np.vstack([cand, near_rival])
            centres = np.vstack([centres, np.repeat(rival[None], len(near_rival), axis=0)])

        def score(p: np.ndarray, around: np.ndarray | None = None):
            """Badness and inlier shares of ``p``. Rendered planar (``observation.rendering``): the
            candidates each about its place ``around`` (a prior's cell: within a metre or so, as the prior
            search renders a newborn's coarse grid about it), the filter's own cloud about references near
            its estimate."""
            if around is None:
                about = self._planar_grid_refs(p, self.last_estimate[None], np.zeros(len(p), np.int64))
            elif self.rendering == "planar":
                places, of = np.unique(around, axis=0, return_inverse=True)
                refs = np.column_stack([places, self.sensor_z(places[:, :2])])
                about = dict(about=refs, about_of=of.reshape(-1).astype(np.int32))
            else:
                about = {}
            _loglik, bad = self.scorer.score(sub, p, self.sensor_z(p[:, :2]), **about)
            return bad, self.scorer.last_inliers

        own_bad, own_inl = score(self.particles)
        j = int(np.argmin(own_bad))
        found = second_opinion(
            score,
            self.last_estimate,
            float(own_bad[j]),
            float(own_inl[j]) if own_inl is not None else math.nan,
            cand,
            min_distance_m=self.separation_m,
            inlier_gain=inlier_gain,
            polish=polish,
            badness_ratio=lost.opinion_badness_ratio,
            saturated_ratio=lost.saturated_badness_ratio,
            look=lambda seeds: self._grid_look(sub, seeds),
            rival=rival,
            rival_m=lost.consistent_m,
            centres=centres,
        )
        if (
            found.better
            and self._recent is not None
            and lost.history_updates > 0
            and own_inl is not None
            and float(own_inl[j]) >= lost.history_min_inliers
        ):
            own = self.particles[j].copy()
            rival_fit = history_fit(self._history_inliers, found.pose, polish)
            own_fit = history_fit(self._history_inliers, own, polish)
            if math.isfinite(rival_fit) and rival_fit < own_fit - lost.history_margin:
                found.better = False  # (NaN own_fit: the comparison is False, the place stays better)
        return found

    def _grid_look(self, rays: ScanRays, seeds: np.ndarray):
        """The second opinion's look around its best places: each seed's coarse grid
        (:data:`~rangemcl.localization.search.POLISH_COARSE`, every third ray), then the fine grid
        (:data:`~rangemcl.localization.search.POLISH_FINE`) around its most likely pose; returns the fine
        grids' poses ``(M, 3)``, badness and inlier shares ``(M,)`` (the search's polish,
        :meth:`~rangemcl.localization.search.SearchMixin._polish_grids`, on the opinion's rays)."""
        seeds = np.asarray(seeds, np.float64).reshape(-1, 3)
        p, _ll, bad, inl = self._polish_grids(rays, seeds)
        return p.reshape(-1, 3), bad.reshape(-1), None if inl is None else inl.reshape(-1)

    def _history_inliers(self, poses: np.ndarray) -> np.ndarray:
        """Each pose's ``(M, 3)`` mean inlier share over the far rays of the previous updates' scans (up to
        ``history_updates``), the pose moved back along the odometry to each of them; NaN with fewer than
        half of them to compare (no scan, too few far rays). The watch's current run of bad updates is
        left out: as many scans as it counts (the current update included), those of its updates and the
        one just before them, so the past is the one before the suspicion (a vehicle alongside that hides
        the far rays at the true pose for a while would otherwise let a distant place fit that past nearly
        as well)."""
        p = np.asarray(poses, np.float64).reshape(-1, 3)
        total = np.zeros(len(p))
        count = 0
        entries = list(self._recent)
        skip = self.lost.watch.bad_updates
        for i in range(len(entries) - 1, 0, -1):
            p = se2_compose(p, se2_inverse(entries[i][1]))  # the pose at the update before
            back = len(entries) - 1 - i  # updates before this one
            if back >= skip + self.lost.history_updates:
                break
            if back < skip:
                continue  # a scan of the current suspicion
            sub = None if entries[i - 1][0] is None else self._far_rays(entries[i - 1][0])
            if sub is None:
                continue
            # (planar: about the first pose, the place that Polish.around spreads around)
            about = self._planar_grid_refs(p, p[:1], np.zeros(len(p), np.int64))
            self.scorer.score(sub, p, self.sensor_z(p[:, :2]), **about)
            total += self.scorer.last_inliers  # (asked only of models with an inlier share)
            count += 1
        if count == 0 or count < 0.5 * self.lost.history_updates:
            return np.full(len(p), math.nan)
        return total / count

    def _far_rays(self, rays: ScanRays) -> ScanRays | None:
        """The rays measured at least ``opinion_min_range_m`` away (what the second opinion compares), or
        None when they are too few (under 20, or under a tenth of the rays)."""
        far = rays.ranges >= self.lost.opinion_min_range_m
        if far.sum() < max(20, 0.1 * len(far)):
            return None
        return rays.subset(far)
