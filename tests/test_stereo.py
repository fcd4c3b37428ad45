"""slam.stereo: conventions, the error model (thesis eq. 5.2, 5.4) against Monte-Carlo
propagation of pixel noise, and SGBM depth on rendered textured terrain."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from slam.stereo import (
    StereoCalibration,
    StereoException,
    StereoMatcher,
    cut_far_points,
    depth_error,
    depth_to_points,
    depth_to_points_at,
    disparity_to_depth,
    distance_error,
    max_depth_for_error,
    point_error,
    triangulate,
)

# LRU narrow stereo (thesis 7.1: b = 9 cm, 50.6 deg) at 320x240
CAL = StereoCalibration(focal_px=160 / math.tan(math.radians(25.3)), cx=159.5, cy=119.5, baseline_m=0.09, width=320, height=240)


def project(points: np.ndarray, cal: StereoCalibration = CAL):
    """Exact image coordinates (u_l, v_l, u_r, v_r) of points in the left camera frame."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    f = cal.focal_px
    v = f * y / z + cal.cy
    return f * x / z + cal.cx, v, f * (x - cal.baseline_m) / z + cal.cx, v


def monte_carlo(points: np.ndarray, pixel_error: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Triangulated points (k, n, 3) from n noisy copies of each point's correspondence."""
    coords = project(points)
    noisy = [c[:, None] + pixel_error * rng.standard_normal((len(points), n)) for c in coords]
    return triangulate(*noisy, CAL)


# --------------------------------------------------------------------------- conventions


def test_calibration_from_intrinsics_roundtrip_and_checks():
    K = np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]])
    cal = StereoCalibration.from_intrinsics(K, 0.12, 640, 480)
    assert (cal.focal_px, cal.cx, cal.cy, cal.baseline_m) == (400.0, 319.5, 239.5, 0.12)
    np.testing.assert_array_equal(cal.K, K)
    assert cal.fb == pytest.approx(48.0)
    with pytest.raises(StereoException, match="square pixels"):
        StereoCalibration.from_intrinsics(np.diag([400.0, 410.0, 1.0]), 0.12, 640, 480)
    with pytest.raises(StereoException, match="positive"):
        StereoCalibration(400.0, 0, 0, 0.0, 640, 480)


def test_disparity_depth_points_roundtrip():
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 20.0, (CAL.height, CAL.width)).astype(np.float32)
    depth[5, 7] = np.nan
    disparity = CAL.fb / depth
    disparity[0, 0] = 0.0  # valid zero disparity: a point at infinity, not missing data
    back = disparity_to_depth(disparity, CAL)
    assert back.dtype == np.float32
    assert np.isnan(back[5, 7]) and back[0, 0] == np.inf
    ok = np.isfinite(back)
    np.testing.assert_allclose(back[ok], depth[ok], rtol=1e-5)

    pts = depth_to_points(depth, CAL)
    assert pts.shape == (CAL.height, CAL.width, 3)
    assert np.all(np.isnan(pts[5, 7]))
    u, v, _, _ = project(pts[ok].astype(float))
    vv, uu = np.nonzero(ok)
    np.testing.assert_allclose(u, uu, atol=1e-3)  # OpenCV frame: x right, y down, z forward
    np.testing.assert_allclose(v, vv, atol=1e-3)


def test_points_of_a_mask_equal_the_masked_image_of_points():
    """``depth_to_points_at`` back-projects only the masked pixels, to the same values bit
    for bit (float32 and float64 depths, NaN and inf kept); a mask of another shape is refused."""
    rng = np.random.default_rng(3)
    for dtype in (np.float32, np.float64):
        depth = rng.uniform(0.3, 9.0, (CAL.height, CAL.width)).astype(dtype)
        depth[rng.random(depth.shape) < 0.1] = np.nan
        depth[rng.random(depth.shape) < 0.05] = np.inf
        mask = rng.random(depth.shape) < 0.4
        at = depth_to_points_at(depth, mask, CAL)
        assert at.dtype == dtype and at.shape == (mask.sum(), 3)
        np.testing.assert_array_equal(at, depth_to_points(depth, CAL)[mask])
    with pytest.raises(StereoException):
        depth_to_points_at(depth, mask[:, 1:], CAL)


def test_sgbm_recovers_a_known_shift():
    """Right image = left image shifted left by d px: a fronto-parallel plane at fb/d."""
    rng = np.random.default_rng(1)
    d = 12
    big = cv2.GaussianBlur(rng.integers(0, 256, (CAL.height, CAL.width + d), dtype=np.uint8), (3, 3), 0.7)
    left, right = big[:, :-d], big[:, d:]  # big[:, k] is at u_l = k in the left image, u_r = k - d in the right
    matcher = StereoMatcher(CAL)
    disp = matcher.disparity(np.ascontiguousarray(left), np.ascontiguousarray(right))
    inner = disp[10:-10, matcher.num_disparities + 10 : -10]
    assert np.mean(np.isfinite(inner)) > 0.95
    assert np.nanmedian(inner) == pytest.approx(d, abs=0.1)
    depth = matcher.depth(np.dstack([left] * 3), np.dstack([right] * 3))  # RGB input is matched as grey
    assert np.nanmedian(depth[10:-10, matcher.num_disparities + 10 : -10]) == pytest.approx(CAL.fb / d, rel=0.01)
    with pytest.raises(StereoException, match="expected"):
        matcher.disparity(left[:100], right[:100])


def test_matcher_disparity_range_follows_min_depth():
    assert StereoMatcher(CAL, min_depth_m=0.5).num_disparities == 64  # fb = 30.4 px m -> 61 px
    assert StereoMatcher(CAL, min_depth_m=1.0).num_disparities == 32
    with pytest.raises(StereoException, match="disparities"):
        StereoMatcher(CAL, min_depth_m=0.05)


# --------------------------------------------------------------------------- error model


POINTS = np.array(
    [
        [0.0, 0.0, 2.0],
        [0.5, 0.3, 1.5],
        [-0.8, 0.6, 3.0],
        [1.2, -0.4, 4.0],
        [0.05, 0.9, 2.5],
    ]
)


def test_eq_5_2_matches_monte_carlo_in_the_linear_regime():
    """First-order propagation is exact for small pixel noise: 1 % agreement."""
    rng = np.random.default_rng(2)
    pixel_error = 0.02
    mc = monte_carlo(POINTS, pixel_error, 100_000, rng)
    np.testing.assert_allclose(mc.std(axis=1), point_error(POINTS, CAL, pixel_error), rtol=0.015)


def test_eq_5_2c_depth_error_at_thesis_pixel_error():
    """Δp = 0.5 px (thesis): Δp_z of eq. 5.2c against Monte-Carlo within 4 % up to 3 m,
    and the quadratic growth with depth."""
    rng = np.random.default_rng(3)
    near = POINTS[POINTS[:, 2] <= 3.0]
    mc = monte_carlo(near, 0.5, 100_000, rng)
    np.testing.assert_allclose(mc[..., 2].std(axis=1), point_error(near, CAL)[:, 2], rtol=0.04)
    np.testing.assert_allclose(depth_error(near[:, 2], CAL), point_error(near, CAL)[:, 2])
    assert depth_error(4.0, CAL) == pytest.approx(4 * depth_error(2.0, CAL))


def test_eq_5_4_distance_error_matches_monte_carlo():
    """Δd of eq. 5.4 (with b for the printed t, and - (q_z - p_z) q_z in 5.4b) against
    Monte-Carlo; the form printed in the thesis is visibly off for some point pairs."""
    rng = np.random.default_rng(4)
    pixel_error = 0.02
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4), (1, 3)]
    p = POINTS[[i for i, _ in pairs]]
    q = POINTS[[j for _, j in pairs]]
    P = monte_carlo(p, pixel_error, 100_000, rng)
    Q = monte_carlo(q, pixel_error, 100_000, rng)
    mc = np.linalg.norm(P - Q, axis=-1).std(axis=1)
    model = distance_error(p, q, CAL, pixel_error)
    np.testing.assert_allclose(model, mc, rtol=0.015)

    b, w = CAL.baseline_m, q - p
    A_printed = (w[:, 0] * (b - q[:, 0]) - w[:, 1] * q[:, 1] + w[:, 2] * q[:, 2]) ** 2
    B = np.einsum("ij,ij->i", w, q) ** 2
    C = 0.5 * (b * w[:, 1]) ** 2
    D = (w[:, 0] * (b - p[:, 0]) - w[:, 1] * p[:, 1] - w[:, 2] * p[:, 2]) ** 2
    E = np.einsum("ij,ij->i", w, p) ** 2
    d = np.linalg.norm(w, axis=1)
    printed = pixel_error / (d * CAL.fb) * np.sqrt(q[:, 2] ** 2 * (A_printed + B + C) + p[:, 2] ** 2 * (C + D + E))
    assert np.max(np.abs(printed / mc - 1)) > 0.05

    assert np.isnan(distance_error(POINTS[0], POINTS[0], CAL))
    assert distance_error(POINTS[:2], POINTS[1:3], CAL).shape == (2,)


def test_far_point_cut_by_depth_error():
    cal = StereoCalibration(1083.0, 511.5, 253.5, 0.09, 1024, 508)  # LRU narrow at the FPGA's 1024 px
    z_max = max_depth_for_error(cal, 0.15)
    assert depth_error(z_max, cal) == pytest.approx(0.15)
    assert 4.0 < z_max < 5.0  # thesis 5.1.1: the narrow-angle rovers used up to about 5 m
    depth = np.array([[1.0, z_max - 1e-3, z_max + 1e-3, np.inf, np.nan]])
    cut = cut_far_points(depth, cal, 0.15)
    assert cut[0, 0] == 1.0 and cut[0, 1] == pytest.approx(z_max - 1e-3)
    assert np.all(np.isnan(cut[0, 2:]))
    assert depth[0, 3] == np.inf  # input untouched


# --------------------------------------------------------------------------- SGBM on rendered terrain


def _render(scene) -> tuple:
    """One rendered stereo pair with true depth of a ``stereo_scenes`` scene (model, data, rig,
    camera) and the rig's calibration."""
    from sim.world.sensors import StereoRenderer

    model, data, rig, camera = scene
    renderer = StereoRenderer(model, rig, camera)
    try:
        frame = renderer.render(data, with_depth=True)
    finally:
        renderer.close()
    return frame, StereoCalibration.from_intrinsics(rig.intrinsics, rig.baseline_m, camera.width, camera.height)


def _median_depth_error(scene_builder, width: int, height: int) -> tuple[float, float]:
    frame, cal = _render(scene_builder(width, height))
    est = StereoMatcher(cal).depth(frame.left, frame.right)
    gt = frame.depth
    in_range = (gt >= 2.0) & (gt <= 6.0)
    valid = in_range & np.isfinite(est)
    rel = np.abs(est[valid] - gt[valid]) / gt[valid]
    return float(np.median(rel)), float(valid.sum() / in_range.sum())


@pytest.mark.parametrize("width,height", [(320, 240), (640, 480)])
def test_sgbm_depth_on_rendered_heightfield(width, height):
    from stereo_scenes import textured_heightfield_scene

    median, valid_share = _median_depth_error(textured_heightfield_scene, width, height)
    assert median < 0.05
    assert valid_share > 0.6


def test_sgbm_depth_on_procedural_terrain():
    """The same check on sim.world.terrain's heightfield and regolith albedo."""
    from stereo_scenes import procedural_terrain_scene

    median, valid_share = _median_depth_error(procedural_terrain_scene, 320, 240)
    assert median < 0.05
    assert valid_share > 0.6


def test_sgbm_borders_outside_the_valid_region_are_invalid():
    """SGBM writes values where OpenCV's valid disparity region ends (cv2.getValidDisparityROI);
    on rendered terrain the last two columns held 3-12 % of depths more than 0.1 m off within
    the mapping range. They are NaN now, and so is the region's outermost pixel (SGBM's
    prefilter reads replicated border pixels there); the outermost valid columns are as good
    as the rest."""
    from stereo_scenes import procedural_terrain_scene

    frame, cal = _render(procedural_terrain_scene(320, 240))
    matcher = StereoMatcher(cal)
    est = matcher.depth(frame.left, frame.right)
    assert not np.isfinite(est[~matcher.valid_region]).any()
    x, y, w, h = cv2.getValidDisparityROI((0, 0, 320, 240), (0, 0, 320, 240), 0, matcher.num_disparities, matcher.block_size)
    roi = np.zeros_like(matcher.valid_region)
    roi[y : y + h, x : x + w] = True
    assert (matcher.valid_region == cv2.erode(roi.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0).astype(bool)).all()
    cols = np.flatnonzero(matcher.valid_region.any(axis=0))
    assert cols[0] >= matcher.num_disparities and cols[-1] < 320 - 1
    mapped = frame.depth < max_depth_for_error(cal, 0.15)
    outer = np.zeros_like(mapped)
    outer[:, cols[-4:]] = True
    for region in (outer, matcher.valid_region & ~outer):
        valid = region & mapped & np.isfinite(est)
        assert valid.sum() > 100
        assert np.mean(np.abs(est[valid] - frame.depth[valid]) > 0.1) < 0.01


def test_noise_in_a_textureless_sky_gives_no_depth_in_the_mapping_range():
    """With the camera's shot and read noise (sim.world.imaging, the Guppy PRO's) a bright
    sky has a mean gradient of about 1 grey level; SGBM matched the noise (18 % of this
    sky's pixels kept a depth, 13 of them within the 2.5 m mapping range, where each is
    an obstacle 1 m above the ground). The texture test measures the gradient after a
    small blur and the speckle filter removes what the masks leave in islands: no sky
    pixel keeps a depth in range, and the ground keeps nearly all of its own."""
    from stereo_scenes import procedural_terrain_scene

    from sim.scenario import CameraConfig
    from sim.world.imaging import GUPPY_PRO_F125B, CameraImaging

    frame, cal = _render(procedural_terrain_scene(320, 240, pitch_deg=17.0, preset="etna"))
    imaging = CameraImaging(GUPPY_PRO_F125B, 320, 240, cal.focal_px, np.random.default_rng(1), flat_field=CameraConfig().flat_field)
    for _ in range(20):  # let the auto exposure settle on the scene
        left, right = imaging.expose(frame.left, frame.right)
    matcher = StereoMatcher(cal)
    est = matcher.depth(left, right)
    in_range = np.isfinite(cut_far_points(est, cal, 0.15))
    sky = matcher.valid_region & ~(frame.depth < 1000.0)
    ground = matcher.valid_region & (frame.depth < max_depth_for_error(cal, 0.15))
    assert sky.sum() > 5000 and ground.sum() > 1000
    assert not (in_range & sky).any()
    assert np.mean(np.isfinite(est[ground])) > 0.9
