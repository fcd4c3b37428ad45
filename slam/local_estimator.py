"""Local state estimation of one robot (thesis 4.1): the local reference filter fed by
its IMU, wheel odometry and keyframe stereo visual odometry, with frame switches.

Pure: the caller (the simulator's lanes, or a log player) hands in timestamped
measurements in the order the robot's computer would process them and reads the
estimates back. The camera-to-body transform of each capture comes from the caller
(on the LRU it changes with the pan-tilt head; thesis 7.1), so VO deltas, computed
between left-camera frames, are turned into body-frame deltas between filter clones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from slam.filter import FilterParams, LocalReferenceFilter
from slam.vo import StereoVO, VoResult, delta_in_body_frame


class EstimatorException(Exception):
    """Measurements the estimator cannot use (out of order, before initialisation)."""


@dataclass
class FrameSwitch:
    """A switch of the local frame (thesis 4.1.2): ``T_old_new`` and its [x, y, z, yaw] covariance."""

    t: float
    frame_index: int  # index of the new frame
    T_old_new: np.ndarray
    cov_xyz_yaw: np.ndarray


@dataclass(frozen=True)
class FramePose:
    """The filter's pose of a captured frame once its VO result was applied: the frame's
    clone in local frame ``frame_index`` (what the mapping integrates the depth along)."""

    frame_id: int
    t: float
    frame_index: int
    T_local_body: np.ndarray
    T_body_cam: np.ndarray


@dataclass
class VoStats:
    frames: int = 0
    ok: int = 0
    applied: int = 0
    rejected: int = 0
    failures: dict[str, int] = field(default_factory=dict)


class LocalEstimator:
    """The robot's local reference filter with its inputs (thesis 4.1, 4.1.1, 4.1.2).

    The filter starts at ``init_time``: roll and pitch and the accelerometer bias along
    gravity from the mean accelerometer, the gyro biases from the mean gyro, over the last
    ``rest_window`` seconds before it (the robot stands still), position and yaw zero, so
    the first local frame is the start pose's x, y, z and yaw. A frame switch is
    triggered by :meth:`frame_switch` (the mapping's submap partition) or, with
    ``frame_switch_distance`` set, after that distance travelled in the current frame.
    """

    def __init__(
        self,
        params: FilterParams,
        vo: StereoVO | None,
        init_time: float,
        rest_window: float,
        frame_switch_distance: float | None = None,
    ):
        if rest_window <= 0 or rest_window > init_time + 1e-9:
            raise EstimatorException(f"rest window {rest_window} s must be > 0 and fit before the start at {init_time} s")
        self.params = params
        self.vo = vo
        self.init_time = init_time
        self.rest_window = rest_window
        self.frame_switch_distance = frame_switch_distance
        self.filter: LocalReferenceFilter | None = None
        self.switches: list[FrameSwitch] = []
        self.vo_stats = VoStats()
        self._rest_accel: list[np.ndarray] = []
        self._rest_gyro: list[np.ndarray] = []
        self._T_body_cam: dict[int, np.ndarray] = {}
        self._keyframes: tuple[int, ...] = ()
        self._pending: set[int] = set()  # captured, VO not yet done
        self._distance = 0.0
        self._last_p: np.ndarray | None = None
        self._propagated = False  # updates need one IMU sample after the start
        self.last_frame: FramePose | None = None  # set by on_vo
        self.frame_origins: list[np.ndarray] = [np.eye(4)]  # local frame k in the first one (switches chained)

    @property
    def initialised(self) -> bool:
        return self.filter is not None

    @property
    def pending(self) -> frozenset[int]:
        """Frames captured (cloned) whose VO result has not been applied yet."""
        return frozenset(self._pending)

    # ------------------------------------------------------------------ inputs

    def on_imu(self, t: float, accel: np.ndarray, gyro: np.ndarray) -> None:
        if self.filter is None:
            if t >= self.init_time - self.rest_window - 1e-9:
                self._rest_accel.append(np.asarray(accel, float))
                self._rest_gyro.append(np.asarray(gyro, float))
            if t >= self.init_time - 1e-9:
                self.filter = LocalReferenceFilter(
                    replace(self.params, initial_gyro_bias_std=self._rest_gyro_bias_std()),
                    t,
                    accel_at_rest=np.mean(self._rest_accel, axis=0),
                    gyro_at_rest=np.mean(self._rest_gyro, axis=0),
                    rest_duration_s=self.rest_window,
                )
                self._last_p = np.zeros(3)
            return
        self.filter.propagate(t, accel, gyro)
        self._propagated = True
        p = self.filter.pose()[:3, 3]
        self._distance += float(np.linalg.norm(p - self._last_p))
        self._last_p = p
        if self.frame_switch_distance is not None and self._distance >= self.frame_switch_distance:
            self.frame_switch()

    def _rest_gyro_bias_std(self) -> float:
        """Error of the resting gyro mean as a bias estimate: white noise averaged over the
        window (``density / sqrt(window)``) and the bias walk within it."""
        p, window = self.params, self.rest_window
        return math.hypot(p.gyro_noise_density / math.sqrt(window), p.gyro_bias_random_walk * math.sqrt(window))

    def on_wheel_odometry(self, v_body: np.ndarray, speed_std: float, yaw_rate_std: float, vz_std: float = 0.05) -> None:
        """Wheel odometry ``(v_x, v_y, yaw_rate)`` as a body-velocity update; ``v_z = 0``
        (the wheels keep the body on the ground) with ``vz_std``."""
        if not self._propagated:
            return
        vx, vy, yaw_rate = v_body
        cov = np.diag([speed_std**2, speed_std**2, vz_std**2])
        self.filter.update_body_velocity(np.array([vx, vy, 0.0]), cov, yaw_rate=yaw_rate, yaw_rate_var=yaw_rate_std**2)

    def on_capture(self, frame_id: int, t: float, T_body_cam: np.ndarray) -> bool:
        """An image trigger: clone the filter state. Returns False before initialisation
        (the frame is then not used for VO)."""
        if not self._propagated or self.vo is None:
            return False
        self.filter.clone(frame_id, t)
        self._T_body_cam[frame_id] = np.asarray(T_body_cam, float)
        self._pending.add(frame_id)
        return True

    def process_vo(self, frame_id: int, t: float, left: np.ndarray, right: np.ndarray, depth: np.ndarray | None) -> VoResult:
        """The VO job itself (no filter access: it runs on its own core)."""
        if self.vo is None:
            raise EstimatorException("this estimator has no visual odometry")
        return self.vo.process(frame_id, t, left, right, depth)

    def on_vo(self, result: VoResult) -> float | None:
        """Apply a VO delta when it arrives (delay compensated by the filter's clones).
        Returns the update's Mahalanobis distance, or None if nothing was applied."""
        stats = self.vo_stats
        stats.frames += 1
        applied = None
        if result.ok:
            stats.ok += 1
            kf = result.keyframe_id
            if kf != result.frame_id and kf in self._T_body_cam and result.frame_id in self._T_body_cam:
                T_b, cov_b = delta_in_body_frame(
                    result.T_kf_cur, result.cov, self._T_body_cam[kf], self._T_body_cam[result.frame_id]
                )
                cov_b = 0.5 * (cov_b + cov_b.T)
                applied = self.filter.update_relative_pose(kf, result.frame_id, T_b, cov_b)
                if applied > self.filter.relative_pose_gate:
                    stats.rejected += 1
                else:
                    stats.applied += 1
        else:
            stats.failures[str(result.reason)] = stats.failures.get(str(result.reason), 0) + 1
        if result.frame_id in self.filter.clone_ids:
            self.last_frame = FramePose(
                result.frame_id, result.t, self.filter.frame_index, self.filter.clone_pose(result.frame_id), self._T_body_cam[result.frame_id]
            )
        self._keyframes = tuple(result.keyframe_history)
        self._pending.discard(result.frame_id)
        self._release_clones()
        return applied

    def abandon(self, frame_id: int) -> None:
        """A captured frame whose VO job was dropped: forget its clone."""
        self._pending.discard(frame_id)
        self._release_clones()

    def _release_clones(self) -> None:
        """Drop the clones of frames that are neither keyframes nor waiting for VO."""
        for frame_id in list(self._T_body_cam):
            if frame_id not in self._keyframes and frame_id not in self._pending:
                self._forget(frame_id)

    def _forget(self, frame_id: int) -> None:
        del self._T_body_cam[frame_id]
        if frame_id in self.filter.clone_ids:
            self.filter.drop_clone(frame_id)

    @property
    def T_first_current(self) -> np.ndarray:
        """The current local frame in the first one."""
        return self.frame_origins[-1]

    @property
    def distance_in_frame(self) -> float:
        """Distance travelled (filter estimate) since the current local frame started."""
        return self._distance

    def position_std(self) -> float:
        """Largest standard deviation of the position in the current local frame (thesis 5.1.3)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.filter.covariance()[:3, :3])[-1]))

    def in_frame(self, T: np.ndarray, frame_index: int) -> np.ndarray:
        """A pose given in local frame ``frame_index`` expressed in the current local frame."""
        if not 0 <= frame_index < len(self.frame_origins):
            raise EstimatorException(f"no local frame {frame_index}: frames 0..{len(self.frame_origins) - 1} exist")
        return np.linalg.solve(self.frame_origins[-1], self.frame_origins[frame_index] @ T)

    def frame_switch(self) -> FrameSwitch:
        """Switch to a new local frame at the current x, y, z and yaw (thesis 4.1.2)."""
        if self.filter is None:
            raise EstimatorException("frame switch before the filter started")
        T_old_new, cov = self.filter.frame_switch()
        self.frame_origins.append(self.frame_origins[-1] @ T_old_new)
        switch = FrameSwitch(self.filter.t, self.filter.frame_index, T_old_new, cov)
        self.switches.append(switch)
        self._distance = 0.0
        self._last_p = self.filter.pose()[:3, 3]
        return switch
