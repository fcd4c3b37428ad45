"""Submap matching (thesis 6.1): the 4D solver and ICP on exact data, keypoint
selection, pairing (eq. 6.1-6.4), and matches of submaps built from rendered stereo
against the true transform, in the modes of 8.1.2."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam.lie import roll_pitch, rot_z, rot_zyx, se3, yaw_of
from slam.matcher import (
    Keypoints,
    KeypointSelection,
    MatcherParams,
    MatchMode,
    PairQueue,
    Prior,
    _refine,
    _refine_best,
    compute_features,
    evaluate_pair,
    match_pair,
    prepare,
    salient_keypoints,
    surface_variation,
)
from slam.registration import Photometric, fit_4d, fit_6d, icp, intensity_gradients, off_line_count, ransac, two_point_4d
from slam.submap import voxel_filter


def random_4d(rng: np.random.Generator) -> np.ndarray:
    return se3(rot_z(rng.uniform(-math.pi, math.pi)), rng.uniform(-5, 5, 3))


def apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and yaw (deg) error of ``T`` against ``T_true``."""
    D = np.linalg.inv(T_true) @ T
    return float(np.linalg.norm(D[:3, 3])), math.degrees(abs(yaw_of(D[:3, :3])))


# ----------------------------------------------------------------------------- solvers


def test_two_point_solver_recovers_an_exact_4d_transform():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = random_4d(rng)
        b = rng.uniform(-3, 3, (2, 3))
        a = apply(T, b)
        np.testing.assert_allclose(two_point_4d(a[0], a[1], b[0], b[1]), T, atol=1e-12)
    assert two_point_4d(np.zeros(3), np.array([0, 0, 1.0]), np.zeros(3), np.array([1.0, 0, 0])) is None  # vertical pair


def test_least_squares_fits_and_ransac_with_outliers():
    rng = np.random.default_rng(1)
    T = random_4d(rng)
    b = rng.uniform(-3, 3, (40, 3))
    a = apply(T, b)
    np.testing.assert_allclose(fit_4d(a, b), T, atol=1e-12)
    np.testing.assert_allclose(fit_6d(a, b), T, atol=1e-10)
    a_noisy = a.copy()
    a_noisy[:15] += rng.uniform(-2, 2, (15, 3))  # 15 of 40 outliers
    for dof in (4, 6):
        found = ransac(a_noisy, b, dof, 0.05, 200, np.random.default_rng(2))
        assert set(found.inliers) == set(range(15, 40))
        np.testing.assert_allclose(found.T_a_b, T, atol=1e-9)


def _terrain_cloud(rng: np.random.Generator) -> np.ndarray:
    """A bumpy 6 x 6 m surface with two boulders: structure in x, y and z."""
    xy = rng.uniform(-3, 3, (6000, 2))
    z = 0.2 * np.sin(1.3 * xy[:, 0]) * np.cos(0.9 * xy[:, 1])
    for cx, cy, r in ((1.0, 0.5, 0.6), (-1.2, -1.0, 0.5)):
        d = np.hypot(xy[:, 0] - cx, xy[:, 1] - cy)
        z += np.where(d < r, np.sqrt(np.maximum(r**2 - d**2, 0)), 0.0)
    return np.column_stack([xy, z])


def _normals(cloud: np.ndarray) -> np.ndarray:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.2, max_nn=30))
    return np.asarray(pcd.normals)


@pytest.mark.parametrize("dof", [4, 6])
def test_icp_converges_from_a_perturbed_start_and_4d_keeps_roll_pitch(dof):
    rng = np.random.default_rng(3)
    target = _terrain_cloud(rng)
    T = se3(rot_z(0.3), [0.5, -0.2, 0.1])
    source = apply(np.linalg.inv(T), target[::2])
    start = se3(rot_z(0.3 + math.radians(4)), [0.65, -0.05, 0.0])
    fit = icp(source, target, _normals(target), start, dof=dof, max_distance_m=0.5, iterations=60)
    assert fit is not None and fit.rmse_m < 0.01
    t_err, yaw_err = errors(fit.T_a_b, T)
    assert t_err < 0.01 and yaw_err < 0.1
    if dof == 4:
        assert max(map(abs, roll_pitch(fit.T_a_b[:3, :3]))) < 1e-12


def _gentle_ground(rng: np.random.Generator, x0: float, x1: float, noise_m: float) -> np.ndarray:
    """A 2.4 m wide strip of gently undulating ground from x0 to x1 with stereo-like noise:
    what two submaps of the same leg share, with little to hold x, y or yaw."""
    xy = np.column_stack([rng.uniform(x0, x1, 12000), rng.uniform(-1.2, 1.2, 12000)])
    z = 0.08 * np.sin(0.7 * xy[:, 0] + 0.3) + 0.05 * np.cos(1.1 * xy[:, 1]) + 0.03 * np.sin(2.3 * xy[:, 0] + 1.7 * xy[:, 1])
    return np.column_stack([xy, z + noise_m * rng.standard_normal(len(z))])


def test_icp_started_at_the_truth_stays_there_on_noisy_gentle_ground():
    """Two independently sampled, noisy (3 cm) strips overlapping by 5 m: the truncated
    cost keeps the ICP at the true transform, where an ICP that minimises the residuals
    of whatever pairs it currently has wanders off along the flat directions (0.07-0.24 m
    on these six draws)."""
    T = se3(rot_z(0.4), [1.0, 0.5, 0.05])
    t_errs, yaw_errs = [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        target = _gentle_ground(rng, -4, 4, 0.03)
        source = apply(np.linalg.inv(T), _gentle_ground(rng, -1, 7, 0.03))
        fit = icp(source, target, _normals(target), T, dof=4, max_distance_m=0.25, iterations=40, min_pairs=300)
        t_err, yaw_err = errors(fit.T_a_b, T)
        t_errs.append(t_err)
        yaw_errs.append(yaw_err)
    assert np.median(t_errs) < 0.03 and max(t_errs) < 0.08, t_errs
    assert max(yaw_errs) < 1.0, yaw_errs


def test_intensity_gradients_of_a_linear_field_are_its_projection_into_the_tangent_plane():
    """On a tilted plane, an intensity linear in space has the in-plane gradient ``a - (a.n) n``."""
    rng = np.random.default_rng(1)
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    xy = rng.uniform(-1, 1, (3000, 2))
    pts = np.column_stack([xy, -(n[0] * xy[:, 0] + n[1] * xy[:, 1]) / n[2]])
    a = np.array([0.8, -0.5, 0.6])
    grads = intensity_gradients(pts, np.tile(n, (len(pts), 1)), pts @ a + 2.0, cKDTree(pts))
    np.testing.assert_allclose(grads, np.tile(a - (a @ n) * n, (len(pts), 1)), atol=1e-9)


def _textured_flat_ground(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat ground (1 cm noise) 4 x 4 m with a smooth albedo pattern: nothing in its relief
    holds x, y or yaw."""
    pts = np.column_stack([rng.uniform(0, 4, (n, 2)), 0.01 * rng.standard_normal(n)])
    return pts, _albedo(pts)


def _albedo(p: np.ndarray) -> np.ndarray:
    return 1 + 0.3 * np.sin(3.1 * p[:, 0] + 1.3 * np.sin(2.3 * p[:, 1])) * np.cos(2.7 * p[:, 1] - 0.7 * p[:, 0])


def test_coloured_icp_holds_what_the_relief_cannot_on_flat_textured_ground():
    """Started 14 cm and 2 deg off over flat ground, the geometric ICP has nothing to pull it
    (it stays off); with the intensities (Park et al. 2017) it comes to the truth."""
    rng = np.random.default_rng(2)
    target, c_target = _textured_flat_ground(rng, 20000)
    T = se3(rot_z(0.2), [0.3, -0.1, 0.0])
    world, _ = _textured_flat_ground(rng, 3000)
    world = world[np.all((world[:, :2] > 0.5) & (world[:, :2] < 3.5), axis=1)]
    source = apply(np.linalg.inv(T), world)
    c_source = _albedo(world) + 0.03 * rng.standard_normal(len(world))
    normals = np.tile([0.0, 0.0, 1.0], (len(target), 1))
    photometric = Photometric(c_target, intensity_gradients(target, normals, c_target, cKDTree(target)), c_source, 0.3)
    start = T @ se3(rot_z(math.radians(2)), [0.12, -0.08, 0.0])
    geometric = icp(source, target, normals, start, dof=4, max_distance_m=0.25, iterations=40, min_pairs=300)
    coloured = icp(source, target, normals, start, dof=4, max_distance_m=0.25, iterations=40, min_pairs=300, photometric=photometric)
    t_geo, _ = errors(geometric.T_a_b, T)
    t_col, yaw_col = errors(coloured.T_a_b, T)
    assert t_geo > 0.1
    assert t_col < 0.02 and yaw_col < 0.2, (t_col, yaw_col)
    assert coloured.pairs <= len(source)  # the geometric pairs, not the intensity rows


def _row_of_boulders(rng: np.random.Generator) -> np.ndarray:
    """Noisy flat ground with five equal boulders 1 m apart along x: shifted by one boulder,
    four of them still fit, a basin of the ICP's cost beside the true one."""
    xy = np.column_stack([rng.uniform(-3, 3, 8000), rng.uniform(-1.5, 1.5, 8000)])
    z = 0.01 * rng.standard_normal(8000)
    for cx in (-2.0, -1.0, 0.0, 1.0, 2.0):
        d = np.hypot(xy[:, 0] - cx, xy[:, 1])
        z += np.where(d < 0.3, np.sqrt(np.maximum(0.09 - d**2, 0)), 0.0)
    return np.column_stack([xy, z])


def test_of_two_icp_starts_the_one_ending_at_the_lower_cost_is_kept():
    """A start one boulder along ends there, 1 m off; a start 10 cm and 2 deg off ends at the
    truth at a lower truncated cost, and is kept whichever of the two is named first."""
    rng = np.random.default_rng(0)
    target = _row_of_boulders(rng)
    T = se3(rot_z(0.3), [0.5, -0.2, 0.1])
    source = apply(np.linalg.inv(T), _row_of_boulders(rng))
    a = Keypoints(("a", 0), 0, target[:10], target[:10], target.astype(np.float32), np.ones(len(target), bool))
    p = MatcherParams()
    near = se3(rot_z(0.3 + math.radians(2)), [0.58, -0.12, 0.1])
    along = T @ se3(np.eye(3), [1.0, 0.05, 0.0])
    stuck = _refine(source, a, along, 4, p)
    assert errors(stuck.T_a_b, T)[0] > 0.9  # the other basin
    for starts in ({"hypothesis": along, "prior": near}, {"hypothesis": near, "prior": along}):
        fit, name = _refine_best(source, a, starts, 4, p)
        assert starts[name] is near
        assert fit.cost < stuck.cost
        t_err, yaw_err = errors(fit.T_a_b, T)
        assert t_err < 0.01 and yaw_err < 0.2


def test_line_test_counts_points_off_the_line():
    rng = np.random.default_rng(4)
    line = np.column_stack([np.linspace(0, 5, 50), 0.05 * rng.standard_normal(50), rng.uniform(0, 0.5, 50)])
    off = np.array([[1.0, 2.0, 0.0], [2.0, -1.5, 0.3], [4.0, 0.8, 0.1]])
    assert off_line_count(line, 0.5, 100, np.random.default_rng(0)) == 0
    assert off_line_count(np.vstack([line, off]), 0.5, 100, np.random.default_rng(0)) == 3


def test_surface_variation_is_zero_on_a_plane_and_high_at_an_edge():
    """Keypoint saliency: an exact plane has none; along a right-angled step (a rock's
    or a rim's edge) the neighbourhood spans two planes."""
    g = np.arange(-1.0, 1.0001, 0.05)
    X, Y = np.meshgrid(g, g)
    plane = np.column_stack([X.ravel(), Y.ravel(), 0.1 * X.ravel() - 0.2 * Y.ravel()])  # tilted: the measure is not height
    assert np.max(surface_variation(plane, 0.2)) < 1e-9
    wall = np.column_stack([np.zeros(len(g) ** 2), X.ravel(), (Y.ravel() + 1) / 2])  # x = 0, z 0..1
    floor = plane[plane[:, 0] > 0] * [1, 1, 0]
    step = np.vstack([floor, wall])
    sv = surface_variation(step, 0.2)
    at_edge = (np.abs(step[:, 0]) < 0.06) & (step[:, 2] < 0.06) & (np.abs(step[:, 1]) < 0.8)
    far = (step[:, 0] > 0.4) & (np.abs(step[:, 1]) < 0.8)
    assert np.min(sv[at_edge]) > MatcherParams().min_surface_variation
    assert np.max(sv[far]) < 1e-9
    # an edge persists at twice the radius (the flat rendered submap's far-range noise does not: test below)
    assert np.min(surface_variation(step, 0.4)[at_edge]) > MatcherParams().min_surface_variation_wide


# ----------------------------------------------------------------------------- pairing


class _Kp:
    def __init__(self, key, selected_xyz):
        self.key = key
        self.selected_xyz = np.asarray(selected_xyz, float)


def _square(x0, y0, size):
    return [[x0, y0, 0], [x0 + size, y0 + size, 0.5]]


def test_pairing_overlap_sigma_widening_and_score():
    p = MatcherParams(stereo_error_m=0.12)
    a, b = _Kp(("lru1", 2), _square(0, 0, 3)), _Kp(("lru2", 5), _square(0, 0, 3))
    S_a, S_b = np.eye(4), se3(np.eye(3), [1.5, 1.5, 0])  # b's box 1.5..4.5 overlaps a's 0..3 by 1.5 x 1.5
    cov = np.diag([1e-4] * 3 + [0.3**2, 0.2**2, 0.1**2])
    cand = evaluate_pair(a, b, S_a, S_b, cov, p)
    # eq. 6.1: 1.5 + 2 * 0.3 and 1.5 + 2 * 0.2; eq. 6.4: 0.125 * area + (0.3 + 0.2 + 0.1)
    assert cand.overlap_m2 == pytest.approx(2.1 * 1.9)
    assert cand.score == pytest.approx(0.125 * 2.1 * 1.9 + 0.6)
    np.testing.assert_allclose(cand.sigma_xyz, [0.3, 0.2, 0.1])
    # eq. 6.2: without the sigmas the overlap is 2.25 m2, with tiny sigmas eq. 6.3 rejects
    assert evaluate_pair(a, b, S_a, S_b, np.diag([1e-4] * 3 + [1e-4] * 3), p) == "already certain"
    far = se3(np.eye(3), [2.6, 2.6, 0])  # 0.4 x 0.4 overlap + 2 sigma each
    assert evaluate_pair(a, b, S_a, far, cov, p) == "no overlap"
    assert evaluate_pair(a, _Kp(("lru1", 3), _square(0, 0, 3)), S_a, S_a, cov, p) == "consecutive"


def test_pair_queue_orders_by_score_and_tries_each_pair_once():
    p = MatcherParams(stereo_error_m=0.01)
    q = PairQueue(p)
    boxes = {("a", 0): (0, 0), ("a", 5): (0.5, 0.5), ("b", 0): (1.0, 1.0)}
    q.prepared = {k: _Kp(k, _square(x, y, 3)) for k, (x, y) in boxes.items()}
    origins = {k: np.eye(4) for k in boxes}
    cov = np.diag([1e-4] * 3 + [0.1**2] * 3)
    q.refresh(origins, {pair: cov for pair in q.open_pairs()})
    order = [c.pair for c in q.candidates()]
    assert order[0] == (("a", 0), ("a", 5))  # the largest overlap first (equal sigmas)
    q.mark_attempted(order[0])
    popped = q.pop()
    assert popped.pair == order[1]
    q.mark_attempted(popped.pair)
    q.refresh(origins, {pair: cov for pair in q.open_pairs()})
    assert [c.pair for c in q.candidates()] == [order[2]]


# ----------------------------------------------------------------------------- rendered submaps


@pytest.fixture(scope="module")
def rendered():
    from sim.tools.rocky_scene import RockyScene

    scene = RockyScene()
    try:
        a = scene.submap("lru1", 3, (-3.0, -0.4), (2.0, -0.4))
        b = scene.submap("lru2", 7, (-2.0, 1.2), (2.5, -0.8))  # the same rocks from another path, 30 deg turned
        far = scene.submap("lru2", 9, (5.0, -8.0), (8.0, -3.0))
        flat_scene = RockyScene(rocks=0)
        flat = flat_scene.submap("lru2", 11, (-3.0, -0.4), (2.0, -0.4))
        flat_scene.close()
    finally:
        scene.close()
    return a, b, far, flat


@pytest.mark.parametrize(
    "mode, keypoints, icp_points",
    [
        ("4d", "obstacles", "all"),
        ("6d", "obstacles", "all"),
        ("4d", "geometry", "all"),
        ("4d", "both", "all"),
        ("4d+6d", "both", "all"),
        ("4d", "both", "classified"),
    ],
)
def test_rendered_submaps_of_the_same_rocks_match(rendered, mode, keypoints, icp_points):
    (A, O_a), (B, O_b), _, _ = rendered
    p = MatcherParams(mode=mode, keypoints=keypoints, icp_points=icp_points)
    ka, kb = prepare(A, p), prepare(B, p)
    res = match_pair(ka, kb, p)
    assert res.success, res.reason
    assert res.reached_icp
    T_true = np.linalg.inv(O_a) @ O_b
    t_err, yaw_err = errors(res.T_a_b, T_true)
    assert t_err < 0.1 and yaw_err < 1.0
    rp = max(map(abs, roll_pitch(res.T_a_b[:3, :3])))
    assert rp == 0.0 if mode == "4d" else rp < p.max_roll_pitch_final_rad
    sigma = np.sqrt(np.diag(res.cov))
    assert t_err < 3 * math.sqrt(3) * sigma[3] and math.radians(yaw_err) < 3 * sigma[2]
    again = match_pair(prepare(A, p), prepare(B, p), p)
    np.testing.assert_array_equal(again.T_a_b, res.T_a_b)  # seeded: the same result


def test_coloured_icp_matches_the_rendered_submaps(rendered):
    """With the rendered intensities in the ICP the same rocks match within the bounds of the
    geometric test, and the submaps carry their points' intensities into the keypoints."""
    (A, O_a), (B, O_b), _, _ = rendered
    p = MatcherParams(keypoints="both", icp_intensity_scale_m=0.3)
    ka, kb = prepare(A, p), prepare(B, p)
    assert ka.intensity is A.intensity and np.ptp(ka.intensity) > 50
    res = match_pair(ka, kb, p)
    assert res.success, res.reason
    t_err, yaw_err = errors(res.T_a_b, np.linalg.inv(O_a) @ O_b)
    assert t_err < 0.1 and yaw_err < 1.0


def test_descriptors_on_a_thinned_cloud_match_the_rendered_submaps(rendered):
    """FPFH on the cloud's 0.05 m voxel centroids: other descriptors than on the full cloud,
    the same rocks matched within the bounds of the full-cloud test."""
    (A, O_a), (B, O_b), _, _ = rendered
    full = MatcherParams(keypoints="both", voting="yaw_sweep")
    thin = MatcherParams(keypoints="both", voting="yaw_sweep", descriptor_resolution_m=0.05)
    ka, kb = prepare(A, thin), prepare(B, thin)
    res = match_pair(ka, kb, thin)
    assert res.success, res.reason
    t_err, yaw_err = errors(res.T_a_b, np.linalg.inv(O_a) @ O_b)
    assert t_err < 0.1 and yaw_err < 1.0
    kf = prepare(A, full)
    compute_features(kf, full)
    assert kf.descriptors.shape == ka.descriptors.shape and not np.allclose(kf.descriptors, ka.descriptors)


def test_released_geometry_is_rebuilt_to_the_same_match(rendered):
    """A queue keeps the cloud geometry of its ``geometry_held`` latest matched submaps
    only; a submap paired again after its release matches exactly as before."""
    (A, _), (B, _), (far, _), _ = rendered
    p = MatcherParams(keypoints="both", geometry_held=2)
    q = PairQueue(p)
    ka, kb, kf = (q.add(s) for s in (A, B, far))
    assert np.shares_memory(ka.source, A.points)  # the submap's cloud, not a copy
    first = match_pair(ka, kb, p)
    assert first.success and "geometry" not in first.timings
    q.hold_geometry((ka.key, kb.key))
    elsewhere = match_pair(kb, kf, p)
    assert elsewhere.reason == "no hypothesis" and not elsewhere.reached_icp  # no shared rock: the ICP's time is not spent
    q.hold_geometry((kb.key, kf.key))
    assert ka.geometry is None and kb.geometry is not None and kf.geometry is not None
    again = match_pair(ka, kb, p)
    assert "geometry" in again.timings and ka.geometry is not None
    np.testing.assert_array_equal(again.T_a_b, first.T_a_b)
    np.testing.assert_array_equal(again.cov, first.cov)


@pytest.mark.parametrize("keypoints,descriptor", [("obstacles", "fpfh"), ("both", "fpfh"), ("both", "spin")])
def test_yaw_sweep_voting_matches_the_rendered_submaps(rendered, keypoints, descriptor):
    """The yaw sweep (no local reference frames) finds the same transform, with and without a
    prior, and voting only inside the prior's plausible translations (``sweep_within_prior``);
    with FPFH and with spin images about the gravity axis."""
    (A, O_a), (B, O_b), _, _ = rendered
    sweep = MatcherParams(keypoints=keypoints, voting="yaw_sweep", descriptor=descriptor)
    T_true = np.linalg.inv(O_a) @ O_b
    prior_T = T_true.copy()
    prior_T[:3, 3] += [0.15, -0.1, 0.05]
    near = Prior(prior_T, np.full(3, 0.2), math.radians(2.0))
    for p, prior in ((sweep, None), (sweep, near), (replace(sweep, sweep_within_prior=True), near)):
        ka = prepare(A, p)
        res = match_pair(ka, prepare(B, p), p, prior)
        assert res.success, res.reason
        t_err, yaw_err = errors(res.T_a_b, T_true)
        assert t_err < 0.1 and yaw_err < 1.0
        assert ka.descriptors is not None and ka.frames is None  # features computed, reference frames not


@pytest.mark.parametrize("voting", ["hough3d", "yaw_sweep"])
def test_a_prior_off_in_yaw_rejects_the_match(rendered, voting):
    """The plausibility check bounds the yaw where the graph gives its sigma: a prior 10 deg
    off with 1 deg sigma rejects the right match, the same prior without a yaw sigma does not."""
    (A, O_a), (B, O_b), _, _ = rendered
    p = MatcherParams(voting=voting)
    T_true = np.linalg.inv(O_a) @ O_b
    turned = T_true.copy()
    turned[:3, :3] = rot_z(math.radians(10.0)) @ T_true[:3, :3]
    assert not match_pair(prepare(A, p), prepare(B, p), p, Prior(turned, np.full(3, 0.2), math.radians(1.0))).success
    assert match_pair(prepare(A, p), prepare(B, p), p, Prior(turned, np.full(3, 0.2))).success


def test_icp_from_the_prior_keeps_the_lower_cost(rendered):
    """``icp_from_prior``: from a prediction 0.1 m off the second ICP ends near the truth too
    (the lower of the two kept); from one 0.8 m off (within wide sigmas) it ends 0.7 m off
    at a higher cost, and the match is the hypothesis's, as without the second start."""
    (A, O_a), (B, O_b), _, _ = rendered
    p = MatcherParams()
    on = replace(p, icp_from_prior=True)
    T_true = np.linalg.inv(O_a) @ O_b
    for offset, sigma in ((0.1, 0.2), (0.8, 1.0)):
        prior_T = T_true.copy()
        prior_T[:3, 3] += [offset, 0.0, 0.0]
        prior = Prior(prior_T, np.full(3, sigma))
        off_res, on_res = (match_pair(prepare(A, q), prepare(B, q), q, prior) for q in (p, on))
        assert off_res.success and on_res.success, (off_res.reason, on_res.reason)
        assert off_res.start == "hypothesis" and on_res.start in ("hypothesis", "prior")
        assert on_res.icp.cost <= off_res.icp.cost
        assert errors(on_res.T_a_b, T_true)[0] < 0.1
        if offset > 0.5:
            assert on_res.start == "hypothesis"
            np.testing.assert_array_equal(on_res.T_a_b, off_res.T_a_b)


def test_prior_far_from_the_match_rejects_it(rendered):
    (A, O_a), (B, O_b), _, _ = rendered
    p = MatcherParams()
    T_true = np.linalg.inv(O_a) @ O_b
    wrong = T_true.copy()
    wrong[:3, 3] += [1.0, 0.0, 0.0]
    res = match_pair(prepare(A, p), prepare(B, p), p, Prior(wrong, np.array([0.2, 0.2, 0.2])))
    assert not res.success
    assert match_pair(prepare(A, p), prepare(B, p), p, Prior(T_true, np.array([0.2, 0.2, 0.2]))).success


def test_a_graph_more_certain_than_the_match_does_not_veto_it(rendered):
    """The 2-sigma check compares two estimates: a graph 10 cm off with 2 cm sigmas (an
    overconfident filter) keeps the right closure, whose own sigma is at least
    ``hypothesis_sigma_m``; 60 cm off it does not."""
    (A, O_a), (B, O_b), _, _ = rendered
    p = MatcherParams()
    T_true = np.linalg.inv(O_a) @ O_b
    for offset, success in ((0.1, True), (0.6, False)):
        prior = T_true.copy()
        prior[:3, 3] += [offset, 0.0, 0.0]
        res = match_pair(prepare(A, p), prepare(B, p), p, Prior(prior, np.array([0.02, 0.02, 0.02])))
        assert res.success == success, (offset, res.reason)
        if success:
            assert np.linalg.norm(res.T_a_b[:3, 3] - T_true[:3, 3]) < 0.15


def test_non_overlapping_and_featureless_submaps_are_rejected(rendered):
    (A, _), _, (far, _), (flat, _) = rendered
    p = MatcherParams()
    res = match_pair(prepare(A, p), prepare(far, p), p)
    assert not res.success
    reasons = {"obstacles": "too few obstacle points", "geometry": "too few salient points", "both": "too few obstacle or salient points"}
    for selection, reason in reasons.items():
        assert prepare(flat, MatcherParams(keypoints=selection)) == reason


def test_geometry_keypoints_reach_beyond_the_obstacles(rendered):
    """Geometry keypoints (9.3) include salient points away from every obstacle point;
    ``both`` keeps all of the thesis's obstacle keypoints and adds them."""
    (A, _), _, _, _ = rendered
    obstacles = prepare(A, MatcherParams(keypoints="obstacles"))
    geometry = prepare(A, MatcherParams(keypoints="geometry"))
    both = prepare(A, MatcherParams(keypoints="both"))
    obstacle_points = np.asarray(A.points)[np.asarray(A.obstacle)]
    d = np.min(np.linalg.norm(geometry.points[:, None] - obstacle_points[None], axis=2), axis=1)
    assert np.sum(d > 0.3) >= 20
    d_both = np.min(np.linalg.norm(obstacles.points[:, None] - both.points[None], axis=2), axis=1)
    assert np.all(d_both < 0.1)  # each obstacle keypoint is in both's voxel of it
    assert len(both.points) > len(obstacles.points)


def test_icp_on_classified_points_aligns_only_those(rendered):
    """With ``icp_points`` classified the ICP pairs only the two submaps' classified
    points (a strict subset here): fewer pairs than over the whole clouds, and the
    refinement still recovers the true transform from the same hypothesis."""
    (A, O_a), (B, O_b), _, _ = rendered
    near = np.asarray(A.classified, bool)
    assert 0 < near.sum() < len(near)
    whole, classified = MatcherParams(keypoints="both"), MatcherParams(keypoints="both", icp_points="classified")
    ka, kb = prepare(A, whole), prepare(B, whole)
    np.testing.assert_array_equal(ka.classified, near)
    res_whole, res_near = match_pair(ka, kb, whole), match_pair(ka, kb, classified)
    assert res_whole.success and res_near.success, (res_whole.reason, res_near.reason)
    assert res_near.icp.pairs < res_whole.icp.pairs
    t_err, yaw_err = errors(res_near.T_a_b, np.linalg.inv(O_a) @ O_b)
    assert t_err < 0.1 and yaw_err < 1.0


def test_salient_keypoints_are_thinned_to_the_most_salient_per_cell(rendered):
    """Salient keypoints keep one voxel centroid per ``salient_spacing_m`` cell, the most
    salient at the wide radius; with ``both`` every obstacle voxel stays besides them."""
    (A, _), _, _, _ = rendered
    pts, obstacle = np.asarray(A.points, float), np.asarray(A.obstacle, bool)
    p = MatcherParams(keypoints="geometry")
    thinned = salient_keypoints(pts, np.zeros(len(pts), bool), p)
    dense = salient_keypoints(pts, np.zeros(len(pts), bool), replace(p, salient_spacing_m=p.keypoint_resolution_m))
    cells = np.floor(thinned / p.salient_spacing_m).astype(int)
    assert len(np.unique(cells, axis=0)) == len(thinned) >= 50
    assert len(dense) > 1.5 * len(thinned)
    assert np.isin(thinned.view([("", float)] * 3), dense.view([("", float)] * 3)).all()
    centroids = voxel_filter(pts, np.zeros(len(pts), bool), np.zeros(len(pts)), p.keypoint_resolution_m)[0]
    _, at = cKDTree(centroids).query(dense)
    wide = surface_variation(centroids, 2 * p.saliency_radius_m)[at]  # each kept one beats the others of its cell
    dense_cells = np.floor(dense / p.salient_spacing_m).astype(int)
    for point, cell in zip(thinned[:40], cells[:40]):
        same = np.all(dense_cells == cell, axis=1)
        best = dense[same][np.argmax(wide[same])]
        np.testing.assert_allclose(point, best, atol=1e-9)
    both = salient_keypoints(pts, obstacle, p)
    obstacle_voxels = np.unique(np.floor(pts[obstacle] / p.keypoint_resolution_m).astype(int), axis=0)
    both_voxels = np.unique(np.floor(both / p.keypoint_resolution_m).astype(int), axis=0)
    assert np.isin(obstacle_voxels.view([("", int)] * 3), both_voxels.view([("", int)] * 3)).all()
    assert len(both) >= len(obstacle_voxels) + 0.5 * len(thinned)


def test_4d_6d_recovers_a_roll_pitch_offset_that_4d_cannot(rendered):
    """8.1.2's 4D+6D: when an origin's roll and pitch are off (here B's frame tilted by
    0.6 deg roll and -0.5 deg pitch, under the 1 deg check), the 4D match cannot
    represent the tilt; the 6D ICP after the 4D alignment recovers most of it."""
    (A, O_a), (B, O_b), _, _ = rendered
    tilt = rot_zyx(math.radians(0.6), math.radians(-0.5), 0.0)
    tilted = replace(B, points=np.asarray(B.points, float) @ tilt.T)  # p_B' = tilt p_B
    T_true = np.linalg.inv(O_a) @ O_b @ se3(tilt.T, np.zeros(3))
    found = {}
    for mode in ("4d", "4d+6d"):
        p = MatcherParams(mode=mode, keypoints="both")  # obstacle keypoints alone find no hypothesis for the tilted pair
        res = match_pair(prepare(A, p), prepare(tilted, p), p)
        assert res.success, (mode, res.reason)
        assert errors(res.T_a_b, T_true)[0] < 0.1
        found[mode] = math.degrees(math.hypot(*np.subtract(roll_pitch(res.T_a_b[:3, :3]), roll_pitch(T_true[:3, :3]))))
    assert found["4d"] > 0.75  # the whole tilt (0.78 deg) stays
    assert found["4d+6d"] < 0.35


def test_params_validation():
    with pytest.raises(ValueError, match="mode"):
        MatcherParams(mode="5d")
    with pytest.raises(ValueError, match="alpha=-1"):
        MatcherParams(alpha=-1)
    assert MatcherParams(mode="6d").mode is MatchMode.SIX_D
    assert MatcherParams(mode="4d+6d").mode is MatchMode.FOUR_SIX_D
    with pytest.raises(ValueError, match="keypoints"):
        MatcherParams(keypoints="edges")
    assert MatcherParams(keypoints="geometry").keypoints is KeypointSelection.GEOMETRY
    with pytest.raises(ValueError, match="icp_points"):
        MatcherParams(icp_points="near")
    with pytest.raises(ValueError, match="voting"):
        MatcherParams(voting="lrf")
    with pytest.raises(ValueError, match="hough_yaw_step_rad"):
        MatcherParams(hough_yaw_step_rad=0.0)
    with pytest.raises(ValueError, match="geometry_held"):
        MatcherParams(geometry_held=1)


def _chain(graph, robot: str, target: np.ndarray, frames: int, sigma_m: float) -> None:
    """Frame switches 0 -> ``frames`` of ``robot`` whose last origin lands on ``target``,
    each with ``sigma_m`` translation and 1 deg yaw standard deviation."""
    cov = np.diag([1e-6, 1e-6, math.radians(1) ** 2] + [sigma_m**2] * 3)
    T_step = se3(rot_z(yaw_of(target[:3, :3]) / frames), target[:3, 3] / frames)
    first = target @ np.linalg.inv(np.linalg.matrix_power(T_step, frames - 1))  # s0 -> s1 carries the rest
    for k in range(frames):
        graph.add_frame_switch(robot, k, float(k), first if k == 0 else T_step, cov)


def test_team_matcher_pairs_from_the_graph_and_its_closure_corrects_it(rendered):
    """Pairing with the graph's joint marginals (eq. 6.1-6.4), matching against the
    graph's prior, and the c factor pulling the graph toward the true relative pose."""
    from slam.graph import MultiRobotGraph
    from slam.team_matcher import TeamMatcher, pair_owner

    (A, O_a), (B, O_b), _, _ = rendered
    graph = MultiRobotGraph("lru1")
    _chain(graph, "lru1", O_a, 3, 0.05)
    drift = se3(rot_z(math.radians(2)), [0.25, -0.15, 0.0])
    _chain(graph, "lru2", O_b @ drift, 7, 0.05)
    graph.add_match("lru1", 0, "lru2", 0, np.eye(4), np.diag([1e-4] * 3 + [0.01] * 3))  # lru2 starts where lru1 did
    graph.update()
    T_true = np.linalg.inv(O_a) @ O_b
    before, _ = errors(np.linalg.inv(graph.submap_origin("lru1", 3)) @ graph.submap_origin("lru2", 7), T_true)
    assert before > 0.2

    matcher = TeamMatcher(MatcherParams(stereo_error_m=0.094), pair_owner(A.key, B.key))
    matcher.add_submap(A)
    matcher.add_submap(B)
    assert matcher.pair(graph) == 1
    cand = matcher.next_candidate()
    assert cand.pair == (A.key, B.key) and np.all(cand.sigma_xyz[:2] > 0.1)
    record = matcher.attempt(cand, 10.0)
    assert record.result.success, record.result.reason
    assert errors(record.result.T_a_b, T_true)[0] < 0.1
    assert matcher.next_candidate() is None  # tried once

    graph.add_match("lru1", record.frame_a, "lru2", record.frame_b, record.result.T_a_b, record.result.cov)
    graph.update()
    after, _ = errors(np.linalg.inv(graph.submap_origin("lru1", 3)) @ graph.submap_origin("lru2", 7), T_true)
    assert after < 0.1 < before
