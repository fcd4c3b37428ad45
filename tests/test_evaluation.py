import math

import numpy as np
import pytest

from sim.evaluation.statistics import StatisticsType, statistics
from sim.evaluation.trajectory import (
    MIN_DISTANCE_M,
    Trajectory,
    in_start_frame,
    path_length,
    trajectory_metrics,
    truth_since,
    write_tum,
)
from slam.lie import gravity_aligned


def circle(n=200, radius=5.0, z=0.0):
    t = np.linspace(0, 60, n)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    a = t / 60 * math.pi  # half circle
    poses[:, 0, 3] = radius * np.sin(a)
    poses[:, 1, 3] = radius * (1 - np.cos(a))
    poses[:, 2, 3] = z
    for i, yaw in enumerate(a):
        c, s = math.cos(yaw), math.sin(yaw)
        poses[i, :2, :2] = [[c, -s], [s, c]]
    return t, poses


def test_start_frame_drops_roll_and_pitch_but_keeps_yaw():
    T = np.eye(4)
    T[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])
    T[:3, 3] = [1, 2, 3]
    G = gravity_aligned(T)
    assert np.allclose(G[:3, 2], [0, 0, 1]) and np.allclose(G[:3, 0], [0, 1, 0]) and np.allclose(G[:3, 3], [1, 2, 3])
    local = in_start_frame(np.stack([T, T]))
    assert np.allclose(local[0][:3, 3], 0)


def test_constant_offset_is_the_unaligned_ate_and_vanishes_when_aligned():
    t, gt = circle()
    est = gt.copy()
    est[:, :3, 3] += [0.3, -0.4, 0.0]  # 0.5 m off everywhere
    m, errors = trajectory_metrics(Trajectory(t, est), Trajectory(t, gt))
    assert m["ate_m"]["rmse"] == pytest.approx(0.5, abs=1e-9)
    assert m["ate_aligned_m"]["rmse"] < 1e-6
    assert m["final_error_m"] == pytest.approx(0.5)
    assert m["distance_m"] == pytest.approx(5 * math.pi, rel=1e-3)
    assert m["final_error_percent_of_distance"] == pytest.approx(50 / (5 * math.pi), rel=1e-3)
    assert m["mean_error_percent_of_distance"] == pytest.approx(50 / (5 * math.pi), rel=1e-3)
    assert np.allclose(errors.position_m, 0.5) and np.array_equal(errors.t, t)
    assert "error_over_time" not in m  # the series travel apart from the metrics


def test_no_rates_per_metre_for_a_robot_that_barely_moved():
    """A robot at rest moves millimetres; its error over that distance is no drift rate
    (2 mm over 1 cm would read 16 %): no % of distance and no RPE below MIN_DISTANCE_M."""
    t = np.linspace(0, 8, 100)
    gt = np.repeat(np.eye(4)[None], len(t), axis=0)
    gt[:, 0, 3] = 0.01 * t / t[-1]  # 1 cm of settling
    est = gt.copy()
    est[:, 1, 3] += 0.002
    m, _ = trajectory_metrics(Trajectory(t, est), Trajectory(t, gt))
    assert m["distance_m"] == pytest.approx(0.01) and m["final_error_m"] == pytest.approx(0.002)
    assert m["final_error_percent_of_distance"] is None and m["mean_error_percent_of_distance"] is None
    assert m["rpe_per_m"]["status"].startswith("not computed")
    assert m["ate_aligned_m"]["status"].startswith("not computed")  # on one line: no alignment
    assert m["ate_m"]["max"] == pytest.approx(0.002)
    gt[:, 0, 3] = MIN_DISTANCE_M * t / t[-1]  # just far enough
    est = gt.copy()
    est[:, 1, 3] += 0.002
    m, _ = trajectory_metrics(Trajectory(t, est), Trajectory(t, gt))
    assert m["final_error_percent_of_distance"] == pytest.approx(100 * 0.002 / MIN_DISTANCE_M)


def test_yaw_drift_shows_in_yaw_error_and_rpe():
    t, gt = circle()
    est = gt.copy()
    drift = np.radians(10) * t / t[-1]  # 10 deg of yaw drift at the end, positions rotated with it
    for i, d in enumerate(drift):
        c, s = math.cos(d), math.sin(d)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        est[i, :3, :3] = R @ gt[i, :3, :3]
        est[i, :3, 3] = R @ gt[i, :3, 3]
    m, errors = trajectory_metrics(Trajectory(t, est), Trajectory(t, gt))
    assert m["yaw_error_deg"]["final"] == pytest.approx(10, abs=1e-6)
    assert m["rpe_per_m"]["mean"] > 0.0
    assert m["ate_m"]["max"] > m["ate_aligned_m"]["max"]
    assert errors.yaw_deg[-1] == pytest.approx(10, abs=1e-6)
    # the error grows along the arc: its mean over the distance stays below the final error's share
    assert m["mean_error_percent_of_distance"] == pytest.approx(100 * errors.position_m.mean() / m["distance_m"], rel=1e-9)
    assert m["mean_error_percent_of_distance"] < 0.5 * m["final_error_percent_of_distance"]


def test_an_exact_estimate_between_truth_samples_scores_no_error():
    """Poses logged between two ground-truth samples (the filter runs behind the physics)
    are scored against the truth at their own time: on a turning robot the nearest
    sample would be off by the turn since."""
    t, gt = circle(n=601)  # truth every 0.1 s, turning at 3 deg/s
    t_est = t[:-1] + 0.07  # the estimate 30 ms before the next truth sample, exact
    _, est = circle(n=601)
    a = t_est / 60 * math.pi
    est = est[:-1]
    est[:, 0, 3], est[:, 1, 3] = 5.0 * np.sin(a), 5.0 * (1 - np.cos(a))
    est[:, 0, 0], est[:, 0, 1], est[:, 1, 0], est[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    m, errors = trajectory_metrics(Trajectory(t_est, est), Trajectory(t, gt), max_time_diff=0.05)
    assert m["poses"] == 600 and np.array_equal(errors.t, t_est)
    assert m["ate_m"]["max"] < 1e-4 and abs(m["yaw_error_deg"]["max_abs"]) < 1e-6  # chord of a 0.1 s arc: 0.02 mm
    far = Trajectory(t_est + 0.1, est)  # beyond max_time_diff of every truth sample at the end: dropped
    assert trajectory_metrics(far, Trajectory(t, gt), max_time_diff=0.05)[0]["poses"] == 599


def test_statistics_are_named_by_their_type_in_the_order_asked():
    values = [3.0, 1.0, 2.0, 4.0]
    s = statistics(values, (StatisticsType.RMSE, StatisticsType.MEDIAN, StatisticsType.P90, StatisticsType.FINAL))
    assert list(s) == ["rmse", "median", "p90", "final"]
    assert s["rmse"] == pytest.approx(math.sqrt(7.5)) and s["median"] == 2.5 and s["p90"] == pytest.approx(3.7) and s["final"] == 4.0
    assert statistics([], tuple(StatisticsType)) == {}


def test_truth_since_starts_in_the_gravity_aligned_first_pose(tmp_path):
    t, poses = circle(n=50)
    poses[:, :3, 3] += [10.0, -2.0, 1.0]
    rows = [np.concatenate([T[:3, 3], [math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)]]) for T, a in zip(poses, t / 60 * math.pi)]
    world = Trajectory.from_pose_rows(t, rows)
    assert np.allclose(world.T, poses) and path_length(world) == pytest.approx(path_length(Trajectory(t, poses)))
    start = truth_since(world, t[10])
    assert len(start.trajectory) == 40 and start.trajectory.t[0] == t[10]
    assert np.allclose(start.trajectory.T[0], np.eye(4)) and np.allclose(start.T_world_start, poses[10])
    assert np.allclose(world.at(t[20] - 1e-7), poses[20]) and np.allclose(world.at(1e9), poses[-1])
    write_tum(tmp_path / "gt.tum", world)  # the logged quaternions, as they came
    first = (tmp_path / "gt.tum").read_text().splitlines()[1].split()
    assert [float(v) for v in first[4:]] == pytest.approx([*rows[1][4:], rows[1][3]], abs=1e-8)


# ---------------------------------------------------------------------------- the VO's deltas against truth


def test_vo_delta_scores_fit_deltas_drawn_from_their_covariance_and_flag_overconfident_ones():
    """sim.evaluation.vo_consistency: deltas drawn with the covariance they report score a
    NEES near 6 (3 + 3); the same deltas reporting a hundredth of it, a hundred times more.
    Frames older than the VO's oldest keyframe are dropped, and a delta whose keyframe has
    no true pose is counted, not scored. Deltas all 3 % too long show as that scale error."""
    from sim.evaluation.vo_consistency import VoDeltaScores
    from slam.lie import se3, so3_exp
    from slam.vo import VoResult

    def run(report_scale: float) -> dict:
        rng = np.random.default_rng(3)
        scores = VoDeltaScores()
        cov = np.diag([np.radians(0.05) ** 2] * 3 + [0.002**2] * 3)
        L = np.linalg.cholesky(cov)
        poses = [se3(so3_exp(np.array([0.0, 0.0, 0.02 * k])), [0.1 * k, 0.01 * k, 0.0]) for k in range(400)]
        for k, T in enumerate(poses):
            scores.capture(k, T)
            kf = 5 * (k // 5)
            if k == kf:
                continue
            true = np.linalg.inv(poses[kf]) @ T
            xi = L @ rng.standard_normal(6)  # T_true = T_est Exp(xi)
            est = true @ np.linalg.inv(se3(so3_exp(xi[:3]), xi[3:]))
            result = VoResult(t=0.1 * k, frame_id=k, ok=True, reason=None, keyframe_id=kf, T_kf_cur=est, cov=cov * report_scale,
                              inliers=50, keypoints=np.zeros((0, 2)), new_keyframe=False, keyframe_history=(kf,))
            scores.score(result)
        assert len(scores._true) <= 6  # only the frames since the oldest keyframe
        lost = VoResult(t=0.0, frame_id=399, ok=True, reason=None, keyframe_id=3, T_kf_cur=np.eye(4), cov=cov,
                        inliers=50, keypoints=np.zeros((0, 2)), new_keyframe=False, keyframe_history=(395,))
        scores.score(lost)
        report = scores.report()
        assert report["status"] == "ok" and report["deltas"] == 320 and report["unscored"] == 1
        return report

    fit = run(1.0)
    assert 5.0 < fit["nees"]["mean"] < 7.0 and 2.4 < fit["nees_rotation"]["mean"] < 3.6 and 2.4 < fit["nees_translation"]["mean"] < 3.6
    assert 0.02 < fit["median_rotation_error_deg"] < 0.15 and 1.0 < fit["median_translation_error_mm"] < 6.0
    assert run(0.01)["nees"]["mean"] > 100 * 5.0
    assert abs(fit["scale_error"]["median"]) < 0.01 and fit["scale_error"]["deltas"] == 320
    # every delta 3 % too long (a depth bias common to all of them): the scale error says so
    scores = VoDeltaScores()
    for k in range(20):
        scores.capture(k, se3(np.eye(3), [0.1 * k, 0.0, 0.0]))
        if k:
            long = se3(np.eye(3), [0.1 * k * 1.03, 0.0, 0.0])
            scores.score(VoResult(t=0.1 * k, frame_id=k, ok=True, reason=None, keyframe_id=0, T_kf_cur=long, cov=np.eye(6) * 1e-4,
                                  inliers=50, keypoints=np.zeros((0, 2)), new_keyframe=False, keyframe_history=(0,)))
    assert scores.report()["scale_error"]["median"] == pytest.approx(0.03)
    assert VoDeltaScores().report()["status"] == "no deltas scored"


def test_vo_heading_report_reads_the_keyframe_chain_turn_scale():
    """A rover turning left and right about the world's vertical (net +105 deg) with a
    camera looking ahead and down, its keyframe deltas' rotations 0.4 % too large (what a
    0.4 % focal error does) plus noise: the heading report's rotation scale error is 0.4 %
    within its stated std, the chained heading error (estimated minus true) 0.4 % of the net turn, and one link off
    by 20 deg is counted apart; deltas that made no keyframe do not enter it."""
    from sim.evaluation.vo_consistency import VoDeltaScores
    from slam.lie import rot_z, rot_zyx, se3, so3_exp, so3_log
    from slam.vo import VoResult

    rng = np.random.default_rng(5)
    cam = rot_zyx(-np.pi / 2, 0.0, -np.pi / 2 - 0.4)  # camera z ahead, tilted down
    turns = np.radians(np.r_[np.full(30, 3.0), np.full(15, -3.0), np.full(30, 2.0), np.full(5, 0.0)])
    scores, yaw, pose_kf, k = VoDeltaScores(), 0.0, None, 0
    for i, d in enumerate(turns):
        for step in (0.5, 1.0):  # a delta half-way (no keyframe), then the link
            T = se3(rot_z(yaw + step * d) @ cam, [0.1 * i + 0.05 * step, 0.0, 0.5])
            k += 1
            scores.capture(k, T)
            if pose_kf is None:
                continue
            true = np.linalg.inv(pose_kf[1]) @ T
            rv = so3_log(true[:3, :3]) * 1.004 + rng.normal(0.0, np.radians(0.01), 3)
            if i == 40 and step == 1.0:
                rv = rv + cam.T @ [0.0, 0.0, np.radians(20.0)]
            est = se3(so3_exp(rv), true[:3, 3])
            scores.score(VoResult(t=0.1 * k, frame_id=k, ok=True, reason=None, keyframe_id=pose_kf[0], T_kf_cur=est,
                                  cov=np.eye(6) * 1e-6, inliers=50, keypoints=np.zeros((0, 2)), new_keyframe=step == 1.0,
                                  keyframe_history=(pose_kf[0],)))
        pose_kf = (k, T)
        yaw += d
    h = scores.report()["heading"]
    assert h["links"] == len(turns) - 1 and h["gross_links"] == 1
    assert h["net_turn_deg"] == pytest.approx(np.degrees(turns[1:].sum()) - np.degrees(turns[40]), abs=0.05)
    assert h["rotation_scale_error"] == pytest.approx(0.004, abs=3 * h["rotation_scale_error_std"])
    assert h["rotation_scale_error_std"] < 0.001
    assert h["error_deg"] == pytest.approx(0.004 * h["net_turn_deg"], abs=0.1)
