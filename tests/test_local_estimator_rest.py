"""slam.local_estimator: rest detection and zero-velocity updates (thesis 4.1 aided at
rest) on synthetic IMU data with known truth, no simulator: the detector fires at rest
and not in motion (rover-like driving, a vibrating hover), quiet constant-velocity motion
is vetoed or gated, and the updates bound the drift of a resting robot.

IMU noise: white noise and bias random walks of the presets in sim/world/sensors.py
(``IMU_PRESETS``) at 200 Hz, as sim.world.sensors.ImuModel draws them."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

from sim.world.sensors import IMU_PRESETS, ImuSpec
from slam.filter import FilterParams
from slam.health import HealthState
from slam.lie import rot_zyx, se3, se3_inv, so3_exp
from slam.local_estimator import LocalEstimator
from slam.rest import RestDetector, RestException, RestParams
from slam.vo import VoFailure, VoResult

G = 9.81
GVEC = np.array([0.0, 0.0, -G])
RATE = 200.0
DT = 1.0 / RATE
INIT_TIME = 1.0  # the estimator starts here, after resting from t = 0
ROLL0, PITCH0 = 0.03, -0.02  # a robot standing on a gentle slope
REST = RestParams()


# --------------------------------------------------------------------------- truth and IMU


@dataclass
class Truth:
    t: np.ndarray  # (N,)
    p: np.ndarray  # (N, 3) local frame
    v: np.ndarray
    R: np.ndarray  # (N, 3, 3) body -> local
    f: np.ndarray  # (N, 3) specific force, body
    w: np.ndarray  # (N, 3) angular rate, body
    moving: np.ndarray  # (N,) bool: not at rest

    def T(self, k: int) -> np.ndarray:
        return se3(self.R[k], self.p[k])


def truth_from(t, p, v, a, yaw, yaw_rate) -> Truth:
    """Constant roll and pitch, yaw ``yaw(t)``: attitude, specific force ``R^T (a - g)`` and
    body rates from the ZYX Euler rates."""
    R = np.stack([rot_zyx(ROLL0, PITCH0, y) for y in yaw])
    f = np.einsum("nji,nj->ni", R, a - GVEC)
    sr, cr, sp, cp = math.sin(ROLL0), math.cos(ROLL0), math.sin(PITCH0), math.cos(PITCH0)
    w = np.stack([-yaw_rate * sp, yaw_rate * cp * sr, yaw_rate * cp * cr], axis=1)
    moving = (np.linalg.norm(v, axis=1) > 1e-9) | (np.abs(yaw_rate) > 1e-9)
    return Truth(t, p, v, R, f, w, moving)


def _quintic(x):
    """Smoothstep ``s(x) = 10 x^3 - 15 x^4 + 6 x^5`` clipped to [0, 1], with s', s''."""
    x = np.clip(x, 0.0, 1.0)
    return 10 * x**3 - 15 * x**4 + 6 * x**5, 30 * x**2 - 60 * x**3 + 30 * x**4, 60 * x - 180 * x**2 + 120 * x**3


def rest_and_moves(duration: float, moves) -> Truth:
    """At rest except for ``moves``: ``(t0, T, dx, dy, dyaw)`` each a smooth (quintic)
    displacement over ``T`` seconds from ``t0``, zero velocity and acceleration at both ends."""
    t = np.arange(round(duration * RATE) + 1) * DT
    p, v, a = np.zeros((len(t), 3)), np.zeros((len(t), 3)), np.zeros((len(t), 3))
    yaw, yaw_rate = np.zeros(len(t)), np.zeros(len(t))
    for t0, T, dx, dy, dyaw in moves:
        s, ds, dds = _quintic((t - t0) / T)
        inside = (t > t0) & (t < t0 + T)
        d = np.array([dx, dy, 0.0])
        p += s[:, None] * d
        v += np.where(inside, ds / T, 0.0)[:, None] * d
        a += np.where(inside, dds / T**2, 0.0)[:, None] * d
        yaw += s * dyaw
        yaw_rate += np.where(inside, ds / T, 0.0) * dyaw
    return truth_from(t, p, v, a, yaw, yaw_rate)


def circling(duration: float, start: float, radius: float = 2.0, omega: float = 0.15, ramp: float = 3.0) -> Truth:
    """At rest until ``start``, then along a circle (heading tangent) at angular speed
    ``omega`` reached smoothly over ``ramp`` seconds: never quiet to a gyro."""
    t = np.arange(round(duration * RATE) + 1) * DT
    x = np.clip((t - start) / ramp, 0.0, 1.0)
    S = 2.5 * x**4 - 3 * x**5 + x**6  # integral of the smoothstep
    s, ds, _ = _quintic(x)
    after = np.maximum(t - start - ramp, 0.0)
    phi = omega * (ramp * S + after)
    dphi = omega * s
    ddphi = np.where((t > start) & (t < start + ramp), omega * ds / ramp, 0.0)
    c, sn = np.cos(phi), np.sin(phi)
    z = 0 * t
    p = radius * np.stack([sn, 1 - c, z], axis=1)
    v = radius * np.stack([dphi * c, dphi * sn, z], axis=1)
    a = radius * np.stack([ddphi * c - dphi**2 * sn, ddphi * sn + dphi**2 * c, z], axis=1)
    return truth_from(t, p, v, a, phi, dphi)


@dataclass
class Imu:
    f: np.ndarray
    w: np.ndarray
    ba: np.ndarray  # (N, 3) true biases per sample
    bw: np.ndarray


def noisy_imu(truth: Truth, spec: ImuSpec, rng: np.random.Generator, accel_vibration: float = 0.0, gyro_vibration: float = 0.0,
              vibrate=None) -> Imu:
    """``truth + bias + white noise`` as sim.world.sensors.ImuModel (turn-on biases from the
    spec, bias random walks), plus optional zero-mean vibration (std per axis) where
    ``vibrate`` (bool per sample, default everywhere): a blade-pass tone aliased by the
    200 Hz sampling and broadband noise, half the power each."""
    n = len(truth.t)
    ba = rng.normal(0, spec.accel_bias_initial_std, 3) + np.cumsum(rng.normal(0, spec.accel_random_walk * math.sqrt(DT), (n, 3)), 0)
    bw = rng.normal(0, spec.gyro_bias_initial_std, 3) + np.cumsum(rng.normal(0, spec.gyro_random_walk * math.sqrt(DT), (n, 3)), 0)
    f = truth.f + ba + rng.normal(0, spec.accel_noise_density * math.sqrt(RATE), (n, 3))
    w = truth.w + bw + rng.normal(0, spec.gyro_noise_density * math.sqrt(RATE), (n, 3))
    mask = np.ones(n, bool) if vibrate is None else np.asarray(vibrate)
    for out, std in ((f, accel_vibration), (w, gyro_vibration)):
        if std > 0:
            phase = rng.uniform(0, 2 * math.pi, 3)
            tone = math.sqrt(2) * np.sin(2 * math.pi * 83.0 * truth.t[:, None] + phase)  # e.g. 83 Hz rotor harmonic, unit RMS
            vib = std * math.sqrt(0.5) * (tone + rng.normal(0, 1, (n, 3)))
            out += vib * mask[:, None]
    return Imu(f, w, ba, bw)


def filter_params(spec: ImuSpec) -> FilterParams:
    """As sim.run.onboard.filter_params: the datasheet values the robot knows; no consider
    parameters, since this file's IMU is aligned and its VO deltas come from the truth."""
    return FilterParams(
        initial_roll_pitch_std=math.radians(0.2),
        gyro_noise_density=spec.gyro_noise_density,
        accel_noise_density=spec.accel_noise_density,
        gyro_bias_random_walk=spec.gyro_random_walk,
        accel_bias_random_walk=spec.accel_random_walk,
        initial_accel_bias_std=spec.accel_bias_initial_std,
        initial_gyro_bias_std=spec.gyro_bias_initial_std,
        gravity=G,
        accel_misalignment_std=0.0,
        extrinsic_rotation_std=0.0,
        extrinsic_translation_std=0.0,
        disparity_bias_std=0.0,
    )


def estimator(spec: ImuSpec, vo=None, **kwargs) -> LocalEstimator:
    return LocalEstimator(filter_params(spec), vo, init_time=INIT_TIME, rest_window=0.5, **kwargs)


def feed(est: LocalEstimator, truth: Truth, imu: Imu, each=None) -> None:
    """Every IMU sample in order; ``each(k, est)`` after each one."""
    for k in range(len(truth.t)):
        est.on_imu(truth.t[k], imu.f[k], imu.w[k])
        if each is not None:
            each(k, est)


def detector_windows(spec: ImuSpec, truth: Truth, imu: Imu, params: RestParams = REST):
    """The IMU test alone on raw samples, with the bias estimates the filter starts with
    (the resting gyro mean; the accelerometer's along gravity from the resting magnitude);
    each window with whether the truth moved in it."""
    det = RestDetector(params, spec.accel_noise_density, spec.gyro_noise_density, G)
    k0 = round(INIT_TIME * RATE)
    bw = imu.w[: k0 + 1].mean(axis=0)
    f_rest = imu.f[: k0 + 1].mean(axis=0)
    ba = (np.linalg.norm(f_rest) - G) * f_rest / np.linalg.norm(f_rest)  # along gravity, as the filter's start
    out = []
    for k in range(len(truth.t)):
        w = det.add(truth.t[k], imu.f[k], imu.w[k], ba, bw)
        if w is not None:
            j0, j1 = round(w.t_start * RATE) + 1, round(w.t_end * RATE) + 1
            out.append((w, bool(truth.moving[j0:j1].any())))
    return out


SPECS = sorted(IMU_PRESETS)


# --------------------------------------------------------------------------- the IMU test


def test_detector_is_quiet_at_rest_and_not_while_driving():
    """A rover (its Xsens MTi-10): rest, drive (terrain vibration of 0.05 m/s^2 and
    0.006 rad/s per axis, the lower end of what the simulated LRU shows while driving at
    0.3 m/s), rest, point turn, rest. The IMU test passes ~99.9 % of resting windows and
    no moving one. (The hexacopter's ADIS16407 has 0.07 m/s^2 of white noise per sample:
    this vibration would be below its noise.)"""
    spec = IMU_PRESETS["xsens_mti10"]
    tr = rest_and_moves(60.0, [(10.0, 15.0, 3.0, 0.5, 0.0), (35.0, 8.0, 0.0, 0.0, math.pi / 2)])
    imu = noisy_imu(tr, spec, np.random.default_rng(1), accel_vibration=0.05, gyro_vibration=0.006, vibrate=tr.moving)
    windows = detector_windows(spec, tr, imu)
    rest = [w.quiet for w, moving in windows if not moving]
    moving = [w.quiet for w, moving in windows if moving]
    assert len(rest) > 300 and len(moving) > 200
    assert np.mean(rest) > 0.99, np.mean(rest)
    assert not any(moving)
    # the statistic at rest is chi-square: mean 6 - 3/N per sample
    stats = [w.statistic for w, moving in windows if not moving]
    assert abs(np.mean(stats) - (6 - 3 / 20)) < 0.3


@pytest.mark.parametrize("preset", SPECS)
def test_vibrating_hover_is_not_rest(preset):
    """A hovering multicopter: mean specific force = gravity (level, no motion), but rotor
    vibration in the samples. Assumed: 0.3 m/s^2 and 0.5 deg/s RMS per axis after the
    IMU's own filtering, 50x below the 15 m/s^2 std that ArduPilot's "Measuring
    Vibration" guide calls normal for the raw accelerometer of a small copter: a
    conservatively quiet airframe. Not one window passes; neither does a tenth of it
    (0.03 m/s^2 on the accelerometer alone) on the low-noise rover IMU."""
    spec = IMU_PRESETS[preset]
    tr = rest_and_moves(30.0, [])
    vibrating = tr.t > INIT_TIME + 1.0
    imu = noisy_imu(tr, spec, np.random.default_rng(2), accel_vibration=0.3, gyro_vibration=math.radians(0.5), vibrate=vibrating)
    windows = detector_windows(spec, tr, imu)
    hover = [w for w in windows if w[0].t_start > INIT_TIME + 1.0]
    assert len(hover) > 250 and not any(w.quiet for w, _ in hover)
    if preset == "xsens_mti10":
        imu = noisy_imu(tr, spec, np.random.default_rng(3), accel_vibration=0.03, vibrate=vibrating)
        hover = [w for w in detector_windows(spec, tr, imu) if w[0].t_start > INIT_TIME + 1.0]
        assert not any(w.quiet for w, _ in hover)


def test_rest_params_are_checked():
    with pytest.raises(RestException, match="window_s"):
        RestParams(window_s=0.0)
    with pytest.raises(RestException, match="quiet_probability"):
        RestParams(quiet_probability=1.0)
    with pytest.raises(RestException, match="angular_rate_std_rps"):
        RestParams(angular_rate_std_rps=0.0)
    RestParams(gate_probability=None, angular_rate_std_rps=None)


# --------------------------------------------------------------------------- zero-velocity updates


@pytest.mark.parametrize("preset", SPECS)
def test_zero_velocity_bounds_the_drift_at_rest(preset):
    """A robot resting for 20 s with no visual odometry (a landed hexacopter whose downward
    stereo sees the ground too close): with zero-velocity updates its position stays
    within millimetres of the truth and its gyro bias is observed; the IMU alone drifts by
    metres (the gyro bias error of the 0.5 s resting start tilts the estimate, and the
    tilt turns gravity into acceleration). Health: ok at rest with the updates, degraded
    then lost without."""
    spec = IMU_PRESETS[preset]
    tr = rest_and_moves(INIT_TIME + 20.0, [])
    imu = noisy_imu(tr, spec, np.random.default_rng(4))
    results = {}
    for on in (True, False):
        est = estimator(spec, rest_params=RestParams(zero_velocity=on))
        feed(est, tr, imu)
        T = est.T_first_current @ est.filter.pose()
        results[on] = est, float(np.linalg.norm(T[:3, 3])), float(np.linalg.norm(est.filter.velocity()))
    est, drift_on, v_on = results[True]
    _, drift_off, v_off = results[False]
    assert drift_on < 0.01 and v_on < 0.02, (drift_on, v_on)
    assert drift_off > 0.1 and drift_off > 30 * drift_on, (drift_off, drift_on)
    assert v_off > 5 * v_on
    stats = est.rest_stats
    assert stats.applied > 190 and stats.rejected == 0 and stats.vetoed == {}
    # updates from the first window that ends min_rest_s after the start (windows of 0.1 s)
    assert stats.intervals[0][0] == pytest.approx(INIT_TIME + 0.4, abs=0.02) and stats.rest_s > 19.0
    # the zero rate observes the gyro bias (so the yaw stops drifting)
    sig_bw = np.sqrt(np.diag(est.filter.covariance()[12:15, 12:15]))
    assert np.all(np.abs(est.filter.gyro_bias - imu.bw[-1]) < 4 * sig_bw) and np.all(sig_bw < spec.gyro_noise_density / 4)
    assert est.health.state == HealthState.OK and est.at_rest
    # the IMU alone: degraded 3 s after the start, lost once its position std passes 1 m
    off = results[False][0]
    assert [(state, reason) for _, state, reason in off.health_history] == [("ok", ""), ("degraded", "no vo"), ("lost", "no vo")]
    assert off.health_history[1][0] == pytest.approx(INIT_TIME + 3.0, abs=0.11) and "position std" in off.health.detail
    assert results[False][0].rest_stats.applied == 0 and results[False][0].rest_stats.rest_s > 19.0


def test_updates_only_at_rest_and_not_while_driving():
    """Rest, drive with terrain vibration, rest, point turn, rest (rover IMU, no VO): in
    every interval with updates the true speed stays within the updates' own 5 mm/s (a
    window can hold the first milliseconds of a smooth start), and every true rest gets
    them for most of its length."""
    spec = IMU_PRESETS["xsens_mti10"]
    moves = [(5.0, 10.0, 2.0, 0.3, 0.0), (20.0, 6.0, 0.0, 0.0, -math.pi / 2)]
    tr = rest_and_moves(32.0, moves)
    imu = noisy_imu(tr, spec, np.random.default_rng(5), accel_vibration=0.05, gyro_vibration=0.006, vibrate=tr.moving)
    est = estimator(spec)
    feed(est, tr, imu)
    intervals = est.rest_stats.intervals
    speed = np.linalg.norm(tr.v, axis=1)
    for a, b in intervals:
        ka, kb = round(a * RATE), round(b * RATE)
        assert speed[ka : kb + 1].max() < RestParams().velocity_std_mps, (a, b)
        assert np.abs(tr.w[ka : kb + 1]).max() < 1e-3, (a, b)
    true_rests = [(INIT_TIME, 5.0), (15.0, 20.0), (26.0, 32.0)]
    for a, b in true_rests:
        assert any(a <= x < y <= b + 0.1 and y - x > 0.7 * (b - a) - 0.5 for x, y in intervals), (a, b, intervals)


def cruise(duration: float, t_acc: float = 4.0, ramp: float = 4.0, speed: float = 0.3) -> Truth:
    """At rest until ``t_acc``, speed up smoothly (quintic) to ``speed`` along x over
    ``ramp`` seconds, then cruise with no vibration: the simulated hexacopter's quiet IMU
    (accelerometer RMS below 1e-3 m/s^2 in 0.1 s windows while cruising, measured in the
    simulator)."""
    t = np.arange(round(duration * RATE) + 1) * DT
    x = np.clip((t - t_acc) / ramp, 0, 1)
    s, ds, _ = _quintic(x)
    S = 2.5 * x**4 - 3 * x**5 + x**6
    z = 0 * t
    p = np.stack([speed * (ramp * S + np.maximum(t - t_acc - ramp, 0)), z, z], 1)
    v = np.stack([speed * s, z, z], 1)
    a = np.stack([np.where((t > t_acc) & (t < t_acc + ramp), speed * ds / ramp, 0.0), z, z], 1)
    return truth_from(t, p, v, a, z, z)


VO_COV = np.diag([0.002**2] * 3 + [0.005**2] * 3)  # [rotation (rad), translation (m)], as tests/test_filter.py


class NoImages:
    """Stands in for slam.vo.StereoVO where the test hands in VO results itself (from
    the truth: no calibration error to allow for)."""


class VoFeed:
    """Plays slam.vo.StereoVO's part from the truth: a frame every ``every`` IMU samples
    (5 Hz), cloned by :meth:`LocalEstimator.on_capture` and answered at once with a
    :class:`VoResult`: ``mode`` ``"ok"`` (the true body delta from the active keyframe,
    noise of ``cov``; every ``kf_every``-th frame becomes the next keyframe, five kept),
    ``"fail"`` (too few inliers; the frame restarts tracking as a keyframe, as StereoVO
    does on a textured image), ``"outlier"`` (an ok delta 1 m off) or ``"none"`` (no
    frames)."""

    def __init__(self, truth: Truth, rng: np.random.Generator, every: int = 40, kf_every: int = 5, cov: np.ndarray = VO_COV):
        self.truth, self.rng, self.every, self.kf_every, self.cov = truth, rng, every, kf_every, cov
        self.k_of: dict[int, int] = {}
        self.history: list[int] = []
        self.active: int | None = None
        self.next_id = 0
        self.mode = "ok"

    def __call__(self, k: int, est: LocalEstimator) -> None:
        if k % self.every or self.mode == "none" or not est.initialised:
            return
        j, t = self.next_id, self.truth.t[k]
        self.next_id += 1
        if not est.on_capture(j, t, np.eye(4)):
            return
        self.k_of[j] = k
        empty = np.zeros((0, 2))
        if self.active is None or self.mode == "fail":
            reason = VoFailure.FIRST_FRAME if self.active is None else VoFailure.TOO_FEW_INLIERS
            self._keyframe(j)
            result = VoResult(t, j, False, reason, None, None, None, 0, empty, True, tuple(self.history))
        else:
            kf = self.active
            T = se3_inv(self.truth.T(self.k_of[kf])) @ self.truth.T(k)
            n = self.rng.multivariate_normal(np.zeros(6), self.cov)
            T = se3(T[:3, :3] @ so3_exp(n[:3]), T[:3, 3] + T[:3, :3] @ n[3:])
            if self.mode == "outlier":
                T = T @ se3(np.eye(3), [1.0, 0.0, 0.0])
            new_kf = j - kf >= self.kf_every
            if new_kf:
                self._keyframe(j)
            result = VoResult(t, j, True, None, kf, T, self.cov, 100, empty, new_kf, tuple(self.history))
        est.on_vo(result)

    def _keyframe(self, j: int) -> None:
        self.history = (self.history + [j])[-5:]
        self.active = j


def test_smooth_acceleration_ends_the_rest_and_quiet_cruise_is_gated_for_a_while():
    """Rest, a smooth (quintic) speed-up to 0.3 m/s over 2 s, cruise; no vibration, no VO,
    the ADIS16407. No window's variance shows the acceleration; the change of the specific
    force within the resting run does, within 0.6 s (the first cm/s are lost to the
    updates). Constant velocity is invisible to an IMU: in the cruise the gate rejects
    the updates while the filter, which integrated the acceleration, is sure it moves.
    Its velocity uncertainty grows with the IMU alone (about 0.07 m/s 3 to 5 s after the
    last update), and then the gate lets the updates in: this limit is why the vetoes
    of the next test exist."""
    spec = IMU_PRESETS["adis16407"]
    tr = cruise(14.0, ramp=2.0)
    imu = noisy_imu(tr, spec, np.random.default_rng(6))
    est = estimator(spec)
    v_cruise = []
    feed(est, tr, imu, lambda k, e: v_cruise.append(e.filter.velocity()[0]) if k == round(6.0 * RATE) else None)
    r = est.rest_stats
    assert r.vetoed.get("acceleration", 0) >= 1
    assert r.intervals[0][0] < 1.5 and 4.0 < r.intervals[0][1] < 4.6
    assert abs(v_cruise[0] - 0.3) < 0.05  # at the start of the cruise
    assert r.rejected > 10 and all(a > 7.0 for a, _ in r.intervals[1:])  # the gate held 2.5 s after the last update
    assert len(r.intervals) >= 2  # and then gave way (the IMU alone cannot hold it)


def test_quiet_cruise_is_vetoed_by_the_controller_wheels_or_vo():
    """The same quiet cruise for 20 s: updates at rest only, when the controller says it
    commands motion from the start of the route (rotors spinning), or the wheel odometry
    or the visual odometry shows the motion. Without gate and vetoes the updates stop
    the estimate dead in the cruise."""
    spec = IMU_PRESETS["adis16407"]
    tr = cruise(24.0, ramp=2.0)
    imu = noisy_imu(tr, spec, np.random.default_rng(6))

    def run(params: RestParams = REST, command=False, wheels=False, vo=False):
        est = estimator(spec, NoImages() if vo else None, rest_params=params)
        vo_feed = VoFeed(tr, np.random.default_rng(8)) if vo else None

        def each(k, e):
            if command:
                e.on_motion_command(tr.t[k] >= 4.0)
            if wheels and k % 4 == 0 and e.initialised:
                e.on_wheel_odometry(tr.t[k], np.array([tr.v[k, 0], 0.0, 0.0]), 0.03, 0.03)
            if vo_feed is not None:
                vo_feed(k, e)

        feed(est, tr, imu, each)
        return est

    for kwargs, reason in ((dict(command=True), "command"), (dict(wheels=True), "wheels"), (dict(vo=True), "vo")):
        est = run(**kwargs)
        r = est.rest_stats
        assert r.vetoed.get(reason, 0) > 100, (reason, r.vetoed)
        assert r.intervals and r.intervals[0][0] < 1.5 and all(b < 4.6 for _, b in r.intervals), (reason, r.intervals)
        assert r.applied > 20, reason
    assert abs(est.filter.velocity()[0] - 0.3) < 0.02  # with VO
    naive = run(RestParams(gate_probability=None))
    assert naive.rest_stats.applied > 150 and abs(naive.filter.velocity()[0] - 0.3) > 0.25


def test_zero_velocity_update_reads_the_window_mean_gyro():
    """The zero-rate part uses the window's mean raw gyro with the variance of that mean:
    after 5 s at rest the gyro bias is known to the white noise of 5 s of samples."""
    spec = IMU_PRESETS["adis16407"]
    tr = rest_and_moves(INIT_TIME + 5.0, [])
    imu = noisy_imu(tr, spec, np.random.default_rng(7))
    est = estimator(spec, rest_params=replace(RestParams(), angular_rate_std_rps=1e-6))
    feed(est, tr, imu)
    sig = np.sqrt(np.diag(est.filter.covariance()[12:15, 12:15]))
    expected = spec.gyro_noise_density / math.sqrt(5.0)  # mean over all resting samples (init window + updates)
    assert np.all(sig < 1.2 * expected) and np.all(sig > 0.5 * expected * math.sqrt(5.0 / 5.5)), (sig, expected)
    assert np.all(np.abs(est.filter.gyro_bias - imu.bw[-1]) < 4 * sig)
