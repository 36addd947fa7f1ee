"""Pose hypotheses of a global search: clusters of particles, the evidence each has gathered, and the
decision that one of them has won.

The paper declares convergence when all particles lie in one tile and then keeps 100 of them: a decision
taken by particle depletion (the runner-up lost its particles by chance or by one bad update), which a
look-alike street wins as easily as the true one. Here instead:

* the cloud is split into **clusters** (:func:`cluster_labels`: particles in touching grid cells of
  ``cell_m``);
* a cluster's **evidence** is its share of the total weight. Resampling keeps each cluster's share
  (:func:`resample_by_cluster`: a cluster's copies carry its weight, ``log(mass / copies)``) and at least
  ``min_particles`` copies for every cluster within ``prune_nats`` of the best, so a hypothesis is dropped
  by the evidence against it, never by sampling. Shares then multiply by every update's likelihood: the
  log ratio of two clusters' shares is their accumulated log-likelihood ratio;
* convergence (:class:`ConvergenceTest`) is a sequential test: the leader's log share must beat the
  runner-up's by ``margin_nats`` *and* the leader must have kept the lead over ``min_distance_m`` of driving
  (a look-alike street fits for a stretch, not for ever), and be compact. The runner-up is the best
  cluster more than ``separation_m`` from the leader: a satellite a few metres behind the leader on the
  same street is the same place at the resolution that matters (tracking settles it), not a rival;
* while it is undecided the cloud's size follows the KLD bound (Fox, 2003) on the number of occupied
  ``(x, y, yaw)`` bins (:func:`kld_sample_size`): many particles while the posterior is spread, few once
  it sits on a handful of places.

Pure numpy and scipy; all randomness from the generator handed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rangemcl.localization.particles import low_variance_resample
from rangemcl.se2 import circular_mean


def cluster_labels(xy: np.ndarray, cell_m: float) -> tuple[np.ndarray, int]:
    """Connected groups of particles: two particles share a cluster when their ``cell_m`` grid cells
    touch (8-neighbourhood), directly or through others. Returns ``(labels (N,), count)``."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return np.zeros(0, np.int64), 0
    ij = np.floor(xy / cell_m).astype(np.int64)
    cells, inverse = np.unique(ij, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    # cells are sorted lexicographically: find each neighbour by a sorted search on a 1-D key
    span = int(cells[:, 1].max() - cells[:, 1].min() + 3)
    key = (cells[:, 0] - cells[:, 0].min() + 1) * span + (cells[:, 1] - cells[:, 1].min() + 1)
    order = np.argsort(key)
    skey = key[order]
    rows, cols = [], []
    for di, dj in ((1, -1), (1, 0), (1, 1), (0, 1)):  # half the neighbourhood: the graph is undirected
        nk = key + di * span + dj
        pos = np.clip(np.searchsorted(skey, nk), 0, len(skey) - 1)
        hit = skey[pos] == nk
        rows.append(np.flatnonzero(hit))
        cols.append(order[pos[hit]])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(len(cells), len(cells)))
    count, cell_label = connected_components(graph, directed=False)
    return cell_label[inverse].astype(np.int64), int(count)


@dataclass
class Hypothesis:
    """One cluster: its ``label``, weight ``share`` (and its log), particle ``count``, weighted centroid
    ``(x, y, yaw)`` and the radius holding 95 % of its weight around the centroid."""

    label: int
    share: float
    log_share: float
    count: int
    centroid: np.ndarray
    radius95_m: float


def summarize(particles: np.ndarray, weights: np.ndarray, labels: np.ndarray, count: int) -> list[Hypothesis]:
    """The clusters as :class:`Hypothesis`, largest share first."""
    w = np.asarray(weights, np.float64)
    mass = np.bincount(labels, weights=w, minlength=count)
    n = np.bincount(labels, minlength=count)
    out = []
    for lab in np.argsort(-mass, kind="stable"):
        if n[lab] == 0:
            continue
        idx = np.flatnonzero(labels == lab)
        wi = w[idx]
        wn = wi / wi.sum() if wi.sum() > 0 else np.full(len(idx), 1.0 / len(idx))
        p = particles[idx]
        c = np.array([wn @ p[:, 0], wn @ p[:, 1], circular_mean(p[:, 2], wn)])
        d = np.hypot(p[:, 0] - c[0], p[:, 1] - c[1])
        o = np.argsort(d)
        r95 = float(d[o][min(np.searchsorted(np.cumsum(wn[o]), 0.95), len(o) - 1)])
        share = float(mass[lab])
        out.append(Hypothesis(int(lab), share, math.log(share) if share > 0 else -math.inf, len(idx), c, r95))
    return out


def kld_sample_size(bins: int, epsilon: float = 0.05, z: float = 2.326) -> int:
    """Particles needed so that the KL divergence between the sample-based and the true posterior stays
    below ``epsilon`` with probability ``1 − δ`` (``z`` its normal quantile; 2.326 for δ = 0.01), the
    posterior occupying ``bins`` bins (Fox, IJRR 2003)."""
    k = int(bins)
    if k <= 1:
        return 1
    a = 2.0 / (9.0 * (k - 1))
    return int(math.ceil((k - 1) / (2 * epsilon) * (1 - a + math.sqrt(a) * z) ** 3))


def occupied_bins(particles: np.ndarray, xy_m: float, yaw_deg: float) -> int:
    """How many ``xy_m × xy_m × yaw_deg`` bins the particles occupy."""
    if len(particles) == 0:
        return 0
    b = np.column_stack(
        [
            np.floor(particles[:, 0] / xy_m),
            np.floor(particles[:, 1] / xy_m),
            np.floor((particles[:, 2] + math.pi) / math.radians(yaw_deg)),
        ]
    ).astype(np.int64)
    return len(np.unique(b, axis=0))


def allocate(shares: np.ndarray, total: int, min_each: int) -> np.ndarray:
    """Copies per cluster: proportional to the shares (largest remainders), at least ``min_each`` each."""
    s = np.asarray(shares, np.float64)
    s = s / s.sum()
    k = len(s)
    total = max(int(total), k * min_each)
    free = total - k * min_each
    raw = s * free
    base = np.floor(raw).astype(np.int64)
    rest = free - int(base.sum())
    if rest > 0:
        base[np.argsort(-(raw - base), kind="stable")[:rest]] += 1
    return base + min_each


def resample_by_cluster(
    particles: np.ndarray,
    weights: np.ndarray,
    labels: np.ndarray,
    keep: list[Hypothesis],
    total: int,
    min_each: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Low-variance resampling inside each kept cluster, its copies carrying its share of the weight.

    Returns ``(particles (M, 3), log_weights (M,), cluster_index (M,))``: ``cluster_index`` is the
    position in ``keep`` each copy came from. The shares of the kept clusters are renormalised to 1."""
    w = np.asarray(weights, np.float64)
    shares = np.array([h.share for h in keep])
    counts = allocate(shares, total, min_each)
    parts, logw, origin = [], [], []
    norm = shares.sum()
    for j, (h, n) in enumerate(zip(keep, counts, strict=True)):
        idx = np.flatnonzero(labels == h.label)
        wi = w[idx]
        wi = wi / wi.sum() if wi.sum() > 0 else np.full(len(idx), 1.0 / len(idx))
        pick = idx[low_variance_resample(wi, rng, int(n))]
        parts.append(particles[pick])
        logw.append(np.full(int(n), math.log(max(h.share / norm, 1e-300) / n)))
        origin.append(np.full(int(n), j))
    return np.concatenate(parts), np.concatenate(logw), np.concatenate(origin)


class ConvergenceTest:
    """The sequential test of the module docstring: :meth:`update` once per weighted update with the
    current hypotheses, whether the leader is the same as at the previous update, and the distance driven
    since; ``True`` once the leader has won."""

    def __init__(
        self, margin_nats: float, min_distance_m: float, compact_radius_m: float, separation_m: float = 0.0
    ):
        self.margin_nats = float(margin_nats)
        self.min_distance_m = float(min_distance_m)
        self.compact_radius_m = float(compact_radius_m)
        self.separation_m = float(separation_m)
        self.lead_distance_m = 0.0
        self.margin = 0.0

    def reset(self) -> None:
        self.lead_distance_m = 0.0
        self.margin = 0.0

    def update(self, hyps: list[Hypothesis], same_leader: bool, moved_m: float) -> bool:
        if not hyps:
            self.reset()
            return False
        best = hyps[0]
        rivals = [
            h
            for h in hyps[1:]
            if math.hypot(h.centroid[0] - best.centroid[0], h.centroid[1] - best.centroid[1])
            > self.separation_m
        ]
        self.margin = best.log_share - rivals[0].log_share if rivals else math.inf
        self.lead_distance_m = self.lead_distance_m + moved_m if same_leader else 0.0
        return (
            self.margin >= self.margin_nats
            and self.lead_distance_m >= self.min_distance_m
            and best.radius95_m <= self.compact_radius_m
        )
