"""The scenario's ``realism`` section against what the simulator knows: profiles and
overrides, calibration errors in the rendered geometry and in the transform the robot
believes, IMU scale and misalignment, wheel slip and radius errors."""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

import math
from types import SimpleNamespace

import sim  # noqa: F401  (MUJOCO_GL)
import cv2
import mujoco
import numpy as np
import pytest

from sim.scenario import REALISM_PROFILES, CalibrationRealism, CameraConfig, ImuRealism, WheelOdometryConfig, WheelRealism, load_scenario
from sim.world.calibration_errors import (
    CalibrationError,
    LensDistortion,
    RigError,
    believed_body_camera,
    draw_calibration_errors,
    perturb_cameras,
)
from sim.world.sensors import (
    IMU_PRESETS,
    ImuErrors,
    ImuModel,
    SensorError,
    StereoRenderer,
    WheelErrors,
    WheelOdometryModel,
    body_velocity_from_wheels,
)
from slam.lie import rotation_angle, se3, so3_exp
from tests.test_sensors import RIG, camera_scene, steered_wheels

QUICKSTART = "scenarios/quickstart.yaml"


# --------------------------------------------------------------------------- profiles


def test_profiles_fill_every_key_and_overrides_win():
    default = load_scenario(QUICKSTART).realism
    assert default.profile == "realistic"
    assert default.calibration.focal_error == REALISM_PROFILES["realistic"]["calibration"]["focal_error"] > 0
    ideal = load_scenario(QUICKSTART, ["realism.profile=ideal", "realism.calibration.focal_error=0.01"]).realism
    assert ideal.calibration.focal_error == 0.01  # the override
    assert ideal.calibration.stereo_rotation_deg == 0.0 and not ideal.camera.noise and ideal.light.headlight  # the profile
    harsh = load_scenario(QUICKSTART, ["realism.profile=harsh"]).realism
    assert harsh.calibration.stereo_rotation_deg == 2 * default.calibration.stereo_rotation_deg
    assert harsh.light.shadows
    for profile in REALISM_PROFILES:
        resolved = load_scenario(QUICKSTART, [f"realism.profile={profile}"]).realism
        for section in ("camera", "calibration", "imu", "wheels"):
            assert None not in getattr(resolved, section).model_dump().values(), (profile, section)


# --------------------------------------------------------------------------- calibration errors


def red_sphere_columns(model, data, rig=RIG, error=None) -> tuple[float, float]:
    with StereoRenderer(model, rig, CameraConfig(color="rgb"), error) as renderer:
        frame = renderer.render(data)

    def columns(img):
        mask = (img[..., 0].astype(int) - img[..., 1] > 80) & (img[..., 0] > 100)
        return np.nonzero(mask)[1].mean()

    return columns(frame.left), columns(frame.right)


def test_a_right_camera_yaw_error_shifts_every_disparity_by_f_delta():
    """The true right camera turned by delta about its y axis (towards +x): a point seen by
    both moves left in the right image by f tan(delta), whatever its depth; the renderer
    accepts the true cameras only with their error."""
    sphere = '<geom type="sphere" size="0.04" pos="0.3 0 1" rgba="1 0 0 1"/>'
    model, data = camera_scene("0 0 3", "0 0 0", extra=sphere)
    u_l0, u_r0 = red_sphere_columns(model, data)
    delta = math.radians(0.5)
    error = CalibrationError({"head": RigError(R_right=so3_exp([0.0, delta, 0.0]))})
    robot = SimpleNamespace(stereo_rigs=[RIG])
    perturb_cameras(model, robot, error)
    mujoco.mj_forward(model, data)
    with pytest.raises(SensorError, match="rotation"):
        StereoRenderer(model, RIG, CameraConfig())._check_geometry(data)
    u_l, u_r = red_sphere_columns(model, data, error=error.rigs["head"])
    assert u_l == pytest.approx(u_l0, abs=0.05)  # the left camera is untouched
    assert (u_l - u_r) - (u_l0 - u_r0) == pytest.approx(RIG.focal_px * math.tan(delta), abs=0.3)


def test_baseline_and_focal_errors_change_the_true_cameras():
    sphere = '<geom type="sphere" size="0.15" pos="0.3 0 1" rgba="1 0 0 1"/>'  # large: its centroid to a tenth of a pixel'
    model, data = camera_scene("0 0 3", "0 0 0", extra=sphere)
    u_l0, u_r0 = red_sphere_columns(model, data)
    error = CalibrationError({"head": RigError(baseline_scale=1.1, focal_scale=1.05)})
    perturb_cameras(model, SimpleNamespace(stereo_rigs=[RIG]), error)
    mujoco.mj_forward(model, data)
    with pytest.raises(SensorError, match="fovy"):
        StereoRenderer(model, RIG, CameraConfig())
    u_l, u_r = red_sphere_columns(model, data, error=error.rigs["head"])
    c = RIG.intrinsics[0, 2]
    assert (u_l - c) / (u_l0 - c) == pytest.approx(1.05, abs=0.01)  # the image scales with the focal length
    assert (u_l - u_r) / (u_l0 - u_r0) == pytest.approx(1.05 * 1.1, abs=0.02)  # disparity = f b / z


def test_drawn_errors_have_the_configured_spread_and_encoders_only_on_heads():
    cfg = CalibrationRealism(
        stereo_rotation_deg=0.5,
        baseline_error=0.01,
        focal_error=0.02,
        camera_imu_rotation_deg=1.0,
        camera_imu_translation_m=0.01,
        pan_tilt_offset_deg=2.0,
    )
    rng = np.random.default_rng(3)
    head = SimpleNamespace(stereo_rigs=[RIG], pan_tilt_head=True)
    fixed = SimpleNamespace(stereo_rigs=[RIG], pan_tilt_head=False)
    draws = [draw_calibration_errors(head, cfg, rng) for _ in range(400)]
    focal = np.array([d.rigs["head"].focal_scale for d in draws]) - 1
    angles = np.array([rotation_angle(d.rigs["head"].R_right) for d in draws])
    pans = np.array([d.pan_offset_rad for d in draws])
    assert focal.std() == pytest.approx(0.02, rel=0.15)
    assert np.sqrt(np.mean(angles**2)) == pytest.approx(math.radians(0.5) * math.sqrt(3), rel=0.15)
    assert pans.std() == pytest.approx(math.radians(2.0), rel=0.15)
    assert draw_calibration_errors(fixed, cfg, rng).pan_offset_rad == 0.0
    zero = draw_calibration_errors(head, CalibrationRealism(**{k: 0.0 for k in cfg.model_dump()}), rng)
    assert zero.rigs["head"].focal_scale == 1.0 and np.array_equal(zero.rigs["head"].R_right, np.eye(3))


def test_lens_distortion_moves_what_each_pixel_shows_by_its_field():
    """Pixel u shows the rendered image at u + shift(u): an object seen at u0 by the nominal
    camera is delivered at u0 - shift(u0); a camera whose field is zero (here the right
    one) delivers its render unchanged, and the ground-truth depth is not resampled."""
    sphere = '<geom type="sphere" size="0.15" pos="0.5 0.3 1" rgba="1 0 0 1"/>'
    model, data = camera_scene("0 0 3", "0 0 0", extra=sphere)

    def red(img):
        rows, cols = np.nonzero((img[..., 0].astype(int) - img[..., 1] > 80) & (img[..., 0] > 100))
        return np.stack([cols, rows], axis=1).astype(float)

    with StereoRenderer(model, RIG, CameraConfig(color="rgb")) as renderer:
        nominal = renderer.render(data)
    distortion = np.array([[0.0, 0.0, 0.01, -0.02], [0.0, 0.0, 0.0, 0.0]])  # left camera: tangential, px-sized near the sphere
    error = RigError(distortion=distortion)
    with StereoRenderer(model, RIG, CameraConfig(color="rgb"), error) as renderer:
        distorted = renderer.render(data)
    shift = error.lens_distortions(RIG)[0].shift

    def shift_at(points):
        return shift[:, np.rint(points[:, 1]).astype(int), np.rint(points[:, 0]).astype(int)].T

    seen = red(nominal.left)  # where each red pixel is delivered: u with u + shift(u) = u0, by fixed-point steps
    delivered = seen - shift_at(seen)
    delivered = seen - shift_at(delivered)
    assert np.linalg.norm(shift_at(seen).mean(axis=0)) > 1.0
    np.testing.assert_allclose(red(distorted.left).mean(axis=0), delivered.mean(axis=0), atol=0.05)
    np.testing.assert_array_equal(distorted.right, nominal.right)
    np.testing.assert_array_equal(distorted.depth, nominal.depth)  # the truth stays along the nominal rays


def test_lens_distortion_resamples_bilinearly_to_the_exact_position():
    from scipy import ndimage

    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 256, (48, 64)).astype(np.uint8), (5, 5), 1.0)
    v, u = np.mgrid[0:48, 0:64]
    shift = np.stack([0.3 * np.sin(u / 7.0) + 0.013, 0.2 * np.cos(v / 5.0) - 0.021])
    exact = ndimage.map_coordinates(image.astype(np.float64), [v + shift[1], u + shift[0]], order=1, mode="nearest")
    out = LensDistortion(shift)(image)
    assert np.abs(out.astype(float) - exact).max() <= 0.5 + 1e-9  # only the 8-bit rounding
    colour = LensDistortion(shift)(np.dstack([image, 255 - image, image]))
    np.testing.assert_array_equal(colour[..., 0], out)


def test_drawn_lens_distortion_has_the_configured_rms_and_leaves_the_other_errors():
    rig = SimpleNamespace(stereo_rigs=[RIG], pan_tilt_head=True)
    base = dict(stereo_rotation_deg=0.04, baseline_error=0.001, focal_error=0.002, camera_imu_rotation_deg=0.2,
                camera_imu_translation_m=0.005, pan_tilt_offset_deg=0.1)
    rng = np.random.default_rng(5)
    draws = [draw_calibration_errors(rig, CalibrationRealism(**base, lens_distortion_mrad=0.2), rng) for _ in range(300)]
    mean_square = np.mean([(d.rigs["head"].lens_distortions(RIG)[k].shift ** 2).sum(axis=0).mean() for d in draws for k in (0, 1)])
    assert np.sqrt(mean_square) / RIG.focal_px == pytest.approx(0.2e-3, rel=0.15)
    with_it = draw_calibration_errors(rig, CalibrationRealism(**base, lens_distortion_mrad=0.2), np.random.default_rng(9))
    without = draw_calibration_errors(rig, CalibrationRealism(**base, lens_distortion_mrad=0.0), np.random.default_rng(9))
    assert without.rigs["head"].lens_distortions(RIG) is None
    np.testing.assert_array_equal(with_it.rigs["head"].R_right, without.rigs["head"].R_right)
    assert with_it.pan_offset_rad == without.pan_offset_rad


def test_drawn_time_offset_has_the_configured_spread_and_leaves_the_other_errors():
    rig = SimpleNamespace(stereo_rigs=[RIG], pan_tilt_head=True)
    base = dict(stereo_rotation_deg=0.04, baseline_error=0.001, focal_error=0.002, camera_imu_rotation_deg=0.2,
                camera_imu_translation_m=0.005, pan_tilt_offset_deg=0.1, lens_distortion_mrad=0.2)
    rng = np.random.default_rng(4)
    cfg = CalibrationRealism(**base, camera_imu_time_offset_ms=3.0)
    offsets = np.array([draw_calibration_errors(rig, cfg, rng).time_offset_s for _ in range(400)])
    assert offsets.std() == pytest.approx(3e-3, rel=0.15) and abs(offsets.mean()) < 0.5e-3
    with_it = draw_calibration_errors(rig, CalibrationRealism(**base, camera_imu_time_offset_ms=3.0), np.random.default_rng(9))
    without = draw_calibration_errors(rig, CalibrationRealism(**base, camera_imu_time_offset_ms=0.0), np.random.default_rng(9))
    assert without.time_offset_s == 0.0 and with_it.time_offset_s != 0.0
    np.testing.assert_array_equal(with_it.rigs["head"].distortion, without.rigs["head"].distortion)
    assert with_it.pan_offset_rad == without.pan_offset_rad


def test_believed_camera_transform_carries_extrinsic_and_encoder_errors():
    T_true = se3(so3_exp([0.3, -0.2, 1.0]), [0.2, 0.0, 1.1])
    none = CalibrationError({"head": RigError()})
    np.testing.assert_array_equal(believed_body_camera(T_true, RIG, none), T_true)
    pan = CalibrationError({"head": RigError()}, pan_offset_rad=0.01)
    T = believed_body_camera(T_true, RIG, pan)
    np.testing.assert_allclose(T, se3(so3_exp([0, 0, 0.01]), np.zeros(3)) @ T_true, atol=1e-12)  # about the body's z
    tilt = CalibrationError({"head": RigError()}, tilt_offset_rad=0.01)
    T = believed_body_camera(T_true, RIG, tilt)
    np.testing.assert_allclose(T[:3, :3].T @ T_true[:3, :3], so3_exp([-0.01, 0, 0]), atol=1e-12)  # about the camera's x
    mount = CalibrationError({"head": RigError(T_cam_error=se3(so3_exp([0, 0.02, 0]), [0.01, 0, 0]))})
    T = believed_body_camera(T_true, RIG, mount)
    assert rotation_angle(T[:3, :3].T @ T_true[:3, :3]) == pytest.approx(0.02)
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) == pytest.approx(0.01)


# --------------------------------------------------------------------------- IMU


def test_imu_errors_scale_and_misalign_the_true_signals():
    spec = IMU_PRESETS["xsens_mti10"]
    quiet = type(spec)(**{**spec.__dict__, **{k: 0.0 for k in spec.__dict__ if k.endswith(("density", "instability", "std"))}})
    errors = ImuErrors.draw(ImuRealism(scale_factor=0.01, misalignment_deg=0.5, g_sensitivity_dps_per_g=0.1), np.random.default_rng(1))
    assert not np.allclose(errors.gyro, np.eye(3))
    imu = ImuModel(quiet, 200.0, np.random.default_rng(2), errors=errors)
    f, w = np.array([0.1, -0.2, 9.81]), np.array([0.0, 0.0, 0.5])
    accel, gyro = imu.measure(f, w)
    np.testing.assert_allclose(accel, errors.accel @ f, atol=1e-12)
    np.testing.assert_allclose(gyro, errors.gyro @ w + errors.g_sensitivity @ f, atol=1e-12)
    # a yaw rate leaks into the other gyro axes by the misalignment (~0.5 deg = 0.0087 rad/rad)
    assert 1e-4 < np.abs(gyro[:2]).max() < 0.05
    none = ImuErrors.draw(ImuRealism(scale_factor=0.0, misalignment_deg=0.0, g_sensitivity_dps_per_g=0.0), np.random.default_rng(1))
    plain = ImuModel(quiet, 200.0, np.random.default_rng(2), errors=none)
    np.testing.assert_array_equal(plain.measure(f, w)[1], w)


# --------------------------------------------------------------------------- wheels


def test_wheel_slip_grows_uphill_and_the_radius_error_scales():
    cfg = WheelOdometryConfig(speed_noise_std_mps=0.0, yaw_rate_noise_std_rps=0.0)
    wheels = steered_wheels(0.3, 0.0, 0.0)
    errors = WheelErrors(radius_scale=1.01, slip=0.02, slip_per_10deg=0.07)
    odom = WheelOdometryModel(cfg, np.random.default_rng(0), errors)
    level = odom.measure(wheels, 0.0)[0]
    assert level == pytest.approx(0.3 * 1.01 / 0.98)
    uphill = odom.measure(wheels, math.sin(math.radians(10)))[0]
    assert odom.last_slip == pytest.approx(0.09) and uphill == pytest.approx(0.3 * 1.01 / 0.91)
    assert odom.measure(wheels, -math.sin(math.radians(10)))[0] == pytest.approx(0.3 * 1.01 / 1.05)  # downhill: skid
    backwards = odom.measure(steered_wheels(-0.3, 0.0, 0.0), -math.sin(math.radians(10)))[0]  # reversing up the slope
    assert backwards == pytest.approx(-0.3 * 1.01 / 0.91)
    exact = WheelOdometryModel(cfg, np.random.default_rng(0), WheelErrors())
    np.testing.assert_array_equal(exact.measure(wheels, 0.3), body_velocity_from_wheels(wheels)[0])  # no error: exactly the fit


def test_wheel_slip_varies_with_the_soil_at_its_std():
    cfg = WheelOdometryConfig(rate_hz=50.0, speed_noise_std_mps=0.0, yaw_rate_noise_std_rps=0.0)
    errors = WheelErrors.draw(WheelRealism(radius_error=0.0, slip=0.02, slip_per_10deg=0.0, slip_std=0.03), np.random.default_rng(5))
    odom = WheelOdometryModel(cfg, np.random.default_rng(4), errors)
    wheels = steered_wheels(0.3, 0.0, 0.0)
    slips = []
    for _ in range(50 * 2000):  # 2000 s, 400 correlation times
        odom.measure(wheels)
        slips.append(odom.last_slip)
    slips = np.array(slips)
    assert slips.mean() == pytest.approx(0.02, abs=0.006)
    assert slips.std() == pytest.approx(0.03, rel=0.15)
    lag = int(50 * 5.0)  # one correlation time: correlation 1/e
    assert np.corrcoef(slips[:-lag], slips[lag:])[0, 1] == pytest.approx(math.exp(-1), abs=0.08)
