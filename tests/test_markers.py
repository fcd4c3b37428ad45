"""slam.markers: AprilTag detection and PnP on warped and MuJoCo-rendered tags (thesis
6.2.1), the planar pose ambiguity, the constant and quadratic uncertainty models (eq.
8.1-8.2) and the robot-detection composition of eq. 4.7 with its covariance."""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

import math

import sim  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
import cv2
import mujoco
import numpy as np
import pytest
from dm_control import mjcf

from sim.world.markers import MARKER_THICKNESS_M, MarkerSpec, add_marker, apriltag_image
from slam.lie import adjoint, rot_zyx, se3, se3_inv, skew, so3_exp, so3_log
from slam.markers import (
    SIGMA_CONSTANT,
    CornerRefinement,
    MarkerDetection,
    MarkerDetector,
    MarkerException,
    UncertaintyModel,
    detection_covariance,
    refine_corners,
    relative_pose,
)

W, H = 640, 480
K640 = np.array([[500.0, 0, (W - 1) / 2], [0, 500.0, (H - 1) / 2], [0, 0, 1]])
# LRU-like camera at 320x240, 50 deg horizontal field of view
F320 = 160 / math.tan(math.radians(25.0))
K320 = np.array([[F320, 0, 159.5], [0, F320, 119.5], [0, 0, 1]])
SUPERSAMPLE = 4


# --------------------------------------------------------------------------- helpers


def marker_corners(size_m: float) -> np.ndarray:
    """The 4 black-square corners in the marker frame, cv2.aruco order."""
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def project(K: np.ndarray, T_cam_marker: np.ndarray, size_m: float) -> np.ndarray:
    p = marker_corners(size_m) @ T_cam_marker[:3, :3].T + T_cam_marker[:3, 3]
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:3]


def facing(roll: float, pitch: float, yaw: float, t) -> np.ndarray:
    """``T_cam_marker`` of a tag that faces the camera (its z towards -z_cam, printed upright)
    when the angles are zero, then turned by ``Rz(yaw) Ry(pitch) Rx(roll)`` in the camera."""
    return se3(rot_zyx(roll, pitch, yaw) @ np.diag([1.0, -1.0, -1.0]), t)


def background(rng: np.random.Generator, w: int = W, h: int = H) -> np.ndarray:
    """Smooth grey texture (no tag-like structure), at the supersampled resolution."""
    coarse = rng.integers(50, 210, (h // 8, w // 8), dtype=np.uint8)
    return cv2.resize(coarse, (w * SUPERSAMPLE, h * SUPERSAMPLE), interpolation=cv2.INTER_CUBIC)


def draw_tags(K: np.ndarray, tags: list[tuple[int, float, np.ndarray]], rng: np.random.Generator, w: int = W, h: int = H) -> np.ndarray:
    """Grey image of AprilTags (id, size, T_cam_marker) warped from sim.world.markers.apriltag_image
    into a textured background: drawn at 4x, box-filtered down (an anti-aliased camera)."""
    img = background(rng, w, h)
    for tag_id, size_m, T in tags:
        ppc = 16
        tag = apriltag_image(tag_id, ppc)
        a, b = ppc - 0.5, tag.shape[0] - ppc - 0.5  # black-square edges, pixel centres at integers
        src = np.float32([[a, a], [b, a], [b, b], [a, b]])  # top-left first = marker (-s/2, +s/2)
        dst = (SUPERSAMPLE * project(K, T, size_m) + (SUPERSAMPLE - 1) / 2).astype(np.float32)
        Hm = cv2.getPerspectiveTransform(src, dst)
        img = cv2.warpPerspective(tag, Hm, (img.shape[1], img.shape[0]), dst=img, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_TRANSPARENT)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)


def rot_err_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(so3_log(R_a.T @ R_b))))


def se3_exp(xi) -> np.ndarray:
    """``Exp([w, v])`` of the GTSAM Pose3 tangent (rotation first)."""
    w, v = np.asarray(xi[:3], float), np.asarray(xi[3:], float)
    return se3(so3_exp(w), _left_jacobian(w) @ v)


def se3_log(T: np.ndarray) -> np.ndarray:
    w = so3_log(T[:3, :3])
    return np.concatenate([w, np.linalg.solve(_left_jacobian(w), T[:3, 3])])


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    t = float(np.linalg.norm(w))
    S = skew(w)
    if t < 1e-8:
        return np.eye(3) + 0.5 * S
    return np.eye(3) + (1 - math.cos(t)) / t**2 * S + (t - math.sin(t)) / t**3 * (S @ S)


# --------------------------------------------------------------------------- synthetic images

SYNTHETIC_POSES = {
    "frontal": facing(0.0, 0.0, 0.0, [0.0, 0.0, 1.5]),
    "tilted_about_x": facing(math.radians(35), 0.0, 0.0, [0.1, -0.05, 1.5]),
    "tilted_about_y": facing(0.0, math.radians(-45), 0.0, [-0.2, 0.1, 1.5]),
    "turned_in_plane": facing(0.0, math.radians(10), math.radians(90), [0.0, 0.15, 1.5]),
    "upside_down_oblique": facing(math.radians(25), math.radians(-30), math.radians(150), [0.3, -0.2, 1.5]),
}


@pytest.mark.parametrize("refinement", list(CornerRefinement))
@pytest.mark.parametrize("name", list(SYNTHETIC_POSES))
def test_synthetic_tag_pose_and_conventions(name, refinement):
    T_true = SYNTHETIC_POSES[name]
    size = 0.15
    img = draw_tags(K640, [(5, size, T_true)], np.random.default_rng(1))
    detector = MarkerDetector(K640, {5: size}, corner_refinement=refinement)
    dets = detector.detect(img)
    assert len(dets) == 1
    d = dets[0]
    assert isinstance(d, MarkerDetection) and d.tag_id == 5
    # corner order: corners[0] is the tag's top-left corner, marker (-s/2, +s/2)
    uv_true = project(K640, T_true, size)
    assert d.corners.shape == (4, 2)
    assert np.max(np.linalg.norm(d.corners - uv_true, axis=1)) < 0.5
    assert np.linalg.norm(d.T_cam_marker[:3, 3] - T_true[:3, 3]) < 0.01
    assert rot_err_deg(d.T_cam_marker[:3, :3], T_true[:3, :3]) < 2.0
    # the face is seen: the marker z axis points back towards the camera
    assert d.T_cam_marker[2, 2] < 0
    cos_true = -T_true[:3, 2] @ T_true[:3, 3] / np.linalg.norm(T_true[:3, 3])
    assert d.view_angle_rad == pytest.approx(math.acos(cos_true), abs=math.radians(2))
    assert d.distance_m == pytest.approx(np.linalg.norm(T_true[:3, 3]), abs=0.01)
    assert 0.0 <= d.ambiguity <= 1.0
    assert d.T_cam_marker_alt is not None and d.T_cam_marker_alt.shape == (4, 4)
    assert d.reprojection_error_px < 0.5
    assert d.side_px == pytest.approx(np.min(np.linalg.norm(uv_true - np.roll(uv_true, -1, axis=0), axis=1)), abs=1.0)


def test_two_tags_of_different_sizes_sorted_by_id():
    T_big = facing(0.2, -0.3, 0.1, [-0.35, 0.0, 2.0])
    T_small = facing(-0.3, 0.4, -0.2, [0.3, 0.1, 1.2])
    img = draw_tags(K640, [(12, 0.2, T_big), (3, 0.08, T_small)], np.random.default_rng(2))
    dets = MarkerDetector(K640, {3: 0.08, 12: 0.2}).detect(img)
    assert [d.tag_id for d in dets] == [3, 12]
    for d, T in zip(dets, (T_small, T_big)):
        assert np.linalg.norm(d.T_cam_marker[:3, 3] - T[:3, 3]) < 0.01
        assert rot_err_deg(d.T_cam_marker[:3, :3], T[:3, :3]) < 2.0
    # a wrong size scales the translation (the size is what fixes the scale)
    wrong = MarkerDetector(K640, {3: 0.16, 12: 0.2}).detect(img)
    np.testing.assert_allclose(wrong[0].T_cam_marker[:3, 3], 2 * dets[0].T_cam_marker[:3, 3], rtol=1e-6)


def test_refine_corners_from_rough_corners():
    T = SYNTHETIC_POSES["upside_down_oblique"]
    img = draw_tags(K640, [(5, 0.15, T)], np.random.default_rng(8))
    truth = project(K640, T, 0.15)
    rough = truth + np.random.default_rng(9).uniform(-1.0, 1.0, (4, 2))
    refined = refine_corners(img, rough)
    assert np.max(np.linalg.norm(refined - truth, axis=1)) < 0.15
    assert refine_corners(np.full((H, W), 128, np.uint8), rough) is None  # no edges to fit


def test_rgb_input_matches_grey():
    T = SYNTHETIC_POSES["tilted_about_y"]
    grey = draw_tags(K640, [(5, 0.15, T)], np.random.default_rng(3))
    detector = MarkerDetector(K640, {5: 0.15})
    a = detector.detect(grey)[0]
    b = detector.detect(np.repeat(grey[:, :, None], 3, axis=2))[0]
    np.testing.assert_allclose(a.T_cam_marker, b.T_cam_marker, atol=1e-9)


# --------------------------------------------------------------------------- ambiguity


def test_ambiguity_small_far_frontal_marker_with_corner_noise():
    """A 15 cm tag 6 m away (about 9 px) nearly frontal: the two IPPE solutions explain
    noisy corners almost equally well; both are reported and the better one is chosen."""
    size = 0.15
    detector = MarkerDetector(K320, {1: size})
    polishing = MarkerDetector(K320, {1: size}, refine_lm=True)
    T_true = facing(math.radians(4), math.radians(-3), 0.2, [0.1, 0.05, 6.0])
    rng = np.random.default_rng(4)
    ambiguities = []
    for _ in range(30):
        corners = project(K320, T_true, size) + rng.normal(0.0, 0.3, (4, 2))
        d = detector.pose_from_corners(1, corners)
        assert d is not None and d.T_cam_marker_alt is not None
        # the chosen pose has the lower reprojection error
        alt_err = math.sqrt(np.mean(np.sum((project(K320, d.T_cam_marker_alt, size) - corners) ** 2, axis=1)))
        own_err = math.sqrt(np.mean(np.sum((project(K320, d.T_cam_marker, size) - corners) ** 2, axis=1)))
        assert own_err == pytest.approx(d.reprojection_error_px, rel=1e-6, abs=1e-9)
        assert d.reprojection_error_px <= alt_err
        assert d.ambiguity * alt_err == pytest.approx(d.reprojection_error_px, rel=1e-6, abs=1e-12)
        # the optional LM polish starts from the chosen pose and never raises its error
        polished = polishing.pose_from_corners(1, corners)
        assert polished.reprojection_error_px <= d.reprojection_error_px + 1e-12
        assert polished.ambiguity == d.ambiguity  # the ratio of the IPPE errors
        # the two solutions: same position, normals mirrored about the line of sight
        assert np.linalg.norm(d.T_cam_marker[:3, 3] - d.T_cam_marker_alt[:3, 3]) < 0.1 * d.distance_m
        ambiguities.append(d.ambiguity)
    assert np.median(ambiguities) > 0.6
    assert max(ambiguities) > 0.9

    # the same noise on a close, tilted tag is resolved clearly
    T_close = facing(math.radians(40), 0.0, 0.0, [0.0, 0.0, 1.0])
    clear = [detector.pose_from_corners(1, project(K320, T_close, size) + rng.normal(0.0, 0.3, (4, 2))).ambiguity for _ in range(30)]
    assert np.max(clear) < 0.3


def test_pose_from_corners_exact_and_checks():
    detector = MarkerDetector(K320, {1: 0.15})
    T = facing(0.3, -0.5, 1.0, [0.2, -0.1, 2.5])
    d = detector.pose_from_corners(1, project(K320, T, 0.15))
    np.testing.assert_allclose(d.T_cam_marker, T, atol=1e-6)
    assert d.reprojection_error_px < 1e-6
    # the alternative is the tilt mirrored about the line of sight: the same view angle
    n_alt, t_alt = d.T_cam_marker_alt[:3, 2], d.T_cam_marker_alt[:3, 3]
    assert math.acos(-n_alt @ t_alt / np.linalg.norm(t_alt)) == pytest.approx(d.view_angle_rad, abs=math.radians(1))
    assert rot_err_deg(d.T_cam_marker_alt[:3, :3], T[:3, :3]) > 30
    # exactly fronto-parallel on the optical axis (OpenCV's IPPE returns a mirrored pose there)
    T_front = facing(0.0, 0.0, 0.0, [0.0, 0.0, 2.0])
    corners = np.array([[K320[0, 2], K320[1, 2]]]) + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * F320 * 0.075 / 2.0
    d = detector.pose_from_corners(1, corners)
    np.testing.assert_allclose(d.T_cam_marker, T_front, atol=1e-6)
    np.testing.assert_allclose(d.T_cam_marker_alt, T_front, atol=1e-6)
    assert d.ambiguity == 1.0 and d.view_angle_rad == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(MarkerException, match="no known size"):
        detector.pose_from_corners(2, project(K320, T, 0.15))
    with pytest.raises(MarkerException, match="4 image points"):
        detector.pose_from_corners(1, np.zeros((3, 2)))


# --------------------------------------------------------------------------- rendered (MuJoCo)

MJ_W, MJ_H = 320, 240
MJ_HFOV_DEG = 50.0
MJ_TAG = MarkerSpec(name="tag", tag_id=7, size_m=0.15, pos=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0))
MJ_TAG_CENTRE = np.array([0.0, 0.0, 0.6])
# sim.world.markers puts the box geom half its thickness behind the marker frame (the printed face)
FACE_IN_GEOM = se3(np.eye(3), [0.0, 0.0, MARKER_THICKNESS_M / 2])


def _tag_rotation() -> np.ndarray:
    """The tag faces -x (towards the camera), its top edge up."""
    z = np.array([-1.0, 0.0, 0.0])
    y = np.array([0.0, 0.0, 1.0])
    return np.column_stack([np.cross(y, z), y, z])


def _camera_pose(distance_m: float, azimuth_deg: float, elevation_deg: float, roll_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo camera position and rotation (x right, y up, looking along -z) at
    ``distance_m`` from the tag, seen ``azimuth_deg`` off its normal, looking at it."""
    az, el, ro = (math.radians(v) for v in (azimuth_deg, elevation_deg, roll_deg))
    d = np.array([-math.cos(el) * math.cos(az), -math.cos(el) * math.sin(az), math.sin(el)])
    pos = MJ_TAG_CENTRE + distance_m * d
    look = -d
    x = np.cross(look, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(x, look)
    x, y = math.cos(ro) * x + math.sin(ro) * y, -math.sin(ro) * x + math.cos(ro) * y
    return pos, np.column_stack([x, y, -look])


@pytest.fixture(scope="module")
def tag_scene():
    root = mjcf.RootElement(model="tag_scene")
    glob = getattr(root.visual, "global")
    glob.offwidth, glob.offheight = 640, 480
    root.visual.quality.offsamples = 0
    root.asset.add("texture", name="sky", type="skybox", builtin="gradient", rgb1=[0.7, 0.6, 0.5], rgb2=[0.3, 0.25, 0.2], width=32, height=32)
    root.asset.add("texture", name="ground", type="2d", builtin="checker", rgb1=[0.45, 0.4, 0.35], rgb2=[0.3, 0.28, 0.25], width=256, height=256)
    root.asset.add("material", name="ground", texture="ground", texrepeat=[20, 20])
    root.worldbody.add(
        "light", directional=True, castshadow=False, dir=[-0.3, 0.2, -0.9], pos=[0, 0, 10], diffuse=[0.8, 0.8, 0.8], ambient=[0.3, 0.3, 0.3]
    )
    root.worldbody.add("geom", type="plane", size=[20, 20, 0.1], material="ground")
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, _tag_rotation().ravel())
    body = root.worldbody.add("body", name="mast", pos=MJ_TAG_CENTRE.tolist(), quat=quat.tolist())
    add_marker(body, MJ_TAG)
    vfov = math.degrees(2 * math.atan(math.tan(math.radians(MJ_HFOV_DEG) / 2) * MJ_H / MJ_W))
    root.worldbody.add("body", name="cam_body", mocap=True).add("camera", name="cam", fovy=vfov)
    model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, MJ_H, MJ_W)
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "cam")
    f = (MJ_H / 2) / math.tan(math.radians(model.cam_fovy[cam_id]) / 2)
    K = np.array([[f, 0, (MJ_W - 1) / 2], [0, f, (MJ_H - 1) / 2], [0, 0, 1]])

    def render(distance_m: float, azimuth_deg: float, elevation_deg: float, roll_deg: float = 0.0):
        """Grey image and the true T_cam_marker (OpenCV camera frame)."""
        pos, R = _camera_pose(distance_m, azimuth_deg, elevation_deg, roll_deg)
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, R.ravel())
        data.mocap_pos[0], data.mocap_quat[0] = pos, q
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera="cam")
        rgb = renderer.render()
        geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "tag")
        T_world_cam = se3(data.cam_xmat[cam_id].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0]), data.cam_xpos[cam_id])
        T_world_geom = se3(data.geom_xmat[geom].reshape(3, 3), data.geom_xpos[geom])
        return rgb, se3_inv(T_world_cam) @ T_world_geom @ FACE_IN_GEOM

    yield K, render
    renderer.close()


@pytest.mark.parametrize(
    ("distance", "azimuth", "elevation", "roll"),
    [(2.0, 30.0, 10.0, 0.0), (2.0, -40.0, 20.0, 15.0), (2.0, 20.0, -8.0, -20.0), (3.0, -25.0, 5.0, 30.0)],
)
def test_rendered_marker_pose(tag_scene, distance, azimuth, elevation, roll):
    K, render = tag_scene
    rgb, T_true = render(distance, azimuth, elevation, roll)
    dets = MarkerDetector(K, {MJ_TAG.tag_id: MJ_TAG.size_m}).detect(rgb)
    assert [d.tag_id for d in dets] == [MJ_TAG.tag_id]
    d = dets[0]
    assert d.ambiguity < 0.5
    assert np.linalg.norm(d.T_cam_marker[:3, 3] - T_true[:3, 3]) < 0.03
    assert rot_err_deg(d.T_cam_marker[:3, :3], T_true[:3, :3]) < 3.0
    assert d.view_angle_rad == pytest.approx(math.radians(math.hypot(azimuth, elevation)), abs=math.radians(4))
    assert np.max(np.linalg.norm(d.corners - project(K, T_true, MJ_TAG.size_m), axis=1)) < 1.0


def test_rendered_marker_unknown_id_and_min_side(tag_scene):
    K, render = tag_scene
    rgb, _ = render(2.0, 30.0, 10.0)
    assert MarkerDetector(K, {MJ_TAG.tag_id + 1: 0.15}).detect(rgb) == []
    assert len(MarkerDetector(K, {MJ_TAG.tag_id: 0.15}, min_side_px=20.0).detect(rgb)) == 1  # about 22 px at 2 m
    assert MarkerDetector(K, {MJ_TAG.tag_id: 0.15}, min_side_px=25.0).detect(rgb) == []


# --------------------------------------------------------------------------- uncertainty models


def test_constant_and_quadratic_models():
    cov = detection_covariance(UncertaintyModel.CONSTANT, 3.0)
    np.testing.assert_array_equal(cov, np.diag([0.0005] * 3 + [0.0001] * 3))  # eq. 8.1, [rot, trans]
    np.testing.assert_array_equal(cov, SIGMA_CONSTANT)
    assert math.degrees(math.sqrt(cov[0, 0])) == pytest.approx(1.28, abs=0.01)  # "1.3 deg"
    assert math.sqrt(cov[3, 3]) == pytest.approx(0.01)  # 1 cm
    cov[0, 0] = 1.0  # a copy: the module constant is untouched
    assert SIGMA_CONSTANT[0, 0] == 0.0005
    for d in (0.0, 1.5, 4.0):
        np.testing.assert_allclose(detection_covariance("quadratic", d), SIGMA_CONSTANT * (1 + d) ** 2)  # eq. 8.2
    np.testing.assert_array_equal(detection_covariance("constant", 10.0), SIGMA_CONSTANT)
    with pytest.raises(MarkerException, match="unknown uncertainty model 'cubic'"):
        detection_covariance("cubic", 1.0)
    with pytest.raises(MarkerException, match="distance_m"):
        detection_covariance(UncertaintyModel.QUADRATIC, -1.0)
    with pytest.raises(MarkerException, match="distance_m"):
        detection_covariance(UncertaintyModel.QUADRATIC, float("nan"))


def _detection_setup():
    """Robot a (camera on a pan-tilt mast) detects a tag on robot b's mast (eq. 4.7)."""
    T_w_a = se3(rot_zyx(0.05, -0.02, 0.7), [1.0, 2.0, 0.1])
    T_w_b = se3(rot_zyx(-0.03, 0.04, -2.2), [4.0, 3.5, 0.2])
    R_body_cv = np.column_stack([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # OpenCV camera looking along x
    T_a_cam = se3(rot_zyx(0.0, 0.3, 0.2) @ R_body_cv, [0.1, 0.05, 1.2])  # on a pan-tilt mast: tilted down, panned left
    T_b_marker = se3(rot_zyx(math.pi / 2, 0.0, 2.0), [-0.1, 0.2, 0.9])  # a tilted mast tag, off the body origin
    T_cam_marker = se3_inv(T_a_cam) @ se3_inv(T_w_a) @ T_w_b @ T_b_marker
    return T_w_a, T_w_b, T_a_cam, T_b_marker, T_cam_marker


def test_relative_pose_composition():
    T_w_a, T_w_b, T_a_cam, T_b_marker, T_cam_marker = _detection_setup()
    T_a_b, cov = relative_pose(T_a_cam, T_cam_marker, T_b_marker, SIGMA_CONSTANT)
    np.testing.assert_allclose(T_a_b, se3_inv(T_w_a) @ T_w_b, atol=1e-12)
    assert cov.shape == (6, 6)
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    with pytest.raises(MarkerException, match="cov_marker"):
        relative_pose(T_a_cam, T_cam_marker, T_b_marker, np.eye(3))
    with pytest.raises(MarkerException, match="T_b_marker"):
        relative_pose(T_a_cam, T_cam_marker, np.eye(3), SIGMA_CONSTANT)


def test_adjoint_moves_right_perturbations():
    T = se3(rot_zyx(0.3, -0.7, 2.0), [0.4, -1.2, 0.9])
    xi = np.array([0.02, -0.01, 0.03, 0.05, 0.02, -0.04])
    np.testing.assert_allclose(T @ se3_exp(xi) @ se3_inv(T), se3_exp(adjoint(T) @ xi), atol=1e-12)
    np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-12)


def test_relative_pose_covariance_finite_differences_and_monte_carlo():
    """Σ_ab = Ad(T_b_marker) Σ Ad^T: the Jacobian of xi -> Log(T_ab^-1 T_ab(T_cam_marker Exp(xi)))
    by central differences, and the sample covariance of that map under Σ (quadratic model, 4 m)."""
    _, _, T_a_cam, T_b_marker, T_cam_marker = _detection_setup()
    cov_m = detection_covariance(UncertaintyModel.QUADRATIC, 4.0)
    T_a_b, cov_ab = relative_pose(T_a_cam, T_cam_marker, T_b_marker, cov_m)

    def residual(xi):
        return se3_log(se3_inv(T_a_b) @ (T_a_cam @ T_cam_marker @ se3_exp(xi) @ se3_inv(T_b_marker)))

    eps = 1e-6
    J = np.column_stack([(residual(eps * e) - residual(-eps * e)) / (2 * eps) for e in np.eye(6)])
    np.testing.assert_allclose(J, adjoint(T_b_marker), atol=1e-7)
    np.testing.assert_allclose(cov_ab, J @ cov_m @ J.T, rtol=1e-6, atol=1e-12)

    rng = np.random.default_rng(5)
    samples = rng.multivariate_normal(np.zeros(6), cov_m, size=4000)
    eta = np.array([residual(xi) for xi in samples])
    sample_cov = np.cov(eta.T)
    scale = np.sqrt(np.outer(np.diag(cov_ab), np.diag(cov_ab)))
    assert np.max(np.abs(sample_cov - cov_ab) / scale) < 0.1
    # the lever arm of the mast tag couples rotation into translation: not block diagonal
    assert np.max(np.abs(cov_ab[3:, :3]) / scale[3:, :3]) > 0.1


# --------------------------------------------------------------------------- input checks


def test_blank_images_give_no_detections():
    detector = MarkerDetector(K640, {i: 0.15 for i in range(20)})
    assert detector.detect(np.zeros((H, W), np.uint8)) == []
    assert detector.detect(np.full((H, W), 128, np.uint8)) == []
    assert detector.detect(cv2.resize(background(np.random.default_rng(6)), (W, H), interpolation=cv2.INTER_AREA)) == []


def test_unknown_ids_are_ignored():
    T = SYNTHETIC_POSES["tilted_about_x"]
    img = draw_tags(K640, [(5, 0.15, T), (9, 0.15, facing(0.2, 0.3, 0.0, [0.45, 0.2, 1.8]))], np.random.default_rng(7))
    assert [d.tag_id for d in MarkerDetector(K640, {5: 0.15, 9: 0.15}).detect(img)] == [5, 9]
    assert [d.tag_id for d in MarkerDetector(K640, {9: 0.15, 100: 0.1}).detect(img)] == [9]
    assert MarkerDetector(K640, {6: 0.15}).detect(img) == []


def test_bad_images_and_parameters_raise():
    detector = MarkerDetector(K640, {5: 0.15})
    with pytest.raises(MarkerException, match="uint8"):
        detector.detect(np.zeros((H, W), np.float32))
    with pytest.raises(MarkerException, match="uint8"):
        detector.detect(np.zeros((H, W), np.uint16))
    with pytest.raises(MarkerException, match="shape"):
        detector.detect(np.zeros((H, W, 4), np.uint8))
    with pytest.raises(MarkerException, match="shape"):
        detector.detect(np.zeros(W, np.uint8))
    with pytest.raises(MarkerException, match="numpy array"):
        detector.detect([[0, 0], [0, 0]])
    with pytest.raises(MarkerException, match="3x3"):
        MarkerDetector(np.eye(4), {5: 0.15})
    with pytest.raises(MarkerException, match="positive sizes"):
        MarkerDetector(K640, {5: 0.0})
    with pytest.raises(MarkerException, match="positive sizes"):
        MarkerDetector(K640, {"5": 0.15})
    with pytest.raises(MarkerException, match="unknown corner refinement"):
        MarkerDetector(K640, {5: 0.15}, corner_refinement="subpix")
    with pytest.raises(MarkerException, match="min_side_px"):
        MarkerDetector(K640, {5: 0.15}, min_side_px=-1.0)
