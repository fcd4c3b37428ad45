"""slam.stereo_offset: fusing the VO's per-keyframe measurements of a rig's disparity offset."""

from __future__ import annotations

import numpy as np
import pytest

from slam.stereo import StereoCalibration, remove_disparity_offset
from slam.stereo_offset import DisparityOffsetEstimate, StereoOffsetException


def test_measurements_of_a_constant_converge_with_the_stated_uncertainty():
    """Independent measurements of 0.3 px, one per keyframe with its own information: the
    fused estimate is their weighted mean with the prior, and its error over many runs
    scatters as ``std`` says."""
    rng = np.random.default_rng(0)
    errors, stds = [], []
    for _ in range(300):
        est = DisparityOffsetEstimate(0.25)
        for k in range(40):
            info = rng.uniform(20, 200)
            est.add(k, 0.3 + rng.standard_normal() / np.sqrt(info), info)
        errors.append(est.value - 0.3)
        stds.append(est.std)
    assert abs(np.mean(errors)) < 0.003  # the prior's pull towards zero is below 0.4 % here
    assert np.std(errors) == pytest.approx(np.mean(stds), rel=0.15)


def test_one_measurement_per_keyframe_the_most_informative():
    est = DisparityOffsetEstimate(0.25)
    assert (est.value, est.std, est.keyframes) == (0.0, 0.25, 0)
    assert est.add(7, 0.2, 50.0)
    first = est.value
    assert not est.add(7, 0.4, 40.0)  # less informative than the keyframe's first
    assert est.value == first
    assert est.add(7, 0.1, 80.0)  # replaces it, not added to it
    assert est.keyframes == 1
    assert est.value == pytest.approx(0.1 * 80 / (80 + 16))
    assert est.std == pytest.approx(1 / np.sqrt(96))


def test_outliers_are_gated():
    est = DisparityOffsetEstimate(0.25)
    for k in range(20):
        est.add(k, 0.2, 400.0)
    assert not est.add(99, 3.0, 400.0)  # a mismatched keyframe
    assert est.rejected == 1 and est.value == pytest.approx(0.2, abs=0.001)
    assert not est.add(100, np.nan, 10.0) and not est.add(101, 0.2, 0.0)


def test_bad_parameters():
    for prior, gate in ((0.0, 3.0), (0.25, 0.0), (-1.0, 3.0)):
        with pytest.raises(StereoOffsetException):
            DisparityOffsetEstimate(prior, gate)


def test_removing_the_offset_from_a_depth():
    calib = StereoCalibration(focal_px=300.0, cx=159.5, cy=119.5, baseline_m=0.1, width=320, height=240)
    depth = np.array([[1.0, 3.0, np.nan, np.inf, 30.0, 60.0]], dtype=np.float32)
    out = remove_disparity_offset(depth, calib, 0.5)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[0, :2], [30 / 29.5, 30 / 9.5], rtol=1e-6)  # d = 30 / z, less 0.5 px
    assert np.isnan(out[0, 2]) and out[0, 3] == np.inf  # 0 - 0.5 px: no finite depth
    assert out[0, 4] == pytest.approx(60.0) and out[0, 5] == np.inf  # 1 px less 0.5 px; 0.5 px less 0.5 px
    assert remove_disparity_offset(depth, calib, 0.0) is depth
