"""Trajectory evaluation against ground truth, with ``evo`` as the metrics library.

Each robot is evaluated in its own start frame: the gravity-aligned frame at its
first ground-truth pose (x, y, z and yaw of the body, roll and pitch dropped), which is
how the robots' map frames are defined (thesis 4.1.2, design notes §3). ATE is
reported unaligned in that frame, as the thesis reports its errors, and SE(3)-aligned
(Umeyama, evo) for comparison; RPE per metre travelled; final error absolute and as a
percentage of the distance driven; yaw error over time.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit
from scipy.spatial.transform import Rotation


class EvaluationError(ValueError):
    """Trajectories that cannot be compared (too short, no common time span)."""


def pose_matrix(xyz_qwxyz: np.ndarray) -> np.ndarray:
    """4x4 from ``[x, y, z, qw, qx, qy, qz]`` (the run log's ground-truth rows)."""
    T = np.eye(4)
    T[:3, 3] = xyz_qwxyz[:3]
    qw, qx, qy, qz = xyz_qwxyz[3:7]
    T[:3, :3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
    return T


def yaw_of(R: np.ndarray) -> float:
    """Yaw of a rotation matrix (z-y-x Euler convention, z up)."""
    return math.atan2(R[1, 0], R[0, 0])


def gravity_aligned(T: np.ndarray) -> np.ndarray:
    """The frame with T's position and yaw, roll and pitch dropped (thesis 4.1.2)."""
    out = np.eye(4)
    c, s = math.cos(yaw_of(T[:3, :3])), math.sin(yaw_of(T[:3, :3]))
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = T[:3, 3]
    return out


def in_start_frame(poses_world: np.ndarray) -> np.ndarray:
    """Express world poses (N, 4, 4) in the gravity-aligned frame of the first one."""
    start_inv = np.linalg.inv(gravity_aligned(poses_world[0]))
    return start_inv[None] @ poses_world


def truth_since(gt_t, gt_pose_rows, t0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth from its first sample at or after ``t0`` (a robot's filter start):
    the times, the poses (N, 4, 4) in the gravity-aligned frame of that first pose (the
    robot's start and map frame), and that frame in the world, ``T_world_start``."""
    gt_t = np.asarray(gt_t, dtype=float)
    first = int(np.searchsorted(gt_t, t0 - 1e-9))
    poses = np.stack([pose_matrix(p) for p in gt_pose_rows[first:]])
    return gt_t[first:], in_start_frame(poses), gravity_aligned(poses[0])


def write_tum(path: Path, times, poses: np.ndarray) -> None:
    """(N, 4, 4) poses as a TUM file: ``t x y z qx qy qz qw`` per line."""
    quats = Rotation.from_matrix(np.asarray(poses)[:, :3, :3]).as_quat()  # x, y, z, w
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        for t, T, q in zip(times, poses, quats):
            f.write(f"{t:.6f} {T[0, 3]:.6f} {T[1, 3]:.6f} {T[2, 3]:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}\n")


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()) if len(poses) > 1 else 0.0


def _traj(times: np.ndarray, poses: np.ndarray) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.asarray(times, dtype=float))


def _stats(metric) -> dict[str, float]:
    s = metric.get_all_statistics()
    return {k: float(s[k]) for k in ("rmse", "mean", "median", "max")}


def trajectory_metrics(
    t_est: np.ndarray, T_est: np.ndarray, t_gt: np.ndarray, T_gt: np.ndarray, max_time_diff: float = 0.011
) -> dict[str, float | dict]:
    """Compare an estimated trajectory with ground truth, both (N, 4, 4) in the same frame."""
    ref, est = _traj(t_gt, T_gt), _traj(t_est, T_est)
    try:
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_time_diff)
    except sync.SyncException as exc:
        raise EvaluationError(f"no common timestamps within {max_time_diff} s: {exc}") from None
    if ref.num_poses < 2:
        raise EvaluationError(f"only {ref.num_poses} associated poses")
    distance = float(ref.path_length)
    ate = metrics.APE(metrics.PoseRelation.translation_part)
    ate.process_data((ref, est))
    aligned = PoseTrajectory3D(poses_se3=list(est.poses_se3), timestamps=est.timestamps)
    aligned.align(ref, correct_scale=False)
    ate_aligned = metrics.APE(metrics.PoseRelation.translation_part)
    ate_aligned.process_data((ref, aligned))
    out: dict[str, float | dict] = {
        "poses": int(ref.num_poses),
        "distance_m": distance,
        "ate_m": _stats(ate),
        "ate_aligned_m": _stats(ate_aligned),
    }
    if distance > 1.5:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=1.0, delta_unit=Unit.meters, all_pairs=True)
        try:
            rpe.process_data((ref, est))
            out["rpe_per_m"] = _stats(rpe)
        except metrics.MetricsException as exc:
            out["rpe_per_m"] = {"status": f"not computed: {exc}"}
    else:
        out["rpe_per_m"] = {"status": f"not computed: only {distance:.2f} m travelled"}
    final = float(np.linalg.norm(ref.positions_xyz[-1] - est.positions_xyz[-1]))
    yaw_err = np.array(
        [wrap(yaw_of(e[:3, :3]) - yaw_of(r[:3, :3])) for r, e in zip(ref.poses_se3, est.poses_se3)]
    )
    out["final_error_m"] = final
    out["final_error_percent_of_distance"] = 100.0 * final / distance if distance > 0 else None
    out["yaw_error_deg"] = {"final": math.degrees(yaw_err[-1]), "max_abs": math.degrees(np.abs(yaw_err).max())}
    out["error_over_time"] = {
        "t": ref.timestamps.tolist(),
        "position_m": ate.error.tolist(),
        "yaw_deg": np.degrees(yaw_err).tolist(),
    }
    return out


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def nees_report(estimate: np.ndarray, truth: np.ndarray, cov: np.ndarray, angle_dims: int = 2) -> dict:
    """NEES over time of an estimate (N, d) with covariances (N, d, d) against truth.

    The first ``angle_dims`` components are angles (wrapped). Reports the mean NEES, the
    share of samples inside the two-sided 95 % chi-square interval of ``d`` degrees of
    freedom, and that interval; a consistent filter has a mean near ``d`` and about
    95 % of its samples inside (consecutive samples are correlated, so the mean is not
    held to the much tighter interval of independent samples).
    """
    from scipy.stats import chi2

    err = estimate - truth
    err[:, :angle_dims] = (err[:, :angle_dims] + np.pi) % (2 * np.pi) - np.pi
    values = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)
    d = estimate.shape[1]
    lo, hi = chi2.ppf(0.025, d), chi2.ppf(0.975, d)
    return {
        "dof": d,
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "share_in_95_interval": float(np.mean((values >= lo) & (values <= hi))),
        "share_above_95_interval": float(np.mean(values > hi)),
        "interval_95": [float(lo), float(hi)],
        "series": values.tolist(),
    }
