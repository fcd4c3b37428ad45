"""slam.vo: keyframe stereo VO against MuJoCo ground truth, and its covariance.

Sequences (``tests/vo_sequences.py``, 5 Hz, 320x240, moon terrain):
- rover: LRU head camera (b = 9 cm, 50.6 deg), 17 s: 3 m straight, a 90 deg turn,
  2.5 m straight, about 4.9 m of camera path;
- hexacopter: ARDEA's downward pair (b = 12 cm, 80 deg, 60 deg below the horizon) at
  2 m, 10 s of flight with a 47 deg heading change, about 6 m of camera path.

Bounds, for the VO alone (deltas chained through the keyframes, no filter):
- translation drift below 0.75 % of the distance travelled (measured 0.09-0.28 %);
  the same VO with a baseline 25 % too long must exceed it;
- rotation drift below 0.2 deg per metre (measured 0.03-0.07 deg/m);
- covariance: with the thesis's 0.5 px (5.1.1) the mean NEES of the 6D deltas is
  below 6 (conservative; measured 0.3-0.7: rendered images have no calibration error,
  their KLT noise is about 0.15 px); with 0.15 px it lies within a factor 3 of 6
  (measured 3-7). On synthetic data with exactly the modelled noise it is 6 +- 10 %.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from vo_sequences import COPTER, ROVER, ROVER_SCAN, StereoSequence, render_sequence

from sim.world.calibration_errors import RigError
from slam.lie import pose_error, se3, so3_exp, so3_log
from slam.stereo import StereoCalibration, StereoMatcher, point_error, row_offset_sensitivity, triangulate
from slam.vo import (
    StereoVO,
    VoException,
    VoParams,
    delta_in_body_frame,
    disparity_bias_sensitivity,
    extrinsic_sensitivity,
    focal_scale_sensitivity,
    map_covariance,
    refine_pose,
    row_offset_measurement,
    stereo_point_covariance,
    two_view_disparity_offset,
)

MAX_DRIFT = 0.0075  # translation error per metre travelled
MAX_ROT_DEG_PER_M = 0.2
CAL = StereoCalibration(focal_px=160 / math.tan(math.radians(25.3)), cx=159.5, cy=119.5, baseline_m=0.09, width=320, height=240)


# --------------------------------------------------------------------------- sequences and evaluation


@pytest.fixture(scope="module")
def rover() -> StereoSequence:
    return render_sequence(ROVER, "head", duration_s=17)


@pytest.fixture(scope="module")
def rover_yawed() -> StereoSequence:
    """The rover sequence with the right camera turned by 0.05 deg about its y axis."""
    return render_sequence(ROVER, "head", duration_s=17, rig_error=RigError(R_right=so3_exp([0.0, math.radians(0.05), 0.0])))


@pytest.fixture(scope="module")
def rover_rolled() -> StereoSequence:
    """The rover sequence with the right camera turned by -0.08 deg about its z axis (a
    roll: -0.47 px) and 0.03 deg about its x axis (a pitch: 0.18 px), no yaw."""
    return render_sequence(ROVER, "head", duration_s=17, rig_error=RigError(R_right=so3_exp(np.radians([0.03, 0.0, -0.08]))))


@pytest.fixture(scope="module")
def rover_scan() -> StereoSequence:
    """The rover stops after 0.3 m and scans: its head slews to -180 deg at 1 rad/s
    (11.5 deg a frame), then sweeps back at 36 deg/s."""
    return render_sequence(ROVER_SCAN, "head", duration_s=6)


@pytest.fixture(scope="module")
def copter() -> StereoSequence:
    return render_sequence(COPTER, "down", duration_s=10, skip_s=3)


_RUNS: dict = {}


def vo_run(seq: StereoSequence, params: VoParams | None = None, *, dense: bool = False, calib: StereoCalibration | None = None):
    """The VO after the whole sequence, with its results (cached per sequence and settings)."""
    params = params or VoParams()
    key = (id(seq), params, dense, calib)
    if key not in _RUNS:
        calib = calib or seq.calib
        vo = StereoVO(calib, params)
        matcher = StereoMatcher(calib) if dense else None
        _RUNS[key] = vo, [vo.process(i, seq.t[i], seq.left[i], seq.right[i], matcher.depth(seq.left[i], seq.right[i]) if dense else None)
                          for i in range(len(seq))]
    return _RUNS[key]


def run_vo(seq: StereoSequence, params: VoParams | None = None, *, dense: bool = False, calib: StereoCalibration | None = None):
    return vo_run(seq, params, dense=dense, calib=calib)[1]


def evaluate(seq: StereoSequence, results) -> dict:
    """Chain the deltas through the keyframes; compare with the true camera poses."""
    T_vo = {0: np.eye(4)}
    nees, n_kf = [], 0
    for i, r in enumerate(results):
        if r.ok:
            T_vo[i] = T_vo[r.keyframe_id] @ r.T_kf_cur
            e = pose_error(r.T_kf_cur, seq.relative(r.keyframe_id, i))
            nees.append(e @ np.linalg.solve(r.cov, e))
        n_kf += r.new_keyframe
    last = len(seq) - 1
    e = pose_error(T_vo[last], seq.relative(0, last))
    path = seq.path_length(0, last)
    return {"drift": np.linalg.norm(T_vo[last][:3, 3] - seq.relative(0, last)[:3, 3]) / path,
            "rot_deg_per_m": math.degrees(np.linalg.norm(e[:3])) / path, "nees": float(np.mean(nees)),
            "keyframes": n_kf, "path": path, "failed": [(i, r.reason) for i, r in enumerate(results) if not r.ok]}


# --------------------------------------------------------------------------- error model and refinement


def test_point_covariance_diagonal_is_eq_5_2_and_matches_monte_carlo():
    rng = np.random.default_rng(0)
    X = np.stack([rng.uniform(-1, 1, 5), rng.uniform(-0.5, 1, 5), rng.uniform(1.5, 6, 5)], axis=1)
    cov = stereo_point_covariance(X, CAL, 0.5)
    np.testing.assert_allclose(np.sqrt(np.einsum("nii->ni", cov)), point_error(X, CAL, 0.5), rtol=1e-12)
    f, b = CAL.focal_px, CAL.baseline_m
    ul, v, ur = f * X[:, 0] / X[:, 2] + CAL.cx, f * X[:, 1] / X[:, 2] + CAL.cy, f * (X[:, 0] - b) / X[:, 2] + CAL.cx
    noisy = [c[:, None] + 0.05 * rng.standard_normal((5, 20000)) for c in (ul, v, ur, v)]  # small noise: first order holds
    mc = triangulate(*noisy, CAL)
    for k in range(5):
        np.testing.assert_allclose(np.cov(mc[k].T), stereo_point_covariance(X[k : k + 1], CAL, 0.05)[0], rtol=0.08,
                                   atol=1e-3 * np.abs(stereo_point_covariance(X[k : k + 1], CAL, 0.05)[0]).max())


def synthetic_scene(rng: np.random.Generator, n: int, z_max: float, T: np.ndarray):
    """``n`` points at depths 1.5-``z_max`` m spread over the keyframe's image, their pixels
    ``uv1`` in a current camera at ``T`` (noise-free) and their keyframe stereo
    observations ``(u_left, v, u_right)``."""
    uv0 = np.stack([rng.uniform(10, 310, n), rng.uniform(10, 230, n)], axis=1)
    z = rng.uniform(1.5, z_max, n)
    X = np.stack([(uv0[:, 0] - CAL.cx) * z / CAL.focal_px, (uv0[:, 1] - CAL.cy) * z / CAL.focal_px, z], axis=1)
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    uv1 = CAL.focal_px * Xc[:, :2] / Xc[:, 2:3] + [CAL.cx, CAL.cy]
    f, b = CAL.focal_px, CAL.baseline_m
    return X, uv1, (f * X[:, 0] / z + CAL.cx, f * X[:, 1] / z + CAL.cy, f * (X[:, 0] - b) / z + CAL.cx)


def test_refined_pose_covariance_is_consistent_on_synthetic_noise():
    """Pixel noise on the keyframe's stereo pair and on the current image, exactly as
    modelled: the weighted Gauss-Newton estimate's NEES averages 6."""
    rng = np.random.default_rng(1)
    n, sigma = 80, 0.5
    T = se3(so3_exp([0.02, 0.1, -0.01]), [0.1, -0.02, 0.4])
    _, uv1, (ul, v, ur) = synthetic_scene(rng, n, 5.0, T)
    nees = []
    for _ in range(300):
        Xn = triangulate(*(c + sigma * rng.standard_normal(n) for c in (ul, v, ur, v)), CAL)
        obs = uv1 + sigma * rng.standard_normal((n, 2))
        T_hat, H, _, _ = refine_pose(np.eye(4), Xn, stereo_point_covariance(Xn, CAL, sigma), obs, CAL.K, sigma, 8)
        e = pose_error(T_hat, T)
        nees.append(e @ H @ e)
    assert 5.4 < np.mean(nees) < 6.6, np.mean(nees)


def test_map_covariance_is_the_share_of_the_keyframe_points():
    """One keyframe's noisy points (drawn once) and many current images with fresh pixel
    noise: the refined poses scatter by the pixel share ``H^-1 - map_covariance`` around a
    pose the points moved; over many keyframes that pose itself scatters by
    ``map_covariance``. Both Monte-Carlo covariances agree with the split."""
    rng = np.random.default_rng(4)
    n, sigma = 80, 0.5
    T = se3(so3_exp([0.02, 0.1, -0.01]), [0.1, -0.02, 0.4])
    X, uv1, (ul, v, ur) = synthetic_scene(rng, n, 5.0, T)
    cov_X = stereo_point_covariance(X, CAL, sigma)
    _, H, _, _ = refine_pose(T, X, cov_X, uv1, CAL.K, sigma, 0)
    M = map_covariance(T, X, cov_X, uv1, CAL.K, sigma)
    pixel = np.linalg.inv(H) - M
    assert np.linalg.eigvalsh(M)[0] >= 0 and np.linalg.eigvalsh(pixel)[0] > 0
    assert 0.3 < np.trace(M[3:, 3:]) / np.trace(np.linalg.inv(H)[3:, 3:]) < 0.9  # a large share: the keyframe's depths
    keyframes, within = [], []
    for _ in range(150):
        Xn = triangulate(*(c + sigma * rng.standard_normal(n) for c in (ul, v, ur, v)), CAL)
        cov_n = stereo_point_covariance(Xn, CAL, sigma)
        poses = [refine_pose(T, Xn, cov_n, uv1 + sigma * rng.standard_normal((n, 2)), CAL.K, sigma, 8)[0] for _ in range(8)]
        errs = np.array([pose_error(T, P) for P in poses])
        keyframes.append(errs.mean(axis=0))
        within.append(errs - errs.mean(axis=0))
    within = np.concatenate(within) * np.sqrt(8 / 7)  # deviations from each keyframe's own mean
    for mc, model in ((np.cov(np.array(keyframes).T) - pixel / 8, M), (within.T @ within / len(within), pixel)):
        np.testing.assert_allclose(np.sqrt(np.diag(mc)), np.sqrt(np.diag(model)), rtol=0.25)


def test_delta_in_body_frame_moves_the_covariance_with_the_adjoint():
    rng = np.random.default_rng(2)

    def pose(r, p):
        return se3(so3_exp(r), p)

    T_cam = pose([0.05, -0.2, 0.02], [0.3, 0.05, 0.8])
    X_kf, X_cur = pose([-1.9, 0.1, 1.6], [0.1, 0.0, 1.0]), pose([-1.7, 0.0, 1.5], [0.1, 0.02, 1.0])  # head moved
    L = np.diag([0.01, 0.02, 0.01, 0.03, 0.01, 0.02]) @ rng.standard_normal((6, 6)) * 0.3
    cov = L @ L.T + 1e-6 * np.eye(6)
    T_b, cov_b = delta_in_body_frame(T_cam, cov, X_kf, X_cur)
    np.testing.assert_allclose(T_b, X_kf @ T_cam @ np.linalg.inv(X_cur), atol=1e-12)
    xi = rng.multivariate_normal(np.zeros(6), cov, 4000)
    errs = np.array([pose_error(T_b, X_kf @ T_cam @ pose(x[:3], x[3:]) @ np.linalg.inv(X_cur)) for x in xi])
    np.testing.assert_allclose(np.cov(errs.T), cov_b, atol=0.05 * np.abs(cov_b).max())


def test_disparity_bias_sensitivity_predicts_the_pose_shift():
    """A disparity offset common to all keyframe points (a residual rectification yaw)
    moves the refined pose by ``δ s``: checked against refining on points triangulated
    with the offset, noise-free, for offsets of 0.1 and 0.3 px."""
    rng = np.random.default_rng(3)
    n = 120
    T = se3(so3_exp([0.01, 0.15, -0.01]), [0.1, -0.02, 0.4])
    X, uv1, (ul, v, ur) = synthetic_scene(rng, n, 6.0, T)
    cov_X = stereo_point_covariance(X, CAL, 0.5)
    s = disparity_bias_sensitivity(T, X, cov_X, uv1, CAL.K, 0.5, CAL.fb)
    for delta in (0.1, 0.3):
        Xb = triangulate(ul, v, ur - delta, v, CAL)  # disparity d + delta
        T_hat, _, _, _ = refine_pose(T, Xb, stereo_point_covariance(Xb, CAL, 0.5), uv1, CAL.K, 0.5, 10)
        shift = pose_error(T, T_hat)
        assert np.linalg.norm(shift[3:]) > 2e-3 * delta / 0.1  # millimetres: worth a covariance term
        np.testing.assert_allclose(shift, delta * s, atol=0.08 * np.abs(delta * s).max())


def test_focal_scale_sensitivity_predicts_the_pose_shift():
    """Both cameras' true focal length ``f (1 + ε)`` where the stack believes ``f``: the
    keyframe's points triangulated and the current image's pixels projected with the true
    focal, refined with the believed one. The pose moves by ``ε s`` (noise-free, ε of 0.2
    and 0.5 %), mostly as a scale of the delta's rotation: a 10 deg turn reads about
    ``10 (1 + ε)`` deg."""
    rng = np.random.default_rng(4)
    n = 120
    T = se3(so3_exp([0.02, 0.17, -0.01]), [0.1, -0.02, 0.3])
    X, _, _ = synthetic_scene(rng, n, 6.0, T)
    cov_X = stereo_point_covariance(X, CAL, 0.5)
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    s = focal_scale_sensitivity(T, X, cov_X, CAL.focal_px * Xc[:, :2] / Xc[:, 2:3] + [CAL.cx, CAL.cy], CAL.K, 0.5)
    for eps in (0.002, 0.005):
        f_true = CAL.focal_px * (1.0 + eps)
        u0 = f_true * X[:, :2] / X[:, 2:3] + [CAL.cx, CAL.cy]
        ur = f_true * (X[:, 0] - CAL.baseline_m) / X[:, 2] + CAL.cx
        Xb = triangulate(u0[:, 0], u0[:, 1], ur, u0[:, 1], CAL)  # the believed focal: depths z / (1 + ε)
        uv1 = f_true * Xc[:, :2] / Xc[:, 2:3] + [CAL.cx, CAL.cy]
        T_hat, _, _, _ = refine_pose(T, Xb, stereo_point_covariance(Xb, CAL, 0.5), uv1, CAL.K, 0.5, 10)
        shift = pose_error(T, T_hat)
        np.testing.assert_allclose(shift, eps * s, atol=0.05 * np.abs(eps * s).max())
        turn = np.linalg.norm(so3_log(T[:3, :3]))
        assert np.linalg.norm(so3_log(T_hat[:3, :3])) / turn - 1.0 == pytest.approx(eps, rel=0.25)


def rotated_right_u(X: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The right-image columns of keyframe points ``X`` when the right camera is turned by
    ``theta`` (rotation vector, OpenCV axes, as ``RigError.R_right``): exact projection."""
    P = (X - [CAL.baseline_m, 0.0, 0.0]) @ so3_exp(theta)  # R^T P, row-wise
    return CAL.focal_px * P[:, 0] / P[:, 2] + CAL.cx


def test_two_view_disparity_offset_is_unbiased_with_the_information_it_states():
    """A keyframe whose right camera is turned (yaw, roll and pitch of 0.05-0.1 deg,
    projected exactly), a later image: the two-view adjustment recovers the three
    coefficients ``c = f θ`` without noise (to the first-order model's 1 %), and the yaw
    alone with roll and pitch held at their values; with the modelled noise (0.2 px per
    pixel coordinate, so 0.28 px of disparity) its mean over draws is ``c`` and its errors
    scatter as its information says (mean NEES 3)."""
    rng = np.random.default_rng(6)
    n, sigma = 120, 0.2
    T = se3(so3_exp([0.01, 0.05, -0.01]), [0.05, -0.02, 0.4])
    X, uv1, (ul, v, _) = synthetic_scene(rng, n, 4.0, T)
    uv0 = np.stack([ul, v], axis=1)
    for theta_deg in ([0.0, 0.0, 0.0], [0.0, -0.05, 0.0], [0.05, 0.1, -0.08]):
        theta = np.radians(theta_deg)
        c, info = two_view_disparity_offset(T, uv0, ul - rotated_right_u(X, theta), uv1, CAL, sigma)
        np.testing.assert_allclose(c, CAL.focal_px * theta, atol=0.01 * CAL.focal_px * np.abs(theta).max() + 1e-6)
        assert np.all(np.linalg.eigvalsh(info) > 0)
        if not theta[[0, 2]].any():  # the yaw alone, roll and pitch held at zero
            c, info = two_view_disparity_offset(T, uv0, ul - rotated_right_u(X, theta), uv1, CAL, sigma, axes=(1,))
            assert c[1] == pytest.approx(CAL.focal_px * theta[1], abs=0.01 * CAL.focal_px * abs(theta[1]) + 1e-6)
            assert c[0] == c[2] == 0.0 and info[1, 1] > 0 and np.count_nonzero(info) == 1
        else:  # the yaw alone, roll and pitch held at their true values: returned as held, no information on them
            held = CAL.focal_px * theta * [1.0, 0.0, 1.0]
            c, info = two_view_disparity_offset(T, uv0, ul - rotated_right_u(X, theta), uv1, CAL, sigma, axes=(1,), held=held)
            assert c[1] == pytest.approx(CAL.focal_px * theta[1], abs=0.01 * CAL.focal_px * abs(theta[1]) + 1e-6)
            assert c[0] == held[0] and c[2] == held[2] and np.count_nonzero(info) == 1
    theta = np.radians([0.05, 0.05, -0.08])
    truth, measured = CAL.focal_px * theta, ul - rotated_right_u(X, theta)
    errors, nees = [], []
    for _ in range(200):
        disparity = measured + sigma * math.sqrt(2) * rng.standard_normal(n)
        obs = uv1 + sigma * rng.standard_normal((n, 2))
        c, info = two_view_disparity_offset(T, uv0, disparity, obs, CAL, sigma)
        errors.append(c - truth)
        nees.append((c - truth) @ info @ (c - truth))
    std = np.std(errors, axis=0)
    assert np.all(np.abs(np.mean(errors, axis=0)) < 3 * std / np.sqrt(len(errors)) + 0.005)
    assert np.mean(nees) == pytest.approx(3.0, rel=0.2)
    assert two_view_disparity_offset(np.eye(4), uv0, measured, uv0, CAL, sigma) is None  # no motion: an offset moves no pixel


def test_extrinsic_sensitivity_predicts_the_body_delta_error():
    """A fixed camera-IMU calibration error ``X_true = X Exp(e)``: the body delta built
    with the believed ``X`` errs from the true one by ``J e`` to first order
    (``extrinsic_sensitivity``), which grows with the motion; none for none."""
    rng = np.random.default_rng(4)
    X = se3(so3_exp([-1.9, 0.1, 1.6]), [0.1, 0.0, 1.0])
    T_cam = se3(so3_exp([0.05, -0.5, 0.02]), [0.3, 0.05, 0.8])
    T_b, _ = delta_in_body_frame(T_cam, np.zeros((6, 6)), X, X)
    J = extrinsic_sensitivity(T_cam, X)
    for e in rng.normal(0.0, 0.005, (20, 6)):
        E = se3(so3_exp(e[:3]), e[3:])
        T_true = X @ E @ T_cam @ np.linalg.inv(E) @ np.linalg.inv(X)
        predicted = J @ e
        assert np.linalg.norm(predicted) > 1e-3
        np.testing.assert_allclose(pose_error(T_true, T_b), predicted, atol=0.03 * np.linalg.norm(predicted))
    np.testing.assert_allclose(extrinsic_sensitivity(np.eye(4), X), 0.0, atol=1e-15)


# --------------------------------------------------------------------------- rendered sequences


@pytest.mark.parametrize("dense", [False, True], ids=["sparse", "sgbm"])
@pytest.mark.parametrize("name", ["rover", "copter"])
def test_drift_and_keyframes_on_rendered_sequences(name, dense, request):
    seq = request.getfixturevalue(name)
    results = run_vo(seq, dense=dense)
    m = evaluate(seq, results)
    assert m["path"] > 4.0
    assert m["failed"] == [(0, "first_frame")], m["failed"]
    assert m["drift"] < MAX_DRIFT, m
    assert m["rot_deg_per_m"] < MAX_ROT_DEG_PER_M, m
    # the keyframe policy follows the motion: a new keyframe every 0.3 .. 1 m
    assert m["path"] / 1.0 < m["keyframes"] < m["path"] / 0.3, m
    kf_ids = [r.frame_id for r in results if r.new_keyframe]
    for r in results:
        assert len(r.keyframe_history) <= 5 and list(r.keyframe_history) == sorted(r.keyframe_history)
        assert r.keyframe_history[-1] == max(k for k in kf_ids if k <= r.frame_id)
        if r.ok:
            assert r.keyframe_id in r.keyframe_history
            assert r.keypoints.shape == (r.inliers, 2) and r.inliers >= VoParams().min_inliers
            assert np.all((r.keypoints >= 0) & (r.keypoints <= [seq.calib.width - 1, seq.calib.height - 1]))
            assert r.cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(r.cov) > 0)


OFFSET_MODELS = pytest.mark.parametrize(("model", "dense"), [("yaw", False), ("yaw", True), ("rotation", False)],
                                        ids=["yaw-sparse", "yaw-sgbm", "rotation-sparse"])


@OFFSET_MODELS
def test_disparity_offset_is_estimated_and_taken_off(rover_yawed, model, dense):
    """The right camera turned by 0.05 deg about its y axis (disparities f θ = 0.30 px too
    large at the image centre, sim/world/calibration_errors.py): after the 17 s sequence
    (15 keyframes) each estimated coefficient is within 2.5 of its standard deviations of
    the truth, the yaw's has at least half of it, and the chained deltas drift less than
    half as much as with the offsets left in (measured, yaw model sparse / SGBM: yaw 0.303
    / 0.314 px with std 0.035 / 0.037, drift 0.34 / 0.33 %; rotation model sparse: yaw
    0.297 +- 0.035 px, pitch -0.000 +- 0.002, roll 0.011 +- 0.006 px, drift 0.38 %)."""
    seq = rover_yawed
    truth = np.array([0.0, seq.calib.focal_px * math.radians(0.05), 0.0])
    vo, estimated = vo_run(seq, VoParams(disparity_offset_model=model), dense=dense)
    without, left_in = vo_run(seq, VoParams(estimate_disparity_offset=False), dense=dense)
    std = np.sqrt(np.diag(vo.offset.covariance))
    assert np.all(np.abs(vo.disparity_offset - truth) < 2.5 * std) and vo.disparity_offset[1] > truth[1] / 2
    if model == "yaw":
        assert vo.disparity_offset[0] == vo.disparity_offset[2] == 0.0
    assert without.offset is None and not without.disparity_offset.any()
    assert evaluate(seq, estimated)["drift"] < 0.5 * evaluate(seq, left_in)["drift"]


@OFFSET_MODELS
def test_disparity_offset_of_a_nominal_rig_stays_near_zero(rover, model, dense):
    """Measured: yaw 0.008 / 0.014 / 0.006 px, the rotation model's pitch and roll -0.001
    and 0.003 px."""
    vo = vo_run(rover, VoParams(disparity_offset_model=model), dense=dense)[0]
    assert np.all(np.abs(vo.disparity_offset) < 2.5 * np.sqrt(np.diag(vo.offset.covariance)))
    assert np.all(np.abs(vo.disparity_offset) < 0.1)


@pytest.mark.parametrize("dense", [False, True], ids=["sparse", "sgbm"])
def test_a_rolled_rig_is_estimated_from_the_rows(rover_rolled, dense):
    """A roll of the right camera offsets the disparities by row (-y f θz) and the rows by
    column (-x f θz). Two views alone hardly see it: the yaw model, which holds it at
    zero, takes a yaw of about -0.17 px for it and the chained deltas drift 1.2-1.5 %.
    The rotation model reads pitch and roll off the stereo matches' rows and the yaw off two
    views: measured pitch 0.192 / 0.194 px (true 0.177), yaw 0.023 / 0.022 (0), roll
    -0.492 / -0.478 (-0.473), drift 0.18 / 0.54 % (sparse / SGBM)."""
    seq = rover_rolled
    truth = seq.calib.focal_px * np.radians([0.03, 0.0, -0.08])
    vo, estimated = vo_run(seq, VoParams(disparity_offset_model="rotation"), dense=dense)
    yaw_only, yaw_results = vo_run(seq, VoParams(disparity_offset_model="yaw"), dense=dense)
    std = np.sqrt(np.diag(vo.offset.covariance))
    np.testing.assert_allclose(vo.disparity_offset[[0, 2]], truth[[0, 2]], rtol=0.15)
    assert abs(vo.disparity_offset[1]) < max(2.5 * std[1], 0.05) < abs(yaw_only.disparity_offset[1])
    assert evaluate(seq, estimated)["drift"] < 0.5 * evaluate(seq, yaw_results)["drift"]


def test_row_offsets_measure_pitch_and_roll():
    """Synthetic matches whose rows are off by ``r · c`` plus 0.05 px of noise, a tenth of
    them mismatched by 0.5-2 px: the fit recovers pitch and roll, leaves the yaw as given
    with no information on it, and its stated information (floor 0.1 px) is conservative."""
    rng = np.random.default_rng(4)
    truth = np.array([0.2, 0.3, -0.4])
    errors, nees = [], []
    for _ in range(200):
        n = 250
        uv = rng.uniform([10, 10], [310, 230], (n, 2))
        disparity = rng.uniform(8, 30, n)
        rows = row_offset_sensitivity(uv[:, 0], uv[:, 1], disparity, CAL) @ truth + rng.normal(0, 0.05, n)
        bad = rng.random(n) < 0.1
        rows[bad] += rng.choice([-1, 1], bad.sum()) * rng.uniform(0.5, 2.0, bad.sum())
        rows[:5] = np.nan
        c, info = row_offset_measurement(uv, disparity, rows, CAL, 0.1, yaw_px=truth[1])
        assert c[1] == truth[1] and not info[1].any() and not info[:, 1].any()
        e = (c - truth)[[0, 2]]
        errors.append(e)
        nees.append(e @ info[np.ix_([0, 2], [0, 2])] @ e)
    assert np.all(np.abs(np.mean(errors, axis=0)) < 0.005)
    assert np.mean(nees) < 2.0  # two degrees of freedom, conservative by the floor
    assert row_offset_measurement(uv[:7], disparity[:7], rows[:7], CAL, 0.1) is None


def test_standing_still_keeps_the_keyframe(rover):
    vo = StereoVO(rover.calib)
    results = [vo.process(i, 0.2 * i, rover.left[0], rover.right[0]) for i in range(4)]
    assert results[0].new_keyframe and not any(r.new_keyframe for r in results[1:])
    for r in results[1:]:
        assert r.ok and r.keyframe_id == 0 and r.keyframe_history == (0,)
        assert np.linalg.norm(r.T_kf_cur[:3, 3]) < 1e-3 and np.allclose(r.T_kf_cur[:3, :3], np.eye(3), atol=1e-4)


def test_wrong_baseline_breaks_the_drift_bound(rover):
    c = rover.calib
    wrong = dataclasses.replace(c, baseline_m=1.25 * c.baseline_m)
    m = evaluate(rover, run_vo(rover, calib=wrong))
    assert m["drift"] > 10 * MAX_DRIFT, m


@pytest.mark.parametrize("name", ["rover", "copter"])
def test_nees_of_the_deltas(name, request):
    seq = request.getfixturevalue(name)
    thesis = evaluate(seq, run_vo(seq))["nees"]
    assert 0.1 < thesis < 6, thesis  # 0.5 px is conservative on rendered images
    rendered = evaluate(seq, run_vo(seq, VoParams(pixel_noise_px=0.15)))["nees"]  # an exact rig
    assert 6 / 3 < rendered < 6 * 3, rendered


def test_covariance_comes_from_the_measurement(rover):
    many = run_vo(rover)
    few = run_vo(rover, VoParams(max_features=60, keyframe_min_inliers=20, min_inliers=10))
    covs = np.array([r.cov for r in many if r.ok])
    assert np.ptp(np.log(np.trace(covs[:, 3:, 3:], axis1=1, axis2=2))) > 0.5  # it varies along the sequence
    # the same frames against the same first keyframe: fewer inliers, larger covariance
    pairs = [(a, b) for a, b in zip(many[1:4], few[1:4]) if a.ok and b.ok and a.keyframe_id == b.keyframe_id == 0]
    assert len(pairs) == 3
    for a, b in pairs:
        assert b.inliers < a.inliers
        assert np.trace(b.cov[3:, 3:]) > 1.5 * np.trace(a.cov[3:, 3:])
        assert np.linalg.det(b.cov) > np.linalg.det(a.cov)


def test_same_input_same_output(rover):
    params = VoParams(seed=3)
    vo_a, vo_b = StereoVO(rover.calib, params), StereoVO(rover.calib, params)
    for i in range(12):
        a, b = (vo.process(i, rover.t[i], rover.left[i], rover.right[i]) for vo in (vo_a, vo_b))
        assert (a.ok, a.reason, a.keyframe_id, a.inliers, a.new_keyframe, a.keyframe_history) == (
            b.ok, b.reason, b.keyframe_id, b.inliers, b.new_keyframe, b.keyframe_history)
        if a.ok:
            assert np.array_equal(a.T_kf_cur, b.T_kf_cur) and np.array_equal(a.cov, b.cov)
            assert np.array_equal(a.keypoints, b.keypoints)


# --------------------------------------------------------------------------- failures and the history


def test_textureless_pair_is_reported_and_tracking_resumes(copter):
    vo = StereoVO(copter.calib)
    grey = np.full_like(copter.left[0], 128)
    first = vo.process(0, 0.0, grey, grey)
    assert (first.ok, first.reason, first.new_keyframe, first.keyframe_history) == (False, "no_texture", False, ())
    kf = vo.process(1, 0.2, copter.left[0], copter.right[0])
    assert (kf.ok, kf.reason, kf.new_keyframe, kf.keyframe_history) == (False, "first_frame", True, (1,))
    blank = vo.process(2, 0.4, grey, grey)
    assert (blank.ok, blank.reason, blank.new_keyframe, blank.keyframe_history) == (False, "no_texture", False, (1,))
    assert blank.T_kf_cur is None and blank.cov is None and blank.keypoints.shape == (0, 2)
    back = vo.process(3, 0.6, copter.left[2], copter.right[2])
    assert back.ok and back.keyframe_id == 1
    e = pose_error(back.T_kf_cur, copter.relative(0, 2))
    assert np.linalg.norm(e[3:]) < 0.01 and np.linalg.norm(e[:3]) < math.radians(0.2)


def test_a_pose_prior_keeps_tracking_through_a_head_slew(rover_scan):
    """The head's slew turns the camera by 11.5 deg (65 px) a frame, and where the scan
    begins it reverses. The VO's constant-velocity prediction knows no motion when the
    slew starts and points the wrong way where it reverses; with the pose the filter and
    the head's encoders predict (here the truth turned by up to 1 deg, a filter's error
    over a keyframe's span) every frame is tracked and every delta, measured from the
    images alone, is accurate. Measured: without the prior 2 of 29 frames lost and one
    delta off by 0.65 deg and 5 cm (an older keyframe's 17 tracks); with it none lost, all
    within 0.04 deg and 0.3 cm."""
    seq = rover_scan
    matcher = StereoMatcher(seq.calib)
    depth = [matcher.depth(seq.left[i], seq.right[i]) for i in range(len(seq))]
    rng = np.random.default_rng(3)
    prior = [T @ se3(so3_exp(rng.uniform(-1, 1, 3) * math.radians(1.0 / math.sqrt(3))), np.zeros(3)) for T in seq.T_world_cam]
    slewing = [i for i in range(1, len(seq)) if np.linalg.norm(pose_error(seq.T_world_cam[i], seq.T_world_cam[i - 1])[:3]) > math.radians(10)]
    assert len(slewing) >= 10
    bad = {}
    for name, use_prior in (("without", False), ("with", True)):
        vo = StereoVO(seq.calib)
        results = [vo.process(i, seq.t[i], seq.left[i], seq.right[i], depth[i], prior[i] if use_prior else None)
                   for i in range(len(seq))]
        bad[name] = []
        for r in results[1:]:
            e = pose_error(r.T_kf_cur, seq.relative(r.keyframe_id, r.frame_id)) if r.ok else None
            if e is None or np.linalg.norm(e[:3]) > math.radians(0.2) or np.linalg.norm(e[3:]) > 0.02:
                bad[name].append(r.frame_id)
    assert bad["with"] == [] and len(bad["without"]) >= 2, bad


def test_corners_are_searched_again_where_the_depth_gives_points(rover):
    """A high-contrast pattern where the stereo has no depth (the skyline, a white robot
    beyond the range) sets Shi-Tomasi's quality level far above the ground's corners, and
    the grid's cells there take their share of the corners: 23 of them get a point. The
    keyframe searches again where the depth is valid and gets its corners from the ground
    (measured 218), spread over the cells that hold any."""
    calib = rover.calib
    left, right = rover.left[0].copy(), rover.right[0].copy()
    depth = StereoMatcher(calib).depth(left, right)
    band = slice(0, 150)  # the upper 150 rows: a checkerboard without depth
    yy, xx = np.mgrid[band, 0:calib.width]
    left[band] = np.where((yy // 6 + xx // 6) % 2 == 0, 0, 255).astype(np.uint8)
    depth[band] = np.nan
    vo = StereoVO(calib)
    u, v = np.rint(vo.detect(left)).astype(int).T
    assert np.isfinite(depth[v, u]).sum() < VoParams().keyframe_min_inliers
    first = vo.process(0, 0.0, left, right, depth)
    assert first.new_keyframe and first.reason == "first_frame"
    kf = vo.active
    assert len(kf.X) >= 150, len(kf.X)
    assert kf.uv[:, 1].min() >= band.stop
    u, v = np.rint(kf.uv).astype(int).T
    assert np.all(np.isfinite(depth[v, u]))
    # no valid depth anywhere: nothing to search again, the frame has no depth
    lost = StereoVO(calib).process(1, 0.2, left, right, np.full_like(depth, np.nan))
    assert (lost.ok, lost.reason, lost.new_keyframe) == (False, "no_depth", False)


def test_history_recovers_a_revisited_keyframe(copter):
    """Frames 0 and 40 of the copter flight do not overlap: the second starts a new
    keyframe; seeing frame 0's place again is matched against the older keyframe."""
    vo = StereoVO(copter.calib)
    vo.process(100, 0.0, copter.left[0], copter.right[0])
    away = vo.process(101, 8.0, copter.left[40], copter.right[40])
    assert not away.ok and away.reason in ("too_few_matches", "too_few_inliers") and away.new_keyframe
    assert away.keyframe_history == (100, 101)
    revisit = vo.process(102, 8.2, copter.left[1], copter.right[1])
    assert revisit.ok and revisit.keyframe_id == 100 and not revisit.new_keyframe
    e = pose_error(revisit.T_kf_cur, copter.relative(0, 1))
    assert np.linalg.norm(e[3:]) < 0.01 and np.linalg.norm(e[:3]) < math.radians(0.2)
    # the old keyframe is the reference again
    again = vo.process(103, 8.4, copter.left[2], copter.right[2])
    assert again.ok and again.keyframe_id == 100


def test_input_checks():
    vo = StereoVO(CAL)
    img = np.zeros((240, 320), np.uint8)
    with pytest.raises(VoException, match="expected uint8"):
        vo.process(0, 0.0, np.zeros((100, 100), np.uint8), img)
    with pytest.raises(VoException, match="depth"):
        vo.process(0, 0.0, img, img, np.zeros((10, 10)))
    vo.process(0, 0.0, img, img)
    with pytest.raises(VoException, match="already processed"):
        vo.process(0, 0.2, img, img)
    with pytest.raises(VoException, match="positive"):
        VoParams(max_features=0)
