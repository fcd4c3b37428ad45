"""Rest detection for zero-velocity updates (thesis 4.1: the local reference filter's
aiding while a robot stands still; the detector after Skog et al. 2010): rovers at
waypoints and a landed hexacopter stop the IMU's drift from accumulating, also while
their stereo odometry sees nothing usable. Used by :class:`slam.local_estimator.LocalEstimator`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np
from scipy.stats import chi2


class RestException(ValueError):
    """Rest-detection parameters out of range."""


@dataclass(frozen=True)
class RestParams:
    """Rest detection and zero-velocity updates (ZUPT) of :class:`LocalEstimator`.

    The IMU test (:class:`RestDetector`) is a generalised-likelihood-ratio test of Skog
    et al. (2010, "Zero-velocity detection: an algorithm evaluation", IEEE Trans. Biomed.
    Eng. 57(11)): the sum of their acceleration-moving-variance (MV) and angular-rate-
    energy (ARE) statistics over a window. Their SHOE detector compares the accelerometer
    with gravity along the mean direction instead of with the window mean; that makes it
    sensitive to the accelerometer bias along gravity, which the filter knows only to a
    few mg, while a low-noise IMU has 0.011 m/s^2 of white noise per sample (Xsens MTi-10
    at 200 Hz, sim/world/sensors.py): a 0.03 m/s^2 bias error alone would read as motion.
    The variance form is bias-free; the magnitude is checked on its own, loosely.

    A window's variance sees vibration and jerks but not a smooth acceleration (a robot
    speeding up gently). At rest the specific force in the body frame is constant, so a
    run of quiet windows is also tested for a change of it: the mean accelerometer of its
    latest windows (up to ``min_rest_s``) against the mean of its earlier ones (up to
    ``drift_reference_s``), a chi-square test (3 dof) at ``quiet_probability`` with the
    white noise of the two means. A horizontal acceleration ``a`` tilts the specific force
    by ``a``; the test finds about 0.03 m/s^2 on the ADIS16407 and 0.005 on the Xsens.
    (Against the filter's own attitude the test would chase the updates: they explain a
    slow acceleration as a tilt error.)

    An IMU cannot tell rest from motion at constant velocity (a quiet cruise, the
    simulator's vibration-free hexacopter), so a quiet window is vetoed by the robot's
    other knowledge: its controller commanding motion (:meth:`LocalEstimator.on_motion_command`:
    rotors spinning, wheels driven), wheel odometry, or visual odometry showing motion;
    and the update itself is gated by the filter's velocity (a robot the filter knows to
    move at 0.3 m/s is not declared at rest by a quiet IMU).

    - ``zero_velocity``: apply the updates (False: detect and count only, for comparisons).
    - ``window_s``: one test per window (20 samples at the simulator's 200 Hz IMU). Skog et
      al. use a few samples for a foot's 0.3 s stance; a robot rests for seconds, so a
      longer window averages the noise; motion is noticed within one window.
    - ``min_rest_s``: quiet, unvetoed windows for this long before the first update; the
      same as the resting start of the filter (``initial_rest_s`` in sim/scenario.py).
    - ``quiet_probability``: a window of a resting IMU passes with this probability (the
      statistic times the sample count is chi-square with ``6 N - 3`` dof at rest), and so
      does the specific-force change of a resting run.
    - ``drift_reference_s``: the earlier part of a run the change is measured against (the
      bias random walk stays far below the test's noise over it).
    - ``noise_scale``: multiplies the white-noise std the test assumes (margin for
      unmodelled disturbances at rest; 1: the datasheet noise of :class:`FilterParams`).
    - ``max_gravity_deviation_mps2``: bound on ``| |mean f - b_a| - g |`` (a sustained
      vertical acceleration or free fall); well above the filter's accelerometer-bias
      uncertainty along gravity (below 0.01 m/s^2 after the resting start with either IMU).
    - ``wheel_max_speed_mps``, ``wheel_max_yaw_rate_rps``: the window's mean wheel
      odometry above either vetoes (3x the simulated encoder noise of 0.01,
      ``WheelOdometryConfig`` in sim/scenario.py; a window's mean of 5 samples at 50 Hz
      has 0.0045).
    - ``vo_max_speed_mps``, ``vo_max_rate_rps``: an applied VO delta between consecutive
      frames faster than either (and significant against the deltas' own covariance)
      vetoes rest for ``vo_motion_hold_s`` after its capture (a sixth of the routes'
      default 0.3 m/s in sim/scenario.py; the hold covers two frames at 5 Hz after the
      250 ms delay of thesis 4.1.1, then the veto lapses so that a robot whose VO died
      can still rest).
    - ``velocity_std_mps``: std of each zero-velocity pseudo-measurement (a resting body
      moves by mm/s: suspension settling, motors idling; the filter's default).
    - ``angular_rate_std_rps``: std of the zero-rate part, applied to the window's mean
      gyro (observes the gyro bias, so the yaw stops drifting); 1e-4 rad/s (about
      20 deg/h) is near the rover IMU's in-run bias stability (18 deg/h, sim/world/sensors.py).
      The simulated world does not rotate; on real data the Earth's 7.3e-5 rad/s must be
      modelled or allowed for. None: velocity only.
    - ``gate_probability``: chi-square gate (3 dof) on the NIS of the update's velocity
      part, as ``FilterParams.gate_probability`` on VO deltas; None: no gate. It holds
      only while the filter is sure of its velocity: with the IMU alone its velocity
      uncertainty grows (ADIS16407: about 0.07 m/s 3 to 5 s after the last update), and
      a quiet cruise then passes it; the vetoes are what prevents that.
    """

    zero_velocity: bool = True
    window_s: float = 0.1
    min_rest_s: float = 0.5
    quiet_probability: float = 0.999
    drift_reference_s: float = 10.0
    noise_scale: float = 1.0
    max_gravity_deviation_mps2: float = 0.1
    wheel_max_speed_mps: float = 0.03
    wheel_max_yaw_rate_rps: float = 0.03
    vo_max_speed_mps: float = 0.05
    vo_max_rate_rps: float = 0.05
    vo_motion_hold_s: float = 0.5
    velocity_std_mps: float = 0.005
    angular_rate_std_rps: float | None = 1e-4
    gate_probability: float | None = 0.999

    def __post_init__(self):
        positive = ("window_s", "drift_reference_s", "noise_scale", "max_gravity_deviation_mps2", "wheel_max_speed_mps",
                    "wheel_max_yaw_rate_rps", "vo_max_speed_mps", "vo_max_rate_rps", "velocity_std_mps")
        bad = [f"{k}={getattr(self, k)!r}" for k in positive if not getattr(self, k) > 0]
        bad += [f"{k}={getattr(self, k)!r}" for k in ("min_rest_s", "vo_motion_hold_s") if not getattr(self, k) >= 0]
        if self.angular_rate_std_rps is not None and not self.angular_rate_std_rps > 0:
            bad.append(f"angular_rate_std_rps={self.angular_rate_std_rps!r}")
        for k in ("quiet_probability", "gate_probability"):
            v = getattr(self, k)
            if (v is not None or k == "quiet_probability") and not (v is not None and 0 < v < 1):
                bad.append(f"{k}={v!r} (must be in (0, 1))")
        if bad:
            raise RestException(f"RestParams out of range: {', '.join(bad)}")


@cache
def _quiet_threshold(probability: float, samples: int) -> float:
    """Threshold on the per-sample statistic of :class:`RestDetector` for ``samples``."""
    return float(chi2.ppf(probability, 6 * samples - 3)) / samples


@cache
def chi2_3(probability: float) -> float:
    return float(chi2.ppf(probability, 3))


@dataclass(frozen=True)
class RestWindow:
    """One tested window of :class:`RestDetector`: the statistic and its threshold, the
    deviation of the mean specific force from gravity, the mean raw accelerometer, and
    the mean raw gyro with the variance of that mean per axis (for the zero-rate update)."""

    t_start: float
    t_end: float
    samples: int
    statistic: float
    threshold: float
    gravity_deviation: float
    quiet: bool
    accel_mean: np.ndarray
    gyro_mean: np.ndarray
    gyro_mean_var: float


class RestDetector:
    """The IMU test of :class:`RestParams` over consecutive windows.

    ``T = 1/N sum_k (|f_k - mean f|^2 / s_a^2 + |w_k - b_w|^2 / s_w^2)`` with the
    accelerometer ``f`` and gyro ``w`` of the window's ``N`` samples, ``b_w`` the filter's
    gyro bias, and ``s_a = noise_scale * accel_noise_density * sqrt(rate)``, ``s_w``
    alike (the per-sample white noise). At rest ``N T`` is chi-square with ``6 N - 3``
    dof; the window is quiet when ``T`` is below its ``quiet_probability`` quantile over
    ``N`` and ``| |mean f - b_a| - g | <= max_gravity_deviation_mps2``. (Smooth
    accelerations are left to the estimator's test of the specific-force change over a
    resting run, :class:`RestParams`.)

    What it detects (200 Hz): vibration or motion with an accelerometer RMS per axis of
    about ``s_a`` itself (0.07 m/s^2 on the ADIS16407, 0.011 on the Xsens MTi-10) or a
    rate of about ``s_w`` (0.012 and 0.007 rad/s). A multicopter's vibration is far above
    that (ArduPilot's "Measuring Vibration" guide, ardupilot.org: a standard deviation
    of the raw accelerometer below 15 m/s^2 is normal); constant-velocity motion is not
    seen at all (see :class:`RestParams` for the vetoes)."""

    def __init__(self, params: RestParams, accel_noise_density: float, gyro_noise_density: float, gravity: float):
        self.params = params
        self.accel_noise_density = accel_noise_density
        self.gyro_noise_density = gyro_noise_density
        self.gravity = gravity
        self._t_start: float | None = None
        self._accel: list[np.ndarray] = []
        self._gyro: list[np.ndarray] = []

    def restart(self) -> None:
        """Drop the window in progress: the next sample starts a new one (after a gap in
        the usable samples)."""
        self._t_start = None
        self._accel.clear()
        self._gyro.clear()

    def add(self, t: float, accel: np.ndarray, gyro: np.ndarray, accel_bias: np.ndarray, gyro_bias: np.ndarray) -> RestWindow | None:
        """One raw IMU sample with the filter's current bias estimates; returns the tested
        window when this sample completes one (``window_s`` since the last), else None.
        The first sample only starts the first window."""
        if self._t_start is None:
            self._t_start = t
            return None
        self._accel.append(accel)
        self._gyro.append(gyro)
        duration = t - self._t_start
        if duration < self.params.window_s - 1e-9:
            return None
        n = len(self._accel)
        A_raw = np.array(self._accel, dtype=float)
        F = A_raw - accel_bias
        W_raw = np.array(self._gyro, dtype=float)
        W = W_raw - gyro_bias
        rate = n / duration
        scale2 = self.params.noise_scale**2 * rate
        var_a = scale2 * self.accel_noise_density**2
        var_w = scale2 * self.gyro_noise_density**2
        f_mean = F.mean(axis=0)
        statistic = float((np.sum((F - f_mean) ** 2) / var_a + np.sum(W * W) / var_w) / n)
        threshold = _quiet_threshold(self.params.quiet_probability, n)
        deviation = abs(float(np.linalg.norm(f_mean)) - self.gravity)
        quiet = statistic <= threshold and deviation <= self.params.max_gravity_deviation_mps2
        window = RestWindow(self._t_start, t, n, statistic, threshold, deviation, quiet, A_raw.mean(axis=0), W_raw.mean(axis=0),
                            self.gyro_noise_density**2 / duration)
        self._t_start = t
        self._accel.clear()
        self._gyro.clear()
        return window


@dataclass
class RestStats:
    """Counts of the rest detection: ``windows`` tested, ``quiet`` by the IMU test,
    ``vetoed`` quiet windows by reason (``"command"``, ``"wheels"``, ``"vo"``,
    ``"acceleration"``: the specific force changed within the run), zero-velocity updates
    ``applied`` and ``rejected`` by the gate, ``rest_s`` the time at rest
    (updates due: applied, or detected with ``zero_velocity`` off) and its ``intervals``
    ``(t_start, t_end)``."""

    windows: int = 0
    quiet: int = 0
    vetoed: dict[str, int] = field(default_factory=dict)
    applied: int = 0
    rejected: int = 0
    rest_s: float = 0.0
    intervals: list[tuple[float, float]] = field(default_factory=list)
