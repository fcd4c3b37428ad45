"""The learned marker uncertainty model (thesis 6.2.3, eq. 6.9): corner perturbations,
the lookup table's interpolation and post-processing, that a committed table is what
its command builds, and that the predicted sigmas cover rendered detections' errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.marker_lut import LUT_DIR, TAG_ID, _TagScene, cell_errors, lut_path
from slam.marker_uncertainty import (
    MarkerErrorTable,
    corner_perturbations,
    detection_sigmas,
    online_errors,
    pose_error,
    postprocess,
)
from slam.markers import MarkerDetector, MarkerException, UncertaintyModel, detection_covariance

# The LRU head (320x240, 50.6 deg: f = 338.5 px) and its 15 cm mast tags: built by
# `marsyard marker-lut scenarios/etna_two_rovers.yaml`.
CAMERA = (320, 240, 338.5)
SIZE_M = 0.15


def test_eq_6_9_gives_256_distinct_corner_sets_each_coordinate_moved_by_dp():
    corners = np.array([[10.0, 20.0], [40.0, 21.0], [41.0, 50.0], [9.0, 49.0]])
    sets = corner_perturbations(corners, 0.5)
    assert sets.shape == (256, 4, 2)
    assert len({s.tobytes() for s in sets}) == 256
    np.testing.assert_array_equal(np.abs(sets - corners), 0.5)


def _synthetic_table(errors: np.ndarray) -> MarkerErrorTable:
    d, a = np.array([1.0, 2.0, 4.0]), np.radians([0.0, 30.0, 60.0])
    return MarkerErrorTable(d, a, errors, errors, 320, 240, 300.0, 0.1, 0.5, 0.6)


def test_bilinear_lookup_is_exact_on_the_grid_linear_between_and_clamped():
    d, a = np.meshgrid([1.0, 2.0, 4.0], [0.0, 30.0, 60.0], indexing="ij")
    errors = np.stack([d + 0.1 * a] * 6, axis=-1)  # bilinear in (distance, degrees)
    table = _synthetic_table(errors)
    assert table.lookup(2.0, math.radians(30))[0] == pytest.approx(5.0)
    assert table.lookup(3.0, math.radians(45))[0] == pytest.approx(3.0 + 4.5)
    assert table.lookup(10.0, math.radians(80))[0] == pytest.approx(4.0 + 6.0)  # clamped to the corner


def test_postprocess_median_then_fills_rows_and_far_rows():
    raw = np.full((4, 5, 6), np.nan)
    raw[0, :3] = [[1.0] * 6, [2.0] * 6, [9.0] * 6]  # row 0 detected up to angle 2
    raw[1, :2] = [[3.0] * 6, [4.0] * 6]  # row 1 up to angle 1; rows 2-3 never
    out = postprocess(raw)[..., 0]
    # medians over the detected cells of each 3x3 window
    assert out[0, 0] == pytest.approx(np.median([1, 2, 3, 4]))
    assert out[0, 2] == pytest.approx(np.median([2, 9, 4]))
    assert out[1, 1] == pytest.approx(np.median([1, 2, 9, 3, 4]))
    # past the last detected angle, each row keeps its border value
    np.testing.assert_allclose(out[0, 3:], out[0, 2])
    np.testing.assert_allclose(out[1, 2:], out[1, 1])
    # rows without detections: per column the max of the last 10 % (here: the last row) above
    np.testing.assert_allclose(out[2], out[1])
    np.testing.assert_allclose(out[3], out[1])


@pytest.fixture(scope="module")
def scene():
    s = _TagScene(*CAMERA, SIZE_M)
    yield s
    s.close()


def test_committed_table_regenerates_identically(scene):
    path = lut_path(*CAMERA, SIZE_M)
    assert path.exists(), f"{path} missing: marsyard marker-lut scenarios/etna_two_rovers.yaml"
    table = MarkerErrorTable.load(path)
    detector = MarkerDetector(scene.K, {TAG_ID: SIZE_M})
    valid = np.argwhere(np.isfinite(table.raw[..., 0]))
    for i, j in (valid[0], valid[len(valid) // 2], valid[-1]):
        again = cell_errors(scene, detector, float(table.distances_m[i]), float(table.angles_rad[j]), table.dp_px, table.blur_sigma_px)
        np.testing.assert_array_equal(again, table.raw[i, j])
    np.testing.assert_array_equal(postprocess(table.raw), table.errors)
    assert LUT_DIR.joinpath("README.md").exists()


def test_predicted_sigmas_cover_rendered_detection_errors(scene):
    """lut_online takes maximum errors as sigmas (6.2.3), so it is conservative: at views
    off the grid (1-3.5 m, 0-55 deg) every component's error is within 3 sigma for at
    least 95 % of detections and within 1 sigma for at least 68 %."""
    table = MarkerErrorTable.load(lut_path(*CAMERA, SIZE_M))
    detector = MarkerDetector(scene.K, {TAG_ID: SIZE_M})
    rng = np.random.default_rng(7)
    ratios = []
    for _ in range(20):
        d, a = rng.uniform(1.0, 3.5), math.radians(rng.uniform(0, 55))
        grey, T_true = scene.render(d, a, table.blur_sigma_px)
        found = detector.detect(grey)
        if not found:
            continue
        sigma = detection_sigmas(UncertaintyModel.LUT_ONLINE, found[0], table=table, detector=detector)
        ratios.append(pose_error(found[0].T_cam_marker, T_true) / sigma)
    ratios = np.asarray(ratios)
    assert len(ratios) >= 15
    assert np.mean(ratios <= 3) >= 0.95
    assert np.mean(ratios <= 1) >= 0.68


def test_online_sigma_flags_the_ambiguous_far_frontal_view(scene):
    detector = MarkerDetector(scene.K, {TAG_ID: SIZE_M})
    far = detector.detect(scene.render(3.0, 0.0, 0.6)[0])[0]
    near = detector.detect(scene.render(0.8, math.radians(35), 0.6)[0])[0]
    assert online_errors(detector, far)[:2].max() > 5 * online_errors(detector, near)[:2].max()


def test_learned_models_need_their_inputs():
    with pytest.raises(MarkerException, match="lookup table"):
        detection_sigmas(UncertaintyModel.LUT, None)
    with pytest.raises(MarkerException, match="needs the detection"):
        detection_covariance("lut_online", 2.0)
