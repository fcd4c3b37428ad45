"""Simulated sensors: IMU noise model, stereo rendering, wheel odometry.

- :class:`ImuModel` turns MuJoCo's true specific force and angular rate (its
  ``accelerometer`` already includes gravity; MJCF ``noise`` is metadata only, design
  notes §6) into measurements with white noise and bias random walks, after the
  datasheets of the thesis's IMUs (7.1): Xsens MTi-10 (rovers), ADIS16407 (ARDEA).
- :class:`InertialAverager` is the IMU's internal sampling: it averages the true
  specific force and angular rate over every physics step of a sample interval, as the
  MTi-10 (strapdown integration at 2 kHz, output as increments) and the ADIS16407
  (819.2 Hz sampling, Bartlett window filter) do. A single instantaneous physics sample
  per IMU period aliases the wheel-ground contact impulses into velocity errors of
  several cm/s per point turn, which the filter cannot model as white noise.
- :class:`StereoRenderer` renders a rectified pinhole pair (:class:`~sim.world.camera_rig.StereoRig`)
  offscreen, grey or RGB, plus the left camera's ground-truth z-depth, fast on CPU
  (llvmpipe): no reflections, no MSAA, shadows only where the world's sun casts them,
  and depth read from the same pass as the left image (no extra depth-only render).
  With a calibration error (:mod:`sim.world.calibration_errors`) the model's cameras
  are the true ones, which differ from the nominal rig by that error.
- :class:`ImuErrors` are the IMU's deterministic errors beyond noise and biases, drawn
  once per run (scenario ``realism.imu``): scale factors, axis misalignment and the gyros'
  sensitivity to specific force.
- :class:`WheelOdometryModel` fits the planar body velocity to the wheels' contact-point
  velocities by least squares (steered and skid-steered wheels alike); it sees the slip
  the physics produces, because it uses wheel speeds, not ground speed. :class:`WheelErrors`
  (scenario ``realism.wheels``) add what the rigid contact of the physics does not
  produce: slip in loose regolith that grows uphill, and a wheel radius the odometry
  gets wrong.
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Protocol, Self

import cv2
import mujoco
import numpy as np

from sim.scenario import CameraConfig, ImuRealism, WheelOdometryConfig, WheelRealism
from sim.world.calibration_errors import RigError
from sim.world.camera_rig import MUJOCO_TO_OPENCV, StereoRig
from sim.world.terrain_tiles import TerrainTiles
from slam.lie import so3_exp

__all__ = [
    "IMU_PRESETS",
    "ImuErrors",
    "ImuModel",
    "ImuSpec",
    "InertialAverager",
    "SensorError",
    "StereoFrame",
    "StereoRenderer",
    "WheelErrors",
    "WheelLike",
    "WheelOdometryModel",
    "body_velocity_from_wheels",
    "camera_motion_ahead",
    "camera_velocity",
]

#: MuJoCo draws the skybox at 0.5..1 x the far plane, with depth: rendering with the far
#: plane at this multiple of ``CameraConfig.zfar_m`` puts the sky well beyond ``zfar_m``,
#: so ground-truth depth beyond ``zfar_m`` (sky, or geometry out of range) becomes inf.
SKY_FAR_FACTOR = 8.0
G0 = 9.80665  # standard gravity, for datasheet values in g
DEG = math.pi / 180.0


class SensorError(ValueError):
    """A sensor that cannot be built or used as asked; the message says what was expected."""


# =========================================================================== IMU


@dataclass(frozen=True)
class ImuSpec:
    """Noise parameters of a 3-axis IMU, SI units, per axis (1 sigma).

    ``*_noise_density`` is the white-noise density (rad/s/sqrt(Hz), m/s^2/sqrt(Hz)): a
    sample at rate ``r`` has std ``density * sqrt(r)``. ``*_bias_instability`` is the
    datasheet's in-run bias stability; the model turns it into a bias random walk whose
    std reaches that value after ``bias_walk_horizon_s`` (a common reading of the
    Allan-deviation floor for MEMS, whose minimum lies at 10^2..10^3 s), so
    ``*_random_walk = instability / sqrt(horizon)`` (rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz)).
    ``*_bias_initial_std`` is the turn-on bias spread (datasheet repeatability /
    initial bias error), drawn once per run.
    """

    name: str
    gyro_noise_density: float
    accel_noise_density: float
    gyro_bias_instability: float
    accel_bias_instability: float
    gyro_bias_initial_std: float
    accel_bias_initial_std: float
    bias_walk_horizon_s: float = 100.0
    source: str = ""

    @property
    def gyro_random_walk(self) -> float:
        return self.gyro_bias_instability / math.sqrt(self.bias_walk_horizon_s)

    @property
    def accel_random_walk(self) -> float:
        return self.accel_bias_instability / math.sqrt(self.bias_walk_horizon_s)


#: Xsens MTi-10 (thesis 7.1, rovers). Xsens MTi 10-series specifications (MTi User
#: Manual MT0605P, 10-series IMU; values as published for the 4th-generation MTi-10,
#: quoted from memory of the manual, not re-checked here): gyro noise density
#: 0.03 deg/s/sqrt(Hz), in-run bias stability 18 deg/h; accelerometer noise density
#: 80 ug/sqrt(Hz), in-run bias stability 40 ug, bias repeatability (1 yr) 0.03 m/s^2.
#: Gyro turn-on bias: Xsens knowledge base "Bias repeatability of gyroscopes"
#: (base.xsens.com/hc/en-us/articles/203307252): +-0.5 deg/s within one year, used as 1 sigma.
XSENS_MTI10 = ImuSpec(
    name="xsens_mti10",
    gyro_noise_density=0.03 * DEG,
    accel_noise_density=80e-6 * G0,
    gyro_bias_instability=18.0 * DEG / 3600.0,
    accel_bias_instability=40e-6 * G0,
    gyro_bias_initial_std=0.5 * DEG,
    accel_bias_initial_std=0.03,
    source="Xsens MTi User Manual MT0605P (MTi 10-series); Xsens KB 203307252",
)

#: Analog Devices ADIS16407 (thesis 7.1, ARDEA). ADIS16407 data sheet (Analog Devices,
#: 2011; same inertial core as ADIS16400/16405; values quoted from memory of the data
#: sheet, not re-checked here): gyro rate noise density 0.05 deg/s/sqrt(Hz) rms,
#: in-run bias stability 0.007 deg/s (25 deg/h), initial bias error 3 deg/s (1 sigma);
#: accelerometer noise density 0.5 mg/sqrt(Hz) rms, in-run bias stability 0.2 mg,
#: initial bias error 50 mg (1 sigma). The initial errors are before the part's
#: bias-null calibration; a robot that calibrates at start-up sees far less.
ADIS16407 = ImuSpec(
    name="adis16407",
    gyro_noise_density=0.05 * DEG,
    accel_noise_density=0.5e-3 * G0,
    gyro_bias_instability=0.007 * DEG,
    accel_bias_instability=0.2e-3 * G0,
    gyro_bias_initial_std=3.0 * DEG,
    accel_bias_initial_std=50e-3 * G0,
    source="Analog Devices ADIS16407 data sheet (2011)",
)

IMU_PRESETS: dict[str, ImuSpec] = {s.name: s for s in (XSENS_MTI10, ADIS16407)}


@dataclass(frozen=True)
class ImuErrors:
    """An IMU's deterministic errors (1 + scale on the diagonal, misalignment off it):
    ``accel`` and ``gyro`` map true to sensed axes, ``g_sensitivity`` (rad/s per m/s^2)
    adds specific force to the gyros. Typical of MEMS parts after factory calibration
    (the values of ``realism`` profiles and their sources: sim/scenario.py)."""

    accel: np.ndarray = field(default_factory=lambda: np.eye(3))
    gyro: np.ndarray = field(default_factory=lambda: np.eye(3))
    g_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    @classmethod
    def draw(cls, cfg: ImuRealism, rng: np.random.Generator) -> ImuErrors:
        """Each scale error, misalignment angle and g-sensitivity normal with ``cfg``'s std."""
        off = ~np.eye(3, dtype=bool)

        def axes() -> np.ndarray:
            M = np.eye(3) + np.diag(rng.standard_normal(3) * cfg.scale_factor)
            M[off] = rng.standard_normal(6) * cfg.misalignment_deg * DEG
            return M

        accel, gyro = axes(), axes()
        return cls(accel, gyro, rng.standard_normal((3, 3)) * cfg.g_sensitivity_dps_per_g * DEG / G0)


class ImuModel:
    """Accelerometer and gyro measurements from true body-frame specific force and
    angular rate, sampled at ``rate_hz``:

        a_meas = M_a f_true + b_a + n_a,   w_meas = M_g w_true + G f_true + b_g + n_g,
        n ~ N(0, (density * sqrt(rate_hz))^2),   b_{k+1} = b_k + N(0, random_walk^2 / rate_hz),

    with ``M_a``, ``M_g``, ``G`` from :class:`ImuErrors` (identity and zero by default).

    Each :meth:`measure` call is one sample: the biases advance by ``dt = 1/rate_hz``
    first, then the measurement uses them; :attr:`accel_bias` / :attr:`gyro_bias` are
    the true biases of the latest sample (ground truth for evaluation). Initial biases
    are drawn from the spec's turn-on spread (times ``initial_bias_scale``).
    """

    def __init__(
        self, spec: ImuSpec, rate_hz: float, rng: np.random.Generator, initial_bias_scale: float = 1.0, errors: ImuErrors | None = None
    ):
        if rate_hz <= 0:
            raise SensorError(f"IMU rate_hz must be > 0, got {rate_hz}")
        self.spec = spec
        self.errors = errors
        self.rate_hz = float(rate_hz)
        self.dt = 1.0 / self.rate_hz
        self.rng = rng
        sq = math.sqrt(self.rate_hz)
        sdt = math.sqrt(self.dt)
        # per-sample std of [accel noise, gyro noise, accel bias step, gyro bias step]
        self._std = np.repeat(
            [spec.accel_noise_density * sq, spec.gyro_noise_density * sq, spec.accel_random_walk * sdt, spec.gyro_random_walk * sdt],
            3,
        )
        self._bias = np.concatenate(
            [
                rng.normal(0.0, spec.accel_bias_initial_std * initial_bias_scale, 3),
                rng.normal(0.0, spec.gyro_bias_initial_std * initial_bias_scale, 3),
            ]
        )
        self.samples = 0

    @property
    def accel_bias(self) -> np.ndarray:
        """True accelerometer bias (m/s^2, body frame) of the latest sample."""
        return self._bias[:3].copy()

    @property
    def gyro_bias(self) -> np.ndarray:
        """True gyro bias (rad/s, body frame) of the latest sample."""
        return self._bias[3:].copy()

    @property
    def accel_noise_std(self) -> float:
        """Per-sample white-noise std of the accelerometer (m/s^2)."""
        return float(self._std[0])

    @property
    def gyro_noise_std(self) -> float:
        """Per-sample white-noise std of the gyro (rad/s)."""
        return float(self._std[3])

    def measure(self, specific_force_body: np.ndarray, angular_velocity_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One sample: ``(accel m/s^2, gyro rad/s)`` in the body (IMU) frame."""
        n = self.rng.standard_normal(12) * self._std
        self._bias += n[6:]
        f = np.asarray(specific_force_body, dtype=float)
        w = np.asarray(angular_velocity_body, dtype=float)
        if self.errors is not None:
            f, w = self.errors.accel @ f, self.errors.gyro @ w + self.errors.g_sensitivity @ f
        accel = f + self._bias[:3] + n[:3]
        gyro = w + self._bias[3:] + n[3:6]
        self.samples += 1
        return accel, gyro


class InertialAverager:
    """Mean true specific force and angular rate of one IMU site over an output period.

    :meth:`accumulate` after every physics step (MuJoCo's sensors then hold the
    acceleration that step integrated); :meth:`take` at the IMU sample returns the means
    since the last sample and starts a new period. With the body velocity integrated
    explicitly this box filter is the exact mean acceleration of the interval, so the
    strapdown integration of the samples reproduces the velocity change of the physics.
    """

    def __init__(self, model: mujoco.MjModel, accel_sensor: str, gyro_sensor: str):
        self._accel = self._slice(model, accel_sensor)
        self._gyro = self._slice(model, gyro_sensor)
        self._sum = np.zeros(6)
        self._count = 0

    @staticmethod
    def _slice(model: mujoco.MjModel, name: str) -> slice:
        sensor = model.sensor(name)
        if int(sensor.dim[0]) != 3:
            raise SensorError(f"sensor {name!r} has dimension {int(sensor.dim[0])}, expected 3")
        adr = int(sensor.adr[0])
        return slice(adr, adr + 3)

    def accumulate(self, data: mujoco.MjData) -> None:
        self._sum[:3] += data.sensordata[self._accel]
        self._sum[3:] += data.sensordata[self._gyro]
        self._count += 1

    def take(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """``(specific_force, angular_rate)`` averaged since the last call; the current
        sensor values when no physics step has happened since (the first sample)."""
        if self._count == 0:
            return data.sensordata[self._accel].copy(), data.sensordata[self._gyro].copy()
        mean = self._sum / self._count
        self._sum[:] = 0.0
        self._count = 0
        return mean[:3], mean[3:]


# =========================================================================== stereo rendering


@dataclass
class StereoFrame:
    """One rendered stereo pair. ``left``/``right``: uint8 (H, W) grey or (H, W, 3) RGB.
    ``depth``: float32 (H, W) ground-truth z-depth of the left camera in metres (inf
    beyond ``CameraConfig.zfar_m``, sky included), or None when not requested."""

    left: np.ndarray
    right: np.ndarray
    depth: np.ndarray | None = None


class _RenderTarget:
    """One GL context + MuJoCo render context per (model, image size, thread), shared by
    every :class:`StereoRenderer` that draws in that thread (reference counted). A GL
    context is current in one thread at a time, so a thread that draws has its own."""

    _registry: ClassVar[dict[tuple[int, int, int, int], _RenderTarget]] = {}

    @classmethod
    def acquire(cls, model: mujoco.MjModel, width: int, height: int) -> _RenderTarget:
        key = (id(model), width, height, threading.get_ident())
        target = cls._registry.get(key)
        if target is None:
            target = cls(model, width, height, key)
            cls._registry[key] = target
        target.users += 1
        return target

    def __init__(self, model: mujoco.MjModel, width: int, height: int, key: tuple[int, int, int, int]):
        self.model = model  # keeps the model alive while the key (its id) is in use
        self.key = key
        self.width, self.height = width, height
        self.users = 0
        glob = model.vis.global_
        if glob.offwidth < width or glob.offheight < height:
            glob.offwidth, glob.offheight = max(glob.offwidth, width), max(glob.offheight, height)
        model.vis.quality.offsamples = 0  # no MSAA (a main render cost on llvmpipe): read by MjrContext below
        self.gl = mujoco.GLContext(width, height)
        self.gl.make_current()
        self.context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
        self.context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self.rect = mujoco.MjrRect(0, 0, width, height)
        self.rgb = np.empty((height, width, 3), np.uint8)
        self.zbuf = np.empty((height, width), np.float32)

    def make_current(self) -> None:
        # always: other code (a mujoco.Renderer, another target) may have switched contexts
        self.gl.make_current()

    def release(self) -> None:
        self.users -= 1
        if self.users > 0:
            return
        if _RenderTarget._registry.get(self.key) is self:
            del _RenderTarget._registry[self.key]
        self.gl.make_current()  # free the render context's GL objects in their own context
        self.context.free()
        self.gl.free()


#: The GL cameras of a scene's two eyes (MuJoCo renders a mono image from both): position, forward, up.
_Eyes = tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]


def camera_velocity(model: mujoco.MjModel, data: mujoco.MjData, camera_id: int, local: bool = False) -> np.ndarray:
    """The MuJoCo camera's ``[angular, linear]`` velocity at its origin, in world axes or
    (``local``) its own MuJoCo axes (``data``'s velocities must be current, as after ``mj_step``)."""
    velocity = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_CAMERA, camera_id, velocity, int(local))
    return velocity


def camera_motion_ahead(model: mujoco.MjModel, data: mujoco.MjData, camera_id: int, ahead_s: float) -> tuple[np.ndarray, np.ndarray]:
    """How far the MuJoCo camera moves and turns (world frame: displacement of its origin,
    rotation) in the ``ahead_s`` after the state in ``data``, at its present velocity (a
    camera-IMU time offset of a few milliseconds)."""
    if ahead_s == 0.0:
        return np.zeros(3), np.eye(3)
    velocity = camera_velocity(model, data, camera_id)
    return velocity[3:] * ahead_s, so3_exp(velocity[:3] * ahead_s)


def _eyes_moved(eyes: _Eyes, origin: np.ndarray, position: np.ndarray, turn: np.ndarray) -> _Eyes:
    """Eyes of a rig whose camera at ``origin`` moved to ``position`` and turned by ``turn`` (world frame)."""
    return tuple((position + turn @ (pos - origin), turn @ forward, turn @ up) for pos, forward, up in eyes)


def _eyes(scene: mujoco.MjvScene) -> _Eyes:
    return tuple((c.pos.copy(), c.forward.copy(), c.up.copy()) for c in scene.camera)


def _set_eyes(scene: mujoco.MjvScene, eyes: _Eyes) -> None:
    for camera, (pos, forward, up) in zip(scene.camera, eyes):
        camera.pos, camera.forward, camera.up = pos, forward, up


@dataclass
class RenderRequest:
    """A stereo pair as the world stood when it was captured (:meth:`StereoRenderer.snapshot`):
    the scene with the left camera, the right camera's eyes, and the depth range, for
    :meth:`StereoRenderer.draw` in any thread, later."""

    scene: mujoco.MjvScene
    left: _Eyes
    right: _Eyes
    near_m: float
    far_m: float
    with_depth: bool


#: Scenes per renderer: one being drawn while the next is snapshot (a third snapshot waits for a draw).
SCENES_PER_RENDERER = 2


class StereoRenderer:
    """Renders the rectified stereo pair ``rig`` of a compiled model.

    Intrinsics come from ``rig`` (:attr:`StereoRig.intrinsics`: pinhole, square pixels,
    principal point at the image centre, which is MuJoCo's camera model); the model's
    cameras must match it (``fovy == rig.vfov_deg``, right camera at ``+baseline`` along
    the left camera's x with the same orientation: checked, :class:`SensorError`
    otherwise), or, given the rig's calibration ``error``, match it changed by that
    error; the error's lens distortion resamples the images (not the ground-truth
    depth, which stays the depth along each pixel's nominal ray, the one the stack
    assumes). ``camera`` gives the colour mode and the depth range: before each
    snapshot ``model.vis.map.znear * model.stat.extent`` is set to ``camera.znear_m`` (the
    near plane is the camera's own even when one model serves cameras with different
    settings), and the far plane to ``SKY_FAR_FACTOR * camera.zfar_m``; ground-truth
    depth beyond ``camera.zfar_m`` is reported as ``inf`` (the skybox has depth in
    MuJoCo, at 0.5..1 x the far plane, and must not pass for terrain).
    ``time_offset_s`` is the camera-IMU time offset (:mod:`sim.world.calibration_errors`):
    each pair shows the world from where its cameras are that long after the state it is
    snapshot at (:func:`camera_motion_ahead`; the rest of the scene as it is then).

    :meth:`render` = :meth:`draw` of a :meth:`snapshot`. The snapshot reads the simulation
    state (``mjv_updateScene``, the terrain tiles, the right camera) and must be taken when
    the pair is captured; the draw only needs the snapshot and may run later in another
    thread (``sim/run/pipeline.py``): the GL work releases Python's GIL. All draws of
    one renderer happen in one thread, which also :meth:`close` s it.

    Fast on CPU: the terrain drawn as tiles culled to the view, at levels of detail
    (:mod:`sim.world.terrain_tiles`, when the model has them and no light casts shadows),
    reflections off, shadows only if a light casts them, MSAA off (``vis.quality.offsamples = 0``,
    set before the render context is made), one GL context per (model, width, height, thread)
    shared by all renderers, and the ground-truth depth is read from the depth buffer
    of the left image's own pass. Call :meth:`close` when done (EGL teardown).
    """

    def __init__(self, model: mujoco.MjModel, rig: StereoRig, camera: CameraConfig, error: RigError | None = None, time_offset_s: float = 0.0):
        if (rig.width, rig.height) != (camera.width, camera.height):
            raise SensorError(
                f"stereo rig {rig.name!r} is {rig.width}x{rig.height} but its camera config asks for "
                f"{camera.width}x{camera.height}"
            )
        self.model = model
        self.rig = rig
        self.camera = camera
        self.error = error or RigError()
        self.time_offset_s = time_offset_s
        self._distortions = self.error.lens_distortions(rig)
        self._cam_ids = tuple(self._camera_id(name) for name in (rig.left_camera, rig.right_camera))
        for name, cid in zip((rig.left_camera, rig.right_camera), self._cam_ids):
            fovy, expected = float(model.cam_fovy[cid]), self.error.true_vfov_deg(rig)
            if abs(fovy - expected) > 1e-3:
                raise SensorError(f"camera {name!r} has fovy {fovy:.6f} deg, rig {rig.name!r} needs {expected:.6f} deg")
            if hasattr(model, "cam_sensorsize") and np.any(model.cam_sensorsize[cid] > 0):
                raise SensorError(f"camera {name!r} uses sensorsize/focal intrinsics; expected a plain fovy pinhole")
        self._mjv_cams = []
        for cid in self._cam_ids:
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = cid
            self._mjv_cams.append(cam)
        self._geometry_checked = False
        self._shadows = int(bool(np.any(model.light_castshadow)) and model.vis.quality.shadowsize > 0)
        self._option = mujoco.MjvOption()
        self._tiles = TerrainTiles.from_model(model)
        self._free_scenes: queue.SimpleQueue[mujoco.MjvScene] = queue.SimpleQueue()
        for _ in range(SCENES_PER_RENDERER):
            self._free_scenes.put(mujoco.MjvScene(model, maxgeom=10000))
        self._target: _RenderTarget | None = None  # acquired by the first draw, in the thread that draws
        self._closed = False

    def _camera_id(self, name: str) -> int:
        cid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        if cid < 0:
            names = [self.model.camera(i).name for i in range(self.model.ncam)]
            raise SensorError(f"stereo rig {self.rig.name!r}: no camera {name!r} in the model; cameras: {names}")
        return cid

    @property
    def near_m(self) -> float:
        """The near plane the model currently renders with (``vis.map.znear * stat.extent``)."""
        return float(self.model.vis.map.znear * self.model.stat.extent)

    @property
    def far_m(self) -> float:
        """The far clipping plane the model renders with: ``SKY_FAR_FACTOR * camera.zfar_m``."""
        return float(self.model.vis.map.zfar * self.model.stat.extent)

    def _check_geometry(self, data: mujoco.MjData) -> None:
        left, right = self._cam_ids
        R_l = data.cam_xmat[left].reshape(3, 3)
        R_r = data.cam_xmat[right].reshape(3, 3)
        if not np.any(R_l):  # kinematics not computed yet: check on a later frame
            return
        rel = R_l.T @ (data.cam_xpos[right] - data.cam_xpos[left])  # MuJoCo camera frame: x right
        baseline = self.rig.baseline_m * self.error.baseline_scale
        expected = np.array([baseline, 0.0, 0.0])
        R_err = MUJOCO_TO_OPENCV @ self.error.R_right @ MUJOCO_TO_OPENCV  # the error is in OpenCV camera axes
        angle = np.linalg.norm(cv2.Rodrigues(R_l.T @ R_r @ R_err.T)[0])
        if np.linalg.norm(rel - expected) > 1e-3 or angle > 1e-4:
            raise SensorError(
                f"stereo rig {self.rig.name!r}: right camera must sit at +baseline ({baseline:.5f} m) along "
                f"the left camera's x, turned by its calibration error; found offset {rel.round(4).tolist()} m "
                f"and a rotation {angle:.5f} rad off"
            )
        self._geometry_checked = True

    def render(self, data: mujoco.MjData, with_depth: bool = False) -> StereoFrame:
        """Render the pair at the state in ``data`` (kinematics must be current, as after ``mj_step``)."""
        return self.draw(self.snapshot(data, with_depth))

    def snapshot(self, data: mujoco.MjData, with_depth: bool = False) -> RenderRequest:
        """The pair's scene at the state in ``data``, seen from where the cameras are
        ``time_offset_s`` later; waits while both of this renderer's scenes are still to be drawn."""
        if self._closed:
            raise SensorError(f"StereoRenderer of rig {self.rig.name!r} was closed")
        if not self._geometry_checked:
            self._check_geometry(data)
        m = self.model
        m.vis.map.znear = self.camera.znear_m / m.stat.extent
        m.vis.map.zfar = SKY_FAR_FACTOR * self.camera.zfar_m / m.stat.extent
        scene = self._free_scenes.get()
        try:
            mujoco.mjv_updateScene(m, data, self._option, None, self._mjv_cams[0], mujoco.mjtCatBit.mjCAT_ALL, scene)
            scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self._shadows
            scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            if self._tiles is not None and not self._shadows:  # with shadows: the hfield (sim/world/terrain_tiles.py)
                cam = self._cam_ids[0]
                chosen = self._tiles.select(data.cam_xpos[cam], data.cam_xmat[cam], float(m.cam_fovy[cam]), self.rig.width / self.rig.height,
                                            self.rig.height, self.near_m, self.far_m, margin=self.rig.baseline_m)
                self._tiles.replace_hfield(scene, chosen)
            left = _eyes(scene)
            # the right camera sees the same scene: only the camera changes
            mujoco.mjv_updateCamera(m, data, self._mjv_cams[1], scene)
            right = _eyes(scene)
        except BaseException:
            self._free_scenes.put(scene)
            raise
        if self.time_offset_s:
            origin = data.cam_xpos[self._cam_ids[0]]
            shift, turn = camera_motion_ahead(m, data, self._cam_ids[0], self.time_offset_s)
            position = origin + shift
            left, right = (_eyes_moved(eyes, origin, position, turn) for eyes in (left, right))
            for light in scene.lights[: scene.nlight]:
                if light.headlight:  # it moves with the camera
                    light.pos, light.dir = position + turn @ (light.pos - origin), turn @ light.dir
        return RenderRequest(scene, left, right, self.near_m, self.far_m, with_depth)

    def draw(self, request: RenderRequest) -> StereoFrame:
        """Render a :meth:`snapshot` (in the thread that draws all of this renderer's pairs)."""
        if self._closed:
            raise SensorError(f"StereoRenderer of rig {self.rig.name!r} was closed")
        t = self._target
        if t is None:
            t = self._target = _RenderTarget.acquire(self.model, self.rig.width, self.rig.height)
        elif self.drawing_thread != threading.get_ident():
            raise SensorError(f"StereoRenderer of rig {self.rig.name!r} draws in one thread; it drew in another before")
        scene = request.scene
        try:
            t.make_current()
            _set_eyes(scene, request.left)
            mujoco.mjr_render(t.rect, scene, t.context)
            mujoco.mjr_readPixels(t.rgb, t.zbuf if request.with_depth else None, t.rect, t.context)
            left = self._image(t.rgb)
            depth = self._linear_depth(t.zbuf, request.near_m, request.far_m) if request.with_depth else None
            _set_eyes(scene, request.right)
            mujoco.mjr_render(t.rect, scene, t.context)
            mujoco.mjr_readPixels(t.rgb, None, t.rect, t.context)
            right = self._image(t.rgb)
        finally:
            self._free_scenes.put(scene)
        if self._distortions is not None:
            left, right = self._distortions[0](left), self._distortions[1](right)
        return StereoFrame(left, right, depth)

    def _image(self, rgb: np.ndarray) -> np.ndarray:
        # OpenGL rows run bottom-up: flip to image rows
        if self.camera.color == "grey":
            return cv2.flip(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), 0)
        return cv2.flip(rgb, 0)

    def _linear_depth(self, zbuf: np.ndarray, near: float, far: float) -> np.ndarray:
        """Window depth (reversed z, 1 at the near plane, 0 at the far plane; MuJoCo's
        ``mjDEPTH_ZEROFAR`` read-out, as in ``mujoco.Renderer``) to eye-space z in metres."""
        c = 0.5 * (far + near) / (far - near) - 0.5  # = near / (far - near)
        d = far * near / (far - near)
        z = d / (zbuf.astype(np.float64) + c)
        z[z > self.camera.zfar_m] = np.inf  # sky, or nothing within the camera's range
        return cv2.flip(z.astype(np.float32), 0)

    @property
    def drawing_thread(self) -> int | None:
        """The thread that draws this renderer's pairs (``threading.get_ident``), None before the first draw."""
        return None if self._target is None else self._target.key[3]

    def close(self) -> None:
        """Release the GL context, in the thread that drew (idempotent)."""
        if self._target is not None:
            if self.drawing_thread != threading.get_ident():
                raise SensorError(f"StereoRenderer of rig {self.rig.name!r}: close it in the thread that drew with it")
            self._target.release()
            self._target = None
        self._closed = True

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# =========================================================================== wheel odometry


class WheelLike(Protocol):
    """What wheel odometry reads of a wheel (``sim.robots.base.WheelState`` fits)."""

    position_body: np.ndarray  # (3,) wheel centre on its steering axis, body frame (x fwd, y left, z up)
    steer_angle: float  # rad, 0 = rolling along body x, positive to the left
    angular_speed: float  # rad/s about the axle, positive rolls forward
    radius: float  # m


#: The on-board odometry's encoder check (ours, not the thesis's): a fit whose RMS residual
#: exceeds this (m/s; driving on the simulated LRU it stays below 2 mm/s in 9 of 10
#: samples and below 0.08 m/s in steering transients) is refitted without each wheel's
#: rolling equation in turn, and a wheel whose removal takes the residual below
#: :data:`ENCODER_OUTLIER_RATIO` of it is left out (a failed or slipping encoder).
ENCODER_CHECK_RESIDUAL_MPS = 0.02
ENCODER_OUTLIER_RATIO = 0.2


def body_velocity_from_wheels(wheels: Sequence[WheelLike]) -> tuple[np.ndarray, float, int | None]:
    """Planar body velocity ``(v_x, v_y, yaw_rate)`` from wheel states, the RMS residual
    (m/s) of the fit (a measure of the slip the wheels' kinematics imply), and the index of
    a wheel whose encoder the others outvoted (None: all used).

    Each wheel ``i`` at ``(x_i, y_i)`` with steer angle ``delta_i``, angular speed
    ``omega_i`` and radius ``r_i`` says that its contact point moves at ``r_i omega_i``
    along its heading ``(cos delta_i, sin delta_i)`` and not at all sideways. A rigid
    body moving at ``(v_x, v_y, Omega)`` moves that point at
    ``(v_x - Omega y_i, v_y + Omega x_i)``. Both components for all wheels give 2N
    linear equations in three unknowns, solved by least squares. For steered wheels
    that agree (Ackermann, crab, point turn) the fit is exact; for skid steering the
    wheels cannot agree, and the least-squares answer is the motion with the least
    total contact slip (its yaw rate is the differential-drive one scaled by
    ``sum y^2 / sum (x^2 + y^2)``, the usual effective-track-width correction).
    With four or more wheels a residual above :data:`ENCODER_CHECK_RESIDUAL_MPS` tests each
    wheel's rolling equation against the others (leave one out): an encoder that reads zero
    while the others turn contradicts them all, a skid turn's wheels contradict each other.
    """
    rows = []
    rhs = []
    for w in wheels:
        x, y = float(w.position_body[0]), float(w.position_body[1])
        c, s = math.cos(w.steer_angle), math.sin(w.steer_angle)
        speed = float(w.radius) * float(w.angular_speed)
        # longitudinal: c (v_x - W y) + s (v_y + W x) = speed; lateral: -s (...) + c (...) = 0
        rows.append((c, s, c * -y + s * x))
        rhs.append(speed)
        rows.append((-s, c, -s * -y + c * x))
        rhs.append(0.0)
    if not rows:
        raise SensorError("wheel odometry needs at least one wheel, got none")
    A = np.asarray(rows)
    b = np.asarray(rhs)
    sol, residual = _fit(A, b)
    if len(wheels) < 4 or residual <= ENCODER_CHECK_RESIDUAL_MPS:
        return sol, residual, None
    fits = [_fit(np.delete(A, 2 * i, axis=0), np.delete(b, 2 * i)) for i in range(len(wheels))]
    i = min(range(len(fits)), key=lambda k: fits[k][1])
    if fits[i][1] < ENCODER_OUTLIER_RATIO * residual:
        return fits[i][0], fits[i][1], i
    return sol, residual, None


def _fit(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    return sol, float(np.sqrt(np.mean((A @ sol - b) ** 2)))


#: Correlation time of the soil's slip variation (s): patches of looser and firmer
#: regolith passing under a rover at 0.3 m/s over about 1.5 m (chosen).
SLIP_CORRELATION_S = 5.0
SLIP_RANGE = (-0.5, 0.9)  # skid downhill .. nearly spinning in place


@dataclass(frozen=True)
class WheelErrors:
    """Wheel odometry errors the physics does not produce. The MuJoCo contact is firm
    ground; on loose regolith the wheels turn more than the ground passes under them,
    with a slip ratio ``s = 1 - ground travel / wheel travel`` that grows uphill (Lindemann and Voorhees 2005, MER slip tests):

        s = slip + slip_per_10deg * slope_deg / 10 + e,   e: Ornstein-Uhlenbeck, std ``slip_std``,

    with ``slope_deg`` the gradient along the direction of travel (negative downhill).
    The odometry also assumes a radius ``radius_scale`` times the true one. Together the
    measured velocities are the wheels' fit times ``radius_scale / (1 - s)``."""

    radius_scale: float = 1.0
    slip: float = 0.0
    slip_per_10deg: float = 0.0
    slip_std: float = 0.0

    @classmethod
    def draw(cls, cfg: WheelRealism, rng: np.random.Generator) -> WheelErrors:
        """The radius error drawn with ``cfg.radius_error``'s std; the slip model as given."""
        return cls(1.0 + float(rng.standard_normal()) * cfg.radius_error, cfg.slip, cfg.slip_per_10deg, cfg.slip_std)


class WheelOdometryModel:
    """Wheel odometry: :func:`body_velocity_from_wheels`, scaled by the :class:`WheelErrors`,
    plus white noise (``cfg.speed_noise_std_mps`` on v_x and v_y,
    ``cfg.yaw_rate_noise_std_rps`` on the yaw rate). :meth:`measure` returns
    ``np.array([v_x, v_y, yaw_rate])`` in the body frame; :attr:`last_true` (noise-free
    fit), :attr:`last_residual_mps` (slip indicator of the fit), :attr:`last_slip`
    (the slip ratio applied) and :attr:`outvoted_samples` (samples in which a wheel's
    encoder was left out) are kept for evaluation."""

    def __init__(self, cfg: WheelOdometryConfig, rng: np.random.Generator, errors: WheelErrors | None = None):
        self.cfg = cfg
        self.rng = rng
        self.errors = errors or WheelErrors()
        self._std = np.array([cfg.speed_noise_std_mps, cfg.speed_noise_std_mps, cfg.yaw_rate_noise_std_rps])
        self._dt = 1.0 / cfg.rate_hz
        self._soil = 0.0  # the slip's soil variation e
        self.last_true = np.zeros(3)
        self.last_residual_mps = 0.0
        self.last_slip = 0.0
        self.outvoted_samples = 0  # samples in which the encoder check left a wheel out

    def measure(self, wheels: Sequence[WheelLike], forward_incline_sin: float = 0.0) -> np.ndarray:
        """One sample; ``forward_incline_sin``: sine of the body x axis's angle above the
        horizon (positive nose up), for the slope-dependent slip."""
        velocity, residual, outvoted = body_velocity_from_wheels(wheels)
        self.last_true = velocity
        self.last_residual_mps = residual
        self.outvoted_samples += outvoted is not None
        n = self.rng.standard_normal(3) * self._std
        err = self.errors
        if err.slip_std > 0:  # exact discretisation of the Ornstein-Uhlenbeck process
            a = math.exp(-self._dt / SLIP_CORRELATION_S)
            self._soil = a * self._soil + math.sqrt(1 - a * a) * err.slip_std * float(self.rng.standard_normal())
        uphill_deg = math.degrees(math.asin(max(-1.0, min(1.0, forward_incline_sin)))) * (1.0 if velocity[0] >= 0 else -1.0)
        slip = err.slip + err.slip_per_10deg * uphill_deg / 10.0 + self._soil
        self.last_slip = min(max(slip, SLIP_RANGE[0]), SLIP_RANGE[1])
        return velocity * (err.radius_scale / (1.0 - self.last_slip)) + n
