"""Local reference filter (thesis 4.1): an error-state EKF for vision-aided inertial
navigation with stochastic cloning, delay compensation and frame-of-reference switching.

Pure module: numpy and scipy only. IMU samples, clone triggers, visual-odometry delta
poses and wheel velocities in; pose, velocity, biases and covariances out.

State (thesis eq. 4.1 and 4.2)
------------------------------
Direct state ``x = (p, v, q, b_a, b_w)``: position and velocity of the body (IMU) origin
in the current local frame, attitude ``R`` (body -> local, kept as a rotation matrix
instead of the quaternion ``q``), accelerometer and gyro biases. Error state, 15 entries::

    delta = [dp (0:3), dv (3:6), dtheta (6:9), db_a (9:12), db_w (12:15)]

``p_true = p + dp``, ``v_true = v + dv``, ``b_true = b + db`` and ``R_true = Exp(dtheta) R``:
``dtheta`` (eq. 4.2's ``delta sigma``) is a *left* perturbation, expressed in the local
frame, so ``dtheta_z`` is the heading error about gravity and ``dtheta_x, dtheta_y`` are
the tilt errors. Each clone (state augmentation, eq. 4.3) adds six entries
``[dtheta_c (3), dp_c (3)]`` in the same convention, in the order of :attr:`clone_ids`.

Consider parameters (Schmidt-Kalman filter)
-------------------------------------------
With ``FilterParams.accel_misalignment_std > 0`` two entries ``k = (k_x, k_y)`` follow
the core, before the clones: the accelerometer's z axis senses ``f_z + k . (f_x, f_y)``.
The IMU's calibration leaves ``k`` unknown at a fraction of a milliradian, and it matters
on slopes: the error ``g k sin(tilt)`` is what a tilt error of ``-k`` does to ``f_z``,
so the filter settles on that tilt error while its covariance, blind to ``k``, calls the
tilt known far better. Estimating ``k`` needs the camera-IMU extrinsics estimated with
it (docs/realism.md); instead ``k`` is a consider parameter (Schmidt 1966; Maybeck 1979,
sec. 6.6): its estimate stays 0 and its covariance at the prior, but its
cross-covariances with the state are propagated and updated like any other, so the
state's covariance holds what an unknown ``k`` of that size does to it. The gain's rows
for ``k`` are zero; the other rows and every other block of the update are the ordinary
Kalman update's, since no measurement here depends on ``k`` directly.

The VO camera's calibration error ``e`` (``X_true = X Exp(e)``, six entries
``[rotation, translation]`` in the camera tangent, after ``k``), the VO rig's
disparity offset (one entry, after ``e``) and its relative focal length error (one entry,
after the offset) are held the same way: a
fixed error errs every delta the same way for the same motion, which a covariance per
delta (white noise) averages out over the deltas, and the filter became sure of a tilt
and a vertical velocity the calibration had biased (docs/realism.md). A delta's
sensitivity to ``e`` enters its update as columns of ``H``; the update is again the
Kalman update of every block but the consider parameters' own (Schmidt-Kalman: with
``K_c = 0`` the Joseph form leaves ``P_cc`` and gives the optimal ``K``'s other blocks).

Conventions: local frame gravity-aligned with z up, ``g = [0, 0, -gravity]``; body x
forward, y left, z up, IMU at the body origin; accelerometer ``f = R^T (a - g) + b_a + n``,
gyro ``w = omega + b_w + n``.

Covariance orderings returned
-----------------------------
- :meth:`covariance`: 15x15 core block in the order above (``dtheta`` left, local frame).
- :meth:`full_covariance`: core, the consider parameters that are modelled (``k``, ``e``,
  the disparity offset, the focal error, in this order), then six per clone ``[dtheta_c, dp_c]``, clones
  in :attr:`clone_ids` order.
- :meth:`pose_covariance`: 6x6 ``[rotation, translation]`` of :meth:`pose`, *right*
  perturbation in the body frame, ``T_true = T Exp([omega, rho])`` to first order
  (GTSAM's ``Pose3`` convention): ``omega = R^T dtheta``, ``rho = R^T dp``.
- :meth:`roll_pitch_covariance`: 2x2 of the ZYX Euler roll and pitch.
- :meth:`observable_estimate`: ``[roll, pitch, v_body (3)]`` and its 5x5 covariance.
- :meth:`frame_switch`: 4x4 covariance of ``[x, y, z, yaw]`` of the new frame in the old
  one (additive position, ZYX Euler yaw).
- Inputs: :meth:`update_relative_pose` takes ``[rotation, translation]``, right
  perturbation (``T_meas = T_true Exp(n)``); :meth:`update_body_velocity` the
  covariance of the body-frame velocity components given.

Propagation (strapdown, thesis 4.1.1)
-------------------------------------
Each :meth:`propagate` call integrates from the previous sample to this one with rates
and specific forces interpolated linearly between the two samples: the attitude with
the mean rate over the interval, velocity and position with Simpson's rule on the
local-frame acceleration at the start, middle and end (exact for constant body rates
and specific forces linear in time). The covariance uses the continuous-time error model
``F`` (Schmid et al. 2014a) held at the interval midpoint, ``Phi = exp(F dt) = I + F dt +
F^2 dt^2 / 2 + F^3 dt^3 / 6`` (exact: ``F^4 = 0`` in the chain ``b_w -> theta -> v -> p``),
with white noise and bias random walks of the given continuous densities.

Delay compensation (thesis 4.1.1)
---------------------------------
A clone records the pose at an image trigger; a visual-odometry delta between two
clones arrives later (about 250 ms). The update is exact, not merely linearised: every
clone also stores a snapshot of the whole filter (mean and covariance) at its trigger,
and the filter keeps a log of every input since the oldest snapshot within
``FilterParams.replay_horizon_s``. A delta that arrives late is inserted in the log right
after the later of its two clones; the filter rolls back to that clone's snapshot,
applies the delta there and re-applies the logged IMU samples, clones, drops and updates
up to the present. The result is the one the filter would have had with the delta in
time (same operations in the same order). Cost: re-propagating the delay (about 50
samples at 200 Hz), which is cheap next to the image pipeline; plain stochastic cloning
differs from the in-time result by linearisation (corrections applied through
cross-covariances rather than re-integrated). Without a snapshot (older than the
horizon, or captured before the latest frame switch, whose output has already been
used and cannot be replayed) the delta is applied against the clones at the present
time: stochastic cloning, the thesis's mechanism, correct to first order.

Frame switch (thesis 4.1.2)
---------------------------
The new local frame is the current position and ZYX yaw (roll and pitch excluded, so it
stays gravity-aligned). All states are expressed in it: ``x' = Rz(yaw)^T (x - p)`` for
positions and clone positions, ``Rz(yaw)^T`` for velocity and attitudes; biases are kept.
The covariance is mapped with the Jacobian of that transform with respect to the old
errors, *including* the error of the frame itself (the true frame is at the true
position and yaw), so position and yaw uncertainty are exactly zero afterwards while
roll, pitch, velocity, biases and clones keep theirs (Schmid et al. 2014b).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy.stats import chi2

from slam.lie import adjoint, euler_zyx, euler_zyx_jacobian, euler_zyx_jacobian_inv, rot_z, rot_zyx, se3, skew, so3_exp, so3_exp_batch, so3_log
from slam.strapdown import strapdown_step

CORE = 15  # [dp, dv, dtheta, db_a, db_w]
MISALIGNMENT = 2  # consider [k_x, k_y]: the accelerometer's z-axis misalignment, when modelled
EXTRINSIC = 6  # consider [rotation, translation]: the VO camera's calibration error, when modelled
DISPARITY = 1  # consider: the VO rig's disparity offset (px), when modelled
FOCAL = 1  # consider: the VO rig's relative focal length error, when modelled
CLONE = 6  # [dtheta_c, dp_c]
_P, _V, _TH, _BA, _BW = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
_TIME_EPS = 1e-6  # s: a clone time must match the last propagated time this closely
_ORTHONORMALIZE_EVERY = 1000  # IMU samples between re-orthonormalisations of R


class FilterException(Exception):
    """Bad input to the local reference filter (shapes, times, unknown clones, parameters)."""


@cache
def _chi2_gate(probability: float, dof: int) -> float:
    return float(chi2.ppf(probability, dof))


@dataclass(frozen=True)
class FilterParams:
    """Noise model and initial uncertainty of :class:`LocalReferenceFilter` (SI units).

    The four densities are continuous-time: white noise ``*_noise_density`` (gyro
    rad/s/sqrt(Hz), accelerometer m/s^2/sqrt(Hz); one sample at rate ``r`` has std
    ``density * sqrt(r)``) and bias random walks ``*_bias_random_walk`` (rad/s/sqrt(s),
    m/s^2/sqrt(s)). ``initial_position_std`` and ``initial_yaw_std`` default to 0: the
    first local frame is the start pose. ``gate_probability`` sets the chi-square gate on
    visual-odometry deltas (6 dof); ``velocity_gate_probability`` an optional one on body
    velocities (``None``: none). ``replay_horizon_s`` is how far back delayed deltas are
    applied exactly (0 disables the replay: stochastic cloning only).
    ``gyro_scale_std`` is the gyros' residual scale and axis-misalignment error (relative,
    per axis; MEMS parts after factory calibration: 0.1 %, 0.05 deg), which the state does
    not estimate: an error ``k w`` of the rate, taken as attitude process noise of
    variance ``(k |w|)^2 2 tau dt`` per axis and step, the low-frequency power of a
    first-order Gauss-Markov error with correlation time ``tau =
    gyro_scale_correlation_s`` (Gelb 1974, ch. 3), for turns up to ``2 tau`` long.
    ``accel_misalignment_std`` (rad; 0: not modelled) is the std of each of the two
    angles by which the accelerometer's z axis leans towards x and y, ``k``: the z axis
    senses ``f_z + k . (f_x, f_y)``. A level body absorbs the other misalignments into
    the biases; this one moves with the tilt (``g k sin(roll)`` on a side slope) and
    looks to gravity like a roll or pitch error of ``-k`` (default: the 0.05 deg of a
    factory-calibrated MEMS part, as for the gyros). It is held as two consider
    parameters (Schmidt-Kalman filter, Schmidt 1966; Maybeck 1979, sec. 6.6; module
    docstring), not estimated. ``extrinsic_rotation_std`` (rad) and
    ``extrinsic_translation_std`` (m) per axis: the error ``e`` of the VO camera's
    calibrated pose on the body, ``X_true = X Exp(e)`` (camera tangent; hand-eye
    calibration, thesis 4.1: 0.2 deg, 5 mm), six more consider parameters that every
    visual-odometry delta sees through its own Jacobian (:meth:`update_relative_pose`).
    ``disparity_bias_std`` (px): a disparity offset common to all points of the VO rig (a
    residual yaw of the rectified pair; 0.25 px: 0.04 deg at the LRU's 338 px focal
    length), one more consider parameter, seen through each delta's sensitivity.
    ``focal_scale_std`` (relative; 0: not modelled, the default): the VO rig's focal
    length error, both cameras alike, one more consider parameter seen through each
    delta's sensitivity (:func:`slam.vo.focal_scale_sensitivity`): it scales the deltas'
    rotations, so that a net turn leaves a heading error the gyro has to tell apart. At
    the realistic profile's 0.2 % it made Etna's filters more consistent but not more
    accurate, and its graphs closed fewer loops (docs/realism.md, "The VO's turns").
    ``keyframe_map_error``: the VO deltas' share of error from their keyframe's 3D points
    goes onto the keyframe's clone once (:meth:`LocalReferenceFilter.update_relative_pose`,
    ``keyframe_map_cov``) instead of into every delta; False: each delta with its whole
    covariance, as thesis 4.1.1.
    ``motion_accel_density`` (m/s^2/sqrt(Hz)) and ``motion_turn_density`` (rad/s/sqrt(Hz)):
    the robot's own motion as white-noise acceleration and turn rate, the process noise of
    :meth:`LocalReferenceFilter.propagate_without_imu` while the IMU gives nothing usable
    (None: no such model).
    """

    gyro_noise_density: float
    accel_noise_density: float
    gyro_bias_random_walk: float
    accel_bias_random_walk: float
    initial_position_std: float = 0.0
    initial_yaw_std: float = 0.0
    initial_roll_pitch_std: float = math.radians(1.0)
    initial_velocity_std: float = 0.01
    initial_accel_bias_std: float = 0.05
    initial_gyro_bias_std: float = math.radians(0.5)
    gravity: float = 9.81
    max_clones: int = 24  # e.g. two stereo rigs x (5 keyframes + pending captures), with margin
    gate_probability: float = 0.999
    velocity_gate_probability: float | None = None
    replay_horizon_s: float = 2.0
    gyro_scale_std: float = 0.001
    gyro_scale_correlation_s: float = 5.0
    accel_misalignment_std: float = math.radians(0.05)
    extrinsic_rotation_std: float = math.radians(0.2)
    extrinsic_translation_std: float = 0.005
    disparity_bias_std: float = 0.25
    focal_scale_std: float = 0.0
    keyframe_map_error: bool = True
    motion_accel_density: float | None = None
    motion_turn_density: float | None = None

    def __post_init__(self):
        for name in ("gyro_noise_density", "accel_noise_density", "gyro_bias_random_walk", "accel_bias_random_walk"):
            if not getattr(self, name) > 0.0:
                raise FilterException(f"FilterParams.{name} must be > 0, got {getattr(self, name)!r}")
        for name in (
            "initial_position_std",
            "initial_yaw_std",
            "initial_roll_pitch_std",
            "initial_velocity_std",
            "initial_accel_bias_std",
            "initial_gyro_bias_std",
            "replay_horizon_s",
            "gyro_scale_std",
            "gyro_scale_correlation_s",
            "accel_misalignment_std",
            "extrinsic_rotation_std",
            "extrinsic_translation_std",
            "disparity_bias_std",
            "focal_scale_std",
        ):
            if not getattr(self, name) >= 0.0:
                raise FilterException(f"FilterParams.{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.gravity > 0.0:
            raise FilterException(f"FilterParams.gravity must be > 0 (magnitude, m/s^2), got {self.gravity!r}")
        if not (isinstance(self.max_clones, int) and self.max_clones >= 2):
            raise FilterException(f"FilterParams.max_clones must be an int >= 2, got {self.max_clones!r}")
        for name in ("gate_probability", "velocity_gate_probability"):
            p = getattr(self, name)
            if p is not None and not 0.0 < p < 1.0:
                raise FilterException(f"FilterParams.{name} must be in (0, 1) or None, got {p!r}")
        if self.gate_probability is None:
            raise FilterException("FilterParams.gate_probability must be in (0, 1), got None")
        densities = (self.motion_accel_density, self.motion_turn_density)
        if (densities[0] is None) != (densities[1] is None) or any(d is not None and not d > 0.0 for d in densities):
            raise FilterException(f"FilterParams.motion_accel_density and motion_turn_density must both be > 0 or both None, got {densities}")


def _vector(x, n: int, name: str) -> np.ndarray:
    a = np.array(x, dtype=float)
    if a.shape != (n,):
        raise FilterException(f"{name} must have shape ({n},), got {a.shape}")
    return a


def _covariance(c, n: int, name: str, semidefinite: bool = False) -> np.ndarray:
    a = np.array(c, dtype=float)
    if a.shape != (n, n):
        raise FilterException(f"{name} must have shape ({n}, {n}), got {a.shape}")
    if not np.all(np.isfinite(a)) or np.abs(a - a.T).max() > 1e-9 * np.abs(a).max():
        raise FilterException(f"{name} must be a finite symmetric matrix")
    if semidefinite:
        lam = np.linalg.eigvalsh(0.5 * (a + a.T))
        if lam[0] < -1e-9 * max(lam[-1], 0.0):
            raise FilterException(f"{name} must be positive semidefinite, eigenvalues {lam}")
        return 0.5 * (a + a.T)
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise FilterException(f"{name} must be positive definite, eigenvalues {np.linalg.eigvalsh(a)}") from None
    return 0.5 * (a + a.T)


def _resting_specific_force(accel_at_rest, gravity: float) -> np.ndarray:
    """The mean specific force ``f = -R^T g + b_a`` of a resting accelerometer, checked to be
    near ``gravity`` in magnitude."""
    f = _vector(accel_at_rest, 3, "accel_at_rest")
    if not 0.5 * gravity < np.linalg.norm(f) < 1.5 * gravity:
        raise FilterException(f"accel_at_rest {f} is not a resting specific force (|f| should be near {gravity})")
    return f


def _roll_pitch_at_rest(f: np.ndarray | None) -> tuple[float, float]:
    """ZYX roll and pitch of the body from the resting specific force ``f`` (the gravity
    direction in the body: roll and pitch are observable, thesis 4.1.2); 0, 0 without one."""
    if f is None:
        return 0.0, 0.0
    return math.atan2(f[1], f[2]), math.atan2(-f[0], math.hypot(f[1], f[2]))


def _gravity_direction_at_rest(f: np.ndarray | None, rest_duration_s: float) -> np.ndarray:
    """Unit vector along the resting specific force ``f`` (body frame), the direction in
    which ``|f| - g`` observes the accelerometer bias over ``rest_duration_s``."""
    if f is None or not rest_duration_s > 0.0:
        raise FilterException(f"rest_duration_s needs accel_at_rest and must be > 0, got {rest_duration_s!r}")
    return f / np.linalg.norm(f)


def _tilt_from_accel_bias(f: np.ndarray, M: np.ndarray) -> np.ndarray:
    """3x3 map from the accelerometer bias error to the tilt error ``dtheta`` (left
    perturbation, eq. 4.2) of the roll and pitch of :func:`_roll_pitch_at_rest`: the true
    roll and pitch are those of ``f - b_a``, so ``dtheta = -M J_f b_a`` with ``J_f`` the
    derivative of the two ``atan2`` and ``M`` the ZYX Euler-rate Jacobian."""
    fx, fy, fz = f
    h2, n2 = fy * fy + fz * fz, f @ f
    h = math.sqrt(h2)
    J_f = np.array([[0.0, fz / h2, -fy / h2], [-h / n2, fx * fy / (h * n2), fx * fz / (h * n2)]])
    return -M[:, :2] @ J_f


@dataclass(frozen=True, slots=True)
class _Snapshot:
    """The whole filter at a clone's image trigger (mean, IMU interpolation memory, clones
    and covariance), rolled back to by the delay compensation of thesis 4.1.1 (module
    docstring). Core arrays are shared with the filter (it replaces them, never modifies
    them in place); clone arrays and ``P`` are copies."""

    t: float
    p: np.ndarray
    v: np.ndarray
    R: np.ndarray
    ba: np.ndarray
    bw: np.ndarray
    f_prev: np.ndarray | None
    w_prev: np.ndarray | None
    dt_last: float
    steps: int
    clone_ids: tuple[int, ...]
    clone_t: tuple[float, ...]
    mapped: frozenset[int]  # clones that carry their keyframe's map error
    cR: np.ndarray  # (n, 3, 3) clone attitudes, in clone_ids order
    cp: np.ndarray  # (n, 3) clone positions
    P: np.ndarray  # (15 + 6 n) square covariance


class LocalReferenceFilter:
    """Error-state EKF of thesis 4.1 (eq. 4.1-4.3) on one robot; see the module docstring.

    Call order on the robot: :meth:`propagate` for every IMU sample; :meth:`clone` at an
    image trigger right after the IMU sample of that time; :meth:`update_relative_pose`
    when the visual odometry's delta between two clones arrives (delays are compensated);
    :meth:`drop_clone` when a clone is no longer referenced; :meth:`update_body_velocity`
    for wheel odometry; :meth:`update_zero_velocity` while the robot rests (detected by
    slam.local_estimator); :meth:`frame_switch` when the mapping starts a new submap.
    """

    def __init__(
        self,
        params: FilterParams,
        t0: float,
        accel_at_rest: np.ndarray | None = None,
        gyro_at_rest: np.ndarray | None = None,
        rest_duration_s: float | None = None,
    ):
        """Start at time ``t0`` at rest in the first local frame (the start pose's x, y, z
        and yaw: position 0, yaw 0). Roll and pitch come from the mean specific force of a
        resting accelerometer ``accel_at_rest`` (it measures ``-R^T g + b_a``) if given, else
        0; then the tilt error is the accelerometer bias across gravity over ``g``, and the
        prior holds that correlation on top of ``initial_roll_pitch_std`` (which then only
        describes what else tilts the estimate: vibration, a non-rigid stand). With
        ``rest_duration_s`` (the time ``accel_at_rest`` was averaged over), the bias along
        gravity is observed too: ``|f| - g`` along ``f``, with the variance of the mean
        (``accel_noise_density^2 / rest_duration_s``); otherwise it starts at 0 with
        ``initial_accel_bias_std``. ``gyro_at_rest`` (mean resting gyro) sets the initial
        gyro bias estimate if given (``initial_gyro_bias_std`` should then describe its
        error)."""
        self.params = params
        self._g = np.array([0.0, 0.0, -params.gravity])
        f = None if accel_at_rest is None else _resting_specific_force(accel_at_rest, params.gravity)
        roll, pitch = _roll_pitch_at_rest(f)
        u = None if rest_duration_s is None else _gravity_direction_at_rest(f, rest_duration_s)
        self._init_consider()
        self._init_direct_state(t0, roll, pitch, f, u, gyro_at_rest)
        self._init_clones()
        self._init_error_covariance(roll, pitch, f, u, rest_duration_s)
        self._init_process_noise()
        # delay compensation (thesis 4.1.1): the input log since the oldest clone snapshot
        # in the horizon, events [kind, t, *inputs]; a clone's event is
        # ["clone", t, clone_id, _Snapshot], also found by clone id in _clone_event
        self._log: list[list] = []
        self._clone_event: dict[int, list] = {}

    def _init_direct_state(self, t0: float, roll: float, pitch: float, f: np.ndarray | None, u: np.ndarray | None, gyro_at_rest) -> None:
        """Direct state ``x = (p, v, q, b_a, b_w)`` of eq. 4.1 at rest in the first local
        frame: position and velocity 0, attitude from ``roll`` and ``pitch`` with yaw 0,
        accelerometer bias ``(|f| - g) u`` along the gravity direction ``u`` where it is
        observed (else 0), gyro bias the resting gyro mean (else 0); then the strapdown's
        memory (previous IMU sample, last interval, step count) and the frame count."""
        self._t = float(t0)
        self._p = np.zeros(3)
        self._v = np.zeros(3)
        self._R = rot_zyx(roll, pitch, 0.0)
        self._ba = np.zeros(3) if u is None else (np.linalg.norm(f) - self.params.gravity) * u
        self._bw = np.zeros(3) if gyro_at_rest is None else _vector(gyro_at_rest, 3, "gyro_at_rest")
        self._f_prev: np.ndarray | None = None
        self._w_prev: np.ndarray | None = None
        self._dt_last = 0.0
        self._steps = 0
        self._frame_index = 0

    def _init_consider(self) -> None:
        """The consider parameters' place after the core (``_k``: misalignment, ``_e``:
        extrinsics, ``_d``: disparity offset, ``_f``: focal error; empty slices when not modelled), the first
        clone entry ``_base`` and their prior covariance ``_Pcc``, which the Schmidt updates
        keep."""
        params = self.params
        nk = MISALIGNMENT if params.accel_misalignment_std > 0.0 else 0
        ne = EXTRINSIC if max(params.extrinsic_rotation_std, params.extrinsic_translation_std) > 0.0 else 0
        nd = DISPARITY if params.disparity_bias_std > 0.0 else 0
        nf = FOCAL if params.focal_scale_std > 0.0 else 0
        self._k = slice(CORE, CORE + nk)
        self._e = slice(CORE + nk, CORE + nk + ne)
        self._d = slice(CORE + nk + ne, CORE + nk + ne + nd)
        self._f = slice(self._d.stop, self._d.stop + nf)
        self._base = self._f.stop
        std = [params.accel_misalignment_std] * nk + ([params.extrinsic_rotation_std] * 3 + [params.extrinsic_translation_std] * 3) * (ne > 0)
        std += [params.disparity_bias_std] * nd + [params.focal_scale_std] * nf
        self._Pcc = np.diag(np.square(std))

    def _init_clones(self) -> None:
        """No clones yet (state augmentation, eq. 4.3): ids and capture times; attitudes and
        positions in fixed buffers of ``max_clones`` rows, the first ``len(_clone_ids)`` in use."""
        self._clone_ids: list[int] = []
        self._mapped: set[int] = set()  # keyframe clones that carry their map's error (:meth:`update_relative_pose`)
        self._clone_t: list[float] = []
        self._cR = np.zeros((self.params.max_clones, 3, 3))
        self._cp = np.zeros((self.params.max_clones, 3))

    def _init_error_covariance(self, roll: float, pitch: float, f: np.ndarray | None, u: np.ndarray | None, rest_duration_s: float | None) -> None:
        """Prior covariance of the error state ``delta`` of eq. 4.2, in a buffer sized for
        ``max_clones`` clones: the ``initial_*_std`` of :class:`FilterParams` (roll, pitch and
        yaw mapped to ``dtheta`` through the ZYX Euler-rate Jacobian ``M``); along the
        gravity direction ``u`` (``rest_duration_s`` given) the accelerometer bias has the
        variance of the resting mean instead; with a resting specific force ``f`` the tilt
        error is the bias across gravity (:func:`_tilt_from_accel_bias`), fully correlated
        with the bias error (their sum is what gravity observes)."""
        params = self.params
        dim = self._base + CLONE * params.max_clones
        self._Pbuf = np.zeros((dim, dim))
        P0 = self._Pbuf[:CORE, :CORE]
        P0[_P, _P] = np.eye(3) * params.initial_position_std**2
        P0[_V, _V] = np.eye(3) * params.initial_velocity_std**2
        M = euler_zyx_jacobian(roll, pitch, 0.0)
        rp2, y2 = params.initial_roll_pitch_std**2, params.initial_yaw_std**2
        P0[_TH, _TH] = M @ np.diag([rp2, rp2, y2]) @ M.T
        P0[_BA, _BA] = np.eye(3) * params.initial_accel_bias_std**2
        if u is not None:
            along = params.accel_noise_density**2 / rest_duration_s + params.accel_bias_random_walk**2 * rest_duration_s
            P0[_BA, _BA] += (along - params.initial_accel_bias_std**2) * np.outer(u, u)
        P0[_BW, _BW] = np.eye(3) * params.initial_gyro_bias_std**2
        self._Pbuf[CORE : self._base, CORE : self._base] = self._Pcc
        if f is not None:
            T = _tilt_from_accel_bias(f, M)
            Pb = P0[_BA, _BA]
            P0[_TH, _TH] += T @ Pb @ T.T
            P0[_TH, _BA] = T @ Pb
            P0[_BA, _TH] = (T @ Pb).T

    def _init_process_noise(self) -> None:
        """Constant parts of the covariance prediction (thesis 4.1.1: the continuous-time
        error model of Schmid et al. 2014a, module docstring): the discrete process noise
        ``Qd = dt Q1 + dt^2 Q2 + dt^3 Q3`` (isotropic densities, so independent of the
        attitude), and the transition matrix ``Phi`` (a buffer the step per sample writes its blocks into) and its column scales."""
        params = self.params
        self._Q1, self._Q2, self._Q3 = self._noise_terms(params.accel_noise_density, params.gyro_noise_density)
        self._Q_motion = None  # the same for propagate_without_imu, with the robot's motion densities
        if params.motion_accel_density is not None:
            self._Q_motion = self._noise_terms(params.motion_accel_density, params.motion_turn_density)
        self._Phi = np.eye(self._base)
        self._phi_p_scale = np.repeat([-0.5, -0.5, 1.0 / 6.0], 3)  # times dt: Phi = I + F dt + F^2 dt^2/2 + F^3 dt^3/6
        self._phi_v_scale = np.repeat([-1.0, -1.0, 0.5], 3)
        self._q_key = math.nan
        self._Qd = np.zeros((CORE, CORE))

    def _noise_terms(self, accel_density: float, turn_density: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Q1, Q2, Q3`` of ``Qd = dt Q1 + dt^2 Q2 + dt^3 Q3`` for white acceleration and turn-rate
        noise of these densities (velocity and position integrate the acceleration's), the biases'
        random walks on top."""
        params = self.params
        sa2, sg2 = accel_density**2, turn_density**2
        I3 = np.eye(3)
        Q1 = np.zeros((CORE, CORE))
        Q1[_V, _V] = sa2 * I3
        Q1[_TH, _TH] = sg2 * I3
        Q1[_BA, _BA] = params.accel_bias_random_walk**2 * I3
        Q1[_BW, _BW] = params.gyro_bias_random_walk**2 * I3
        Q2 = np.zeros((CORE, CORE))
        Q2[_P, _V] = Q2[_V, _P] = 0.5 * sa2 * I3
        Q3 = np.zeros((CORE, CORE))
        Q3[_P, _P] = sa2 / 3.0 * I3
        return Q1, Q2, Q3

    # ------------------------------------------------------------------ read-outs

    @property
    def t(self) -> float:
        """Time of the latest propagated IMU sample (or ``t0``)."""
        return self._t

    @property
    def frame_index(self) -> int:
        """Number of frame switches so far (0: the start frame)."""
        return self._frame_index

    @property
    def accel_bias(self) -> np.ndarray:
        return self._ba.copy()

    @property
    def gyro_bias(self) -> np.ndarray:
        return self._bw.copy()

    @property
    def clone_ids(self) -> list[int]:
        """Held clones, in the order of their blocks in :meth:`full_covariance`."""
        return list(self._clone_ids)

    def pose(self) -> np.ndarray:
        """4x4 ``T_local_body``."""
        return se3(self._R, self._p)

    def velocity(self) -> np.ndarray:
        """Velocity of the body origin in the local frame."""
        return self._v.copy()

    def roll_pitch(self) -> np.ndarray:
        """ZYX Euler ``[roll, pitch]`` of the body in the (gravity-aligned) local frame."""
        roll, pitch, _ = euler_zyx(self._R)
        return np.array([roll, pitch])

    def covariance(self) -> np.ndarray:
        """15x15 core covariance ``[dp, dv, dtheta, db_a, db_w]`` (``dtheta`` left, local frame)."""
        return self._Pbuf[:CORE, :CORE].copy()

    def full_covariance(self) -> np.ndarray:
        """Core, consider and clone covariance, ``15 + c + 6 n`` square (``c``: the consider
        parameters modelled, up to 9; clones ``[dtheta_c, dp_c]`` in :attr:`clone_ids` order)."""
        d = self._dim
        return self._Pbuf[:d, :d].copy()

    def pose_covariance(self) -> np.ndarray:
        """6x6 covariance of :meth:`pose`, ``[rotation, translation]``, right perturbation (body frame)."""
        J = np.zeros((6, CORE))
        J[0:3, _TH] = self._R.T
        J[3:6, _P] = self._R.T
        return J @ self._Pbuf[:CORE, :CORE] @ J.T

    def roll_pitch_covariance(self) -> np.ndarray:
        """2x2 covariance of :meth:`roll_pitch` (ZYX Euler)."""
        Mi = euler_zyx_jacobian_inv(*euler_zyx(self._R))[:2]
        return Mi @ self._Pbuf[_TH, _TH] @ Mi.T

    def observable_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """The modes a VINS observes (thesis 4.1.2): ``[roll, pitch, v_body_x, v_body_y,
        v_body_z]`` with ``v_body = R^T v``, and their 5x5 covariance (for NEES)."""
        roll, pitch, yaw = euler_zyx(self._R)
        J = np.zeros((5, CORE))
        J[0:2, _TH] = euler_zyx_jacobian_inv(roll, pitch, yaw)[:2]
        J[2:5, _V] = self._R.T
        J[2:5, _TH] = self._R.T @ skew(self._v)
        x = np.concatenate([[roll, pitch], self._R.T @ self._v])
        return x, J @ self._Pbuf[:CORE, :CORE] @ J.T

    def clone_pose(self, clone_id: int) -> np.ndarray:
        """4x4 ``T_local_body`` of a held clone, in the current local frame."""
        k = self._clone_index(clone_id)
        return se3(self._cR[k], self._cp[k])

    def predict_relative_pose(self, kf_clone_id: int, cur_clone_id: int) -> tuple[np.ndarray, np.ndarray]:
        """The filter's ``T_kf_cur`` between two clones and its 6x6 covariance
        ``[rotation, translation]`` (right perturbation): a motion prior for the VO."""
        T, _, idx, H = self._relative_pose_model(kf_clone_id, cur_clone_id)
        P = self._Pbuf[np.ix_(idx, idx)]
        return T, H @ P @ H.T

    @property
    def _dim(self) -> int:
        return self._base + CLONE * len(self._clone_ids)

    def _clone_index(self, clone_id: int) -> int:
        try:
            return self._clone_ids.index(clone_id)
        except ValueError:
            raise FilterException(f"no clone {clone_id!r} is held (held: {self._clone_ids})") from None

    # ------------------------------------------------------------------ propagation

    def propagate(self, t: float, accel: np.ndarray, gyro: np.ndarray) -> None:
        """Strapdown integration (eq. 4.1) and error covariance propagation (eq. 4.2) to
        the IMU sample ``(accel, gyro)`` taken at ``t``. A sample at the current time (such
        as the first one at ``t0``) only becomes the start of the next interval; before
        the first sample, the first interval holds the sample's value constant."""
        f = np.array(accel, dtype=float)
        w = np.array(gyro, dtype=float)
        if f.shape != (3,) or w.shape != (3,):
            raise FilterException(f"accel and gyro must have shape (3,), got {f.shape} and {w.shape}")
        t = float(t)
        if t < self._t:
            raise FilterException(f"IMU sample at t={t} is older than the filter time {self._t}")
        self._propagate(t, f, w)
        self._log_imu(t, f, w)

    def _log_imu(self, t: float, f: np.ndarray | None, w: np.ndarray | None) -> None:
        """Keep an IMU step for the replays (``None``: one without the IMU)."""
        if self._log:
            self._log.append(["imu", t, f, w])
            if self._log[0][1] < self._t - self.params.replay_horizon_s:
                self._trim()

    def _propagate(self, t: float, f1: np.ndarray, w1: np.ndarray) -> None:
        if self._f_prev is None:
            self._f_prev, self._w_prev = f1, w1
        dt = t - self._t
        if dt <= 0.0:
            self._f_prev, self._w_prev = f1, w1
            return
        f0, w0 = self._f_prev, self._w_prev
        gyro_scale_q = 2.0 * self.params.gyro_scale_std**2 * self.params.gyro_scale_correlation_s
        R1, self._p, self._v = strapdown_step(
            self._R, self._p, self._v, f0, f1, w0, w1, self._ba, self._bw, self._g, dt, self._Phi,
            self._phi_p_scale, self._phi_v_scale, self._k.start, self._k.stop - self._k.start,
            self._Pbuf, self._base, self._dim, self._process_noise(dt), gyro_scale_q)
        self._steps += 1
        if self._steps % _ORTHONORMALIZE_EVERY == 0:
            U, _, Vt = np.linalg.svd(R1)
            R1 = U @ Vt
        self._R = R1
        self._t = t
        self._f_prev, self._w_prev, self._dt_last = f1, w1, dt

    def propagate_without_imu(self, t: float) -> None:
        """Advance to ``t`` without IMU samples (the IMU's output is unusable, e.g. stuck):
        constant velocity and attitude, with the robot's own motion as white-noise
        acceleration and turn rate (``FilterParams.motion_accel_density``,
        ``motion_turn_density``) for process noise; the biases walk as usual. Unlike a
        strapdown step no bias, tilt or consider parameter enters the motion, so the
        visual-odometry deltas that follow calibrate none of them. The next IMU sample
        starts the next interval afresh."""
        if self._Q_motion is None:
            raise FilterException("propagate_without_imu needs FilterParams.motion_accel_density and motion_turn_density")
        t = float(t)
        if t < self._t:
            raise FilterException(f"propagation to t={t} is older than the filter time {self._t}")
        self._propagate_without_imu(t)
        self._log_imu(t, None, None)

    def _propagate_without_imu(self, t: float) -> None:
        dt = t - self._t
        self._f_prev = self._w_prev = None
        if dt <= 0.0:
            return
        self._p = self._p + dt * self._v
        d = self._dim
        P = self._Pbuf
        P[_P, :d] += dt * P[_V, :d]  # Phi = I with dp += dt dv, applied to rows, then to columns
        P[:d, _P] += dt * P[:d, _V]
        Q1, Q2, Q3 = self._Q_motion
        P[:CORE, :CORE] += dt * (Q1 + dt * (Q2 + dt * Q3))  # the consider parameters and clones stand still
        self._t = t
        self._dt_last = dt

    def _process_noise(self, dt: float) -> np.ndarray:
        """``Qd = dt Q1 + dt^2 Q2 + dt^3 Q3``, cached for the IMU interval rounded to 1 ns (a
        pure function of the rounded interval, so a replay reproduces it bit for bit)."""
        key = round(dt, 9)
        if key != self._q_key:
            self._q_key = key
            self._Qd = key * (self._Q1 + key * (self._Q2 + key * self._Q3))
        return self._Qd

    # ------------------------------------------------------------------ clones

    def clone(self, clone_id: int, t: float) -> None:
        """Stochastic clone (state augmentation, eq. 4.3) of the current pose at an image
        trigger; ``t`` must be the time of the last propagated IMU sample."""
        if abs(float(t) - self._t) > _TIME_EPS:
            raise FilterException(f"clone {clone_id!r} at t={t} but the filter is at t={self._t}: propagate to the trigger time first")
        if clone_id in self._clone_ids:
            raise FilterException(f"clone {clone_id!r} is already held")
        if len(self._clone_ids) >= self.params.max_clones:
            raise FilterException(f"max_clones={self.params.max_clones} reached (held: {self._clone_ids}); drop clones no longer referenced")
        self._clone(clone_id)
        if self.params.replay_horizon_s > 0.0:
            event = ["clone", self._t, clone_id, self._snapshot()]
            self._log.append(event)
            self._clone_event[clone_id] = event
            self._trim()

    def _clone(self, clone_id: int) -> None:
        d = self._dim
        P = self._Pbuf
        sel = [6, 7, 8, 0, 1, 2]  # [dtheta, dp] of the core
        rows = P[sel, :d]
        P[d : d + CLONE, :d] = rows
        P[:d, d : d + CLONE] = rows.T
        P[d : d + CLONE, d : d + CLONE] = rows[:, sel]
        n = len(self._clone_ids)
        self._cR[n] = self._R
        self._cp[n] = self._p
        self._clone_ids.append(clone_id)
        self._clone_t.append(self._t)

    def drop_clone(self, clone_id: int) -> None:
        """Marginalise a clone out of the state (it is no longer referenced by the VO)."""
        self._clone_index(clone_id)
        self._drop(clone_id)
        if self._log:
            self._log.append(["drop", self._t, clone_id])

    def _drop(self, clone_id: int) -> None:
        k = self._clone_ids.index(clone_id)
        d = self._dim
        o = self._base + CLONE * k
        keep = np.r_[0:o, o + CLONE : d]
        P = self._Pbuf
        P[: d - CLONE, : d - CLONE] = P[np.ix_(keep, keep)]
        n = len(self._clone_ids)
        self._cR[k : n - 1] = self._cR[k + 1 : n].copy()
        self._cp[k : n - 1] = self._cp[k + 1 : n].copy()
        del self._clone_ids[k], self._clone_t[k]
        self._mapped.discard(clone_id)

    # ------------------------------------------------------------------ updates

    def update_relative_pose(
        self,
        kf_clone_id: int,
        cur_clone_id: int,
        T_kf_cur: np.ndarray,
        cov: np.ndarray,
        extrinsic_jacobian: np.ndarray | None = None,
        disparity_sensitivity: np.ndarray | None = None,
        keyframe_map_cov: np.ndarray | None = None,
        focal_sensitivity: np.ndarray | None = None,
    ) -> float:
        """Visual-odometry delta pose ``T_kf_cur`` (body frames of the two clones) with
        6x6 covariance ``[rotation, translation]``, right perturbation. Applied as if it
        had arrived right after the later of the two clones (delay compensation, module
        docstring). Returns the squared Mahalanobis distance (NIS) of the innovation; the
        update is rejected (state unchanged) when it exceeds the chi-square gate
        ``chi2.ppf(params.gate_probability, 6)`` (:attr:`relative_pose_gate`).

        ``extrinsic_jacobian`` (6x6): how the delta errs with the camera's calibration
        error ``e`` (``T_meas = T_true Exp(J e)``, :func:`slam.vo.extrinsic_sensitivity`);
        where the filter holds ``e`` as consider parameters, the update accounts for it
        through them (the same ``e`` in every delta), else it is ignored.
        ``disparity_sensitivity`` (6,): the same for the rig's disparity offset, in the
        body delta's tangent (per pixel); ``focal_sensitivity`` (6,) for its relative focal
        length error.

        ``keyframe_map_cov`` (6x6, the delta's tangent): the error the keyframe's 3D points
        put into every delta against it (:func:`slam.vo.map_covariance`), left out of
        ``cov``. The first such delta moves it onto the keyframe's clone, once: the clone
        then stands for the frame of the keyframe's map, ``T_kf Exp(eps)`` with
        ``eps = -Ad_T n`` for a delta error ``n`` (``(T_kf Exp(eps))^-1 T_cur = T Exp(-Ad_{T^-1}
        eps)``), independent of the rest of the state; in the clone's error state (``dtheta``
        left, ``dp`` additive, local frame) that is ``blockdiag(R_kf, R_kf)``. Every later delta
        against the keyframe then sees the same map error instead of a new one (it stays on the
        clone even when the gate rejects that first delta: the error is the keyframe's) (thesis 4.1.1
        fuses each delta as independent; consecutive deltas against one keyframe err alike,
        docs/slam.md)."""
        T = np.array(T_kf_cur, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise FilterException(f"T_kf_cur must be a finite 4x4 transform, got shape {T.shape}")
        if np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() > 1e-6 or np.any(T[3] != (0.0, 0.0, 0.0, 1.0)):
            raise FilterException("T_kf_cur must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        C = _covariance(cov, 6, "cov")
        M = None if keyframe_map_cov is None else _covariance(keyframe_map_cov, 6, "keyframe_map_cov", semidefinite=True)
        J = self._consider_jacobian(extrinsic_jacobian, disparity_sensitivity, focal_sensitivity)
        if kf_clone_id == cur_clone_id:
            raise FilterException(f"a relative pose needs two different clones, got {kf_clone_id!r} twice")
        ks = [self._clone_index(kf_clone_id), self._clone_index(cur_clone_id)]
        anchor_id = cur_clone_id if self._clone_t[ks[1]] >= self._clone_t[ks[0]] else kf_clone_id
        anchor_t = max(self._clone_t[ks[0]], self._clone_t[ks[1]])
        event = ["relpose", anchor_t, kf_clone_id, cur_clone_id, T, C, J, M]
        anchor = self._clone_event.get(anchor_id)
        replayable = anchor is not None and anchor[1] == anchor_t and {kf_clone_id, cur_clone_id} <= set(anchor[3].clone_ids)
        if anchor_t == self._t or not replayable:
            nis = self._relpose(kf_clone_id, cur_clone_id, T, C, J, M)  # in time, or stochastic cloning only
            if self._log:
                self._log.append(event)
            return nis
        i = self._event_index(anchor)
        j = i + 1
        while j < len(self._log) and self._log[j][0] == "relpose" and self._log[j][1] == anchor_t:
            j += 1
        self._log.insert(j, event)
        return self._replay_from(i, event)

    def _consider_jacobian(self, extrinsic_jacobian, disparity_sensitivity, focal_sensitivity) -> tuple[np.ndarray, np.ndarray] | None:
        """The consider parameters a relative pose sees and its Jacobian over them (None: none)."""
        idx, cols = [], []
        for given, block, shape, name in (
            (extrinsic_jacobian, self._e, (6, EXTRINSIC), "extrinsic_jacobian"),
            (disparity_sensitivity, self._d, (6,), "disparity_sensitivity"),
            (focal_sensitivity, self._f, (6,), "focal_sensitivity"),
        ):
            if given is None or block.stop == block.start:
                continue
            A = np.array(given, dtype=float)
            if A.shape != shape or not np.all(np.isfinite(A)):
                raise FilterException(f"{name} must be finite with shape {shape}, got {A.shape}")
            idx.append(np.arange(block.start, block.stop))
            cols.append(A.reshape(6, -1))
        return (np.concatenate(idx), np.hstack(cols)) if idx else None

    @property
    def relative_pose_gate(self) -> float:
        """Chi-square threshold on the NIS of :meth:`update_relative_pose`."""
        return _chi2_gate(self.params.gate_probability, 6)

    def _relative_pose_model(self, kf_id: int, cur_id: int):
        """Predicted ``T_kf_cur``, its rotation and translation, the state indices it
        depends on and the 6x12 Jacobian over them (right-perturbation residual)."""
        k, c = self._clone_index(kf_id), self._clone_index(cur_id)
        Rk, pk, Rc, pc = self._cR[k], self._cp[k], self._cR[c], self._cp[c]
        R_pred = Rk.T @ Rc
        p_pred = Rk.T @ (pc - pk)
        ok, oc = self._base + CLONE * k, self._base + CLONE * c
        idx = np.r_[ok : ok + CLONE, oc : oc + CLONE]
        RcT = Rc.T
        H = np.zeros((6, 12))
        # rotation residual Log(R_pred^T R_meas) ~ Rc^T (dtheta_c - dtheta_k)
        H[0:3, 0:3] = -RcT
        H[0:3, 6:9] = RcT
        # translation residual R_pred^T (p_meas - p_pred) ~ Rc^T (dp_c - dp_k + [p_c - p_k]x dtheta_k)
        H[3:6, 0:3] = RcT @ skew(pc - pk)
        H[3:6, 3:6] = -RcT
        H[3:6, 9:12] = RcT
        return se3(R_pred, p_pred), (R_pred, p_pred), idx, H

    def _relpose(
        self, kf_id: int, cur_id: int, T: np.ndarray, C: np.ndarray, J: tuple[np.ndarray, np.ndarray] | None, M: np.ndarray | None
    ) -> float:
        if M is not None and kf_id not in self._mapped:  # the keyframe's map error, onto its clone (update_relative_pose)
            k = self._clone_index(kf_id)
            o = self._base + CLONE * k
            A = adjoint(T)
            G = np.zeros((6, 6))
            G[0:3, 0:3] = G[3:6, 3:6] = self._cR[k]
            GA = G @ A
            self._Pbuf[o : o + CLONE, o : o + CLONE] += GA @ M @ GA.T
            self._mapped.add(kf_id)
        _, (R_pred, p_pred), idx, H = self._relative_pose_model(kf_id, cur_id)
        r = np.concatenate([so3_log(R_pred.T @ T[:3, :3]), R_pred.T @ (T[:3, 3] - p_pred)])
        if J is not None:  # the consider parameters it sees (Schmidt, module docstring)
            idx, H = np.r_[idx, J[0]], np.hstack([H, J[1]])
        return self._update(idx, H, r, C, self.relative_pose_gate)

    def update_body_velocity(self, v_body: np.ndarray, cov: np.ndarray, yaw_rate: float | None = None, yaw_rate_var: float | None = None) -> float:
        """Wheel odometry at the current time: body-frame velocity ``v_body = R^T v``, either
        ``(v_x, v_y)`` with a 2x2 ``cov`` or ``(v_x, v_y, v_z)`` with 3x3 (pass ``v_z = 0`` with a
        small variance for the no-lift constraint of a rover). Optionally the body yaw rate
        (rate about body z) with its variance, which observes the z gyro bias through the
        latest gyro sample (left out without one: before the first sample, or after
        :meth:`propagate_without_imu`). Returns the NIS; gated only if ``params.velocity_gate_probability``
        is set (then a rejected update leaves the state unchanged)."""
        v_body = np.array(v_body, dtype=float)
        m = v_body.shape[0] if v_body.ndim == 1 else 0
        if m not in (2, 3):
            raise FilterException(f"v_body must have shape (2,) or (3,), got {v_body.shape}")
        C = _covariance(cov, m, "cov")
        if (yaw_rate is None) != (yaw_rate_var is None):
            raise FilterException("yaw_rate and yaw_rate_var go together")
        if yaw_rate is not None:
            if not yaw_rate_var > 0.0:
                raise FilterException(f"yaw_rate_var must be > 0, got {yaw_rate_var!r}")
        args = (v_body, C, None if yaw_rate is None else float(yaw_rate), None if yaw_rate_var is None else float(yaw_rate_var))
        nis = self._velocity(*args)
        if self._log:
            self._log.append(["vel", self._t, *args])
        return nis

    def _velocity(self, v_body, C, yaw_rate, yaw_rate_var) -> float:
        m = v_body.shape[0]
        RT = self._R.T
        if self._w_prev is None:  # no gyro sample to compare the rate with (propagate_without_imu)
            yaw_rate = None
        n = m + (yaw_rate is not None)
        idx = np.r_[3:9, 12:15]  # dv, dtheta, db_w
        H = np.zeros((n, 9))
        H[:m, 0:3] = RT[:m]
        H[:m, 3:6] = (RT @ skew(self._v))[:m]
        r = np.zeros(n)
        r[:m] = v_body - (RT @ self._v)[:m]
        Rm = np.zeros((n, n))
        Rm[:m, :m] = C
        if yaw_rate is not None:
            # omega_z = w_z - b_wz - n_w: the latest gyro sample's noise adds to the variance
            H[m, 8] = -1.0
            r[m] = yaw_rate - (self._w_prev[2] - self._bw[2])
            Rm[m, m] = yaw_rate_var + self.params.gyro_noise_density**2 / max(self._dt_last, 1e-3)
        p = self.params.velocity_gate_probability
        return self._update(idx, H, r, Rm, None if p is None else _chi2_gate(p, n))

    def update_zero_velocity(
        self,
        velocity_std: float = 0.005,
        angular_rate_std: float | None = None,
        gyro_mean: np.ndarray | None = None,
        gyro_mean_var: float | None = None,
        gate_probability: float | None = None,
    ) -> float:
        """Zero-velocity update for a robot known to stand still: ``v = 0`` with
        ``velocity_std`` per axis and, if ``angular_rate_std`` is given, ``omega = 0``
        (observes the gyro biases). The rate is read from the latest gyro sample (variance
        ``angular_rate_std^2`` plus one sample's white noise; left out without one), or from ``gyro_mean``, the
        mean raw gyro reading over the rest window, whose variance per axis is
        ``angular_rate_std^2 + gyro_mean_var`` (``gyro_mean_var``: the white noise of that
        mean, ``gyro_noise_density^2 / duration``). With the IMU alone this is what makes
        roll and pitch converge at rest: a tilt error turns gravity into horizontal
        acceleration that the zero velocity contradicts. ``gate_probability`` sets a
        chi-square gate (3 dof) on the NIS of the velocity part alone (the rate part
        is about the gyro bias, not about rest, and would only dilute it): a rest that the
        filter's velocity contradicts is rejected (state unchanged), as the
        visual-odometry deltas are. Returns the NIS of the velocity part."""
        if not velocity_std > 0.0 or (angular_rate_std is not None and not angular_rate_std > 0.0):
            raise FilterException(f"standard deviations must be > 0, got {velocity_std!r}, {angular_rate_std!r}")
        if (gyro_mean is None) != (gyro_mean_var is None):
            raise FilterException("gyro_mean and gyro_mean_var go together")
        if gyro_mean is not None:
            if angular_rate_std is None:
                raise FilterException("gyro_mean needs angular_rate_std")
            gyro_mean = _vector(gyro_mean, 3, "gyro_mean")
            if not gyro_mean_var > 0.0:
                raise FilterException(f"gyro_mean_var must be > 0, got {gyro_mean_var!r}")
            gyro_mean_var = float(gyro_mean_var)
        if gate_probability is not None and not 0.0 < gate_probability < 1.0:
            raise FilterException(f"gate_probability must be in (0, 1) or None, got {gate_probability!r}")
        args = (float(velocity_std), None if angular_rate_std is None else float(angular_rate_std), gyro_mean, gyro_mean_var, gate_probability)
        nis = self._zero_velocity(*args)
        if self._log:
            self._log.append(["zupt", self._t, *args])
        return nis

    @staticmethod
    def zero_velocity_gate(gate_probability: float) -> float:
        """Chi-square threshold (3 dof) on the velocity NIS of :meth:`update_zero_velocity`."""
        return _chi2_gate(gate_probability, 3)

    def _zero_velocity(self, velocity_std, angular_rate_std, gyro_mean=None, gyro_mean_var=None, gate_probability=None) -> float:
        if angular_rate_std is None or (gyro_mean is None and self._w_prev is None):
            idx = np.r_[3:6]
            H = np.eye(3)
            r = -self._v
            Rm = np.eye(3) * velocity_std**2
        else:
            idx = np.r_[3:6, 12:15]
            H = np.zeros((6, 6))
            H[0:3, 0:3] = np.eye(3)
            H[3:6, 3:6] = -np.eye(3)
            if gyro_mean is None:
                w, wnoise = self._w_prev, self.params.gyro_noise_density**2 / max(self._dt_last, 1e-3)
            else:
                w, wnoise = gyro_mean, gyro_mean_var
            r = np.concatenate([-self._v, -(w - self._bw)])
            Rm = np.diag([velocity_std**2] * 3 + [angular_rate_std**2 + wnoise] * 3)
        S_v = self._Pbuf[_V, _V] + np.eye(3) * velocity_std**2
        nis_v = float(self._v @ np.linalg.solve(S_v, self._v))
        if gate_probability is not None and nis_v > _chi2_gate(gate_probability, 3):
            return nis_v
        self._update(idx, H, r, Rm, None)
        return nis_v

    def _update(self, idx: np.ndarray, H: np.ndarray, r: np.ndarray, Rm: np.ndarray, gate: float | None) -> float:
        """EKF update with a Jacobian ``H`` over the state entries ``idx``; error injection
        on the manifold (left perturbations). Returns the NIS; skips the update above ``gate``."""
        d = self._dim
        P = self._Pbuf[:d, :d]
        PHt = P[:, idx] @ H.T  # d x m
        S = H @ PHt[idx] + Rm
        S = 0.5 * (S + S.T)
        sol = np.linalg.solve(S, np.column_stack([r, PHt.T]))
        nis = float(r @ sol[:, 0])
        if gate is not None and nis > gate:
            return nis
        dx = PHt @ sol[:, 0]
        P -= PHt @ sol[:, 1:]
        P[:] = 0.5 * (P + P.T)
        P[CORE : self._base, CORE : self._base] = self._Pcc  # Schmidt: the consider parameters keep their prior (and their estimate 0)
        self._p = self._p + dx[_P]
        self._v = self._v + dx[_V]
        self._R = so3_exp(dx[_TH]) @ self._R
        self._ba = self._ba + dx[_BA]
        self._bw = self._bw + dx[_BW]
        n = len(self._clone_ids)
        if n:
            D = dx[self._base :].reshape(n, CLONE)
            self._cR[:n] = so3_exp_batch(D[:, 0:3]) @ self._cR[:n]
            self._cp[:n] += D[:, 3:6]
        return nis

    # ------------------------------------------------------------------ frame switch

    def frame_switch(self) -> tuple[np.ndarray, np.ndarray]:
        """Switch the local frame into the current x, y, z and yaw (thesis 4.1.2).

        Returns ``T_old_new`` (4x4, gravity-aligned: a rotation about z and a
        translation) and the 4x4 covariance of ``[x, y, z, yaw]`` of the new frame in the
        old one. Afterwards the pose is at the origin with yaw 0 and zero position and
        yaw uncertainty; roll, pitch, velocity (rotated), biases and clones (expressed in
        the new frame) keep their uncertainty. Delayed deltas for clones captured before
        the switch are applied by stochastic cloning (no replay across a switch)."""
        roll, pitch, yaw = euler_zyx(self._R)
        j_yaw = euler_zyx_jacobian_inv(roll, pitch, yaw)[2]  # d_yaw = j_yaw . dtheta
        d = self._dim
        P = self._Pbuf[:d, :d]
        J4 = np.zeros((4, d))
        J4[0:3, _P] = np.eye(3)
        J4[3, _TH] = j_yaw
        cov4 = J4 @ P @ J4.T
        Rz = rot_z(yaw)
        RzT = Rz.T
        p0 = self._p
        T_old_new = se3(Rz, p0)

        e3 = np.array([0.0, 0.0, 1.0])
        v_new = RzT @ self._v
        J = np.zeros((d, d))
        # dp' = 0 (the new frame sits at the true position)
        J[_V, _V] = RzT
        J[_V, _TH] = np.outer(np.cross(v_new, e3), j_yaw)
        J[_TH, _TH] = RzT - np.outer(e3, j_yaw)
        J[9 : self._base, 9 : self._base] = np.eye(self._base - 9)
        n = len(self._clone_ids)
        pc_all = (self._cp[:n] - p0) @ Rz  # rows: Rz^T (p_c - p)
        for k in range(n):
            o = self._base + CLONE * k
            pc_new = pc_all[k]
            J[o : o + 3, o : o + 3] = RzT
            J[o : o + 3, _TH] = -np.outer(e3, j_yaw)
            J[o + 3 : o + 6, o + 3 : o + 6] = RzT
            J[o + 3 : o + 6, _P] = -RzT
            J[o + 3 : o + 6, _TH] = np.outer(np.cross(pc_new, e3), j_yaw)
        self._cp[:n] = pc_all
        self._cR[:n] = RzT @ self._cR[:n]
        Pn = J @ P @ J.T
        P[:] = 0.5 * (Pn + Pn.T)
        self._p = np.zeros(3)
        self._v = v_new
        self._R = RzT @ self._R
        self._frame_index += 1
        self._log.clear()
        self._clone_event.clear()
        return T_old_new, cov4

    # ------------------------------------------------------------------ delay compensation

    def _snapshot(self) -> _Snapshot:
        d = self._dim
        n = len(self._clone_ids)
        return _Snapshot(
            t=self._t,
            p=self._p,
            v=self._v,
            R=self._R,
            ba=self._ba,
            bw=self._bw,
            f_prev=self._f_prev,
            w_prev=self._w_prev,
            dt_last=self._dt_last,
            steps=self._steps,
            clone_ids=tuple(self._clone_ids),
            clone_t=tuple(self._clone_t),
            mapped=frozenset(self._mapped),
            cR=self._cR[:n].copy(),
            cp=self._cp[:n].copy(),
            P=self._Pbuf[:d, :d].copy(),
        )

    def _restore(self, s: _Snapshot) -> None:
        # core arrays are replaced, never modified in place, so sharing them is safe; clones and P are copied
        self._t, self._p, self._v, self._R = s.t, s.p, s.v, s.R
        self._ba, self._bw = s.ba, s.bw
        self._f_prev, self._w_prev, self._dt_last, self._steps = s.f_prev, s.w_prev, s.dt_last, s.steps
        self._clone_ids, self._clone_t = list(s.clone_ids), list(s.clone_t)
        self._mapped = set(s.mapped)
        n = len(self._clone_ids)
        self._cR[:n] = s.cR
        self._cp[:n] = s.cp
        d = s.P.shape[0]
        self._Pbuf[:d, :d] = s.P

    def _event_index(self, event: list) -> int:
        for i in range(len(self._log) - 1, -1, -1):
            if self._log[i] is event:
                return i
        raise AssertionError("clone event missing from the log")  # unreachable: trimmed events leave _clone_event

    def _replay_from(self, i: int, watch: list) -> float:
        """Roll back to the snapshot of the clone event at log index ``i`` and re-apply
        every later logged input; returns the NIS of the ``watch`` event."""
        self._restore(self._log[i][3])
        nis = float("nan")
        for event in self._log[i + 1 :]:
            kind = event[0]
            if kind == "imu":
                if event[2] is None:
                    self._propagate_without_imu(event[1])
                else:
                    self._propagate(event[1], event[2], event[3])
            elif kind == "clone":
                self._clone(event[2])
                event[3] = self._snapshot()
            elif kind == "drop":
                self._drop(event[2])
            elif kind == "relpose":
                value = self._relpose(*event[2:8])
                if event is watch:
                    nis = value
            elif kind == "vel":
                self._velocity(*event[2:6])
            else:  # "zupt"
                self._zero_velocity(*event[2:])
        return nis

    def _trim(self) -> None:
        """Forget inputs before the oldest clone snapshot within the replay horizon."""
        cutoff = self._t - self.params.replay_horizon_s
        log = self._log
        start = len(log)
        for i, event in enumerate(log):
            if event[0] == "clone" and event[1] >= cutoff:
                start = i
                break
        if start == 0:
            return
        for event in log[:start]:
            if event[0] == "clone" and self._clone_event.get(event[2]) is event:
                del self._clone_event[event[2]]
        del log[:start]


def switch_pose3_covariance(T_old_new: np.ndarray, cov4: np.ndarray, roll_pitch_var: float = 1e-10) -> np.ndarray:
    """6x6 ``[rotation, translation]`` right-perturbation covariance (GTSAM ``Pose3``) of
    a frame switch from :meth:`LocalReferenceFilter.frame_switch`'s ``[x, y, z, yaw]``
    covariance. Both frames are gravity-aligned, so roll and pitch of ``T_old_new`` are
    exact; ``roll_pitch_var`` keeps the matrix positive definite for the graph."""
    cov4 = np.asarray(cov4, dtype=float)
    RT = np.asarray(T_old_new, dtype=float)[:3, :3].T
    J = np.zeros((6, 4))
    J[2, 3] = 1.0  # Rz Exp(omega) = Rz(yaw + d_yaw): omega = e_z d_yaw
    J[3:6, 0:3] = RT  # rho = R^T dp
    C = J @ cov4 @ J.T
    C[0, 0] += roll_pitch_var
    C[1, 1] += roll_pitch_var
    return C
