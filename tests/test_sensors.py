"""sim.world.sensors against what the simulator knows: IMU at rest, bias random walk
statistics, rendered depth against known planes, stereo geometry, wheel odometry."""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

import dataclasses
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import sim  # noqa: F401  (MUJOCO_GL)
import mujoco
import numpy as np
import pytest

from sim.world.camera_rig import StereoRig
from sim.scenario import CameraConfig, WheelOdometryConfig
from sim.world.sensors import (
    IMU_PRESETS,
    SKY_FAR_FACTOR,
    ImuModel,
    SensorError,
    StereoRenderer,
    WheelOdometryModel,
    body_velocity_from_wheels,
    camera_motion_ahead,
)

# --------------------------------------------------------------------------- IMU

RESTING_BOX = """
<mujoco>
  <option timestep="0.002" gravity="0 0 -9.81"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body name="box" pos="0 0 0.105" euler="0 0 35">
      <freejoint/>
      <geom type="box" size="0.3 0.2 0.1" mass="20"/>
      <site name="imu" pos="0.05 -0.02 0.03"/>
    </body>
  </worldbody>
  <sensor><accelerometer name="accel" site="imu"/><gyro name="gyro" site="imu"/></sensor>
</mujoco>"""


@pytest.mark.parametrize("preset", sorted(IMU_PRESETS))
def test_imu_at_rest_reads_gravity(preset):
    model = mujoco.MjModel.from_xml_string(RESTING_BOX)
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=500)  # settle for 1 s
    rate = 200.0
    imu = ImuModel(IMU_PRESETS[preset], rate, np.random.default_rng(7))
    substeps = round(1 / (rate * model.opt.timestep))
    n = 400
    accel, gyro, true_f, biases = [], [], [], []
    for _ in range(n):
        mujoco.mj_step(model, data, nstep=substeps)
        f = data.sensor("accel").data.copy()
        a, g = imu.measure(f, data.sensor("gyro").data.copy())
        accel.append(a)
        gyro.append(g)
        true_f.append(f)
        biases.append(np.concatenate([imu.accel_bias, imu.gyro_bias]))
    accel, gyro, true_f, biases = map(np.asarray, (accel, gyro, true_f, biases))
    # MuJoCo's accelerometer gives specific force: +g upwards at rest
    np.testing.assert_allclose(true_f, np.tile([0.0, 0.0, 9.81], (n, 1)), atol=1e-3)
    sa, sg = imu.accel_noise_std, imu.gyro_noise_std
    # per sample: |a| = 9.81 within a few sigma of the noise plus the (true) bias
    norm_err = np.abs(np.linalg.norm(accel, axis=1) - 9.81)
    assert np.all(norm_err < 5 * sa + np.linalg.norm(biases[:, :3], axis=1))
    # bias-corrected mean: exactly gravity within the noise of the mean
    mean_err = (accel - biases[:, :3]).mean(axis=0) - [0, 0, 9.81]
    assert np.all(np.abs(mean_err) < 4 * sa / math.sqrt(n))
    # gyro: zero within noise + bias, and zero within the noise of the mean once de-biased
    assert np.all(np.abs(gyro) < 5 * sg + np.abs(biases[:, 3:]))
    assert np.all(np.abs((gyro - biases[:, 3:]).mean(axis=0)) < 4 * sg / math.sqrt(n))
    # the white noise has the density the spec says: std = density * sqrt(rate)
    resid = np.concatenate([(accel - true_f - biases[:, :3]).ravel() / sa, (gyro - biases[:, 3:]).ravel() / sg])
    assert resid.std() == pytest.approx(1.0, abs=0.06)


def test_imu_bias_random_walk_variance_grows_linearly():
    spec = dataclasses.replace(IMU_PRESETS["xsens_mti10"], accel_bias_initial_std=0.0, gyro_bias_initial_std=0.0)
    rate, seeds, steps = 100.0, 300, 400
    checkpoints = (100, 200, 400)
    drift = {k: [] for k in checkpoints}
    zero = np.zeros(3)
    for seed in range(seeds):
        imu = ImuModel(spec, rate, np.random.default_rng(seed))
        for k in range(1, steps + 1):
            imu.measure(zero, zero)
            if k in drift:
                drift[k].append(np.concatenate([imu.accel_bias / spec.accel_random_walk, imu.gyro_bias / spec.gyro_random_walk]))
    for k in checkpoints:
        t = k / rate
        var = np.var(np.asarray(drift[k]))  # 300 seeds x 6 axes, in units of the walk density
        assert var == pytest.approx(t, rel=0.12), f"variance at t={t} s"
    assert np.var(np.asarray(drift[400])) / np.var(np.asarray(drift[100])) == pytest.approx(4.0, rel=0.2)


def test_imu_is_reproducible_and_draws_initial_biases():
    spec = IMU_PRESETS["adis16407"]
    a = ImuModel(spec, 200.0, np.random.default_rng(3))
    b = ImuModel(spec, 200.0, np.random.default_rng(3))
    for _ in range(5):
        np.testing.assert_array_equal(a.measure(np.ones(3), np.zeros(3))[0], b.measure(np.ones(3), np.zeros(3))[0])
    biases = np.array([ImuModel(spec, 200.0, np.random.default_rng(s)).gyro_bias for s in range(400)])
    assert biases.std() == pytest.approx(spec.gyro_bias_initial_std, rel=0.1)
    with pytest.raises(SensorError):
        ImuModel(spec, 0.0, np.random.default_rng(0))


# --------------------------------------------------------------------------- stereo rendering

RIG = StereoRig("head", "left", "right", 0.09, 50.6, 320, 240)


def camera_scene(body_pos, body_euler, extra: str = "", extent: float = 40.0, rig: StereoRig = RIG, right_x=None, free: bool = False) -> tuple:
    """A textured plane at z = 0, a stereo pair on a body (``free``: on a free joint, without
    gravity); MuJoCo cameras look along the body's -z (an unrotated body looks straight down)."""
    right_x = rig.baseline_m if right_x is None else right_x
    xml = f"""
    <mujoco>
      <statistic extent="{extent}"/>
      <option gravity="0 0 0"/>
      <asset>
        <texture name="g" type="2d" builtin="checker" width="512" height="512" rgb1=".2 .2 .2" rgb2=".8 .8 .8"/>
        <material name="g" texture="g" texrepeat="40 40"/>
        <texture name="sky" type="skybox" builtin="gradient" rgb1=".4 .5 .7" rgb2=".1 .1 .1" width="32" height="32"/>
      </asset>
      <worldbody>
        <light directional="true" dir="0 0 -1" pos="0 0 10"/>
        <geom type="plane" size="30 30 1" material="g"/>
        {extra}
        <body pos="{body_pos}" euler="{body_euler}">
          {'<freejoint/><inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>' if free else ""}
          <camera name="left" pos="0 0 0" fovy="{rig.vfov_deg!r}"/>
          <camera name="right" pos="{right_x} 0 0" fovy="{rig.vfov_deg!r}"/>
        </body>
      </worldbody>
    </mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def ray_factor(rig: StereoRig) -> np.ndarray:
    """Ray length / z-depth per pixel."""
    K = rig.intrinsics
    u, v = np.meshgrid(np.arange(rig.width), np.arange(rig.height))
    return np.sqrt(1 + ((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2)


def test_depth_is_z_depth_on_a_plane_seen_head_on():
    model, data = camera_scene("0 0 3", "0 0 0")
    with StereoRenderer(model, RIG, CameraConfig()) as renderer:
        frame = renderer.render(data, with_depth=True)
        assert renderer.near_m == pytest.approx(CameraConfig().znear_m)
        assert renderer.far_m == pytest.approx(SKY_FAR_FACTOR * CameraConfig().zfar_m)
    assert frame.depth.dtype == np.float32 and frame.depth.shape == (240, 320)
    # z-depth is 3 m everywhere; the ray length would be 3.3 m in the corners
    np.testing.assert_allclose(frame.depth, 3.0, atol=1e-3)
    assert ray_factor(RIG)[0, 0] * 3.0 > 3.25


def test_depth_on_a_tilted_view_matches_ray_casting():
    """Looking 10 deg down from 1.2 m: every pixel's depth against mj_ray, sky is inf,
    and the image is upright (ground at the bottom)."""
    model, data = camera_scene("0 0 1.2", "80 0 0")  # body -z tilted towards +y, 10 deg below horizontal
    with StereoRenderer(model, RIG, CameraConfig()) as renderer:
        frame = renderer.render(data, with_depth=True)
    cam = model.camera("left").id
    R = data.cam_xmat[cam].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes in world
    K = RIG.intrinsics
    geomid = np.zeros(1, np.int32)
    for v in range(0, 240, 20):
        for u in range(0, 320, 40):
            ray = R @ np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
            dist = mujoco.mj_ray(model, data, data.cam_xpos[cam], ray, None, 1, -1, geomid)
            expected = dist if dist >= 0 else np.inf  # ray is z-normalised: distance = z-depth
            if np.isfinite(expected) and expected > CameraConfig().zfar_m:
                expected = np.inf
            assert frame.depth[v, u] == pytest.approx(expected, rel=1e-4), (u, v)
    assert np.all(np.isinf(frame.depth[0])) and np.all(np.isfinite(frame.depth[-1]))


def test_near_plane_is_the_cameras_own():
    """With extent 40, MuJoCo's default znear (0.01 x extent = 0.4 m) would clip a plane 0.1 m away."""
    model, data = camera_scene("0 0 0.1", "0 0 0", extent=40.0)
    with StereoRenderer(model, RIG, CameraConfig(znear_m=0.05)) as renderer:
        frame = renderer.render(data, with_depth=True)
        assert model.vis.map.znear * model.stat.extent == pytest.approx(0.05)
    np.testing.assert_allclose(frame.depth, 0.1, atol=1e-4)


def test_right_camera_sees_points_shifted_left_by_the_disparity():
    """A small red sphere 2 m in front (camera looking straight down) at x = +0.3 m
    appears right of the image centre, and u_l - u_r = f b / z."""
    sphere = '<geom type="sphere" size="0.04" pos="0.3 0 1" rgba="1 0 0 1"/>'
    model, data = camera_scene("0 0 3", "0 0 0", extra=sphere)
    with StereoRenderer(model, RIG, CameraConfig(color="rgb")) as renderer:
        frame = renderer.render(data, with_depth=True)

    def red_columns(img):
        mask = (img[..., 0].astype(int) - img[..., 1] > 80) & (img[..., 0] > 100)
        return np.nonzero(mask)[1]

    u_l, u_r = red_columns(frame.left), red_columns(frame.right)
    assert u_l.size > 20 and u_r.size > 20
    nearer = np.nonzero(frame.depth < 2.5)[1]  # only the sphere is nearer than the ground
    assert abs(nearer.mean() - u_l.mean()) < 0.5
    assert u_l.mean() > RIG.intrinsics[0, 2]  # x = +0.3 m is right of the image centre
    assert u_l.mean() - u_r.mean() == pytest.approx(RIG.focal_px * RIG.baseline_m / 2.0, abs=0.5)


@pytest.mark.parametrize("color", ["grey", "rgb"])
def test_image_formats(color):
    model, data = camera_scene("0 0 2", "0 0 0")
    with StereoRenderer(model, RIG, CameraConfig(color=color)) as renderer:
        frame = renderer.render(data, with_depth=False)
    shape = (240, 320) if color == "grey" else (240, 320, 3)
    assert frame.left.shape == shape and frame.right.shape == shape
    assert frame.left.dtype == np.uint8 and frame.depth is None
    assert frame.left.std() > 10  # the checker texture is visible
    assert not np.array_equal(frame.left, frame.right)


def test_renderers_share_a_context_and_close_independently():
    from sim.world.sensors import _RenderTarget

    model, data = camera_scene("0 0 2", "0 0 0")
    a = StereoRenderer(model, RIG, CameraConfig())
    b = StereoRenderer(model, RIG, CameraConfig())
    first = a.render(data).left
    np.testing.assert_array_equal(b.render(data).left, first)
    assert a._target is b._target and a._target.users == 2
    a.close()
    a.close()  # idempotent
    np.testing.assert_array_equal(b.render(data).left, first)
    b.close()
    assert (id(model), 320, 240, threading.get_ident()) not in _RenderTarget._registry
    with pytest.raises(SensorError, match="closed"):
        b.render(data)


def test_a_snapshot_draws_the_state_it_was_taken_at_in_another_thread():
    """The image pipeline's contract (sim/run/pipeline.py): the scene is fixed at the
    snapshot, the state may move on before the draw, and the draw may happen in another thread."""
    model, data = camera_scene("0 0 2", "0 0 0")
    with StereoRenderer(model, RIG, CameraConfig()) as here:
        before = here.render(data, with_depth=True)
    renderer = StereoRenderer(model, RIG, CameraConfig())
    request = renderer.snapshot(data, with_depth=True)
    model.body_pos[1] += [0.3, 0.0, 0.2]  # the camera body moves on
    mujoco.mj_forward(model, data)
    with ThreadPoolExecutor(1) as worker:
        frame = worker.submit(renderer.draw, request).result()
        moved = worker.submit(renderer.render, data).result()
        with pytest.raises(SensorError, match="thread"):
            renderer.render(data)  # it draws in the worker now
        worker.submit(renderer.close).result()
    for image in ("left", "right", "depth"):
        np.testing.assert_array_equal(getattr(frame, image), getattr(before, image))
    assert not np.array_equal(moved.left, before.left)


def test_a_time_offset_draws_the_pair_from_where_the_cameras_are_that_much_later():
    """A camera-IMU time offset (sim/world/calibration_errors.py): the pair snapshot now with
    ``time_offset_s`` is the pair the state that much later shows, for a rig moving and
    turning fast (2 m/s, 170 deg/s: 4 cm and 3.4 deg in 20 ms), the headlight with them."""
    model, data = camera_scene("0 0 2", "30 0 0", free=True)
    data.qvel[:] = [1.5, -1.0, 0.8, 1.0, -2.0, 2.0]  # world linear, body angular velocity
    mujoco.mj_forward(model, data)
    dt = 0.02
    later = mujoco.MjData(model)
    later.qpos[:] = data.qpos
    mujoco.mj_integratePos(model, later.qpos, data.qvel, dt)  # constant velocity: exact for a free body
    mujoco.mj_forward(model, later)
    cam = model.camera("left").id  # at the body's origin, which moves at constant velocity
    shift, turn = camera_motion_ahead(model, data, cam, dt)
    np.testing.assert_allclose(data.cam_xpos[cam] + shift, later.cam_xpos[cam], atol=1e-9)
    np.testing.assert_allclose(turn @ data.cam_xmat[cam].reshape(3, 3), later.cam_xmat[cam].reshape(3, 3), atol=1e-9)
    with StereoRenderer(model, RIG, CameraConfig(), time_offset_s=dt) as ahead, StereoRenderer(model, RIG, CameraConfig()) as plain:
        shifted = ahead.render(data, with_depth=True)
        now, truth = plain.render(data, with_depth=True), plain.render(later, with_depth=True)
    for image in ("left", "right"):
        error = np.abs(getattr(shifted, image).astype(int) - getattr(truth, image)).mean()
        assert (getattr(shifted, image) != getattr(truth, image)).mean() < 0.005, (image, error)  # float rounding flips a few edge pixels
        assert np.abs(getattr(now, image).astype(int) - getattr(truth, image)).mean() > 100 * max(error, 0.1)
    np.testing.assert_allclose(shifted.depth, truth.depth, rtol=1e-3)


def test_renderer_rejects_cameras_that_do_not_match_the_rig():
    model, data = camera_scene("0 0 2", "0 0 0", right_x=0.12)
    with StereoRenderer(model, RIG, CameraConfig()) as renderer, pytest.raises(SensorError, match="baseline"):
        renderer.render(data)
    wide = dataclasses.replace(RIG, hfov_deg=90.0)
    with pytest.raises(SensorError, match="fovy"):
        StereoRenderer(model, wide, CameraConfig())
    with pytest.raises(SensorError, match="no camera"):
        StereoRenderer(model, dataclasses.replace(RIG, left_camera="nope"), CameraConfig())
    with pytest.raises(SensorError, match="640x480"):
        StereoRenderer(model, RIG, CameraConfig(width=640, height=480))


# --------------------------------------------------------------------------- wheel odometry

LRU_WHEELS = [(0.35, 0.32), (0.35, -0.32), (-0.35, 0.32), (-0.35, -0.32)]  # x fwd, y left
RADIUS = 0.1


def wheel(x, y, steer, omega, radius=RADIUS):
    return SimpleNamespace(position_body=np.array([x, y, -0.2]), steer_angle=steer, angular_speed=omega, radius=radius)


def steered_wheels(vx, vy, yaw_rate):
    """Wheel states of individually steered wheels that roll without slip for the body motion."""
    out = []
    for x, y in LRU_WHEELS:
        cx, cy = vx - yaw_rate * y, vy + yaw_rate * x
        speed = math.hypot(cx, cy)
        steer = math.atan2(cy, cx) if speed > 0 else 0.0
        if abs(steer) > math.pi / 2:  # steer within +-90 deg and roll backwards
            steer -= math.copysign(math.pi, steer)
            speed = -speed
        out.append(wheel(x, y, steer, speed / RADIUS))
    return out


@pytest.mark.parametrize(
    "motion",
    [(0.3, 0.0, 0.0), (-0.2, 0.0, 0.0), (0.3, 0.0, 0.25), (0.2, 0.1, 0.0), (0.0, 0.0, 0.4), (0.25, -0.05, -0.15)],
    ids=["straight", "reverse", "turning", "crab", "point-turn", "general"],
)
def test_wheel_odometry_recovers_body_velocity_of_steered_wheels(motion):
    velocity, residual, outvoted = body_velocity_from_wheels(steered_wheels(*motion))
    np.testing.assert_allclose(velocity, motion, atol=1e-12)
    assert residual < 1e-12 and outvoted is None


def test_wheel_odometry_with_the_robots_wheel_state_type():
    base = pytest.importorskip("sim.robots.base")
    wheels = [base.WheelState(w.position_body, w.steer_angle, w.angular_speed, w.radius) for w in steered_wheels(0.3, 0.0, 0.2)]
    np.testing.assert_allclose(body_velocity_from_wheels(wheels)[0], [0.3, 0.0, 0.2], atol=1e-12)


def test_wheel_odometry_skid_steer():
    """Unsteered wheels: straight is exact; a skid turn has no slip-free solution, and the
    fit is the least-slip motion (differential yaw rate x sum y^2 / sum (x^2 + y^2))."""
    straight = [wheel(x, y, 0.0, 0.3 / RADIUS) for x, y in LRU_WHEELS]
    velocity, residual, _ = body_velocity_from_wheels(straight)
    np.testing.assert_allclose(velocity, [0.3, 0.0, 0.0], atol=1e-12)
    v_left, v_right = 0.2, 0.4
    turn = [wheel(x, y, 0.0, (v_left if y > 0 else v_right) / RADIUS) for x, y in LRU_WHEELS]
    velocity, residual, outvoted = body_velocity_from_wheels(turn)
    differential = (v_right - v_left) / (2 * 0.32)  # right wheels faster: a left (ccw, positive) turn
    least_slip = differential * 0.32**2 / (0.32**2 + 0.35**2)
    np.testing.assert_allclose(velocity, [0.3, 0.0, least_slip], atol=1e-12)
    assert residual > 0.01 and outvoted is None  # the wheels contradict each other: none is outvoted


@pytest.mark.parametrize("failed", range(4))
@pytest.mark.parametrize(
    "motion", [(0.3, 0.0, 0.0), (0.3, 0.0, 0.25), (0.2, 0.1, 0.0), (0.0, 0.0, 0.4)], ids=["straight", "turning", "crab", "point-turn"]
)
def test_a_failed_encoder_is_outvoted_by_the_other_wheels(motion, failed):
    """One encoder reads zero (the scenario's ``encoder_failure``): with it the fit is off
    by a quarter; the other three give the body velocity exactly, and the wheel is named."""
    wheels = steered_wheels(*motion)
    wheels[failed] = wheel(wheels[failed].position_body[0], wheels[failed].position_body[1], wheels[failed].steer_angle, 0.0)
    velocity, residual, outvoted = body_velocity_from_wheels(wheels)
    assert outvoted == failed
    np.testing.assert_allclose(velocity, motion, atol=1e-12)
    assert residual < 1e-12


def test_wheel_odometry_shows_slip_and_noise():
    """Wheels spinning at 0.6 m/s while the body (truth) moves at 0.3 m/s: odometry reports
    the wheels, so its error is the slip; white noise has the configured std."""
    cfg = WheelOdometryConfig(speed_noise_std_mps=0.02, yaw_rate_noise_std_rps=0.01)
    odom = WheelOdometryModel(cfg, np.random.default_rng(5))
    true_speed = 0.3
    spinning = steered_wheels(2 * true_speed, 0.0, 0.0)
    samples = np.array([odom.measure(spinning) for _ in range(4000)])
    assert samples[:, 0].mean() == pytest.approx(2 * true_speed, abs=0.002)
    assert samples[:, 0].mean() - true_speed > 0.25  # the slip shows up as odometry error
    np.testing.assert_allclose(samples.std(axis=0), [0.02, 0.02, 0.01], rtol=0.05)
    np.testing.assert_allclose(odom.last_true, [2 * true_speed, 0.0, 0.0], atol=1e-12)
    with pytest.raises(SensorError):
        odom.measure([])
