"""Local state estimation of one robot (thesis 4.1): the local reference filter fed by
its IMU, wheel odometry and keyframe stereo visual odometry, with frame switches.

Pure: the caller (the simulator's lanes, or a log player) hands in timestamped
measurements in the order the robot's computer would process them and reads the
estimates back. The camera-to-body transform of each capture comes from the caller
(on the LRU it changes with the pan-tilt head; thesis 7.1), so VO deltas, computed
between left-camera frames, are turned into body-frame deltas between filter clones.

Three additions make sure the estimator never fails silently:

- Rest detection and zero-velocity updates (:mod:`slam.rest`):
  a robot standing still (rovers at waypoints, a landed hexacopter) applies
  :meth:`slam.filter.LocalReferenceFilter.update_zero_velocity` (with the zero angular
  rate), so the IMU's drift does not accumulate while it rests, also when its stereo
  odometry sees nothing usable.
- Health (:mod:`slam.health`): ``ok`` while visual-odometry deltas
  are applied (or the robot rests), ``degraded`` with a reason when no delta has been
  applied for a while, ``lost`` when that lasts or the filter's own covariance says the
  estimate is no longer usable; transitions are kept in :attr:`LocalEstimator.health_history`.
- A stuck IMU (ours; the thesis's filter trusts every sample): a driver or bus that
  freezes repeats its last sample, and a saturated axis repeats its range's limit, which
  a working IMU's white noise never does on any channel. When a channel has given
  :data:`STUCK_SAMPLES` bit-identical samples in a row the estimator stops integrating
  the samples and propagates with the robot's own motion model instead
  (:meth:`slam.filter.LocalReferenceFilter.propagate_without_imu`), leaves them out of
  rest detection (a frozen IMU looks perfectly still) and calls its health ``degraded``
  (``imu stuck``, the channels in the detail) until every channel moves again. Without
  that model in :class:`slam.filter.FilterParams` every sample is integrated as before.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from slam.filter import FilterParams, LocalReferenceFilter
from slam.health import Health, HealthParams, HealthState
from slam.lie import adjoint, se3_inv, so3_log
from slam.rest import RestDetector, RestParams, RestStats, chi2_3
from slam.vo import StereoVO, VoResult, delta_in_body_frame, extrinsic_sensitivity

#: Bit-identical values of one IMU channel in a row from which it counts as stuck (the
#: first of them is the last good one; at 200 Hz the two repeats before the detection span 10 ms).
STUCK_SAMPLES = 3
_CHANNELS = ("accel x", "accel y", "accel z", "gyro x", "gyro y", "gyro z")


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
    """What became of the VO results: ``frames = ok + sum(failures)`` and ``ok = applied +
    rejected``. ``failures`` counts the VO's own failures by :class:`slam.vo.VoFailure`;
    ``rejections_by_reason`` the deltas the estimator did not apply: ``"gate"`` (the
    filter's chi-square gate on the NIS, :attr:`LocalReferenceFilter.relative_pose_gate`)
    and ``"no clone"`` (the keyframe's or the frame's clone is no longer held).
    ``last_applied_t``: capture time of the latest applied delta (None: none yet)."""

    frames: int = 0
    ok: int = 0
    applied: int = 0
    rejected: int = 0
    failures: dict[str, int] = field(default_factory=dict)
    rejections_by_reason: dict[str, int] = field(default_factory=dict)
    last_applied_t: float | None = None

    def reject(self, reason: str) -> None:
        self.rejected += 1
        self.rejections_by_reason[reason] = self.rejections_by_reason.get(reason, 0) + 1


class LocalEstimator:
    """The robot's local reference filter with its inputs (thesis 4.1, 4.1.1, 4.1.2).

    The filter starts at ``init_time``: roll and pitch and the accelerometer bias along
    gravity from the mean accelerometer, the gyro biases from the mean gyro, over the last
    ``rest_window`` seconds before it (the robot stands still), position and yaw zero, so
    the first local frame is the start pose's x, y, z and yaw. A frame switch is
    triggered by :meth:`frame_switch` (the mapping's submap partition) or, with
    ``frame_switch_distance`` set, after that distance travelled in the current frame.

    While the robot rests (``rest_params``, :class:`RestParams`) the filter gets
    zero-velocity updates; :attr:`health` (``health_params``, :class:`HealthParams`) says
    whether the estimate is aided, with its transitions in :attr:`health_history` as
    ``(t, state, reason)``; :attr:`vo_stats` and :attr:`rest_stats` count what happened.
    """

    def __init__(
        self,
        params: FilterParams,
        vo: StereoVO | None,
        init_time: float,
        rest_window: float,
        frame_switch_distance: float | None = None,
        rest_params: RestParams | None = None,
        health_params: HealthParams | None = None,
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
        self._camera_prior: dict[int, np.ndarray] = {}  # the filter's left-camera pose at capture, in the first frame
        self._keyframes: tuple[int, ...] = ()
        self._pending: set[int] = set()  # captured, VO not yet done
        self._distance = 0.0
        self._last_p: np.ndarray | None = None
        self._propagated = False  # updates need one IMU sample after the start
        self.last_frame: FramePose | None = None  # set by on_vo
        self.frame_origins: list[np.ndarray] = [np.eye(4)]  # local frame k in the first one (switches chained)
        # rest detection and zero-velocity updates
        self.rest_params = rest_params = rest_params or RestParams()
        self.rest_stats = RestStats()
        self._rest_detector = RestDetector(rest_params, params.accel_noise_density, params.gyro_noise_density, params.gravity)
        self._rest_since: float | None = None  # start of the current run of quiet, unvetoed windows
        self._run: deque[tuple[float, np.ndarray]] = deque(  # (duration, mean accelerometer) of the run's windows
            maxlen=max(2, round((rest_params.min_rest_s + rest_params.drift_reference_s) / rest_params.window_s)))
        self._at_rest = False
        self._commanded_motion: bool | None = None
        self._wheel_sum = np.zeros(3)  # wheel odometry (v_x, v_y, yaw rate) since the last window
        self._wheel_n = 0
        self._wheel_t: float | None = None  # time of the latest wheel sample
        self._capture_t: dict[int, float] = {}
        self._vo_prev: tuple[int, float, int, np.ndarray, np.ndarray] | None = None  # (frame, t, keyframe, T_kf_frame, cov) body
        self._vo_moving_t: float | None = None  # capture time of the latest VO step that showed motion
        # health
        self.health_params = health_params or HealthParams()
        self.health = Health(HealthState.OK, "", init_time)
        self.health_history: list[tuple[float, str, str]] = []
        self._last_zupt_t = -math.inf
        self._vo_trouble: tuple[str, str] | None = None  # the latest VO outcome since the last applied delta
        # stuck IMU
        self._imu_last: np.ndarray | None = None  # the latest sample's six channels
        self._imu_repeats = np.zeros(6, int)  # per channel: samples equal to the one before, in a row
        self.imu_outages: list[list[float]] = []  # [start, end] of each stuck interval the filter bridged
        self._imu_stuck_now = False

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
                self.health = Health(HealthState.OK, "", self.filter.t)
                self.health_history.append((self.filter.t, HealthState.OK.value, ""))
            return
        stuck = self._stuck(np.array(accel, float), np.array(gyro, float))
        changed = stuck != self._imu_stuck_now
        if changed:
            self._imu_stuck_now = stuck
            self._rest_detector.restart()
            if stuck:
                self.imu_outages.append([float(t), float(t)])
                self._rest_since, self._at_rest = None, False
                self._run.clear()
        if stuck:
            self.filter.propagate_without_imu(t)
            self.imu_outages[-1][1] = float(t)
        else:
            self.filter.propagate(t, accel, gyro)
        self._propagated = True
        p = self.filter.pose()[:3, 3]
        self._distance += float(np.linalg.norm(p - self._last_p))
        self._last_p = p
        if self.frame_switch_distance is not None and self._distance >= self.frame_switch_distance:
            self.frame_switch()
        window_ended = not stuck and self._rest_step(t, accel, gyro)
        if changed or window_ended:
            self._update_health(t)

    @property
    def imu_bridged(self) -> bool:
        """Whether the estimate still rests on the motion model that bridged a stuck IMU:
        while it is stuck, and after it until a VO delta captured since has been applied
        (at most ``health_params.vo_timeout_s``). Until then the current state's attitude
        and position carry the unaided turn and drift of the bridge."""
        if self._imu_stuck_now:
            return True
        if not self.imu_outages:
            return False
        end = self.imu_outages[-1][1]
        last = self.vo_stats.last_applied_t
        return (last is None or last <= end) and self.filter.t - end < self.health_params.vo_timeout_s

    def _stuck(self, accel: np.ndarray, gyro: np.ndarray) -> bool:
        """Count each channel's repeats of the sample before; stuck while any channel has
        :data:`STUCK_SAMPLES` identical values in a row (only where the filter has a motion
        model to bridge them with)."""
        x = np.concatenate([accel, gyro])
        same = x == self._imu_last if self._imu_last is not None else np.zeros(6, bool)
        self._imu_repeats = np.where(same, self._imu_repeats + 1, 0)
        self._imu_last = x
        return self.params.motion_accel_density is not None and bool(np.any(self._imu_repeats >= STUCK_SAMPLES - 1))

    def _stuck_detail(self) -> str:
        frozen = self._imu_repeats >= STUCK_SAMPLES - 1
        names = "all channels" if frozen.all() else ", ".join(n for n, f in zip(_CHANNELS, frozen, strict=True) if f)
        return f"{names} since {self.imu_outages[-1][0]:.2f} s"

    def _rest_gyro_bias_std(self) -> float:
        """Error of the resting gyro mean as a bias estimate: white noise averaged over the
        window (``density / sqrt(window)``) and the bias walk within it."""
        p, window = self.params, self.rest_window
        return math.hypot(p.gyro_noise_density / math.sqrt(window), p.gyro_bias_random_walk * math.sqrt(window))

    def on_wheel_odometry(
        self,
        t: float,
        v_body: np.ndarray,
        speed_std: float,
        yaw_rate_std: float,
        vz_std: float = 0.05,
        slip_std: float = 0.03,
        slip_correlation_s: float = 5.0,
    ) -> None:
        """Wheel odometry ``(v_x, v_y, yaw_rate)`` sampled at ``t`` as a body-velocity
        update; ``v_z = 0`` (the wheels keep the body on the ground) with ``vz_std``.

        Besides the white ``speed_std`` and ``yaw_rate_std``, the wheels err by slip and
        an unknown rolling radius (thesis 4.1.1: wheel odometry "taking into account
        possible slip", Bussmann et al. 2018): a relative error of ``slip_std`` that
        changes with the soil over ``slip_correlation_s``. A first-order Gauss-Markov
        error of std ``σ`` and correlation time ``τ`` has the low-frequency power
        ``2 σ^2 τ`` (Gelb 1974, ch. 3), so each update at interval ``Δt`` carries
        it as white noise of variance ``(slip_std |v|)^2 2 τ / Δt``; without it, 50 updates
        a second of a slipping wheel outvote the visual odometry (thesis 4.1.1: VO "often
        performs better in high-slip environments"). The first sample only sets the
        interval."""
        if not self._propagated:
            return
        vx, vy, yaw_rate = v_body
        self._wheel_sum += (vx, vy, yaw_rate)
        self._wheel_n += 1
        t_prev, self._wheel_t = self._wheel_t, t
        if t_prev is None or t <= t_prev:
            return
        k = slip_std**2 * 2.0 * slip_correlation_s / (t - t_prev)
        speed_var = speed_std**2 + k * (vx * vx + vy * vy)
        cov = np.diag([speed_var, speed_var, vz_std**2])
        self.filter.update_body_velocity(np.array([vx, vy, 0.0]), cov, yaw_rate=yaw_rate, yaw_rate_var=yaw_rate_std**2 + k * yaw_rate**2)

    def on_capture(self, frame_id: int, t: float, T_body_cam: np.ndarray) -> bool:
        """An image trigger: clone the filter state. Returns False before initialisation
        (the frame is then not used for VO)."""
        if not self._propagated or self.vo is None:
            return False
        self.filter.clone(frame_id, t)
        self._T_body_cam[frame_id] = np.asarray(T_body_cam, float)
        if not self._imu_stuck_now:  # bridged without the IMU the filter cannot predict a turn: the VO's own motion model then
            self._camera_prior[frame_id] = self.T_first_current @ self.filter.clone_pose(frame_id) @ self._T_body_cam[frame_id]
        self._capture_t[frame_id] = float(t)
        self._pending.add(frame_id)
        return True

    def process_vo(self, frame_id: int, t: float, left: np.ndarray, right: np.ndarray, depth: np.ndarray | None) -> VoResult:
        """The VO job itself (no filter access: it runs on its own core). Its tracking is
        placed by the camera pose the filter and the head's encoders gave at capture
        (``StereoVO.process``'s ``T_prior``)."""
        if self.vo is None:
            raise EstimatorException("this estimator has no visual odometry")
        return self.vo.process(frame_id, t, left, right, depth, self._camera_prior.get(frame_id))

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
                X_cur = self._T_body_cam[result.frame_id]
                T_b, cov_b = delta_in_body_frame(result.T_kf_cur, result.cov, self._T_body_cam[kf], X_cur)
                cov_b = 0.5 * (cov_b + cov_b.T)
                Ad = adjoint(X_cur)  # camera tangent -> body tangent (delta_in_body_frame)
                map_b = None
                if self.params.keyframe_map_error and result.map_cov is not None:  # the keyframe's share, onto its clone
                    map_b = Ad @ result.map_cov @ Ad.T
                    map_b = 0.5 * (map_b + map_b.T)
                    lam, V = np.linalg.eigh(cov_b - map_b)  # the pixel noise's share: positive definite, up to rounding
                    cov_b = (V * np.maximum(lam, 1e-9 * lam[-1])) @ V.T
                J = extrinsic_sensitivity(result.T_kf_cur, X_cur)
                s = None if result.disparity_sensitivity is None else Ad @ result.disparity_sensitivity
                s_f = None if result.focal_sensitivity is None else Ad @ result.focal_sensitivity
                applied = self.filter.update_relative_pose(
                    kf, result.frame_id, T_b, cov_b, extrinsic_jacobian=J, disparity_sensitivity=s, keyframe_map_cov=map_b,
                    focal_sensitivity=s_f,
                )
                if applied > self.filter.relative_pose_gate:
                    stats.reject("gate")
                    self._vo_trouble = ("vo rejected", "gate")
                else:
                    stats.applied += 1
                    stats.last_applied_t = result.t if stats.last_applied_t is None else max(stats.last_applied_t, result.t)
                    self._vo_trouble = None
                    self._note_vo_motion(result, T_b, cov_b)
            else:
                stats.reject("no clone")
                self._vo_trouble = ("vo rejected", "no clone")
        else:
            stats.failures[str(result.reason)] = stats.failures.get(str(result.reason), 0) + 1
            self._vo_trouble = ("vo lost", str(result.reason))
        if result.frame_id in self.filter.clone_ids:
            self.last_frame = FramePose(
                result.frame_id, result.t, self.filter.frame_index, self.filter.clone_pose(result.frame_id), self._T_body_cam[result.frame_id]
            )
        self._keyframes = tuple(result.keyframe_history)
        self._pending.discard(result.frame_id)
        self._release_clones()
        self._update_health(self.filter.t)
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
        self._camera_prior.pop(frame_id, None)
        self._capture_t.pop(frame_id, None)
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

    # ------------------------------------------------------------------ rest and zero velocity

    def on_motion_command(self, moving: bool | None) -> None:
        """What the robot's own controller knows: True while it commands motion (rotors
        spinning, wheels driven), False while it commands standstill, None unknown. True
        vetoes rest detection (a quiet IMU at constant velocity is not rest); False does not
        replace the IMU test (a robot can slide or be pushed)."""
        self._commanded_motion = None if moving is None else bool(moving)

    @property
    def at_rest(self) -> bool:
        """The latest window was taken as rest (a zero-velocity update was due)."""
        return self._at_rest

    def _note_vo_motion(self, result: VoResult, T_b: np.ndarray, cov_b: np.ndarray) -> None:
        """Body motion between consecutive VO frames of an applied delta ``T_b`` (keyframe
        to frame, body frames, covariance ``cov_b``): from the previous frame if it used the
        same keyframe (covariance: the sum of both, an upper bound as they share the
        keyframe), else from the keyframe's capture. A translation or rotation faster than
        ``vo_max_*`` and significant against its covariance (chi-square, 3 dof, at
        ``quiet_probability``) marks motion at the frame's capture."""
        kf, t = result.keyframe_id, result.t
        prev = self._vo_prev
        if prev is not None and prev[2] == kf and prev[0] != result.frame_id:
            T_step, cov, dt = se3_inv(prev[3]) @ T_b, prev[4] + cov_b, t - prev[1]
        else:
            T_step, cov, dt = T_b, cov_b, t - self._capture_t.get(kf, math.nan)
        self._vo_prev = (result.frame_id, t, kf, T_b, cov_b)
        if not dt > 0:
            return
        rp = self.rest_params
        gate = chi2_3(rp.quiet_probability)
        p, r = T_step[:3, 3], so3_log(T_step[:3, :3])
        moving_p = np.linalg.norm(p) > rp.vo_max_speed_mps * dt and p @ np.linalg.solve(cov[3:6, 3:6], p) > gate
        moving_r = np.linalg.norm(r) > rp.vo_max_rate_rps * dt and r @ np.linalg.solve(cov[0:3, 0:3], r) > gate
        if moving_p or moving_r:
            self._vo_moving_t = t if self._vo_moving_t is None else max(self._vo_moving_t, t)

    def _motion_veto(self, t: float) -> str | None:
        """Why a quiet window at ``t`` is not rest: ``"command"``, ``"wheels"``, ``"vo"``, or None."""
        rp = self.rest_params
        if self._commanded_motion:
            return "command"
        if self._wheel_n:
            vx, vy, yaw_rate = self._wheel_sum / self._wheel_n
            if math.hypot(vx, vy) > rp.wheel_max_speed_mps or abs(yaw_rate) > rp.wheel_max_yaw_rate_rps:
                return "wheels"
        if self._vo_moving_t is not None and t - self._vo_moving_t <= rp.vo_motion_hold_s:
            return "vo"
        return None

    def _acceleration_veto(self) -> str | None:
        """``"acceleration"`` if the mean accelerometer of the run's latest windows (up to
        ``min_rest_s``, at most half the run) differs from that of its earlier ones by more
        than their white noise allows (chi-square, 3 dof): a smooth acceleration that no
        single window shows (:class:`RestParams`)."""
        rp = self.rest_params
        run = self._run
        if len(run) < 2:
            return None
        k = min(max(1, round(rp.min_rest_s / rp.window_s)), len(run) // 2)
        d = np.array([x for x, _ in run])
        f = np.array([x for _, x in run])
        t_new, t_old = float(d[-k:].sum()), float(d[:-k].sum())
        change = d[-k:] @ f[-k:] / t_new - d[:-k] @ f[:-k] / t_old
        var = (rp.noise_scale * self.params.accel_noise_density) ** 2 * (1.0 / t_new + 1.0 / t_old)
        return "acceleration" if float(change @ change) / var > chi2_3(rp.quiet_probability) else None

    def _rest_step(self, t: float, accel: np.ndarray, gyro: np.ndarray) -> bool:
        """Feed the rest detector; at the end of a window decide rest and apply the
        zero-velocity update (with the window's mean gyro for the zero rate). Returns
        True when a window ended."""
        f = self.filter
        window = self._rest_detector.add(t, np.asarray(accel, float), np.asarray(gyro, float), f.accel_bias, f.gyro_bias)
        if window is None:
            return False
        rp, stats = self.rest_params, self.rest_stats
        stats.windows += 1
        veto = None
        if window.quiet:
            stats.quiet += 1
            self._run.append((window.t_end - window.t_start, window.accel_mean))
            veto = self._motion_veto(window.t_end) or self._acceleration_veto()
            if veto is not None:
                stats.vetoed[veto] = stats.vetoed.get(veto, 0) + 1
        self._wheel_sum[:] = 0.0
        self._wheel_n = 0
        self._at_rest = False
        if not window.quiet or veto is not None:
            self._rest_since = None
            self._run.clear()
            if veto == "acceleration":  # this window starts the next run
                self._run.append((window.t_end - window.t_start, window.accel_mean))
            return True
        if self._rest_since is None:
            self._rest_since = window.t_start
        if window.t_end - self._rest_since < rp.min_rest_s - 1e-9:
            return True
        if rp.zero_velocity:
            rate = rp.angular_rate_std_rps is not None
            nis = f.update_zero_velocity(
                rp.velocity_std_mps,
                rp.angular_rate_std_rps,
                window.gyro_mean if rate else None,
                window.gyro_mean_var if rate else None,
                rp.gate_probability,
            )
            if rp.gate_probability is not None and nis > f.zero_velocity_gate(rp.gate_probability):
                stats.rejected += 1
                return True
            stats.applied += 1
            self._last_zupt_t = window.t_end
        self._at_rest = True
        stats.rest_s += window.t_end - window.t_start
        if stats.intervals and abs(stats.intervals[-1][1] - window.t_start) < 1e-9:
            stats.intervals[-1] = (stats.intervals[-1][0], window.t_end)
        else:
            stats.intervals.append((window.t_start, window.t_end))
        return True

    # ------------------------------------------------------------------ health

    @property
    def time_since_vo(self) -> float:
        """Seconds from the capture of the latest applied VO delta (or the filter's start)
        to the filter's time."""
        last = self.vo_stats.last_applied_t
        return self.filter.t - (self.init_time if last is None else last) if self.filter is not None else 0.0

    def _vo_reason(self) -> tuple[str, str]:
        if self.vo is None:
            return "no vo", ""
        return self._vo_trouble or ("vo lost", "no results")

    def _update_health(self, t: float) -> None:
        """Re-evaluate :attr:`health` at ``t`` (after each rest window and VO result)."""
        hp, f = self.health_params, self.filter
        last_vo = self.vo_stats.last_applied_t
        aided = max(self.init_time if last_vo is None else last_vo, self._last_zupt_t)
        unaided = t - aided
        P = f.covariance()
        bound = None
        if hp.max_position_std_m is not None:
            std = math.sqrt(max(np.linalg.eigvalsh(P[0:3, 0:3])[-1], 0.0))
            if std > hp.max_position_std_m:
                bound = f"position std {std:.2f} m > {hp.max_position_std_m} m"
        if bound is None and hp.max_velocity_std_mps is not None:
            std = math.sqrt(max(np.linalg.eigvalsh(P[3:6, 3:6])[-1], 0.0))
            if std > hp.max_velocity_std_mps:
                bound = f"velocity std {std:.2f} m/s > {hp.max_velocity_std_mps} m/s"
        if unaided > hp.vo_timeout_s:
            reason, detail = self._vo_reason()
            if unaided > hp.vo_timeout_s + hp.lost_after_s:
                state = HealthState.LOST
            elif bound is not None:
                state, detail = HealthState.LOST, bound
            else:
                state = HealthState.DEGRADED
        elif bound is not None:
            state, reason, detail = HealthState.LOST, "uncertain", bound
        else:
            state, reason, detail = HealthState.OK, "", ""
        if self._imu_stuck_now and state is not HealthState.LOST:
            state, reason, detail = HealthState.DEGRADED, "imu stuck", self._stuck_detail()
        h = self.health
        if state != h.state or reason != h.reason:
            self.health = Health(state, reason, t if state != h.state else h.since, detail)
            self.health_history.append((t, state.value, reason))
        elif detail != h.detail:
            self.health = replace(h, detail=detail)

    # ------------------------------------------------------------------ reports

    def health_report(self, t_end: float | None = None) -> dict:
        """JSON-ready health summary: the current state, its transitions and the time
        spent in each state up to ``t_end`` (default: the filter's time)."""
        h = self.health
        t_end = (self.filter.t if self.filter is not None else self.init_time) if t_end is None else t_end
        time_in = {s.value: 0.0 for s in HealthState}
        hist = self.health_history
        for (t0, state, _), t1 in zip(hist, [t for t, _, _ in hist[1:]] + [t_end]):
            time_in[state] += max(t1 - t0, 0.0)
        return {
            "state": h.state.value,
            "reason": h.reason,
            "detail": h.detail,
            "since": h.since,
            "time_since_vo_s": self.time_since_vo,
            "time_s": time_in,
            "transitions": [[t, state, reason] for t, state, reason in hist],
            "imu_stuck": [list(span) for span in self.imu_outages],
        }

    def rest_report(self) -> dict:
        """JSON-ready summary of rest detection and zero-velocity updates."""
        r = self.rest_stats
        return {
            "enabled": self.rest_params.zero_velocity,
            "windows": r.windows,
            "quiet": r.quiet,
            "vetoed": dict(r.vetoed),
            "applied": r.applied,
            "rejected_by_gate": r.rejected,
            "rest_s": r.rest_s,
            "intervals": [[a, b] for a, b in r.intervals],
        }

    def vo_report(self) -> dict:
        """JSON-ready :class:`VoStats` with the time since the latest applied delta."""
        v = self.vo_stats
        return {
            "frames": v.frames,
            "ok": v.ok,
            "applied": v.applied,
            "rejected": v.rejected,
            "rejections_by_reason": dict(v.rejections_by_reason),
            "failures": dict(v.failures),
            "last_applied_t": v.last_applied_t,
            "time_since_last_applied_s": self.time_since_vo,
            "disparity_offset": None if self.vo is None or self.vo.offset is None else self.vo.offset.report(),
        }
