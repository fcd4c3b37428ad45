"""The learned marker uncertainty model (thesis 6.2.3, eq. 6.9): corner perturbations,
the lookup table's interpolation and post-processing, that a committed table is what
its command builds, and that the predicted sigmas cover rendered detections' errors."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from sim.tools.marker_lut import LUT_DIR, TAG_ID, MarkerLutError, _TagScene, cell_errors, load_tables, lut_path
from slam.agent import Agent, AgentParams
from slam.marker_uncertainty import (
    MAX_ROTATION_SIGMA_RAD,
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


def test_postprocess_median_then_fills_rows_near_and_far_rows():
    raw = np.full((5, 5, 6), np.nan)
    raw[1, :3] = [[1.0] * 6, [2.0] * 6, [9.0] * 6]  # row 1 detected up to angle 2
    raw[2, :2] = [[3.0] * 6, [4.0] * 6]  # row 2 up to angle 1; row 0 (too near) and rows 3-4 never
    out = postprocess(raw)[..., 0]
    # medians over the detected cells of each 3x3 window
    assert out[1, 0] == pytest.approx(np.median([1, 2, 3, 4]))
    assert out[1, 2] == pytest.approx(np.median([2, 9, 4]))
    assert out[2, 1] == pytest.approx(np.median([1, 2, 9, 3, 4]))
    # past the last detected angle, each row keeps its border value
    np.testing.assert_allclose(out[1], [2.5, 3.0, 4.0, 4.0, 4.0])
    np.testing.assert_allclose(out[2], [2.5, 3.0, 3.0, 3.0, 3.0])
    # nearer than any detection: the first detected row (the border value)
    np.testing.assert_allclose(out[0], out[1])
    # rows beyond detection: per column the max of the last 10 % (here: the last row) before them
    np.testing.assert_allclose(out[3], out[2])
    np.testing.assert_allclose(out[4], out[2])


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
        np.testing.assert_allclose(again, table.raw[i, j], rtol=1e-12, atol=0)  # to the last bits, which library versions move
    np.testing.assert_array_equal(postprocess(table.raw), table.errors)
    assert LUT_DIR.joinpath("README.md").exists()


def test_predicted_sigmas_cover_rendered_detection_errors(scene):
    """lut_online takes maximum errors as sigmas (6.2.3), so it is conservative: at 20
    views off the grid (1-5 m, 0-60 deg, turned in the tag's plane by any angle, so the
    tilt axis is not the table's) at least 85 % of the rotation and 95 % of the
    translation components are within 1 sigma and all within 3 sigma (measured with this
    seed: 92.6 % and 100 % within 1 sigma, 18 of 20 detected). The table alone misses mirrored IPPE solutions
    (it was built with them compensated); the online step catches them."""
    table = MarkerErrorTable.load(lut_path(*CAMERA, SIZE_M))
    detector = MarkerDetector(scene.K, {TAG_ID: SIZE_M})
    rng = np.random.default_rng(7)
    ratios, lut_ratios = [], []
    for _ in range(20):
        d, a, roll = rng.uniform(1.0, 5.0), math.radians(rng.uniform(0, 60)), rng.uniform(-math.pi, math.pi)
        grey, T_true = scene.render(d, a, table.blur_sigma_px, roll)
        found = detector.detect(grey)
        if not found:
            continue
        error = pose_error(found[0].T_cam_marker, T_true)
        ratios.append(error / detection_sigmas(UncertaintyModel.LUT_ONLINE, found[0], table=table, detector=detector))
        lut_ratios.append(error / detection_sigmas(UncertaintyModel.LUT, found[0], table=table))
    ratios, lut_ratios = np.asarray(ratios), np.asarray(lut_ratios)
    assert len(ratios) >= 15
    assert np.mean(ratios[:, :3] <= 1) >= 0.85 and np.all(ratios[:, :3] <= 3)
    assert np.mean(ratios[:, 3:] <= 1) >= 0.95 and np.all(ratios[:, 3:] <= 3)
    assert lut_ratios[:, :3].max() > 3  # a mirrored solution, beyond the table's sigma


def test_online_sigma_flags_the_ambiguous_far_frontal_view(scene):
    detector = MarkerDetector(scene.K, {TAG_ID: SIZE_M})
    far = detector.detect(scene.render(3.0, 0.0, 0.6)[0])[0]
    near = detector.detect(scene.render(0.8, math.radians(35), 0.6)[0])[0]
    assert online_errors(detector, far)[:2].max() > 5 * online_errors(detector, near)[:2].max()


def test_learned_models_need_their_inputs():
    with pytest.raises(MarkerException, match="lookup table"):
        detection_sigmas(UncertaintyModel.LUT, None)
    with pytest.raises(MarkerException, match="needs the detector"):
        detection_sigmas(UncertaintyModel.ONLINE, None)
    with pytest.raises(MarkerException, match="needs the detection"):
        detection_covariance("lut_online", 2.0)


def test_agent_rejects_detections_with_a_rotational_sigma_above_75_deg(scene):
    """Thesis 8.1.3: a steep view of a small tag (51 deg, 2 m: its short side 16 px) is
    estimated well (0.1 deg), but 16 of the 256 half-pixel corner shifts flip it to the
    mirrored solution (104 deg off), so the online sigma exceeds 75 deg and the agent
    drops it; a near tilted view gets the diagonal of its squared sigmas."""
    table = MarkerErrorTable.load(lut_path(*CAMERA, SIZE_M))
    params = AgentParams(uncertainty=UncertaintyModel.LUT_ONLINE, marker_tables={("head", SIZE_M): table})
    agent = Agent("a", ["a"], [], None, params=params)  # the covariance needs no estimator
    detector = MarkerDetector(scene.K, {TAG_ID: SIZE_M})
    steep = detector.detect(scene.render(1.98, math.radians(50.71), 0.6, math.radians(87.1))[0])[0]
    assert online_errors(detector, steep)[:3].max() > MAX_ROTATION_SIGMA_RAD
    assert agent._marker_covariance("head", steep, SIZE_M, detector) is None
    near = detector.detect(scene.render(0.8, math.radians(35), 0.6)[0])[0]
    cov = agent._marker_covariance("head", near, SIZE_M, detector)
    sigma = detection_sigmas(UncertaintyModel.LUT_ONLINE, near, table=table, detector=detector)
    np.testing.assert_allclose(cov, np.diag(sigma**2))
    assert sigma[0] == sigma[1] and sigma[3] == sigma[4]  # the in-plane axes share the larger sigma


def test_a_missing_table_names_the_file_and_the_command():
    rig = SimpleNamespace(name="head", width=321, height=240, focal_px=300.0)
    with pytest.raises(MarkerLutError, match=r"lut_321x240_f300.0_s0.150.npz.*marsyard marker-lut"):
        load_tables([rig], {0.15})
