"""Lost detection of a converged filter (rangemcl.localization.lost): the evidence watch turns suspicious
only after enough bad updates in a row, and the second opinion says "lost" only when another place
explains the scan clearly better than where the filter is."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl.localization.factory import lost_detector, signal_watch
from rangemcl.localization.lost import (
    Opinion,
    Polish,
    candidate_particles,
    history_fit,
    second_opinion,
)
from rangemcl.localization.settings import RecoverySettings
from rangemcl.se2 import se2_compose


def test_the_watch_needs_bad_updates_in_a_row_against_its_own_level():
    w = signal_watch(RecoverySettings(signal="inliers", updates=3), floor=0.3)
    for _ in range(20):
        assert not w.update(0.1, 0.9)
    # an actor alongside: the residual doubles, the share dips a little: not bad
    assert not w.is_bad(0.25, 0.8)
    # half the usual share: bad, but suspicious only at the third in a row
    assert not w.update(0.1, 0.4)
    assert not w.update(0.1, 0.4)
    assert not w.update(0.1, 0.9)  # one good update resets the count
    assert [w.update(0.1, 0.4) for _ in range(3)] == [False, False, True]
    # the look-alike rule: the share at 70 % of its level is bad only while the residual jumped (> 3x)
    assert not w.is_bad(0.2, 0.63)
    assert w.is_bad(0.5, 0.63)
    w.reset()
    assert w.bad_updates == 0 and not w.residuals


def test_the_residual_signal_judges_a_new_convergence_by_the_floor():
    w = signal_watch(RecoverySettings(signal="residual", factor=2.0, updates=1), floor=0.3)
    assert w.is_bad(0.5)  # no history: 1.5 x floor = 0.45
    assert not w.is_bad(0.4)
    for _ in range(10):
        w.update(0.2)
    assert w.is_bad(0.41) and not w.is_bad(0.39)  # 2 x the median 0.2


@pytest.mark.parametrize("per_place", [9, 16, 25])
def test_candidate_particles_cover_each_place_cell(per_place):
    rng = np.random.default_rng(0)
    xy = rng.uniform(-100, 100, (40, 2))
    yaw = rng.uniform(-math.pi, math.pi, 40)
    cell = 2.0
    p = candidate_particles(xy, yaw, per_place, cell, math.radians(2.0), rng)
    k = int(round(math.sqrt(per_place)))
    assert p.shape == (40 * k * k, 3)
    # every point of every cell has a particle of its place within one grid spacing (diagonal)
    probe = xy[:, None, :] + rng.uniform(-cell / 2, cell / 2, (40, 50, 2))
    mine = p[:, :2].reshape(40, k * k, 2)
    d = np.linalg.norm(probe[:, :, None, :] - mine[:, None, :, :], axis=-1).min(axis=2)
    assert d.max() <= math.sqrt(2) * cell / k + 1e-9
    # all inside their own cell, yaw around the place's
    off = np.abs(mine - xy[:, None, :])
    assert off.max() <= cell / 2 + 1e-9
    dyaw = np.angle(np.exp(1j * (p[:, 2].reshape(40, -1) - yaw[:, None])))
    assert np.abs(dyaw).max() < math.radians(10)


def _scorer(truth):
    """An analytic observation: badness grows with the distance from the true pose, inliers fall."""

    def score(p):
        d = np.hypot(p[:, 0] - truth[0], p[:, 1] - truth[1]) + 5.0 * np.abs(
            np.angle(np.exp(1j * (p[:, 2] - truth[2])))
        )
        return 0.1 + 0.05 * d, np.exp(-0.2 * d)

    return score


def test_the_second_opinion_finds_the_true_place_only_when_the_filter_is_elsewhere():
    rng = np.random.default_rng(1)
    truth = np.array([50.0, 20.0, 0.3])
    places = np.vstack([truth[:2] + np.array([0.4, -0.3]), rng.uniform(-200, 200, (29, 2))])
    yaws = np.concatenate([[truth[2] + 0.01], rng.uniform(-3, 3, 29)])
    cand = candidate_particles(places, yaws, 16, 2.0, math.radians(2.0), rng)
    score = _scorer(truth)
    # the filter sits on a look-alike 80 m away that fits worse
    wrong = np.array([130.0, 20.0, 0.3])
    bad_w, inl_w = 0.35, 0.45  # what the filter's best particle scored there
    op = second_opinion(score, wrong, bad_w, inl_w, cand, min_distance_m=5.0)
    assert op.better and np.hypot(*(op.pose[:2] - truth[:2])) < 1.0
    # the filter at the true place, with the scene changed (everything fits worse, the truth still best)
    op = second_opinion(score, truth, 0.3, 0.7, cand, min_distance_m=5.0)
    assert not op.better
    # the candidates near the estimate are not a second opinion: they are the filter's own place
    op = second_opinion(score, truth + np.array([1.0, 0.0, 0.0]), 0.5, 0.2, cand, min_distance_m=5.0)
    assert not op.better and np.hypot(*(op.pose[:2] - truth[:2])) > 5.0
    # models without an inlier share: badness alone, by a ratio
    op = second_opinion(lambda p: (score(p)[0], None), wrong, 0.35, math.nan, cand, min_distance_m=5.0)
    assert op.better and math.isnan(op.inliers)
    op = second_opinion(lambda p: (score(p)[0], None), wrong, 0.12, math.nan, cand, min_distance_m=5.0)
    assert not op.better


def test_where_the_inlier_share_saturates_residuals_decide_only_when_asked():
    """A sensor whose far rays nearly all agree at a wrong place as at the true one (the MQ-8 on
    town_medium: 0.91-0.99 against 0.99-1.0): the inlier gain cannot be passed; with
    ``saturated_ratio`` a place with as many inliers and a much smaller residual is better, and one with
    a residual only a little smaller is not."""
    rng = np.random.default_rng(2)
    truth = np.array([50.0, 20.0, 0.3])
    places = np.vstack([truth[:2] + np.array([0.2, -0.1]), rng.uniform(-200, 200, (29, 2))])
    yaws = np.concatenate([[truth[2]], rng.uniform(-3, 3, 29)])
    cand = candidate_particles(places, yaws, 16, 0.5, math.radians(0.5), rng)

    def score(p):  # every place saturates the inlier share; the residual grows away from the truth
        d = np.hypot(p[:, 0] - truth[0], p[:, 1] - truth[1]) + 5.0 * np.abs(
            np.angle(np.exp(1j * (p[:, 2] - truth[2])))
        )
        return 0.15 + 0.01 * d, np.full(len(p), 1.0)

    wrong = np.array([130.0, 20.0, 0.3])
    assert not second_opinion(score, wrong, 0.45, 0.95, cand, min_distance_m=5.0).better
    op = second_opinion(score, wrong, 0.45, 0.95, cand, min_distance_m=5.0, saturated_ratio=0.75)
    assert op.better and np.hypot(*(op.pose[:2] - truth[:2])) < 1.0
    # the filter's residual only a little above the best place's: not better
    assert not second_opinion(score, wrong, 0.19, 0.95, cand, min_distance_m=5.0, saturated_ratio=0.75).better
    # room for the gain (the filter's inlier share well below 1): the usual test alone decides
    op = second_opinion(score, wrong, 0.45, 0.7, cand, min_distance_m=5.0, saturated_ratio=0.75)
    assert op.better and op.inliers == 1.0


def test_the_second_look_searches_around_the_best_distinct_places():
    """A sensor whose evidence peaks within a few decimetres and a degree: the candidates over the true
    place's cell all miss the peak. With ``look`` (the filter's grids), the best distinct places, best
    first, are handed to it as seeds, its poses join the candidates and find the peak, and those of them
    near the estimate are left out; without ``polish`` or with no places there is no second look."""
    truth = np.array([50.0, 20.0, 0.3])

    def score(p):
        d = np.hypot(p[:, 0] - truth[0], p[:, 1] - truth[1]) + 10.0 * np.abs(
            np.angle(np.exp(1j * (p[:, 2] - truth[2])))
        )
        return 0.1 + 0.3 * np.minimum(d, 1.0), np.exp(-d / 0.3)

    seen = []

    def look(seeds):  # a 5 x 5 grid of 0.5 m around each seed, at its yaw, and the truth's yaw
        seen.append(seeds.copy())
        g = np.arange(-1.0, 1.01, 0.5)
        gx, gy = np.meshgrid(g, g)
        out = [
            np.column_stack([s[0] + gx.ravel(), s[1] + gy.ravel(), np.full(gx.size, yaw)])
            for s in seeds
            for yaw in (s[2], truth[2])
        ]
        p = np.vstack(out)
        bad, inl = score(p)
        return p, bad, inl

    wrong = np.array([130.0, 20.0, 0.3])
    cand = np.array([[51.0, 20.5, 0.33], [51.5, 21.5, 0.33], [129.0, 20.0, 0.3], [-80.0, 5.0, 1.0]])
    polish = Polish(places=8, per_place=48, sigma_xy_m=0.3, sigma_yaw_deg=1.0, rng=np.random.default_rng(6))
    plain = second_opinion(score, wrong, 0.35, 0.45, cand, min_distance_m=5.0)
    assert not plain.better
    op = second_opinion(score, wrong, 0.35, 0.45, cand, min_distance_m=5.0, polish=polish, look=look)
    assert op.better and np.hypot(*(op.pose[:2] - truth[:2])) < 1e-9 and op.inliers > 0.99
    # one call; its seeds: the two places farther than 5 m from the estimate at least 3 m apart, best first
    assert len(seen) == 1 and np.allclose(seen[0], [[51.0, 20.5, 0.33], [-80.0, 5.0, 1.0]])
    assert op.candidates == 3 + 2 * 2 * 25
    seeds = polish.seeds(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [10.0, 0.0, 0.0]]))
    assert seeds[:, 0].tolist() == [0.0, 10.0]
    # no places to look at, or no polish: the candidates alone
    none = Polish(places=0, per_place=48, sigma_xy_m=0.3, sigma_yaw_deg=1.0, rng=np.random.default_rng(6))
    for kw in (dict(polish=none, look=look), dict(look=look)):
        op = second_opinion(score, wrong, 0.35, 0.45, cand, min_distance_m=5.0, **kw)
        assert not op.better and op.candidates == 3 and len(seen) == 1
    # around a seed near the estimate, none of the look's poses is taken
    near = second_opinion(score, truth, 0.1, 0.99, cand, min_distance_m=5.0, polish=polish, look=look)
    assert np.hypot(*(near.pose[:2] - truth[:2])) > 5.0


def test_the_rival_is_confirmed_before_a_new_place_that_fits_a_little_more():
    """Two places fit the scan clearly better than the filter's; the look-alike a little
    more than the true place. Without a rival the look-alike is the opinion; with the rival (the last
    better place moved with the odometry) near the true place, the true place is, as long as it is better
    itself; a rival where nothing fits better leaves the verdict to all the candidates."""
    true_place = np.array([50.0, 20.0, 0.3])
    look_alike = np.array([-120.0, 60.0, 2.0])

    def score(p):
        d1 = np.hypot(p[:, 0] - true_place[0], p[:, 1] - true_place[1])
        d2 = np.hypot(p[:, 0] - look_alike[0], p[:, 1] - look_alike[1])
        inl = np.maximum(0.9 * np.exp(-d1), 0.95 * np.exp(-d2))
        return 0.6 - 0.4 * inl, inl

    cand = np.array([true_place, look_alike, [300.0, 0.0, 0.0]])
    wrong = np.array([130.0, 20.0, 0.3])
    op = second_opinion(score, wrong, 0.45, 0.5, cand, min_distance_m=5.0)
    assert op.better and np.allclose(op.pose, look_alike)
    rival = true_place + np.array([1.0, 0.5, 0.05])
    op = second_opinion(score, wrong, 0.45, 0.5, cand, min_distance_m=5.0, rival=rival)
    assert op.better and np.allclose(op.pose, true_place)
    turned = true_place + np.array([1.0, 0.5, math.radians(30.0)])  # beyond rival_deg: not that place
    op = second_opinion(score, wrong, 0.45, 0.5, cand, min_distance_m=5.0, rival=turned)
    assert np.allclose(op.pose, look_alike)
    # the true place no longer better (the filter fits 0.8): the rival is not taken, the verdict is all's
    op = second_opinion(score, wrong, 0.2, 0.8, cand, min_distance_m=5.0, rival=rival)
    assert np.allclose(op.pose, look_alike) and not op.better


def test_the_look_at_the_past_compares_each_place_at_its_best():
    """history_fit: a place found 1 m and 2 degrees from a sharply peaked true pose is scored at its best
    (the polish finds the peak), a place that fits nowhere near stays low, and no evidence is NaN."""
    truth = np.array([50.0, 20.0, 0.3])

    def fit(p):  # the mean inlier share over past scans of poses at the current update
        d = np.hypot(p[:, 0] - truth[0], p[:, 1] - truth[1]) + 10.0 * np.abs(
            np.angle(np.exp(1j * (p[:, 2] - truth[2])))
        )
        return 0.5 + 0.45 * np.exp(-d / 0.3)

    polish = Polish(places=1, per_place=48, sigma_xy_m=0.6, sigma_yaw_deg=3.0, rng=np.random.default_rng(7))
    near = truth + np.array([0.8, -0.6, math.radians(2.0)])
    assert fit(near[None])[0] < 0.6  # as found: hardly better than anywhere
    assert history_fit(fit, near, polish) > 0.75  # near its best
    assert history_fit(fit, np.array([130.0, 20.0, 0.3]), polish) < 0.55
    assert math.isnan(history_fit(lambda p: np.full(len(p), math.nan), near, polish))
    # no polish: the place as it is
    none = Polish(places=0, per_place=48, sigma_xy_m=0.6, sigma_yaw_deg=3.0, rng=np.random.default_rng(7))
    assert history_fit(fit, near, none) == pytest.approx(fit(near[None])[0])


def test_no_candidate_far_enough_is_no_opinion():
    cand = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    op = second_opinion(_scorer(np.zeros(3)), np.zeros(3), 1.0, 0.1, cand, min_distance_m=5.0)
    assert not op.better and op.candidates == 0


def _detector(**kw):
    """A detector whose suspicion comes at the second bad update."""
    settings = {"signal": "inliers", "updates": 2, "probation_updates": 0, **kw}
    det = lost_detector(RecoverySettings(**settings), separation_m=5.0, floor=0.3)
    for _ in range(10):
        det.watch.update(0.1, 0.9)
    return det


def _suspicion_only(**kw):
    """As :func:`_detector`, but doubting only below 0.3 of the level: the bad updates below (at 0.3 / 0.9
    of it) ask for a second opinion only once they make a suspicion, so that a test sees the
    suspicion's own count of confirmations."""
    return _detector(doubt_ratio=0.3, **kw)


def test_a_doubtful_update_asks_for_a_second_opinion_without_a_suspicion():
    """An inlier share at 0.6 of its level (above the suspicion's 0.5, below the doubt's 0.8): a rival
    that keeps fitting better is confirmed without a suspicion."""
    motion = np.array([1.0, 0.0, 0.0])
    det = _detector()
    place = np.array([10.0, 0.0, 0.0])
    calls, out = [], []
    for _ in range(2):

        def op(rival, gain, p=place.copy(), c=calls):
            c.append(rival)
            return Opinion(True, p, 0.1, 0.95, 400)

        out.append(det.update(0.1, 0.55, op, motion))
        place = se2_compose(place, motion)
    assert [o[0] for o in out] == [False, True] and det.watch.bad_updates == 0
    # a doubtful update keeps scoring the last better place (moved with the odometry)
    assert len(calls) == 2 and calls[0] is None
    assert np.allclose(calls[1], se2_compose(np.array([10.0, 0.0, 0.0]), motion))
    # a doubtful update asks its opinion for a clearer win than a suspicion or the probation does
    det = _detector()
    gains = []
    det.update(0.1, 0.55, lambda rival, gain: gains.append(gain) or None, motion)
    det.probation_updates = 1
    det.start_probation()
    det.update(0.1, 0.55, lambda rival, gain: gains.append(gain) or None, motion)
    assert gains == [det.doubt_inlier_gain, det.opinion_inlier_gain] and gains[0] > gains[1]
    # at the running level: no opinion asked
    det = _detector()
    calls = []
    det.update(0.1, 0.9, lambda *_: calls.append(1) or Opinion(False, np.zeros(3), 0.5, 0.5, 1), motion)
    assert calls == []


def test_a_suspicion_is_lost_only_when_one_place_keeps_fitting_better():
    motion = np.array([0.8, 0.0, 0.02])  # the car's odometry between updates
    # better places that jump about (a wall here, a wall there): vetoed every time
    det = _suspicion_only()
    rng = np.random.default_rng(3)
    results = []
    for _ in range(8):
        pose = np.array([*rng.uniform(-200, 200, 2), 0.0])
        results.append(det.update(0.6, 0.3, lambda *_, p=pose: Opinion(True, p, 0.3, 0.9, 400), motion))
    assert results[:2] == [(False, False), (False, True)]  # the second bad update makes the suspicion
    assert all(r == (False, True) for r in results[1:]) and det.vetoed_alarms == 1
    # one place that moves with the odometry: lost at its second confirmation
    det = _suspicion_only()
    place = np.array([50.0, -20.0, 1.0])
    out = []
    for _ in range(4):
        out.append(det.update(0.6, 0.3, lambda *_, p=place.copy(): Opinion(True, p, 0.3, 0.9, 400), motion))
        place = se2_compose(place, motion)
    assert out[0] == (False, False) and out[1] == (False, True) and out[2] == (True, False)
    # no better place: vetoed until the suspicion has lasted max_vetoed_updates
    det = _suspicion_only(max_vetoed_updates=5)
    out = [
        det.update(0.6, 0.3, lambda *_: Opinion(False, np.zeros(3), 0.7, 0.2, 400), motion) for _ in range(5)
    ]
    assert [o[0] for o in out] == [False, False, False, False, True]


def test_probation_undoes_a_convergence_when_a_better_place_is_confirmed():
    r = RecoverySettings(signal="inliers", updates=5, probation_updates=3, probation_hits=2)
    det = lost_detector(r, separation_m=5.0, floor=0.3)
    det.start_probation()
    motion = np.array([1.0, 0.0, 0.0])
    place = np.array([10.0, 0.0, 0.0])
    out = []
    for _ in range(2):
        out.append(
            det.update(0.1, 0.9, lambda *_, p=place.copy(): Opinion(True, p, 0.1, 0.95, 400), motion)[0]
        )
        place = se2_compose(place, motion)
    assert out == [False, True]
    # after the probation, an unsuspicious filter asks nobody
    det.start_probation()
    calls = []

    def ask(*_):
        calls.append(1)
        return Opinion(False, np.zeros(3), 0.5, 0.5, 1)

    for _ in range(5):
        det.update(0.1, 0.9, ask, motion)
    assert len(calls) == 3


def test_one_update_without_the_rival_does_not_undo_its_confirmation():
    motion = np.array([0.8, 0.0, 0.0])
    det = _suspicion_only()
    place = np.array([50.0, -20.0, 0.0])
    better = [True, True, False, True]  # the suspicion starts at the second update
    out = []
    for b in better:
        out.append(
            det.update(0.6, 0.3, lambda *_, p=place.copy(), b=b: Opinion(b, p, 0.3, 0.9, 400), motion)[0]
        )
        place = se2_compose(place, motion)
    assert out == [False, False, False, True]
    # three misses in a row drop the rival: the next better place starts a new count
    det = _suspicion_only()
    out = []
    for b in [True, True, False, False, False, True]:
        out.append(
            det.update(0.6, 0.3, lambda *_, p=place.copy(), b=b: Opinion(b, p, 0.3, 0.9, 400), motion)[0]
        )
        place = se2_compose(place, motion)
    assert not any(out)


def test_the_pose_is_doubtful_after_a_bad_update_or_while_a_rival_counts():
    det = _detector()
    assert not det.doubtful
    det.update(0.1, 0.9, None)
    assert not det.doubtful
    det.update(0.6, 0.3, None)  # one bad update: doubtful (no refinement)
    assert det.doubtful
    det.update(0.1, 0.9, None)  # good again
    assert not det.doubtful
    det.update(0.1, 0.6, None)  # not bad (above half the level, 0.9) but well below it
    assert det.watch.bad_updates == 0 and det.doubtful
