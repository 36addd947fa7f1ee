"""Is a converged filter lost? A watch on the scan's evidence, and a second opinion from the place prior.

A converged filter sees two kinds of bad news. At a **wrong place** (a look-alike street won the search)
part of the rays keep agreeing with the map, but the best particle's residual jumps 5-10x and its inlier
share falls. When the **world changed** at the right place (a parked car gone, a van or a bus alongside
hiding the facades, an object the map never had) the residual rises as well, and the inlier share can
fall as far. The signal alone cannot always tell the two apart (a watch that decided alone would raise
false alarms wherever the street changed), so the watch only raises a *suspicion*, and the suspicion is
tested against the map:

* :class:`SignalWatch`: the best particle's inlier share
  (:func:`rangemcl.localization.models.inlier_share`: rays far beyond the map, i.e. removed objects, left
  out) below ``inlier_factor`` x its running median; or below ``inlier_residual_factor`` x that median
  while the best residual is above ``inlier_residual_jump`` x its own running median (signal
  ``inliers``); or the best residual above ``factor`` x its median and the model's floor (signal
  ``residual``, the simpler watch; also what the ``inliers`` signal falls back on for models without an
  inlier share). Suspicious after ``updates`` bad updates in a row.
* :func:`second_opinion`: the prior's best places for *this* scan (away from the estimate) are scored
  with the same observation model and rays as the filter. If one of them explains the scan clearly
  better than the converged cloud's best particle (inlier share higher by ``inlier_gain``, residual
  lower) at ``opinion_hits`` updates, each time where the previous one's place has moved with the
  odometry (within ``consistent_m``; at most ``max_misses`` updates without it in between), the filter
  is at the wrong place: lost. One better place alone is not enough: at a single update some distant
  place can fit the far rays better than the true pose, but it does not keep doing so as the car drives
  on. The prior's cells are 2 m wide with a few particles each, too coarse for a sensor whose likelihood
  peaks within decimetres and a degree, so the best places get a second look around their best particle
  (the filter's grids: ``look``). The last better place, moved with the odometry, is scored again at the
  next update whether the prior offers it or not (the prior does not rank a place high at every scan),
  and judged first: it is confirmed while it stays better, even where another place fits a little more,
  so that a look-alike does not restart the count of confirmations. If no place is better, the world
  changed and the filter stays where it is (the alarm is *vetoed* and counted). A suspicion that lasts
  ``max_vetoed_updates`` updates is taken as lost all the same, so that a true place missing from the
  prior cannot pin the filter to a wrong one for ever.

The same second opinion also runs at each of the first ``probation_updates`` updates after every
convergence, suspicious or not: a wrong convergence that fits nearly as well as the truth raises no
signal, but the true place, once the prior offers it, fits better (``probation_hits`` consistent checks
in a row are needed). It runs as well at every update whose inlier share is below ``doubt_ratio`` of its
running level (*doubtful*): a wrong place that fit the first scans after its convergence as well as the
true one often fits the next ones clearly worse without falling below the suspicion's share of the
level. There a better place must gain ``doubt_inlier_gain`` of the far rays' inlier share, more than in a
suspicion or the probation: at the true pose in a changed street the filter fits less well than usual,
and a distant place's second look can beat it by the usual gain.

Two more rules decide what counts as better:

* **where the inlier share saturates** (``saturated_ratio``): a sensor whose far rays nearly all fit at a
  wrong place as at the true one leaves no room for the gain; there a place with as many inliers and a
  mean residual well below the filter's is better too;
* **a better place must explain the recent past** (:func:`history_fit`, ``history_updates``): in a street
  that changed since the mapping drive, a distant place can fit the current scans' far rays better than
  the true pose for several updates in a row, but over the previous updates' scans (each place moved
  back along the odometry) the true pose fits better; at a wrong convergence, in turn, the true place
  fits the past better than the wrong one, so the look does not hold it back. A place that fits the past
  worse than the filter's own by more than ``history_margin`` is not better. The look is taken only
  while the filter's own far rays still fit ``history_min_inliers``: a car that jumped (a kidnapping)
  fits nothing where it was, and its new place cannot have explained the scans from before the jump. It
  is taken in the probation after a convergence too: the search chose its place from those same past
  scans, so the past can favour a wrong convergence, but without the look a correct convergence can be
  called lost by a look-alike soon after. And it leaves out the scans of the current suspicion (its bad
  updates and the one before them; ``RecoveryMixin._history_inliers``): a vehicle alongside that
  hides the far rays at the true pose for a while would otherwise let a distant place fit that past
  nearly as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rangemcl.se2 import se2_compose, wrap_angle


class SignalWatch:
    """The running levels of the converged filter's evidence and the bad-update counter."""

    def __init__(
        self,
        *,
        signal: str,
        inlier_factor: float,
        inlier_residual_factor: float,
        inlier_residual_jump: float,
        residual_factor: float,
        floor: float,
        updates: int,
        history: int,
    ):
        if signal not in ("inliers", "residual"):
            raise ValueError(f"signal {signal!r}: expected 'inliers' or 'residual'")
        self.signal = signal
        self.inlier_factor = float(inlier_factor)
        self.inlier_residual_factor = float(inlier_residual_factor)
        self.inlier_residual_jump = float(inlier_residual_jump)
        self.residual_factor = float(residual_factor)
        self.floor = float(floor)
        self.updates = int(updates)
        self.history = int(history)
        self.residuals: list[float] = []  # the best residual at recent good converged updates
        self.inliers: list[float] = []  # ... and the best particle's inlier share
        self.bad_updates = 0
        self.last_ratio = math.nan  # the last update's inlier share over the running level

    def reset(self) -> None:
        self.residuals.clear()
        self.inliers.clear()
        self.bad_updates = 0
        self.last_ratio = math.nan

    def is_bad(self, best: float, inliers: float = math.nan) -> bool:
        """Whether this update's evidence is bad against the running levels (no state change)."""
        res_hist, inl_hist = self.residuals, self.inliers
        warm = len(res_hist) >= min(5, self.history)
        if self.signal == "inliers" and math.isfinite(inliers):
            level = float(np.median(inl_hist)) if len(inl_hist) >= min(5, self.history) else 0.6
            res_level = float(np.median(res_hist)) if res_hist else self.floor
            residual_far = best > max(self.floor, self.inlier_residual_jump * res_level)
            return inliers < self.inlier_factor * level or (
                residual_far and inliers < self.inlier_residual_factor * level
            )
        # just converged (no history yet): judge against the floor, with some room
        limit = (
            max(self.floor, self.residual_factor * float(np.median(res_hist))) if warm else 1.5 * self.floor
        )
        return best > limit

    def level(self) -> float:
        """The running level of the inlier share (its median over recent good updates; 0.6 before five)."""
        return float(np.median(self.inliers)) if len(self.inliers) >= min(5, self.history) else 0.6

    def update(self, best: float, inliers: float = math.nan) -> bool:
        """Record one converged update; True once it has been bad ``updates`` times in a row."""
        self.last_ratio = inliers / self.level() if math.isfinite(inliers) else math.nan
        if self.is_bad(best, inliers):
            self.bad_updates += 1
        else:
            self.bad_updates = 0
            self.residuals.append(best)
            del self.residuals[: -self.history]
            if math.isfinite(inliers):
                self.inliers.append(inliers)
                del self.inliers[: -self.history]
        return self.bad_updates >= self.updates


@dataclass
class Opinion:
    """What :func:`second_opinion` found: the best place away from the estimate, and whether it wins."""

    better: bool
    pose: np.ndarray  # (3,) the best candidate particle
    badness: float  # its badness (the model's units: mean residual in m for the range model)
    inliers: float  # its inlier share (NaN for models without one)
    candidates: int  # particles scored


@dataclass
class Polish:
    """How the second opinion looks again around a place: the prior's candidates sit on a 2 m grid with
    a few particles each, too coarse for a sensor whose likelihood peaks within decimetres and a degree
    (and a place's aligned yaw can be a few degrees off, metres at the far rays' range).
    :meth:`seeds` picks the ``places`` best distinct places (at least ``min_apart_m`` apart, best first)
    that :func:`second_opinion`'s ``look`` searches around; :meth:`around` draws ``per_place`` particles
    around each of some places (normal, ``sigma_xy_m`` and ``sigma_yaw_deg``, times a scale; the first
    at the place itself) from ``rng``: around the last better place, and in :func:`history_fit`'s
    ``rounds`` rounds, each around the best so far with half the spread."""

    places: int
    per_place: int
    sigma_xy_m: float
    sigma_yaw_deg: float
    rng: np.random.Generator
    min_apart_m: float = 3.0
    rounds: int = 3

    def seeds(self, ranked: np.ndarray) -> np.ndarray:
        """The best ``places`` poses of ``ranked`` ``(M, 3)`` (best first) at least ``min_apart_m`` apart."""
        out: list[np.ndarray] = []
        for p in ranked:
            if all(math.hypot(p[0] - q[0], p[1] - q[1]) >= self.min_apart_m for q in out):
                out.append(p)
                if len(out) >= self.places:
                    break
        return np.array(out).reshape(-1, 3)

    def around(self, seeds: np.ndarray, scale: float = 1.0) -> np.ndarray:
        n, m = len(seeds), max(1, self.per_place)
        noise = self.rng.normal(0.0, scale, (n, m, 3)) * np.array(
            [self.sigma_xy_m, self.sigma_xy_m, math.radians(self.sigma_yaw_deg)]
        )
        noise[:, 0] = 0.0
        out = (seeds[:, None, :] + noise).reshape(-1, 3)
        out[:, 2] = wrap_angle(out[:, 2])
        return out


def candidate_particles(
    xy: np.ndarray,
    yaw: np.ndarray,
    per_place: int,
    cell_m: float,
    yaw_sigma_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """``per_place`` particles on each candidate place: spread evenly over its cell (a stratified grid
    with a random offset, so that some land within a fraction of the cell of any point) and around its
    aligned yaw."""
    k = max(1, int(round(math.sqrt(per_place))))
    g = (np.arange(k) + 0.5) / k - 0.5  # cell-relative offsets of a k x k grid
    gx, gy = np.meshgrid(g, g)
    grid = np.column_stack([gx.ravel(), gy.ravel()])  # (k*k, 2)
    n = len(xy)
    m = len(grid)
    jitter = rng.uniform(-0.5 / k, 0.5 / k, (n, m, 2))
    pos = xy[:, None, :] + cell_m * (grid[None, :, :] + jitter)
    ang = yaw[:, None] + rng.normal(0.0, yaw_sigma_rad, (n, m))
    return np.column_stack([pos.reshape(-1, 2), wrap_angle(ang.reshape(-1))])


def second_opinion(
    score,
    estimate: np.ndarray,
    current_badness: float,
    current_inliers: float,
    candidates: np.ndarray,
    *,
    min_distance_m: float,
    inlier_gain: float = 0.15,
    badness_ratio: float = 0.7,
    polish: Polish | None = None,
    saturated_ratio: float | None = None,
    look=None,
    rival: np.ndarray | None = None,
    rival_m: float = 5.0,
    rival_deg: float = 20.0,
    centres: np.ndarray | None = None,
) -> Opinion:
    """Score ``candidates`` ``(M, 3)`` with ``score(particles) -> (badness (M,), inliers (M,) or None)``
    and decide whether the best of those farther than ``min_distance_m`` from ``estimate`` explains the
    scan clearly better than the filter's best particle: its inlier share higher by ``inlier_gain`` and
    its badness lower (models with an inlier share), or its badness below ``badness_ratio`` x the
    filter's (models without). With ``look``, a callable ``look(seeds (K, 3)) -> (poses (M, 3), badness
    (M,), inliers (M,) or None)`` (the filter's grids, ``RecoveryMixin._grid_look``), and
    ``polish``, the best ``polish.places`` distinct places (:meth:`Polish.seeds`) are searched again
    around their best particle before the decision, the look's poses near the estimate left out. With
    ``saturated_ratio``, where the filter's inlier share leaves no room for the gain (``current_inliers +
    inlier_gain > 1``), the place with the least badness among those with at least the filter's inlier
    share (less 0.02) is better when its badness is below ``saturated_ratio`` x the filter's. With
    ``rival`` ``(3,)`` (the last better place, moved with the odometry: :class:`LostDetector`), the
    candidates within ``rival_m`` and ``rival_deg`` of it are judged first, and the best of them is the
    opinion when it is better: a filter at a wrong place can meet the true place at one update and a
    look-alike with a few more inliers at the next, and the count of confirmations would begin again.
    With ``centres`` ``(M, 3)`` (each candidate's place), ``score`` is called as ``score(particles,
    centres)``: a scorer that renders planar renders each candidate about a pose near its place."""
    cand = np.asarray(candidates, np.float64).reshape(-1, 3)
    far = np.hypot(cand[:, 0] - estimate[0], cand[:, 1] - estimate[1]) > min_distance_m
    cand = cand[far]
    if len(cand) == 0:
        return Opinion(False, np.asarray(estimate, np.float64), math.inf, math.nan, 0)
    if centres is not None:
        bad, inl = score(cand, np.asarray(centres, np.float64).reshape(-1, 3)[far])
    else:
        bad, inl = score(cand)
    bad = np.asarray(bad, np.float64)
    if look is not None and polish is not None and polish.places > 0:
        order = np.lexsort((bad, -np.asarray(inl))) if inl is not None else np.argsort(bad, kind="stable")
        extra, bad2, inl2 = look(polish.seeds(cand[order]))
        far = np.hypot(extra[:, 0] - estimate[0], extra[:, 1] - estimate[1]) > min_distance_m
        cand = np.vstack([cand, extra[far]])
        bad = np.concatenate([bad, np.asarray(bad2, np.float64)[far]])
        inl = None if inl is None else np.concatenate([np.asarray(inl), np.asarray(inl2)[far]])
    inl = None if inl is None else np.asarray(inl, np.float64)

    def verdict(idx: np.ndarray) -> Opinion:
        """The decision among the candidates ``idx``."""
        c, b = cand[idx], bad[idx]
        if inl is not None and math.isfinite(current_inliers):
            i = inl[idx]
            j = int(np.lexsort((b, -i))[0])  # the most inliers, then the least badness
            better = bool(i[j] >= current_inliers + inlier_gain and b[j] < current_badness)
            if not better and saturated_ratio is not None and current_inliers + inlier_gain > 1.0:
                ok = np.flatnonzero(i >= current_inliers - 0.02)
                if len(ok):
                    k = int(ok[np.argmin(b[ok])])
                    if b[k] < saturated_ratio * current_badness:
                        return Opinion(True, c[k], float(b[k]), float(i[k]), len(cand))
            return Opinion(better, c[j], float(b[j]), float(i[j]), len(cand))
        j = int(np.argmin(b))
        better = bool(b[j] < badness_ratio * current_badness)
        return Opinion(better, c[j], float(b[j]), math.nan, len(cand))

    if rival is not None:  # the rival confirmed goes before a new place
        rival = np.asarray(rival, np.float64).reshape(3)
        near = (np.hypot(cand[:, 0] - rival[0], cand[:, 1] - rival[1]) <= rival_m) & (
            np.abs(wrap_angle(cand[:, 2] - rival[2])) <= math.radians(rival_deg)
        )
        if near.any():
            found = verdict(np.flatnonzero(near))
            if found.better:
                return found
    return verdict(np.arange(len(cand)))


def history_fit(score_history, pose: np.ndarray, polish: Polish) -> float:
    """How well the place at ``pose`` ``(3,)`` explains the recent past: ``score_history(poses (M, 3))``
    gives each pose's mean inlier share over the previous updates' scans (each pose moved back along the
    odometry; NaN when there is nothing to compare), and the best of ``pose`` and ``polish.rounds``
    rounds of :meth:`Polish.around` it (each around the best so far, with half the spread) is returned:
    a place found within a metre or two of where it should be is compared at its best, as the filter's
    own is."""
    best_pose = np.asarray(pose, np.float64).reshape(1, 3)
    best = float(np.asarray(score_history(best_pose), np.float64)[0])
    if not math.isfinite(best):
        return math.nan
    for r in range(polish.rounds if polish.places > 0 else 0):
        extra = polish.around(best_pose, 0.5**r)
        fit = np.asarray(score_history(extra), np.float64)
        j = int(np.argmax(fit))
        if fit[j] > best:
            best, best_pose = float(fit[j]), extra[j : j + 1]
    return best


class LostDetector:
    """The converged filter's lost decision (module docstring): the :class:`SignalWatch`, the second
    opinion's settings, and the probation after each convergence.

    :meth:`update` takes the update's best badness and inlier share and a callable that gives the second
    opinion, called only when needed as ``opinion(rival, inlier_gain)``: ``rival`` the last better place
    moved with the odometry to where it should be now (to be scored again; None when there is none),
    ``inlier_gain`` the gain in inlier share a better place must show (``doubt_inlier_gain`` at a doubtful
    update outside a suspicion and the probation, else ``opinion_inlier_gain``); it returns an
    :class:`Opinion`, or None when the scan cannot be compared. :meth:`update` returns
    ``(lost, vetoed)``. With ``second_opinion`` off (or no opinion callable: a filter without the
    place prior) the watch alone decides."""

    def __init__(
        self,
        watch: SignalWatch,
        *,
        second_opinion: bool,
        opinion_top: int,
        opinion_per_place: int,
        polish_places: int,
        polish_per_place: int,
        polish_sigma_xy_m: float,
        polish_sigma_yaw_deg: float,
        opinion_inlier_gain: float,
        opinion_badness_ratio: float,
        saturated_badness_ratio: float | None,
        opinion_min_range_m: float,
        max_vetoed_updates: int,
        probation_updates: int,
        probation_hits: int,
        opinion_hits: int,
        consistent_m: float,
        max_misses: int,
        doubt_ratio: float,
        doubt_inlier_gain: float,
        history_updates: int,
        history_margin: float,
        history_min_inliers: float,
    ):
        self.watch = watch
        self.history_updates = int(history_updates)
        self.history_margin = float(history_margin)
        self.history_min_inliers = float(history_min_inliers)
        self.doubt_ratio = float(doubt_ratio)
        self.doubt_inlier_gain = float(doubt_inlier_gain)
        self.second_opinion = bool(second_opinion)
        self.opinion_top = int(opinion_top)
        self.opinion_per_place = int(opinion_per_place)
        self.polish_places = int(polish_places)
        self.polish_per_place = int(polish_per_place)
        self.polish_sigma = (float(polish_sigma_xy_m), float(polish_sigma_yaw_deg))
        self.opinion_inlier_gain = float(opinion_inlier_gain)
        self.opinion_badness_ratio = float(opinion_badness_ratio)
        self.saturated_badness_ratio = (
            None if saturated_badness_ratio is None else float(saturated_badness_ratio)
        )
        self.opinion_min_range_m = float(opinion_min_range_m)
        self.max_vetoed_updates = int(max_vetoed_updates)
        self.probation_updates = int(probation_updates)
        self.probation_hits = int(probation_hits)
        self.opinion_hits = int(opinion_hits)
        self.consistent_m = float(consistent_m)
        self.max_misses = int(max_misses)
        self._misses = 0
        self.vetoed_alarms = 0  # suspicions the second opinion vetoed (episodes)
        self._probation = 0  # updates left in which each update gets a second opinion
        self._hits = 0  # consistent better places in a row
        self._last: np.ndarray | None = None  # the last better place

    def reset(self) -> None:
        """A new particle set: no history, no probation."""
        self.watch.reset()
        self._probation = 0
        self._streak_reset()

    @property
    def doubtful(self) -> bool:
        """The last update was bad, or its inlier share fell below ``doubt_ratio`` of the running level,
        or a rival place is being confirmed: not the time to pull the pose towards the scan (a refinement
        at a wrong place would fit it better and mask the evidence)."""
        return (
            self.watch.bad_updates > 0
            or self._hits > 0
            or self.watch.last_ratio < self.doubt_ratio  # (False when NaN)
        )

    def start_probation(self, with_opinions: bool = True) -> None:
        """A convergence: a second opinion at each of the next ``probation_updates`` updates (none with
        ``with_opinions`` False: the prior search keeps its own rivals through the probation)."""
        self._probation = self.probation_updates if with_opinions else 0
        self._streak_reset()

    def _streak_reset(self) -> None:
        self._hits = 0
        self._misses = 0
        self._last = None

    def _expected(self, motion) -> np.ndarray | None:
        """Where the last better place should be now (moved with the odometry), or None."""
        if self._last is None:
            return None
        return se2_compose(self._last, np.asarray(motion, np.float64).reshape(3))

    def _count(self, found: Opinion | None, motion) -> None:
        """Count the confirmations of one rival place: a better place where the last one has moved to
        (with the odometry) confirms it; a better place elsewhere starts a new count; an update that
        finds no better place keeps the count (the inlier share is noisy from scan to scan) and moves the
        rival on, until more than ``max_misses`` such updates in a row drop it."""
        expected = self._expected(motion)
        if found is None or not found.better:
            self._misses += 1
            if expected is None or self._misses > self.max_misses:
                self._streak_reset()
            else:
                self._last = expected
            return
        consistent = False
        if expected is not None:
            gap = math.hypot(found.pose[0] - expected[0], found.pose[1] - expected[1])
            turn = abs(wrap_angle(found.pose[2] - expected[2]))
            consistent = gap <= self.consistent_m and turn <= math.radians(20.0)
        self._hits = self._hits + 1 if consistent else 1
        self._misses = 0
        self._last = np.asarray(found.pose, np.float64).copy()

    def update(self, best: float, inliers: float, opinion, motion=(0.0, 0.0, 0.0)) -> tuple[bool, bool]:
        """One converged update: its best badness and inlier share, the second opinion's callable (class
        docstring) and ``motion``, the odometry ``(dx, dy, dyaw)`` since the previous update (it moves the
        last better place to where this update should find it). Returns ``(lost, vetoed)``."""
        suspicious = self.watch.update(best, inliers)
        probation = self._probation > 0
        self._probation = max(0, self._probation - 1)
        doubt = self.watch.last_ratio < self.doubt_ratio  # (False when NaN)
        if not (suspicious or probation or doubt):
            self._streak_reset()
            return False, False
        if not self.second_opinion or opinion is None:
            return suspicious, False
        # the rival to score again (where the last better place should be now: a place the prior does not
        # offer at every scan is not lost between two updates), and the gain a better place must show
        doubt_only = not (suspicious or probation)
        gain = self.doubt_inlier_gain if doubt_only else self.opinion_inlier_gain
        found = opinion(self._expected(motion), gain)
        self._count(found, motion)
        if not suspicious:
            return self._hits >= self.probation_hits, False
        if (
            found is None
            or self._hits >= self.opinion_hits
            or self.watch.bad_updates >= self.max_vetoed_updates
        ):
            return True, False
        if self.watch.bad_updates == self.watch.updates:
            self.vetoed_alarms += 1
        return False, True
