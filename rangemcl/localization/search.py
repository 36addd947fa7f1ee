"""The global search (:class:`SearchMixin`): what the filter does while it has not found its place.

* **The place prior's draw**: at the first update with a scan to compare, a share of the uniform spread
  is redrawn around the places whose profile fits the scan (:mod:`rangemcl.localization.place_prior`).
* **The polish**: the heaviest hypotheses are searched on a coarse and a fine grid of poses around their
  best particle, so that the true place is judged at the likelihood's peak (the second opinion of
  :mod:`rangemcl.localization.recovery` looks around its places with the same grids).
* **The hypothesis search** (:mod:`rangemcl.localization.hypotheses`): the cloud is clustered into
  hypotheses, the sequential test decides whether the leader has won (and fits), else the cloud is
  resampled cluster by cluster to the KLD size and particles from the prior are injected; with
  ``convergence="tiles"``, the paper's rule instead (all particles in ``tiles`` tiles).
* **The challenge**: before a winner converges, the place prior's best places for the scan challenge it
  (:meth:`SearchMixin._challenge`). The sequential test weighs the leader against the rivals the cloud
  holds; a look-alike that was never drawn, or was dropped while its particles lay off its likelihood's
  peak, is not among them, and the leader then wins by a margin over places that never were its match
  (on two identical streets, the search converges on the wrong one when the cloud has lost the other
  street's copy of the true place). Each challenger is searched with the polish's grids, as is the
  leader, and both are judged by the same evidence: the log-likelihood summed over the recent scans,
  each place moved back along the odometry. A challenger within the test's margin joins the cloud with
  the weight that evidence gives it, and the search goes on.
* **Convergence**: the winner's particles are resampled to ``converged_count`` and the filter's
  convergence (:meth:`MonteCarloLocalizer._converge`) hands over to the tracking.

A mixin of :class:`rangemcl.localization.filter.MonteCarloLocalizer` rather than a part it composes: the
search rewrites the filter's cloud at every update (poses added by the polish, the cloud resampled cluster
by cluster, each particle's descent from the leading cluster kept in step with it), draws from the
filter's place prior and generator, scores with its observation model and ends in the filter's own
convergence, so its state does not separate from the filter's. What it reads of the filter: the cloud
(``particles``, ``log_w``, ``weights``, ``last_estimate``), ``scorer``, ``sensor_z``, ``rng``, ``map``,
``prior_for`` and ``_elevations``, ``_moved_m`` and ``_spread_count``, the recent updates' rays and odometry
(``_recent``, ``_since_spread``), and the search's settings that the constructor stores (convergence,
particles and place-prior keys); what it keeps: ``hypotheses``, ``convergence_test``, ``_leader`` and
``_prior_pending``.
"""

from __future__ import annotations

import math

import numpy as np

from rangemcl.localization.hypotheses import (
    cluster_labels,
    kld_sample_size,
    occupied_bins,
    resample_by_cluster,
    summarize,
)
from rangemcl.localization.lost import Polish, candidate_particles
from rangemcl.localization.particles import (
    effective_sample_size,
    low_variance_resample,
    pose_estimate,
    resample_roughened,
)
from rangemcl.localization.renderer import planar_references
from rangemcl.localization.scan_prep import ScanRays
from rangemcl.se2 import se2_compose, se2_inverse, wrap_angle

# the search's polish of its heaviest hypotheses (SearchMixin._polish_hypotheses): a coarse grid (half
# width and step in metres along and across the seed's heading, then in degrees of yaw) and a fine one
# around the coarse grid's best pose
POLISH_COARSE = (2.0, 0.5, 8.0, 2.0)
POLISH_FINE = (0.4, 0.2, 1.5, 0.5)
POLISH_COARSE_RAYS_EVERY = 3  # the coarse grid is scored on every third ray
CHALLENGE_PER_PLACE = 16  # particles scored on each challenging place (a grid over its prior cell)
CHALLENGE_APART_M = 3.0  # the challengers that are searched lie at least this far apart


class SearchMixin:
    """Global localization's search, a mixin of :class:`~rangemcl.localization.filter.MonteCarloLocalizer`
    (module docstring)."""

    # --- the place prior's draw ---------------------------------------------------------------------------

    def _needs_prior(self) -> bool:
        return self.use_prior and not self.converged

    def _draw_initial_prior(self, levelled: np.ndarray) -> None:
        n = len(self.particles)
        k = int(round(self.prior_share * n))
        drawn = self._from_prior(k, levelled)
        if drawn is None:
            return  # too little in the scan to compare: stay uniform, try again at the next update
        self.particles[self.rng.choice(n, k, replace=False)] = drawn
        self.log_w = np.zeros(n)
        self._prior_pending = False

    def _from_prior(self, n: int, levelled_points: np.ndarray, top: int | None = None) -> np.ndarray | None:
        """``n`` particles around the prior's ``top`` best places for this scan (default ``prior_top``,
        at most 2 % of the map's cells); None when the scan has too few points in the prior's height band
        to compare."""
        prior = self.prior_for(levelled_points)
        top = min(top or self.prior_top, max(20, len(prior.xy) // 50))
        xy, yaw, _cost, known = prior.candidates(
            levelled_points, self.sensor_height_m, top, self._elevations(prior, levelled_points)
        )
        if known < max(8, prior.params.bins // 20) or n <= 0:
            return None
        k = self.rng.integers(0, len(xy), n)
        half = 0.5 * prior.params.cell_m
        out = np.empty((n, 3))
        out[:, :2] = xy[k] + self.rng.uniform(-half, half, (n, 2))
        out[:, 2] = wrap_angle(yaw[k] + self.rng.normal(0.0, self.prior_yaw_sigma, n))
        return out

    # --- the polish ---------------------------------------------------------------------------------------

    def _polish_hypotheses(
        self, rays: ScanRays, loglik: np.ndarray, bad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """While searching, the ``polish_hypotheses`` heaviest hypotheses (a cluster's particles within one
        30° sector of yaw) are searched around their best particle on this scan: a coarse grid
        (:data:`POLISH_COARSE`, scored on every third ray) and a fine one around its best pose
        (:data:`POLISH_FINE`, all rays); the fine grid's ``polish_keep`` best poses join the cloud. The range
        likelihood is sharp (a pose 0.2 m to the side, or a degree off, can lose about half a nat per update;
        ``tools/likelihood_peak.py`` measures it on a drive) and a hypothesis holds a few dozen particles over
        metres and degrees, so without this the true place is judged by particles off its peak, which can fit
        worse than a look-alike street's best particles for many updates. The coarse grid on a third of the
        rays keeps the cost of finding the peak's neighbourhood low; the fine grid on all rays places it. The
        seed's weight before this scan is shared among itself and the new poses, each then taking its own
        likelihood. Returns ``loglik`` and ``bad`` extended to the new poses (the clusters are found again by
        the search update: the new poses can join neighbouring ones)."""
        labels, _count = cluster_labels(self.particles[:, :2], self.cluster_m)
        sectors = 12
        sector = np.floor((self.particles[:, 2] + math.pi) / (2 * math.pi) * sectors).astype(np.int64)
        labels = labels * sectors + sector.clip(0, sectors - 1)
        lw = self.log_w
        mass = np.bincount(labels, weights=np.exp(lw - lw.max()))
        top = np.argsort(-mass, kind="stable")[: self.polish_hypotheses]
        top = top[mass[top] > 0]
        if len(top) == 0:
            return loglik, bad
        order = np.lexsort((-lw, labels))  # by hypothesis, its heaviest particle first
        seeds_idx = order[np.searchsorted(labels[order], top)]
        k = len(seeds_idx)
        inl0 = self.scorer.last_inliers
        p, ll, b, inl = self._polish_grids(rays, self.particles[seeds_idx])
        keep = min(self.polish_keep, ll.shape[1])
        pick = np.argsort(-ll, axis=1, kind="stable")[:, :keep]
        rows = np.arange(k)[:, None]
        new, ll_new, bad_new = (
            p[rows, pick].reshape(-1, 3),
            ll[rows, pick].reshape(-1),
            b[rows, pick].reshape(-1),
        )
        origin = np.repeat(seeds_idx, keep)  # each new pose's seed
        split = math.log(keep + 1)
        lw = lw.copy()
        before = lw[origin] - loglik[origin]
        lw[seeds_idx] -= split
        n0 = len(self.particles)
        self.log_w = np.concatenate([lw, before - split + ll_new])
        self.particles = np.vstack([self.particles, new])
        if self._leader is not None and len(self._leader) == n0:
            self._leader = np.concatenate([self._leader, self._leader[origin]])
        if inl0 is not None and inl is not None:
            self.scorer.last_inliers = np.concatenate([inl0, inl[rows, pick].reshape(-1)])
        else:
            self.scorer.last_inliers = None
        return np.concatenate([loglik, ll_new]), np.concatenate([bad, bad_new])

    def _polish_grids(self, rays: ScanRays, seeds: np.ndarray):
        """The polish's two grids around each seed ``(K, 3)``: the coarse grid (:data:`POLISH_COARSE`) on
        every third ray, then the fine grid (:data:`POLISH_FINE`) on all of them around the coarse grid's
        most likely pose. Returns the fine grids as :meth:`_grid_search` does."""
        coarse_rays = rays.subset(slice(None, None, POLISH_COARSE_RAYS_EVERY))  # a third: the cost
        p, ll, _b, _i = self._grid_search(coarse_rays, seeds, POLISH_COARSE)
        coarse_best = p[np.arange(len(seeds)), np.argmax(ll, axis=1)]
        return self._grid_search(rays, coarse_best, POLISH_FINE)

    def _grid_search(self, rays: ScanRays, seeds: np.ndarray, grid: tuple[float, float, float, float]):
        """Each seed ``(x, y, yaw)`` scored over a grid of poses in its own frame (forward, left, yaw):
        ``grid`` = ``(half_m, step_m, half_deg, step_deg)``. Returns the poses ``(K, G, 3)``, their
        log-likelihoods, badness and inlier shares ``(K, G)`` (inliers None for models without them)."""
        half_m, step_m, half_deg, step_deg = grid
        ax = np.arange(-half_m, half_m + 1e-9, step_m)
        ay = np.radians(np.arange(-half_deg, half_deg + 1e-9, step_deg))
        g = np.array(np.meshgrid(ax, ax, ay, indexing="ij")).reshape(3, -1).T
        c, s = np.cos(seeds[:, 2])[:, None], np.sin(seeds[:, 2])[:, None]
        p = np.empty((len(seeds), len(g), 3))
        p[:, :, 0] = seeds[:, None, 0] + c * g[None, :, 0] - s * g[None, :, 1]
        p[:, :, 1] = seeds[:, None, 1] + s * g[None, :, 0] + c * g[None, :, 1]
        p[:, :, 2] = wrap_angle(seeds[:, None, 2] + g[None, :, 2])
        flat = p.reshape(-1, 3)
        about = self._planar_grid_refs(flat, seeds, np.repeat(np.arange(len(seeds)), len(g)))
        ll, bad = self.scorer.score(rays, flat, self.sensor_z(flat[:, :2]), **about)
        inl = self.scorer.last_inliers
        shape = (len(seeds), len(g))
        return p, ll.reshape(shape), bad.reshape(shape), None if inl is None else inl.reshape(shape)

    def _planar_grid_refs(self, poses: np.ndarray, centres: np.ndarray, of: np.ndarray) -> dict:
        """The scorer's ``about`` and ``about_of`` for ``poses`` ``(N, 3)`` around ``centres[of]`` with
        ``observation.rendering: planar`` (:func:`~rangemcl.localization.renderer.planar_references`: each
        pose about a reference within a metre and a few degrees of it); ``{}`` (exact) otherwise."""
        if self.rendering != "planar" or len(poses) == 0:
            return {}
        refs, ref_of = planar_references(poses, centres, of)
        return dict(about=np.column_stack([refs, self.sensor_z(refs[:, :2])]), about_of=ref_of)

    # --- one update of the search -------------------------------------------------------------------------

    def _search_update(self, w: np.ndarray, levelled: np.ndarray | None) -> dict:
        """After a weighed update while searching: the hypothesis search, or the paper's rule
        (``convergence="tiles"``). Returns :class:`~rangemcl.localization.filter.StepInfo` fields."""
        if self.convergence == "hypotheses":
            return self._hypothesis_update(w, levelled)
        return self._tiles_update(w)

    def _hypothesis_update(self, w: np.ndarray, levelled: np.ndarray | None) -> dict:
        """One update of the hypothesis search (:mod:`rangemcl.localization.hypotheses`): cluster,
        test for a winner, else resample cluster by cluster to the KLD size and inject prior particles."""
        labels, count = cluster_labels(self.particles[:, :2], self.cluster_m)
        hyps = summarize(self.particles, w, labels, count)
        self.hypotheses = hyps
        best = hyps[0]
        same = False
        if self._leader is not None and len(self._leader) == len(labels):
            same = bool(self._leader[labels == best.label].mean() >= 0.5)
        won = self.convergence_test.update(hyps, same, self._moved_m)
        inl = self.scorer.last_inliers
        if won and inl is not None and len(inl) == len(labels):
            # the winner must also fit: a place that merely fits less badly than the rest has not won
            won = float(inl[labels == best.label].max()) >= self.min_inliers
        challengers = None
        if won:
            inside = np.flatnonzero(labels == best.label)
            own = self.particles[inside[int(np.argmax(self.log_w[inside]))]]
            challengers = self._challenge(levelled, own, best.centroid, self.convergence_test.margin_nats)
            won = challengers is None
        margin = self.convergence_test.margin
        out = dict(resampled=True, hypotheses=len(hyps), evidence_nats=margin)
        self.last_estimate = best.centroid.copy()  # while searching, the leading hypothesis
        if won:
            inside = np.flatnonzero(labels == best.label)
            wi = w[inside] / w[inside].sum()
            self.particles = self.particles[inside]
            self._resample_searching(wi, self.converged_count)
            self._converge(search=True, settle=True)
            self._leader = None
            self.last_estimate = pose_estimate(self.particles, self.weights, self.estimate_best_share)
            out["converged_now"] = True
            return out
        keep = [h for h in hyps if h.log_share >= best.log_share - self.prune_nats][: self.max_clusters]
        provisional = self.particles[low_variance_resample(w, self.rng, len(w))]
        size = kld_sample_size(occupied_bins(provisional, *self.kld_bin), self.kld_epsilon)
        size = int(
            np.clip(size, self.min_search_particles, max(self._spread_count, self.min_search_particles))
        )
        parts, logw, origin = resample_by_cluster(
            self.particles, w, labels, keep, size, self.min_cluster_particles, self.rng
        )
        n = len(parts)
        sxy, syaw = self.global_jitter[0], math.radians(self.global_jitter[1])
        parts[:, :2] += self.rng.normal(0.0, sxy, (n, 2))
        parts[:, 2] = wrap_angle(parts[:, 2] + self.rng.normal(0.0, syaw, n))
        leader = origin == 0
        if (
            self.use_prior
            and levelled is not None
            and best.share <= self.inject_below_share
            and self.inject_share > 0
        ):
            k = max(1, int(round(self.inject_share * n)))
            fresh = self._from_prior(k, levelled, self.inject_top)
            if fresh is not None and len(fresh):
                share = min(self.inject_share * len(fresh) / k, 1.0 - 1e-12)
                parts = np.vstack([parts, fresh])
                each = math.log(max(self.inject_share, 1e-300) / k)
                logw = np.concatenate([logw + math.log1p(-share), np.full(len(fresh), each)])
                leader = np.concatenate([leader, np.zeros(len(fresh), bool)])
        if challengers is not None:  # each joins with its evidence against the leader's share
            poses, gap = challengers
            m = self.min_cluster_particles
            lead = math.log(max(best.share, 1e-300)) - math.log(sum(h.share for h in keep))
            fresh = self._around_challengers(poses)
            parts = np.vstack([parts, fresh])
            logw = np.concatenate([logw, np.repeat(lead + gap - math.log(m), m)])
            leader = np.concatenate([leader, np.zeros(len(fresh), bool)])
            out["challenged"] = len(poses)
        self.particles, self.log_w, self._leader = parts, logw, leader
        return out

    # --- the challenge ------------------------------------------------------------------------------------

    def _challenge(
        self, levelled: np.ndarray | None, own: np.ndarray, centre: np.ndarray, beat_by_nats: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Is there a place that the pose ``own`` (the leader's heaviest particle; a converged filter's best)
        does not beat by ``beat_by_nats``? The place prior's best ``challenge_top`` places for this update's
        scan, farther than ``separation_m`` from ``centre``, are scored with a few particles each; the best
        ``challenge_places`` distinct ones and ``own`` are searched around with the polish's grids, and
        each grid's best pose is judged by its log-likelihood summed over the last ``challenge_updates``
        scans (:meth:`_window_loglik`). Returns None when ``own`` beats every challenger by
        ``beat_by_nats`` (or there is nothing to challenge it with: no prior, too little in the scan to
        match, no recent scans), else the challengers that it does not beat: their poses ``(K, 3)`` and
        their evidence less its own ``(K,)``, in nats."""
        if (
            self.challenge_places <= 0
            or self.challenge_top <= 0
            or not self.use_prior
            or levelled is None
            or not self._recent
            or self._recent[-1][0] is None
        ):
            return None
        rays = self._recent[-1][0]
        prior = self.prior_for(levelled)
        xy, yaw, _cost, known = prior.candidates(
            levelled, self.sensor_height_m, self.challenge_top, self._elevations(prior, levelled)
        )
        if known < max(8, prior.params.bins // 20):
            return None
        far = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) > self.separation_m
        xy, yaw = xy[far], yaw[far]
        consult = getattr(self.map, "consult", None)  # a map within a budget: only the places held
        if consult is not None and len(xy):
            held = consult(xy)
            xy, yaw = xy[held], yaw[held]
        if len(xy) == 0:
            return None
        cand = candidate_particles(
            xy, yaw, CHALLENGE_PER_PLACE, prior.params.cell_m, self.prior_yaw_sigma, self.rng
        )
        ll, _bad = self.scorer.score(rays, cand, self.sensor_z(cand[:, :2]))
        picker = Polish(self.challenge_places, 1, 0.0, 0.0, self.rng, min_apart_m=CHALLENGE_APART_M)
        seeds = picker.seeds(cand[np.argsort(-ll, kind="stable")])
        p, gll, _b, _i = self._polish_grids(rays, np.vstack([np.asarray(own)[None], seeds]))
        peaks = p[np.arange(len(p)), np.argmax(gll, axis=1)]
        evidence = self._window_loglik(peaks)
        gap = evidence[1:] - evidence[0]
        apart = np.hypot(peaks[1:, 0] - peaks[0, 0], peaks[1:, 1] - peaks[0, 1]) > self.separation_m
        close = apart & (gap > -beat_by_nats)
        if not close.any():
            return None
        return peaks[1:][close], gap[close]

    def _around_challengers(self, poses: np.ndarray) -> np.ndarray:
        """``min_cluster_particles`` particles on each challenger ``(K, 3)``, roughened with the search's
        jitter (``global_jitter``): a hypothesis of its own in the cloud."""
        fresh = np.repeat(np.asarray(poses, np.float64).reshape(-1, 3), self.min_cluster_particles, axis=0)
        sxy, syaw = self.global_jitter[0], math.radians(self.global_jitter[1])
        fresh[:, :2] += self.rng.normal(0.0, sxy, (len(fresh), 2))
        fresh[:, 2] = wrap_angle(fresh[:, 2] + self.rng.normal(0.0, syaw, len(fresh)))
        return fresh

    def _window_loglik(
        self, poses: np.ndarray, updates: int | None = None, rays_every: int = 1
    ) -> np.ndarray:
        """Each pose's ``(K, 3)`` log-likelihood summed over the scans of the last ``updates`` (default
        ``challenge_updates``) updates since the search began (the current one included), the pose moved
        back along the odometry to each of them (updates without a scan add nothing); on every
        ``rays_every``-th ray of each scan."""
        p = np.asarray(poses, np.float64).reshape(-1, 3).copy()
        total = np.zeros(len(p))
        entries = list(self._recent)
        n = min(self.challenge_updates if updates is None else updates, self._since_spread, len(entries))
        for i in range(len(entries) - 1, len(entries) - 1 - n, -1):
            rays, motion = entries[i]
            if rays is not None:
                if rays_every > 1:
                    rays = rays.subset(slice(None, None, rays_every))
                ll, _bad = self.scorer.score(rays, p, self.sensor_z(p[:, :2]))
                total += ll
            p = se2_compose(p, se2_inverse(motion))  # the pose at the update before
        return total

    def _tiles_update(self, w: np.ndarray) -> dict:
        """One update under the paper's rule: converged when :meth:`_tiles_converged`, else resampled when
        the effective sample size falls below ``resample_neff_ratio``."""
        n = len(self.particles)
        if self._tiles_converged():
            self._resample_searching(w, min(self.converged_count, n))
            self._converge(search=True, settle=True)
            return dict(resampled=True, converged_now=True)
        if effective_sample_size(w) < self.resample_neff_ratio * n:
            self._resample_searching(w, n)
            return dict(resampled=True)
        return {}

    def _tiles_converged(self) -> bool:
        """The paper's rule: all particles in ``tiles`` tiles (and 95 % within ``max_radius_m``), or a
        cloud this compact (``compact_radius_m``) across a tile border."""
        est = self.last_estimate
        dist = np.hypot(self.particles[:, 0] - est[0], self.particles[:, 1] - est[1])
        r95 = float(np.quantile(dist, 0.95))
        if r95 <= self.compact_radius_m:
            return True
        tiles = np.unique(self.map.tile_at(self.particles[:, 0], self.particles[:, 1]))
        return len(tiles) <= self.tiles and r95 <= self.max_radius_m

    def _resample_searching(self, w: np.ndarray, n: int) -> None:
        """``n`` particles resampled and roughened with the search's jitter (``global_jitter``)."""
        self.particles, _parents = resample_roughened(self.particles, w, self.rng, n, *self.global_jitter)
        self.log_w = np.zeros(n)
