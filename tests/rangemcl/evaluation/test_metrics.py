"""Honest metrics on hand-built trajectories: a wrong convergence is counted (with its frame, its error
and when it was caught) even when the run recovers, and a "lost" declared while on track is a false
alarm."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.evaluation.metrics import convergence_events, localization_metrics


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


def test_the_first_correct_fix_costs_the_compute_and_the_distance_up_to_it():
    """The wrong convergence at 12 is not a fix; the one at 30 is: the seconds of frames 0-30 (a wrong
    convergence before it costs its time) and the 30 m driven along the true path, frames shifted by the
    run's first frame; a run whose every convergence was wrong has no fix."""
    from rangemcl.evaluation.metrics import first_correct_fix, shift_event_frames

    est, truth = trajectory()
    rng = np.random.default_rng(3)
    seconds = rng.uniform(0.01, 2.0, len(est))
    m = localization_metrics(
        est, truth, 30, convergence_frames=[12, 30], recovery_frames=[25], seconds=seconds
    )
    assert m["first_fix_frame"] == 30
    assert m["first_fix_seconds"] == pytest.approx(seconds[:31].sum())
    assert m["first_fix_driven_m"] == pytest.approx(30.0)
    shift_event_frames(m, 100)
    assert m["first_fix_frame"] == 130 and m["converged_frame"] == 130
    # a winding path: the distance is along it, not the chord
    t = np.linspace(0, np.pi, 50)
    arc = np.column_stack([10 * np.cos(t), 10 * np.sin(t), t])
    fix = first_correct_fix(np.zeros(50), arc, [49], np.ones(50))
    assert fix["first_fix_driven_m"] == pytest.approx(10 * np.pi, rel=1e-3) and fix["first_fix_seconds"] == 50
    none = first_correct_fix(np.full(50, 60.0), arc, [10, 20], np.ones(50))
    assert none == {"first_fix_frame": None, "first_fix_seconds": None, "first_fix_driven_m": None}
    plain = localization_metrics(est, truth, 30, convergence_frames=[12, 30])  # no seconds: no timing
    assert plain["first_fix_frame"] == 30 and "first_fix_seconds" not in plain
    assert plain["first_fix_driven_m"] == pytest.approx(30.0)
    with pytest.raises(InputError, match="seconds: 3 values for 100 frames"):
        localization_metrics(est, truth, 30, seconds=np.ones(3))


def test_no_events_no_counts():
    est, truth = trajectory()
    m = localization_metrics(est[30:], truth[30:], 0)
    assert m["wrong_convergences_count"] == 0 and m["false_alarms_count"] == 0 and m["convergences"] == 0


def test_track_errors_split_the_offset_along_and_across_the_true_heading():
    from rangemcl.evaluation.metrics import track_errors

    truth = np.array([[0.0, 0.0, 0.0], [5.0, 5.0, np.pi / 2], [1.0, 2.0, np.pi]])
    est = truth + np.array([[0.3, 0.1, 0.0], [0.3, 0.1, 0.0], [0.3, 0.1, 0.0]])
    along, cross = track_errors(est, truth)
    np.testing.assert_allclose(along, [0.3, 0.1, -0.3], atol=1e-12)  # ahead when heading +x, ...
    np.testing.assert_allclose(cross, [0.1, -0.3, -0.1], atol=1e-12)  # ... left of the car positive
    rng = np.random.default_rng(0)
    t = np.column_stack([rng.uniform(-50, 50, (200, 2)), rng.uniform(-np.pi, np.pi, 200)])
    e = t + np.column_stack([rng.normal(0, 1, (200, 2)), np.zeros(200)])
    a, c = track_errors(e, t)
    np.testing.assert_allclose(np.hypot(a, c), np.hypot(*(e[:, :2] - t[:, :2]).T))  # a rotation: lengths kept


def test_perturbed_odometry_scales_distance_and_adds_the_gyro_bias():
    from rangemcl.datasets.kitti import perturb_odometry
    from rangemcl.se2 import pose_matrix, xyyaw_of, yaw_matrix

    # a drive along a circle of 20 m radius at 5 m/s, 10 Hz, on a slope (z rises, pitch kept)
    t = np.arange(200) * 0.1
    ang = 0.25 * t
    poses = pose_matrix(20 * np.sin(ang), 20 * (1 - np.cos(ang)), ang, 0.05 * t)
    pitch = np.array([[np.cos(0.05), 0, np.sin(0.05)], [0, 1, 0], [-np.sin(0.05), 0, np.cos(0.05)]])
    poses[:, :3, :3] = poses[:, :3, :3] @ pitch
    same = perturb_odometry(poses, t)
    np.testing.assert_allclose(same, poses, atol=1e-9)
    longer = xyyaw_of(perturb_odometry(poses, t, scale=1.03))
    steps = np.hypot(*np.diff(longer[:, :2], axis=0).T)
    np.testing.assert_allclose(steps.sum(), 1.03 * np.hypot(*np.diff(xyyaw_of(poses)[:, :2], axis=0).T).sum())
    biased = perturb_odometry(poses, t, yaw_bias_rad_s=np.radians(0.5))
    drift = np.unwrap(xyyaw_of(biased)[:, 2]) - np.unwrap(ang)
    np.testing.assert_allclose(drift, np.radians(0.5) * t, atol=1e-9)
    np.testing.assert_allclose(biased[:, 2, 3], poses[:, 2, 3])  # height kept ...
    yaw_b = xyyaw_of(biased)[:, 2]  # ... and the tilt relative to the heading
    tilt = np.einsum("nji,njk->nik", yaw_matrix(yaw_b), biased[:, :3, :3])
    np.testing.assert_allclose(tilt, np.broadcast_to(pitch, tilt.shape), atol=1e-9)
    with pytest.raises(InputError, match="scale"):
        perturb_odometry(poses, t, scale=0.0)


def test_an_interrupted_run_is_evaluated_from_its_frames_csv_and_said_partial(tmp_path):
    """A localization killed outright leaves frames.csv only (its last line may be cut): evaluate reads
    it, against poses.txt in the lidar frame of the calib.txt beside it, and marks the metrics partial."""
    from rangemcl.datasets.kitti import write_poses_txt
    from rangemcl.evaluation.metrics import evaluate_results
    from rangemcl.localization.pipeline import FRAME_COLUMNS

    n, first = 40, 10
    truth = np.zeros((n + first, 4, 4))
    truth[:] = np.eye(4)
    truth[:, 0, 3] = np.arange(n + first) * 0.8
    seq = tmp_path / "seq"
    seq.mkdir()
    write_poses_txt(seq / "poses.txt", truth)
    run = tmp_path / "run"
    run.mkdir()
    cols = FRAME_COLUMNS.split(",")
    lines = [FRAME_COLUMNS]
    for k in range(n):
        i = first + k
        conv = int(k >= 5)
        row = dict.fromkeys(cols, "0")
        row.update(frame=str(i), x=f"{0.8 * i + (0.1 if conv else 30.0):.4f}", y="0", yaw="0")
        row.update(converged=str(conv), recovered="0", updated="1")  # a scan weighed at every frame
        lines.append(",".join(row[c] for c in cols))
    text = "\n".join(lines) + "\n" + "55,5.5,1.0"  # a last line cut by the kill
    (run / "frames.csv").write_text(text)
    m = evaluate_results(run, seq / "poses.txt")
    assert m["partial"] and m["first_frame"] == first and m["frames"] == n
    assert m["converged_frame"] == first + 5 and m["success"]
    assert m["location_rmse_m"] == pytest.approx(0.1, abs=1e-3)
    (run / "frames.csv").write_text(FRAME_COLUMNS + "\n")
    with pytest.raises(InputError, match="no frame"):
        evaluate_results(run, seq / "poses.txt")
