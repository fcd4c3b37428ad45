"""slam.stereo_offset: fusing the VO's per-keyframe measurements of a rig's disparity
offsets; slam.stereo: the offsets' model and their removal from a depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam.lie import so3_exp
from slam.stereo import (
    StereoCalibration,
    StereoException,
    disparity_offset,
    disparity_offset_sensitivity,
    remove_disparity_offset,
    row_offset_sensitivity,
)
from slam.stereo_offset import DisparityOffsetEstimate, StereoOffsetException

TRUTH = np.array([0.1, 0.3, -0.2])
CALIB = StereoCalibration(focal_px=300.0, cx=159.5, cy=119.5, baseline_m=0.1, width=320, height=240)


def random_information(rng: np.random.Generator, scale: float) -> np.ndarray:
    A = rng.standard_normal((3, 3))
    return scale * (A @ A.T + 0.1 * np.eye(3))


def test_measurements_of_a_constant_converge_with_the_stated_uncertainty():
    """Independent measurements of ``c``, one per keyframe with its own 3x3 information:
    the fused estimate's error over many runs is unbiased (but for the prior's small pull)
    and scatters as its covariance says (mean NEES 3)."""
    rng = np.random.default_rng(0)
    errors, nees = [], []
    for _ in range(300):
        est = DisparityOffsetEstimate(0.25)
        for k in range(40):
            info = random_information(rng, 30.0)
            est.add(k, TRUTH + np.linalg.cholesky(np.linalg.inv(info)) @ rng.standard_normal(3), info)
        e = est.coefficients - TRUTH
        errors.append(e)
        nees.append(e @ np.linalg.solve(est.covariance, e))
    assert np.all(np.abs(np.mean(errors, axis=0)) < 0.01)
    assert np.mean(nees) == pytest.approx(3.0, rel=0.15)
    assert est.value == est.coefficients[1] and est.std == pytest.approx(math.sqrt(est.covariance[1, 1]))


def test_one_measurement_per_keyframe_the_most_informative():
    est = DisparityOffsetEstimate(0.25)
    assert (est.value, est.std, est.keyframes) == (0.0, 0.25, 0)
    assert est.add(7, [0.0, 0.2, 0.0], 50.0 * np.eye(3))
    first = est.coefficients
    assert not est.add(7, [0.0, 0.4, 0.0], 40.0 * np.eye(3))  # less informative than the keyframe's first
    np.testing.assert_array_equal(est.coefficients, first)
    assert est.add(7, [0.0, 0.1, 0.0], 80.0 * np.eye(3))  # replaces it, not added to it
    assert est.keyframes == 1
    assert est.value == pytest.approx(0.1 * 80 / (80 + 16))
    assert est.std == pytest.approx(1 / np.sqrt(96))


def test_a_singular_measurement_informs_only_what_it_sees():
    """A measurement blind to the pitch (zero information on it) moves only the other two."""
    est = DisparityOffsetEstimate(0.25)
    assert est.add(0, [5.0, 0.3, -0.2], np.diag([0.0, 400.0, 400.0]))
    c = est.coefficients
    assert c[0] == 0.0 and c[1:] == pytest.approx([0.3 * 400 / 416, -0.2 * 400 / 416])
    assert est.report()["coefficients_std_px"][0] == pytest.approx(0.25)


def test_outliers_are_gated():
    est = DisparityOffsetEstimate(0.25)
    for k in range(20):
        est.add(k, TRUTH, 400.0 * np.eye(3))
    assert not est.add(99, TRUTH + [0.0, 3.0, 0.0], 400.0 * np.eye(3))  # a mismatched keyframe
    assert est.rejected == 1 and est.coefficients == pytest.approx(TRUTH, abs=0.001)
    assert est.add(100, TRUTH + [0.0, 0.05, 0.0], 400.0 * np.eye(3))  # within the gate
    yaw_only = np.diag([0.0, 400.0, 0.0])  # one degree of freedom: gated at its own 3 sigma
    assert not est.add(104, TRUTH + [0.0, 0.17, 0.0], yaw_only) and est.add(105, TRUTH + [0.0, 0.13, 0.0], yaw_only)
    assert not est.add(101, [np.nan, 0.2, 0.0], 10.0 * np.eye(3)) and not est.add(102, TRUTH, np.zeros((3, 3)))
    assert not est.add(103, TRUTH, -np.eye(3))  # not an information
    with pytest.raises(StereoOffsetException):
        est.add(106, 0.2, 10.0)


def test_bad_parameters():
    for prior, gate in ((0.0, 3.0), (0.25, 0.0), (-1.0, 3.0)):
        with pytest.raises(StereoOffsetException):
            DisparityOffsetEstimate(prior, gate)


def test_sensitivity_is_the_rotated_cameras_disparity_change():
    """Points seen by a right camera turned by 0.1 deg about each axis (exact projection):
    their disparities change by ``s · f θ`` and their right rows move by ``r · f θ``
    (:func:`row_offset_sensitivity`), each to within 1 % of the largest change, over the
    whole image and a range of depths."""
    rng = np.random.default_rng(2)
    f, b = CALIB.focal_px, CALIB.baseline_m
    u, v, z = rng.uniform(0, 319, 200), rng.uniform(0, 239, 200), rng.uniform(1.0, 20.0, 200)
    X = np.stack([(u - CALIB.cx) * z / f, (v - CALIB.cy) * z / f, z], axis=1)
    d_true = f * b / z
    for axis in range(3):
        theta = np.zeros(3)
        theta[axis] = math.radians(0.1)
        P = (X - [b, 0.0, 0.0]) @ so3_exp(theta)
        d = u - (f * P[:, 0] / P[:, 2] + CALIB.cx)
        predicted = disparity_offset_sensitivity(u, v, d, CALIB) @ (f * theta)
        np.testing.assert_allclose(d - d_true, predicted, atol=0.01 * np.abs(predicted).max())
        rows = f * P[:, 1] / P[:, 2] + CALIB.cy - v
        predicted_rows = row_offset_sensitivity(u, v, d, CALIB) @ (f * theta)
        np.testing.assert_allclose(rows, predicted_rows, atol=0.01 * np.abs(predicted_rows).max())
    c = np.array([0.3, -0.2, 0.5])  # the offset written out term by term is the same contraction
    np.testing.assert_allclose(disparity_offset(u, v, d_true, CALIB, c), disparity_offset_sensitivity(u, v, d_true, CALIB) @ c,
                               rtol=1e-12, atol=1e-12)


def test_removing_the_offsets_from_a_depth():
    """A yaw offset of 0.5 px: a pixel whose right column is at the image centre gets the
    constant model's correction, ``z' = f b / (f b / z - 0.5)``; at the sides it is 1 + x^2
    times larger. Images keep their dtype; points take their pixels."""
    depth = np.array([[1.0, 3.0, np.nan, np.inf, 30.0, 60.0]], dtype=np.float32)
    grid = np.zeros((240, 320), dtype=np.float32)
    c = [0.0, 0.5, 0.0]
    uv = np.array([[CALIB.cx + 30 / z if np.isfinite(z) else CALIB.cx, CALIB.cy] for z in depth[0]])  # right column at cx
    out = remove_disparity_offset(depth[0], CALIB, c, uv)
    np.testing.assert_allclose(out[:2], [30 / 29.5, 30 / 9.5], rtol=1e-6)  # d = 30 / z, less 0.5 px
    assert np.isnan(out[2]) and out[3] == np.inf  # 0 - 0.5 px: no finite depth
    assert out[4] == pytest.approx(60.0, rel=1e-5) and out[5] == np.inf  # 1 px less 0.5 px; 0.5 px less 0.5 px
    grid[:] = 3.0
    image = remove_disparity_offset(grid, CALIB, c)
    assert image.dtype == np.float32 and image.shape == grid.shape
    x = (np.arange(320) - 10.0 - CALIB.cx) / CALIB.focal_px  # right columns: d = 10 px
    np.testing.assert_allclose(image[120], 30 / (10 - 0.5 * (1 + x * x)), rtol=1e-5)
    assert remove_disparity_offset(grid, CALIB, [0.0, 0.0, 0.0]) is grid
    with pytest.raises(StereoException):
        remove_disparity_offset(grid, CALIB, 0.5)
    with pytest.raises(StereoException):
        remove_disparity_offset(depth[0], CALIB, c)  # points need their pixels
