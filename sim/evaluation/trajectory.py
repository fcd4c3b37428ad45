"""Trajectory evaluation against ground truth, with ``evo`` as the metrics library.

Each robot is evaluated in its own start frame: the gravity-aligned frame at its
first ground-truth pose (x, y, z and yaw of the body, roll and pitch dropped), which is
how the robots' map frames are defined (thesis 4.1.2, docs/slam.md). ATE is
reported unaligned in that frame, as the thesis reports its errors, and SE(3)-aligned
(Umeyama, evo) for comparison; RPE per metre travelled; final error absolute and as a
percentage of the distance driven; yaw error over time. Trajectories travel as
:class:`Trajectory`; the error series over time, for plots, come back apart from the
metrics (:class:`ErrorOverTime`). Statistics: :mod:`sim.evaluation.statistics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from evo.core import metrics, sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit
from scipy.spatial.transform import Rotation, Slerp

from sim.evaluation.statistics import StatisticsType, statistics
from slam.lie import gravity_aligned, quat_to_rot, se3, wrap_angle, yaw_of

ERROR_STATISTICS = (StatisticsType.RMSE, StatisticsType.MEAN, StatisticsType.MEDIAN, StatisticsType.MAX)


class EvaluationError(ValueError):
    """Trajectories that cannot be compared (too short, no common time span)."""


def pose_matrix(xyz_qwxyz: np.ndarray) -> np.ndarray:
    """4x4 from ``[x, y, z, qw, qx, qy, qz]`` (the run log's ground-truth rows)."""
    return se3(quat_to_rot(xyz_qwxyz[3:7]), xyz_qwxyz[:3])


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Body poses over time in one frame: ``t`` (N,) simulated seconds, ``T`` (N, 4, 4).

    ``quat_xyzw`` (N, 4): the orientations as logged, for a trajectory made from the run
    log's quaternion rows (:meth:`from_pose_rows`), so that :func:`write_tum` writes them
    as they came instead of converting the matrices back.
    """

    t: np.ndarray
    T: np.ndarray
    quat_xyzw: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        t, T = np.asarray(self.t, dtype=float), np.asarray(self.T, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or t.shape != (len(T),):
            raise EvaluationError(f"need (N,) times and (N, 4, 4) poses, got {t.shape} and {T.shape}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "T", T)

    @classmethod
    def from_pose_rows(cls, t, rows) -> Trajectory:
        """From the run log's ground-truth rows ``[x, y, z, qw, qx, qy, qz]``."""
        rows = np.asarray(rows, dtype=float).reshape(-1, 7)
        T = np.stack([pose_matrix(p) for p in rows]) if len(rows) else np.zeros((0, 4, 4))
        return cls(t, T, rows[:, [4, 5, 6, 3]])

    @classmethod
    def from_lists(cls, t: list[float], poses: list[np.ndarray]) -> Trajectory:
        """From a log's lists of times and 4x4 poses (empty ones included)."""
        return cls(np.asarray(t, dtype=float), np.stack(poses) if poses else np.zeros((0, 4, 4)))

    def __len__(self) -> int:
        return len(self.t)

    @property
    def positions(self) -> np.ndarray:
        return self.T[:, :3, 3]

    def quaternions_xyzw(self) -> np.ndarray:
        if self.quat_xyzw is not None:
            return self.quat_xyzw
        return Rotation.from_matrix(self.T[:, :3, :3]).as_quat() if len(self) else np.zeros((0, 4))

    def since(self, t0: float) -> Trajectory:
        """The trajectory from its first sample at or after ``t0``."""
        first = int(np.searchsorted(self.t, t0 - 1e-9))
        return Trajectory(self.t[first:], self.T[first:], None if self.quat_xyzw is None else self.quat_xyzw[first:])

    def interpolated(self, times: np.ndarray, max_gap: float) -> Trajectory:
        """The poses at those of ``times`` whose nearest sample is at most ``max_gap``
        away, between the two samples around each: positions linearly, rotations by slerp
        (a pose logged between two ground-truth samples is scored against the truth at its
        own time, not at the nearest sample's)."""
        times = np.asarray(times, dtype=float)
        if len(self) < 2:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        right = np.clip(np.searchsorted(self.t, times), 1, len(self.t) - 1)
        nearest = np.minimum(np.abs(self.t[right] - times), np.abs(times - self.t[right - 1]))
        keep = (times >= self.t[0]) & (times <= self.t[-1]) & (nearest <= max_gap)
        t = times[keep]
        T = np.tile(np.eye(4), (len(t), 1, 1))
        if len(t):
            T[:, :3, :3] = Slerp(self.t, Rotation.from_matrix(self.T[:, :3, :3]))(t).as_matrix()
            T[:, :3, 3] = np.stack([np.interp(t, self.t, self.T[:, k, 3]) for k in range(3)], axis=1)
        return Trajectory(t, T)

    def at(self, t: float) -> np.ndarray:
        """The pose at the first sample at or after ``t`` (the last one after the end;
        ground truth and the logged estimates share the simulation clock)."""
        i = min(int(np.searchsorted(self.t, t - 1e-6)), len(self.t) - 1)
        return self.T[i]


@dataclass(frozen=True, eq=False)
class StartFrameTruth:
    """A robot's ground truth from its filter's start, in its start frame (the
    gravity-aligned frame of that first pose: the robot's map frame), and that frame in
    the world."""

    trajectory: Trajectory
    T_world_start: np.ndarray


@dataclass(frozen=True, eq=False)
class ErrorOverTime:
    """Per pose associated with ground truth: its time, its position error (unaligned)
    and its yaw error; for plots, not for ``metrics.json``."""

    t: np.ndarray
    position_m: np.ndarray
    yaw_deg: np.ndarray


def frame_origins_truth(start_t: float | None, switch_times: dict[int, float], truth: Trajectory) -> dict[int, np.ndarray]:
    """Local frame index -> true world pose of that frame's origin, which is a submap origin
    (thesis 5.1.2): the robot's true pose when the filter switched into it (frame 0: the
    filter's start at ``start_t``), gravity-aligned as the frames are (thesis 4.1.2)."""
    if start_t is None or len(truth) == 0:
        return {}
    out = {0: gravity_aligned(truth.at(start_t))}
    for index, t in switch_times.items():
        out[index] = gravity_aligned(truth.at(t))
    return out


def in_start_frame(poses_world: np.ndarray) -> np.ndarray:
    """Express world poses (N, 4, 4) in the gravity-aligned frame of the first one."""
    start_inv = np.linalg.inv(gravity_aligned(poses_world[0]))
    return start_inv[None] @ poses_world


def truth_since(world: Trajectory, t0: float) -> StartFrameTruth:
    """Ground truth in the world from its first sample at or after ``t0`` (a robot's
    filter start), expressed in the gravity-aligned frame of that first pose."""
    since = world.since(t0)
    return StartFrameTruth(Trajectory(since.t, in_start_frame(since.T)), gravity_aligned(since.T[0]))


def write_tum(path: Path, trajectory: Trajectory) -> None:
    """A trajectory as a TUM file: ``t x y z qx qy qz qw`` per line."""
    quats = trajectory.quaternions_xyzw()
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        for t, T, q in zip(trajectory.t, trajectory.T, quats):
            f.write(f"{t:.6f} {T[0, 3]:.6f} {T[1, 3]:.6f} {T[2, 3]:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}\n")


def path_length(trajectory: Trajectory) -> float:
    """Distance along the positions (0 for fewer than two poses)."""
    xyz = trajectory.positions
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()) if len(xyz) > 1 else 0.0


def _evo(trajectory: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=list(trajectory.T), timestamps=trajectory.t)


#: Below this distance travelled, errors per metre (RPE, % of distance) are not computed: a robot at rest still moves
#: by millimetres (settling, vibration), and 2 mm of error over 1 cm read as 16 %.
MIN_DISTANCE_M = 1.5


def trajectory_metrics(estimate: Trajectory, truth: Trajectory, max_time_diff: float = 0.011) -> tuple[dict[str, float | dict], ErrorOverTime]:
    """Compare an estimated trajectory with ground truth in the same frame: the metrics
    and the errors over time. The truth is interpolated to the estimate's times
    (:meth:`Trajectory.interpolated`, within ``max_time_diff`` of a truth sample)."""
    truth = truth.interpolated(estimate.t, max_time_diff)
    if len(truth) < 2:
        raise EvaluationError(f"only {len(truth)} estimated poses within {max_time_diff} s of the truth")
    ref, est = _evo(truth), _evo(estimate)
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
    try:  # Umeyama's alignment needs positions that span a plane; a robot on one exact line (or at rest) has none
        aligned.align(ref, correct_scale=False)
        ate_aligned = metrics.APE(metrics.PoseRelation.translation_part)
        ate_aligned.process_data((ref, aligned))
        ate_aligned_m = statistics(ate_aligned.error, ERROR_STATISTICS)
    except GeometryException as exc:
        ate_aligned_m = {"status": f"not computed: {exc}"}
    out: dict[str, float | dict] = {
        "poses": int(ref.num_poses),
        "distance_m": distance,
        "ate_m": statistics(ate.error, ERROR_STATISTICS),
        "ate_aligned_m": ate_aligned_m,
    }
    per_distance = distance >= MIN_DISTANCE_M
    if per_distance:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=1.0, delta_unit=Unit.meters, all_pairs=True)
        try:
            rpe.process_data((ref, est))
            out["rpe_per_m"] = statistics(rpe.error, ERROR_STATISTICS)
        except metrics.MetricsException as exc:
            out["rpe_per_m"] = {"status": f"not computed: {exc}"}
    else:
        out["rpe_per_m"] = {"status": f"not computed: only {distance:.2f} m travelled"}
    final = float(np.linalg.norm(ref.positions_xyz[-1] - est.positions_xyz[-1]))
    yaw_err = np.array(
        [wrap_angle(yaw_of(e[:3, :3]) - yaw_of(r[:3, :3])) for r, e in zip(ref.poses_se3, est.poses_se3)]
    )
    out["final_error_m"] = final
    out["final_error_percent_of_distance"] = 100.0 * final / distance if per_distance else None
    # the thesis's measure (8.3.2, Table 8.9): the mean error over the run against the whole distance; on a route that
    # comes back past its start, the final error alone can be a point where accumulated errors cancel (8.1.1)
    out["mean_error_percent_of_distance"] = 100.0 * float(np.mean(ate.error)) / distance if per_distance else None
    out["yaw_error_deg"] = {"final": math.degrees(yaw_err[-1]), "max_abs": math.degrees(np.abs(yaw_err).max())}
    return out, ErrorOverTime(ref.timestamps, ate.error, np.degrees(yaw_err))


def nees_report(estimate: np.ndarray, truth: np.ndarray, cov: np.ndarray, angle_dims: int = 2) -> tuple[dict, np.ndarray]:
    """NEES over time of an estimate (N, d) with covariances (N, d, d) against truth:
    the report and the NEES series (for plots).

    The first ``angle_dims`` components are angles (wrapped). Reports the mean NEES, the
    share of samples inside the two-sided 95 % chi-square interval of ``d`` degrees of
    freedom, and that interval; a consistent filter has a mean near ``d`` and about
    95 % of its samples inside (consecutive samples are correlated, so the mean is not
    held to the much tighter interval of independent samples).
    """
    from scipy.stats import chi2

    err = estimate - truth
    err[:, :angle_dims] = wrap_angle(err[:, :angle_dims])
    values = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)
    d = estimate.shape[1]
    lo, hi = chi2.ppf(0.025, d), chi2.ppf(0.975, d)
    report = {
        "dof": d,
        **statistics(values, (StatisticsType.MEAN, StatisticsType.MEDIAN)),
        "share_in_95_interval": float(np.mean((values >= lo) & (values <= hi))),
        "share_above_95_interval": float(np.mean(values > hi)),
        "interval_95": [float(lo), float(hi)],
    }
    return report, values
