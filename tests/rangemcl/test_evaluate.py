"""Honest metrics on hand-built trajectories: a wrong convergence is counted (with its frame, its error
and when it was caught) even when the run recovers, and a "lost" declared while on track is a false
alarm."""

from __future__ import annotations

import numpy as np

from rangemcl.evaluate import convergence_events, localization_metrics


def trajectory():
    """100 frames along x; the estimate is 60 m off from frame 10 to 24 (a wrong convergence at 12,
    undone by a re-spread at 25), right from 30 on, and a re-spread at 70 while on track."""
    truth = np.column_stack([np.arange(100.0), np.zeros(100), np.zeros(100)])
    est = truth.copy()
    est[10:25, 1] += 60.0
    est[25:30, 1] += 20.0  # searching again
    est[30:, 0] += 0.3
    return est, truth


def test_wrong_convergence_and_false_alarm_are_counted_even_when_the_run_recovers():
    est, truth = trajectory()
    m = localization_metrics(est, truth, 30, convergence_frames=[12, 30], recovery_frames=[25, 70])
    assert m["success"]  # the paper's metric only looks from the last convergence on ...
    assert m["wrong_convergences_count"] == 1  # ... the wrong one at frame 12 is still reported
    (w,) = m["wrong_convergences"]
    assert (
        w["frame"] == 12 and w["error_m"] == 60.0 and w["caught_frame"] == 25 and w["frames_to_catch"] == 13
    )
    assert m["wrong_convergences_uncaught"] == 1  # caught, but not within 10 frames
    assert m["false_alarms_count"] == 1 and m["false_alarms"][0]["frame"] == 70
    assert m["recoveries"] == 2 and m["convergences"] == 2


def test_a_wrong_convergence_caught_quickly_and_a_justified_alarm():
    est, truth = trajectory()
    e = convergence_events(np.hypot(*(est[:, :2] - truth[:, :2]).T), [20, 30], [25])
    assert e["wrong_convergences"][0]["frames_to_catch"] == 5
    assert e["false_alarms_count"] == 0  # at frame 25 the estimate it gave up was 60 m off
    m = localization_metrics(est, truth, 30, convergence_frames=[20, 30], recovery_frames=[25])
    assert m["wrong_convergences_uncaught"] == 0


def test_no_events_no_counts():
    est, truth = trajectory()
    m = localization_metrics(est[30:], truth[30:], 0)
    assert m["wrong_convergences_count"] == 0 and m["false_alarms_count"] == 0 and m["convergences"] == 0
