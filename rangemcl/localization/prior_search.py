"""The prior search (``convergence.method: prior``): global localization with a few dozen pose hypotheses
instead of a cloud of 10,000 particles, each scan costing about as much as a converged update.

The particle search (:mod:`rangemcl.localization.search`) weighs every particle of a cloud spread over the
map with every ray, then searches its heaviest hypotheses' neighbourhoods with dense grids: seconds per
scan on two cores until the cloud has shrunk. Most of those particles lie where the place prior already
says the scan was not taken, and the decision rests on the few places the prior ranks first and on their
local peaks. Here the filter keeps only those places:

* **Births**: at each update the place prior's best places for the scan
  (:meth:`~rangemcl.localization.place_prior.PlacePrior.candidates`, no ray cast) that lie away from every
  hypothesis start as hypotheses (``PRIOR_SEARCH_BIRTHS`` of them at most).
* **Local grids**: every hypothesis moves with the odometry and is searched around on each scan on a fine
  grid (:data:`FINE`; a newborn, which the prior places only to within its cell and a few degrees, on a
  coarse grid first, :data:`COARSE`, on every third ray); it moves to the fine grid's best pose, and that
  pose's log-likelihood adds to its evidence. Every grid is rendered
  planar about its hypothesis (:meth:`~rangemcl.localization.renderer.ParticleRenderer.planar_scores`:
  the scan's rays cast once from each hypothesis, all grids in one launch), so a hypothesis costs about
  one particle's rays.
* **A newborn's evidence**: a place born late has no history, so it is judged as the search's challenge
  judges a challenger: by its log-likelihood summed over the last ``PRIOR_SEARCH_WINDOW`` scans (each
  place moved back along the odometry) against the leader's over the same scans, added to the leader's
  evidence. A look-alike that fits today's scan but not the last metres enters behind.
* **Pruning**: hypotheses that come within :data:`MERGE_M` and :data:`MERGE_DEG` of a better one are
  merged into it; those ``prune_nats`` behind the leader are dropped, and at most
  ``PRIOR_SEARCH_HYPOTHESES`` are kept.
* **Convergence**: the sequential test of the particle search (:class:`~rangemcl.localization.hypotheses.
  ConvergenceTest`: the leader's log share beats the best rival farther than ``separation_m`` by
  ``margin_nats`` after ``min_distance_m`` of driving as the leader, and fits ``min_inliers`` of the
  structure rays); then ``converged_count`` particles start around the leader and the tracking takes over.

* **Probation**: after the convergence the search goes on beside the tracking for
  ``recovery.probation_updates`` updates (:meth:`PriorSearchMixin._rivals_update`): the converged place,
  the rivals it beat and the prior's newborn places are searched and weighed as before; a rival that leads
  the converged place at ``recovery.probation_hits`` updates in a row undoes the convergence and the search
  takes up again with its hypotheses. It stands in for the lost watch's second opinions of the probation,
  which cost ten times as much.

While searching, the filter's particles are the hypotheses and their log weights the evidence, so the
frame log, the estimate (the leader) and the snapshots read them as a cloud.
"""

from __future__ import annotations

import math

import numpy as np

from rangemcl.localization.hypotheses import Hypothesis
from rangemcl.localization.scan_prep import ScanRays
from rangemcl.se2 import se2_compose, wrap_angle

PRIOR_SEARCH_HYPOTHESES = 32  # hypotheses kept at most (the best by evidence)
PRIOR_SEARCH_BIRTHS = 8  # the prior's best places that may start as hypotheses at each update
PRIOR_SEARCH_CANDIDATES = 64  # ... chosen among this many of the prior's best places, best first ...
PRIOR_SEARCH_LONG_SHOTS = 2  # ... but this many of them drawn at random from its best init.prior_top
PRIOR_SEARCH_WINDOW = 4  # updates over which a newborn is judged against the leader ...
WINDOW_RAYS_EVERY = 2  # ... on every second ray of their scans
# the prior's cells matched per update: a larger prior is matched a slice at a time, each update the next
# slice (a town of 24,000 cells in six updates), so that an update's cost does not grow with the map
PRIOR_SEARCH_CELLS_PER_UPDATE = 4000
# the local grids: half width and step in metres along and across the hypothesis' heading, then degrees;
# within the planar rendering's reach (1 m, 3 degrees) of the hypothesis they are rendered about
COARSE = (1.0, 0.5, 3.0, 1.5)
FINE = (0.1, 0.1, 0.6, 0.3)  # a hypothesis follows its peak: the odometry moves it a few cm per update
COARSE_RAYS_EVERY = 3  # the coarse grid on every third ray
MERGE_M = 1.0  # hypotheses this close (and MERGE_DEG) are one place
MERGE_DEG = 5.0


def grid_offsets(grid: tuple[float, float, float, float]) -> np.ndarray:
    """``(G, 3)`` offsets (forward m, left m, yaw rad) of a local grid ``(half_m, step_m, half_deg,
    step_deg)``."""
    half_m, step_m, half_deg, step_deg = grid
    ax = np.arange(-half_m, half_m + 1e-9, step_m)
    ay = np.radians(np.arange(-half_deg, half_deg + 1e-9, step_deg))
    return np.array(np.meshgrid(ax, ax, ay, indexing="ij")).reshape(3, -1).T


def around(poses: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``(K, G, 3)``: each pose ``(K, 3)`` moved by each offset in its own frame."""
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    out = np.empty((len(poses), len(offsets), 3))
    out[:, :, 0] = poses[:, None, 0] + c * offsets[None, :, 0] - s * offsets[None, :, 1]
    out[:, :, 1] = poses[:, None, 1] + s * offsets[None, :, 0] + c * offsets[None, :, 1]
    out[:, :, 2] = wrap_angle(poses[:, None, 2] + offsets[None, :, 2])
    return out


class PriorSearchMixin:
    """The prior search, a mixin of :class:`~rangemcl.localization.filter.MonteCarloLocalizer` (module
    docstring). What it reads of the filter: ``particles`` and ``log_w`` (the hypotheses and their
    evidence), ``scorer``, ``sensor_z``, ``rng``, ``prior_for``, ``_elevations``, ``sensor_height_m``,
    ``_moved_m``, ``convergence_test``, the search's settings (``separation_m``, ``prune_nats``,
    ``min_inliers``, ``converged_count``, ``global_jitter``), ``_window_loglik`` and the recovery's
    ``_unconverge``; what it keeps:
    ``_leader_id`` and ``_hyp_ids``."""

    def _prior_search_reset(self) -> None:
        self.particles = np.zeros((0, 3))
        self.log_w = np.zeros(0)
        self._hyp_ids = np.zeros(0, np.int64)
        self._next_hyp_id = 0
        self._leader_id = -1
        self._prior_slice = 0
        self.convergence_test.reset()

    def _prior_search_update(self, rays: ScanRays, levelled: np.ndarray | None) -> dict:
        """One update of the prior search (the hypotheses have moved with the odometry). Returns
        :class:`~rangemcl.localization.filter.StepInfo` fields."""
        poses, evidence, ids, newborn = self._with_births(levelled, self.particles, self.log_w, self._hyp_ids)
        if len(poses) == 0:
            return dict(resampled=False, hypotheses=0, evidence_nats=0.0, inliers=math.nan)
        poses, loglik, inliers, bad = self._searched(rays, poses, newborn)
        old = ~newborn
        if old.any():
            evidence = evidence + loglik
            lead = int(np.flatnonzero(old)[np.argmax(evidence[old])])
            self._judge_newborns(poses, evidence, newborn, lead)
        else:
            evidence = loglik.copy()
        poses, evidence, ids, inliers, bad = self._pruned(poses, evidence, ids, inliers, bad)
        evidence = evidence - evidence.max()
        order = np.argsort(-evidence, kind="stable")
        poses, evidence, ids = poses[order], evidence[order], ids[order]
        inliers, bad = inliers[order], bad[order]
        total = float(np.log(np.exp(evidence).sum()))
        hyps = [
            Hypothesis(int(i), math.exp(e - total), e - total, 1, p.copy(), 0.0)
            for i, e, p in zip(ids, evidence, poses, strict=True)
        ]
        self.hypotheses = hyps
        same = bool(ids[0] == self._leader_id)
        self._leader_id = int(ids[0])
        won = self.convergence_test.update(hyps, same, self._moved_m)
        if won and np.isfinite(inliers[0]):
            won = float(inliers[0]) >= self.min_inliers
        self.particles, self.log_w, self._hyp_ids = poses, evidence, ids
        self.last_estimate = poses[0].copy()
        out = dict(
            resampled=True,
            hypotheses=len(hyps),
            evidence_nats=self.convergence_test.margin,
            best_residual_m=float(bad[0]),
            inliers=float(inliers[0]),
        )
        if won:
            n = self.converged_count
            sxy, syaw = self.global_jitter[0], math.radians(self.global_jitter[1])
            cloud = np.repeat(poses[:1], n, axis=0)
            cloud[:, :2] += self.rng.normal(0.0, sxy, (n, 2))
            cloud[:, 2] = wrap_angle(cloud[:, 2] + self.rng.normal(0.0, syaw, n))
            self.particles, self.log_w = cloud, np.zeros(n)
            self._keep_rivals(poses, evidence, ids)
            self._converge(search=True, settle=True)
            self.last_estimate = poses[0].copy()
            out["converged_now"] = True
        return out

    def _with_births(self, levelled, poses, evidence, ids):
        """The hypotheses ``poses`` ``(K, 3)``, ``evidence`` and ``ids`` with this update's newborns
        (:meth:`_births`) appended (evidence 0, fresh ids), and the mask of the newborns."""
        born = self._births(levelled, poses)
        if len(born):
            poses = np.vstack([poses, born])
            evidence = np.concatenate([evidence, np.zeros(len(born))])
            ids = np.concatenate([ids, self._next_hyp_id + np.arange(len(born))])
            self._next_hyp_id += len(born)
        newborn = np.zeros(len(poses), bool)
        newborn[len(poses) - len(born) :] = True
        return poses, evidence, ids, newborn

    def _judge_newborns(self, poses, evidence, newborn, lead: int) -> None:
        """A newborn has no history: its evidence (in place) is the leader's (index ``lead``) plus its
        log-likelihood over the last ``PRIOR_SEARCH_WINDOW`` scans less the leader's over the same."""
        if newborn.any():
            window = self._window_loglik(
                np.vstack([poses[lead][None], poses[newborn]]), PRIOR_SEARCH_WINDOW, WINDOW_RAYS_EVERY
            )
            evidence[newborn] = evidence[lead] + (window[1:] - window[0])

    def _births(self, levelled: np.ndarray | None, poses: np.ndarray) -> np.ndarray:
        """The prior's best places for the scan that lie away from every hypothesis (at most
        ``PRIOR_SEARCH_BIRTHS``, ``PRIOR_SEARCH_LONG_SHOTS`` of them drawn from further down its list),
        ``(B, 3)``."""
        if levelled is None or not self.use_prior:
            return np.zeros((0, 3))
        prior = self.prior_for(levelled)
        top = max(self.prior_top, PRIOR_SEARCH_CANDIDATES)
        cells = None
        K = len(prior.xy)
        if K > PRIOR_SEARCH_CELLS_PER_UPDATE:  # this update's slice of the cells, interleaved over the map
            slices = -(-K // PRIOR_SEARCH_CELLS_PER_UPDATE)
            cells = np.arange(self._prior_slice % slices, K, slices)
            self._prior_slice += 1
        xy, yaw, _cost, known = prior.candidates(
            levelled, self.sensor_height_m, top, self._elevations(prior, levelled), cells=cells
        )
        if known < max(8, prior.params.bins // 20):
            return np.zeros((0, 3))
        cand = np.column_stack([xy, yaw])
        # the best places first; a few long shots from further down the prior's list, so that a place the
        # prior ranks behind its best for a while still gets its chance
        head = cand[:PRIOR_SEARCH_CANDIDATES]
        tail = cand[PRIOR_SEARCH_CANDIDATES:]
        shots = tail[self.rng.permutation(len(tail))[:PRIOR_SEARCH_LONG_SHOTS]] if len(tail) else tail
        keep = []
        taken = poses[:, :3]
        for c in np.vstack([shots, head]):
            if len(keep) >= PRIOR_SEARCH_BIRTHS:
                break
            others = np.vstack([taken, np.asarray(keep).reshape(-1, 3)]) if keep else taken
            if len(others):
                near = np.hypot(others[:, 0] - c[0], others[:, 1] - c[1]) < 2.0 * MERGE_M
                near &= np.abs(wrap_angle(others[:, 2] - c[2])) < math.radians(4.0 * MERGE_DEG)
                if near.any():
                    continue
            keep.append(c)
        return np.asarray(keep, np.float64).reshape(-1, 3)

    def _searched(self, rays: ScanRays, poses: np.ndarray, newborn: np.ndarray):
        """Each hypothesis searched on this scan, rendered planar about it: a newborn (placed by the prior
        to within its cell and a few degrees) on the coarse grid on every third ray first, then every
        hypothesis on the fine grid around its pose (one that was searched before sits on its peak, moved
        by the odometry since). Returns the fine grids' best poses ``(K, 3)``, their log-likelihoods,
        inlier shares (NaN for models without) and badness."""
        poses = poses.copy()
        if newborn.any():
            poses[newborn] = self._best_on_grid(
                rays.subset(slice(None, None, COARSE_RAYS_EVERY)), poses[newborn], grid_offsets(COARSE)
            )[0]
        return self._best_on_grid(rays, poses, grid_offsets(FINE))

    def _best_on_grid(self, rays: ScanRays, poses: np.ndarray, offsets: np.ndarray):
        k, g = len(poses), len(offsets)
        grid = around(poses, offsets)
        flat = grid.reshape(-1, 3)
        z_ref = self.sensor_z(poses[:, :2])
        refs = np.column_stack([poses, z_ref])
        of = np.repeat(np.arange(k, dtype=np.int32), g)
        ll, bad = self.scorer.score(rays, flat, self.sensor_z(flat[:, :2]), about=refs, about_of=of)
        inl = self.scorer.last_inliers
        ll, bad = ll.reshape(k, g), bad.reshape(k, g)
        best = np.argmax(ll, axis=1)
        rows = np.arange(k)
        inliers = np.full(k, math.nan) if inl is None else inl.reshape(k, g)[rows, best]
        return grid[rows, best], ll[rows, best], inliers, bad[rows, best]

    def _pruned(self, poses, evidence, ids, inliers, bad):
        """Hypotheses merged into better ones within ``MERGE_M`` and ``MERGE_DEG``, those ``prune_nats``
        behind the best dropped, at most ``PRIOR_SEARCH_HYPOTHESES`` kept (the best)."""
        order = np.argsort(-evidence, kind="stable")
        kept: list[int] = []
        for i in order:
            if evidence[i] < evidence[order[0]] - self.prune_nats or len(kept) >= PRIOR_SEARCH_HYPOTHESES:
                break
            if kept:
                k = np.asarray(kept)
                near = np.hypot(poses[k, 0] - poses[i, 0], poses[k, 1] - poses[i, 1]) < MERGE_M
                near &= np.abs(wrap_angle(poses[k, 2] - poses[i, 2])) < math.radians(MERGE_DEG)
                if near.any():
                    continue
            kept.append(int(i))
        k = np.asarray(kept, np.int64)
        return poses[k], evidence[k], ids[k], inliers[k], bad[k]

    # --- the probation after a convergence ----------------------------------------------------------------

    def _keep_rivals(self, poses: np.ndarray, evidence: np.ndarray, ids: np.ndarray) -> None:
        """At the convergence: the leader (first) and the other hypotheses, with their evidence, carried
        through the probation (:meth:`_rivals_update`) when the lost watch has one."""
        updates = 0 if self.lost is None else self.lost.probation_updates
        if updates <= 0:
            self._rivals = None
            return
        self._rivals = dict(
            poses=poses.copy(),
            evidence=evidence - evidence[0],
            ids=ids.copy(),
            left=updates,
            hits=0,
            challenger=-1,
        )

    def _rivals_update(self, rays: ScanRays, level) -> dict:
        """One update of the probation after the prior search converged: the search goes on beside the
        tracking, as it went before, for ``recovery.probation_updates`` updates. The leader, the rivals it
        beat and the prior's newborn places for this scan are searched on their fine grids (rendered planar
        about each, one launch) and add this scan's log-likelihood to their evidence; a newborn is judged over
        the recent scans against the leader, as in the search. A rival that leads the converged place at
        ``recovery.probation_hits`` updates in a row (the same one) undoes the convergence: the search
        takes up again from the leader and its rivals with their evidence (what the scans have told is
        kept) and the sequential test decides again. This replaces the second opinions of the probation
        (each 0.15-3 s; an update here costs about one search update). Returns
        :class:`~rangemcl.localization.filter.StepInfo` fields (``recovered`` when undone)."""
        r = self._rivals
        # the leader: the converged cloud's best particle (the cloud stays as the tracking left it); the
        # rivals moved with this update's odometry, as the search's hypotheses are
        lead = self.particles[int(np.argmax(self.log_w))][None]
        poses = np.vstack([lead, se2_compose(r["poses"][1:], self._motion)])
        poses, evidence, ids, newborn = self._with_births(level(), poses, r["evidence"].copy(), r["ids"])
        poses, loglik, inliers, bad = self._searched(rays, poses, newborn)
        poses[0] = lead[0]  # the leader is the tracked place, not its grid's peak
        old = ~newborn
        evidence[old] = evidence[old] + loglik[old]
        self._judge_newborns(poses, evidence, newborn, 0)
        # rivals at the leader's place are the leader
        apart = np.hypot(poses[:, 0] - poses[0, 0], poses[:, 1] - poses[0, 1]) > self.separation_m
        apart[0] = True
        poses, evidence, ids = poses[apart], evidence[apart], ids[apart]
        inliers, bad = inliers[apart], bad[apart]
        rest = np.arange(1, len(poses))
        keep = self._pruned(poses[rest], evidence[rest], ids[rest], inliers[rest], bad[rest])
        poses = np.vstack([poses[:1], keep[0]])
        evidence = np.concatenate([[evidence[0]], keep[1]]) - evidence[0]
        ids = np.concatenate([[ids[0]], keep[2]])
        r.update(poses=poses, evidence=evidence, ids=ids, left=r["left"] - 1)
        best = int(np.argmax(evidence[1:])) + 1 if len(evidence) > 1 else 0
        if best and evidence[best] > 0.0:
            r["hits"] = r["hits"] + 1 if ids[best] == r["challenger"] else 1
            r["challenger"] = int(ids[best])
        else:
            r["hits"], r["challenger"] = 0, -1
        need = max(1, self.lost.probation_hits)
        if r["hits"] >= need:  # undone: the search takes up again with these hypotheses
            self.particles, self.log_w, self._hyp_ids = poses, evidence - evidence.max(), ids
            self._leader_id = -1
            self._rivals = None
            self._unconverge()
            self.recoveries += 1
            self.last_estimate = poses[int(np.argmax(evidence))].copy()
            return dict(recovered=True)
        if r["left"] <= 0:
            self._rivals = None
        return {}
