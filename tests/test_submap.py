"""slam.submap: voxel-grid filter, submap integration on analytic depth images, partitioning (thesis 5.1.2, 5.1.3),
freezing and the exchange format (5.2.1).

Size and timing of a realistic submap (the 5 m drive of ``drive_submap``: ground with boxes, 50 images of
320x240; the numbers are in ``slam/submap.py``), timing ``integrate`` alone, from the repository root::

    .venv/bin/python - <<'EOF'
    import sys, time, math; sys.path.insert(0, "tests"); import numpy as np
    from test_submap import BOXES, CALIB, camera_pose, render
    from slam.submap import SubmapBuilder, SubmapParams
    for warm_up in (True, False):  # the first pass loads the numba kernels
        builder, spent = SubmapBuilder("lru1", SubmapParams(), CALIB), 0.0
        for i in range(50):
            x = 5.0 * i / 49; T = camera_pose(x, 0.1 * math.sin(x), 0.1 * math.cos(x)); depth, obstacle, intensity = render(T, BOXES)
            t = time.perf_counter(); builder.integrate(depth, T, obstacle, intensity, 0.2 * i, classified=np.isfinite(depth))
            spent += time.perf_counter() - t
    s = builder.finish(10.0, 1)
    print(s, f"{spent / 50 * 1e3:.1f} ms per image", s.size_bytes, len(s.to_bytes(compress=False)), len(s.voxels.to_bytes()))
    EOF
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from slam.stereo import StereoCalibration, max_depth_for_error
from slam.submap import (
    QUANTUM_M,
    PartitionReason,
    Submap,
    SubmapBuilder,
    SubmapException,
    SubmapParams,
    VoxelSums,
    voxel_filter,
)
from slam.voxels import VoxelGrid, VoxelState

WIDTH, HEIGHT = 320, 240
FOCAL = (WIDTH / 2) / math.tan(math.radians(25.3))  # 50.6 deg, LRU (thesis 7.1)
CALIB = StereoCalibration(FOCAL, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, 0.09, WIDTH, HEIGHT)
# faces off the 5 cm voxel planes, so that recomputed voxel indices of centroids are unambiguous
BOXES = ((np.array([2.013, -0.887, 0.0]), np.array([2.413, -0.487, 0.413])), (np.array([4.513, 0.413, 0.0]), np.array([5.013, 0.913, 0.313])))


def camera_pose(x: float, y: float, yaw: float, height: float = 1.3, tilt_deg: float = 25.0) -> np.ndarray:
    """T_frame_cam of a camera ``height`` m above z = 0 at (x, y), looking along yaw, tilted down (OpenCV axes)."""
    c, s = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    R_yaw = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    R_tilt = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    T = np.eye(4)
    T[:3, :3] = R_yaw @ R_tilt @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    T[:3, 3] = (x, y, height)
    return T


def render(T_frame_cam: np.ndarray, boxes=(), calib: StereoCalibration = CALIB, zfar: float = 20.0, ground_z: float = 0.0):
    """Analytic z-depth of the ground z = ``ground_z`` and axis-aligned boxes (lo, hi): (depth, obstacle, intensity) images.

    Box pixels are obstacles; the intensity is a 0.2 m checkerboard in the frame's x, y."""
    u, v = np.meshgrid(np.arange(calib.width), np.arange(calib.height))
    rays = np.stack([(u - calib.cx) / calib.focal_px, (v - calib.cy) / calib.focal_px, np.ones(u.shape)], axis=-1).reshape(-1, 3)
    d = rays @ T_frame_cam[:3, :3].T  # unit camera z, so the ray parameter is the z-depth
    o = T_frame_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(d[:, 2] < 0, (ground_z - o[2]) / d[:, 2], np.inf)
        obstacle = np.zeros(len(d), bool)
        for lo, hi in boxes:
            t1, t2 = (lo - o) / d, (hi - o) / d
            near, far = np.nanmax(np.minimum(t1, t2), axis=1), np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (near <= far) & (near > 0) & (near < depth)
            depth[hit], obstacle[hit] = near[hit], True
    depth[depth > zfar] = np.inf
    p = o + d * np.where(np.isfinite(depth), depth, 0)[:, None]
    intensity = np.where((np.floor(p[:, 0] / 0.2) + np.floor(p[:, 1] / 0.2)) % 2 == 0, 60, 200).astype(np.uint8)
    shape = (calib.height, calib.width)
    return depth.reshape(shape).astype(np.float32), obstacle.reshape(shape), intensity.reshape(shape)


def integrate(builder: SubmapBuilder, T: np.ndarray, t: float, boxes=()) -> None:
    depth, obstacle, intensity = render(T, boxes)
    builder.integrate(depth, T, obstacle, intensity, t, classified=np.isfinite(depth))  # the render's flags are the truth


def drive_submap(images: int = 50, length: float = 5.0, params: SubmapParams | None = None) -> Submap:
    """A submap of a straight ``length`` m drive along x with a slight weave, past the boxes."""
    builder = SubmapBuilder("lru1", params or SubmapParams(), CALIB)
    for i in range(images):
        x = length * i / (images - 1)
        T = camera_pose(x, 0.1 * math.sin(x), 0.1 * math.cos(x))
        integrate(builder, T, 0.2 * i, BOXES)
        builder.should_partition(0.01, x)
    return builder.finish(0.2 * images, 1)


# --------------------------------------------------------------------------- voxel filter


def test_voxel_filter_centroids_obstacle_any_and_mean_intensity():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.04, 0.02], [0.07, 0.01, 0.01], [-0.01, 0.02, 0.03], [0.02, 0.02, 0.02]])
    obs = np.array([False, True, False, False, False])
    inten = np.array([10, 20, 30, 40, 60], np.uint8)
    p, o, i = voxel_filter(pts, obs, inten, 0.05)
    # voxels (-1,0,0), (0,0,0) holding points 0, 1, 4, and (1,0,0); sorted by x index
    np.testing.assert_allclose(p, [[-0.01, 0.02, 0.03], [0.02, 0.07 / 3, 0.05 / 3], [0.07, 0.01, 0.01]], atol=1e-15)
    np.testing.assert_array_equal(o, [False, True, False])
    np.testing.assert_allclose(i, [40, 30, 30])


def test_voxel_filter_one_point_per_voxel_inside_it():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, (5000, 3))
    p, o, _ = voxel_filter(pts, rng.random(5000) < 0.01, np.zeros(5000), 0.1)
    cells = np.floor(p / 0.1).astype(int)
    assert len(np.unique(cells, axis=0)) == len(p) == len(np.unique(np.floor(pts / 0.1).astype(int), axis=0))
    assert o.sum() <= 50 and o.any()


def test_merged_sums_equal_one_filter_over_the_union():
    rng = np.random.default_rng(2)
    a, b = rng.uniform(0, 1, (800, 3)), rng.uniform(0.5, 1.5, (900, 3))
    oa, ob = rng.random(800) < 0.1, rng.random(900) < 0.1
    ia, ib = rng.integers(0, 256, 800), rng.integers(0, 256, 900)
    two_stage = VoxelSums.of_points(a, oa, ia, 0.1).merged(VoxelSums.of_points(b, ob, ib, 0.1)).centroids()
    once = voxel_filter(np.vstack([a, b]), np.concatenate([oa, ob]), np.concatenate([ia, ib]), 0.1)
    for x, y in zip(two_stage, once):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_merged_sums_are_each_voxels_sums_in_input_order_with_its_first_tag():
    """The numba reduction and merge against a plain per-voxel reduction in Python: the same
    float additions in the same order (bit for bit), the first contributor's tag, any flag."""
    rng = np.random.default_rng(3)
    parts = [(rng.uniform(-0.3, 0.3, (n, 3)), rng.random(n) < 0.2, rng.integers(0, 256, n), rng.random(n) < 0.5) for n in (700, 500, 600)]
    sums = [VoxelSums.of_points(p, o, i, 0.1, tag=k + 1, classified=c) for k, (p, o, i, c) in enumerate(parts)]
    merged = sums[0].merged(sums[1]).merged(sums[2])
    want: dict[tuple, list] = {}
    for k, (p, o, i, c) in enumerate(parts):
        per_part: dict[tuple, list] = {}
        for x, ob, it, cl in zip(p, o, i, c):
            cell = tuple(np.floor(x / 0.1).astype(int))
            s = per_part.setdefault(cell, [0.0, 0.0, 0.0, 0, False, 0.0, k + 1, False])
            s[0], s[1], s[2] = s[0] + x[0], s[1] + x[1], s[2] + x[2]
            s[3], s[4], s[5], s[7] = s[3] + 1, s[4] or bool(ob), s[5] + float(it), s[7] or bool(cl)
        for cell, s in per_part.items():  # a part's sums are added to the earlier parts' whole
            if cell in want:
                w = want[cell]
                w[:6] = [w[0] + s[0], w[1] + s[1], w[2] + s[2], w[3] + s[3], w[4] or s[4], w[5] + s[5]]
                w[7] = w[7] or s[7]
            else:
                want[cell] = s
    cells = sorted(want)  # the packed keys' order: x, then y, then z
    assert [tuple(c) for c in np.floor(merged.centroids()[0] / 0.1).astype(int)] == cells
    rows = [want[c] for c in cells]
    np.testing.assert_array_equal(merged.xyz, [r[:3] for r in rows])
    for k, name in enumerate(("count", "obstacle", "intensity", "tag", "classified"), start=3):
        np.testing.assert_array_equal(getattr(merged, name), [r[k] for r in rows])
    assert set(merged.tag) == {1, 2, 3} and np.all(np.diff(merged.keys) > 0)
    union = VoxelSums.union(sums)  # one reduction over all parts: the same sums
    for name in ("keys", "xyz", "count", "obstacle", "intensity", "tag", "classified"):
        np.testing.assert_array_equal(getattr(union, name), getattr(merged, name))


def test_voxel_filter_rejects_bad_input():
    with pytest.raises(SubmapException, match="shape"):
        voxel_filter(np.zeros((3, 2)), np.zeros(3, bool), np.zeros(3), 0.05)
    with pytest.raises(SubmapException, match="finite"):
        voxel_filter(np.array([[np.nan, 0, 0]]), np.zeros(1, bool), np.zeros(1), 0.05)
    with pytest.raises(SubmapException, match="resolution"):
        voxel_filter(np.zeros((1, 3)), np.zeros(1, bool), np.zeros(1), 0.0)


def test_params_validation_names_the_bad_values():
    with pytest.raises(SubmapException, match=r"max_distance_m=-1.*voxel_max_range_m=0"):
        SubmapParams(max_distance_m=-1, voxel_max_range_m=0)


# --------------------------------------------------------------------------- integration


def flat_builder(params: SubmapParams | None = None) -> tuple[SubmapBuilder, list[np.ndarray]]:
    builder = SubmapBuilder("lru1", params or SubmapParams(), CALIB)
    poses = [camera_pose(0.0, 0.0, 0.0), camera_pose(0.5, 0.2, 0.3), camera_pose(1.0, -0.1, -0.2)]
    for k, T in enumerate(poses):
        integrate(builder, T, float(k))
    return builder, poses


def test_flat_ground_points_on_the_plane_within_the_far_cut():
    builder, poses = flat_builder()
    s = builder.current()
    assert s.images == 3 and len(s.points) > 1000
    np.testing.assert_allclose(s.points[:, 2], 0.0, atol=1e-5)
    assert not s.obstacle.any()
    assert set(np.unique(s.intensity)) <= {60, 200}
    # every point lies within the far cut (z-depth, eq. 5.2c) of at least one camera; none beyond it
    z_max = max_depth_for_error(CALIB, SubmapParams().max_depth_error_m, SubmapParams().pixel_error)
    z = np.stack([(s.points - T[:3, 3]) @ T[:3, :3][:, 2] for T in poses])
    assert np.all(z.min(axis=0) <= z_max + 1e-6)
    # the far part of the image (up to 20 m) is cut there: the nearest camera's depth reaches z_max
    assert z.min(axis=0).max() > z_max - 0.1
    # at most one point per 5 cm voxel
    assert len(np.unique(np.floor(s.points / 0.05), axis=0)) == len(s.points)


def test_flat_ground_voxels_occupied_at_the_ground_and_free_above():
    builder = SubmapBuilder("lru1", SubmapParams(), CALIB)
    T = camera_pose(0.3, 0.2, 0.4)
    integrate(builder, T, 0.0)
    s = builder.current()
    ground = s.points.astype(float)
    assert np.all(s.voxels.state(ground) == VoxelState.OCCUPIED)
    for f in (0.2, 0.5, 0.8):  # on the rays between the camera and the ground
        assert np.all(s.voxels.state(T[:3, 3] + f * (ground - T[:3, 3])) == VoxelState.FREE)
    assert np.all(s.voxels.state(ground - [0, 0, 0.15]) == VoxelState.UNKNOWN)  # below the ground
    assert np.all(s.voxels.state(ground + [4.5, 0, 0]) == VoxelState.UNKNOWN)  # beyond the far cut


def test_voxel_max_range_only_clears_free_space():
    builder, _ = flat_builder(SubmapParams(voxel_max_range_m=2.0))
    s = builder.current()
    near = np.linalg.norm(s.points - [0, 0, 1.3], axis=1) < 1.6
    far = np.linalg.norm(s.points - [1.0, -0.1, 1.3], axis=1) > 2.5  # beyond 2 m of every camera
    far &= np.linalg.norm(s.points - [0.5, 0.2, 1.3], axis=1) > 2.5
    assert far.sum() > 20
    assert np.all(s.voxels.state(s.points[near].astype(float)) == VoxelState.OCCUPIED)
    assert np.all(s.voxels.state(s.points[far].astype(float)) != VoxelState.OCCUPIED)


def test_box_points_are_obstacles_and_occupied():
    builder = SubmapBuilder("lru1", SubmapParams(), CALIB)
    integrate(builder, camera_pose(0.6, -0.7, 0.0), 0.0, BOXES)
    s = builder.current()
    on_box = s.points[:, 2] > 0.05
    # 5 cm voxels touching a box (the second one, 4 m off, is within the far cut)
    near_box = np.any([np.all((s.points > lo - 0.05) & (s.points < hi + 0.05), axis=1) for lo, hi in BOXES], axis=0)
    assert on_box.sum() > 50
    assert np.all(s.obstacle[on_box]) and not np.any(s.obstacle[~near_box])
    assert np.any(s.obstacle & ~on_box)  # ground voxels at the box's foot that hold a box point: obstacle if any
    top = s.points[on_box & (s.points[:, 2] > 0.39)].astype(float)
    assert len(top) and np.all(s.voxels.state(top) == VoxelState.OCCUPIED)


def test_images_without_valid_depth_add_nothing():
    builder = SubmapBuilder("lru1", SubmapParams(), CALIB)
    T = camera_pose(0, 0, 0)
    _, obstacle, intensity = render(T)
    classified = np.ones((HEIGHT, WIDTH), bool)
    builder.integrate(np.full((HEIGHT, WIDTH), np.nan, np.float32), T, obstacle, intensity, 0.0, classified=classified)
    builder.integrate(np.full((HEIGHT, WIDTH), 9.0, np.float32), T, obstacle, intensity, 0.5, classified=classified)  # all beyond the far cut
    s = builder.current()
    assert (s.images, len(s.points), len(s.voxels), s.t_start, s.t_end) == (2, 0, 0, 0.0, 0.5)


def test_integrate_rejects_mismatched_images():
    builder = SubmapBuilder("lru1", SubmapParams(), CALIB)
    depth, obstacle, intensity = render(camera_pose(0, 0, 0), BOXES)
    known = np.isfinite(depth)
    with pytest.raises(SubmapException, match="shape"):
        builder.integrate(depth, camera_pose(0, 0, 0), obstacle[:-1], intensity, 0.0, classified=known)
    with pytest.raises(SubmapException, match="shape"):
        builder.integrate(depth, camera_pose(0, 0, 0), obstacle, intensity, 0.0, classified=known[:-1])
    with pytest.raises(SubmapException, match="4x4"):
        builder.integrate(depth, np.eye(3), obstacle, intensity, 0.0, classified=known)
    with pytest.raises(SubmapException, match=r"\(240, 320\)"):
        builder.integrate(depth[:, :-1], camera_pose(0, 0, 0), obstacle[:, :-1], intensity[:, :-1], 0.0, classified=known[:, :-1])
    assert obstacle.any()
    with pytest.raises(SubmapException, match="obstacle pixels must be classified"):
        builder.integrate(depth, camera_pose(0, 0, 0), obstacle, intensity, 0.0, classified=known & ~obstacle)


# --------------------------------------------------------------------------- partitioning and freezing


def test_partition_fires_exactly_at_the_thresholds():
    builder = SubmapBuilder("lru1", SubmapParams(max_position_std_m=0.1, max_distance_m=3.5), CALIB)
    assert builder.should_partition(np.nextafter(0.1, 0), np.nextafter(3.5, 0)) is None
    assert builder.should_partition(0.1, 0.0) == PartitionReason.POSITION_STD == "position_std"
    assert builder.should_partition(0.0, 3.5) == PartitionReason.DISTANCE == "distance"
    assert builder.should_partition(0.2, 4.0) == "position_std"  # both: std first
    with pytest.raises(SubmapException, match="position_std_m"):
        builder.should_partition(float("nan"), 0.0)


def test_finish_freezes_and_starts_the_next_submap():
    builder, _ = flat_builder()
    builder.should_partition(0.05, 1.2)
    n = len(builder.current().points)
    first = builder.finish(3.0, 4)
    assert (first.robot, first.index, first.frame_index, first.images) == ("lru1", 0, 0, 3)
    assert (first.t_start, first.t_end, first.distance_m) == (0.0, 3.0, 1.2)
    assert len(first.points) == n and first.points.dtype == np.float32 and first.intensity.dtype == np.uint8
    for a in (first.points, first.obstacle, first.intensity):
        assert not a.flags.writeable
        with pytest.raises(ValueError):
            a[0] = 1
    with pytest.raises(AttributeError):
        first.index = 3
    assert (builder.index, builder.frame_index, builder.images) == (1, 4, 0)
    nxt = builder.current()
    assert (len(nxt.points), len(nxt.voxels), nxt.t_start, nxt.distance_m) == (0, 0, 3.0, 0.0)
    # new images go to the new submap only
    T = camera_pose(0, 0, 0)
    integrate(builder, T, 3.5)
    assert len(first.points) == n and len(builder.current().points) > 0
    with pytest.raises(SubmapException, match="next_frame_index"):
        builder.finish(4.0, 4)


def test_current_is_a_snapshot():
    builder, _ = flat_builder()
    snap = builder.current()
    voxels, points = len(snap.voxels), len(snap.points)
    T = camera_pose(2.0, 0.0, 0.0)
    integrate(builder, T, 5.0)
    assert (len(snap.voxels), len(snap.points)) == (voxels, points)
    assert len(builder.current().points) > points and builder.current().t_end == 5.0


# --------------------------------------------------------------------------- exchange format


@pytest.fixture(scope="module")
def submap() -> Submap:
    return drive_submap(images=8, length=2.0)


@pytest.mark.parametrize("compress", [True, False])
def test_round_trip(submap: Submap, compress: bool):
    data = submap.to_bytes(compress=compress)
    back = Submap.from_bytes(data)
    assert (back.robot, back.index, back.frame_index, back.images) == (submap.robot, submap.index, submap.frame_index, submap.images)
    assert (back.t_start, back.t_end, back.distance_m) == (submap.t_start, submap.t_end, submap.distance_m)
    assert np.abs(back.points - submap.points).max() <= QUANTUM_M / 2 + 1e-6
    assert np.abs(back.points - submap.points).max() > 0  # really quantised
    np.testing.assert_array_equal(back.obstacle, submap.obstacle)
    assert submap.obstacle.any() and not submap.obstacle.all()
    np.testing.assert_array_equal(back.intensity, submap.intensity)
    idx_a, _ = submap.voxels.voxels()
    idx_b, _ = back.voxels.voxels()
    np.testing.assert_array_equal(idx_a, idx_b)
    centres = (idx_a + 0.5) * submap.voxels.resolution
    np.testing.assert_array_equal(back.voxels.state(centres), submap.voxels.state(centres))
    assert not back.points.flags.writeable


def test_classified_flags_round_trip_and_bound_the_obstacles():
    rng = np.random.default_rng(3)
    points = rng.uniform(-3, 3, (500, 3))
    classified = np.arange(500) < 200  # the near points, as the classification's range leaves them
    obstacle = classified & (rng.random(500) < 0.3)
    s = Submap("a", 0, 0, 0.0, 1.0, points, obstacle, classified, np.zeros(500), VoxelGrid(0.1), 1, 0.0)
    for compress in (True, False):
        back = Submap.from_bytes(s.to_bytes(compress=compress))
        np.testing.assert_array_equal(back.classified, classified)
        np.testing.assert_array_equal(back.obstacle, obstacle)
    with pytest.raises(SubmapException, match="1 obstacle points are not classified"):
        Submap("a", 0, 0, 0.0, 1.0, points, obstacle | (np.arange(500) == 300), classified, np.zeros(500), VoxelGrid(0.1), 1, 0.0)


def test_a_voxel_is_classified_if_any_of_its_points_is():
    builder = SubmapBuilder("lru1", SubmapParams(), CALIB)
    T = camera_pose(0, 0, 0)
    depth, obstacle, intensity = render(T, BOXES)
    near = np.isfinite(depth) & (depth < 2.0)
    builder.integrate(depth, T, obstacle & near, intensity, 0.0, classified=near)
    s = builder.current()
    z = (s.points.astype(float) - T[:3, 3]) @ T[:3, 2]  # z-depth of each centroid
    assert s.classified.any() and not s.classified.all()
    assert np.all(s.classified[z < 1.95]) and not np.any(s.classified[z > 2.05])  # a 5 cm voxel may straddle 2 m
    builder.integrate(depth, T, obstacle, intensity, 0.1, classified=np.isfinite(depth))  # the same view, all classified
    assert builder.current().classified.all()


def test_compression_and_size(submap: Submap):
    assert submap.size_bytes == len(submap.to_bytes()) < len(submap.to_bytes(compress=False))
    n = len(submap.points)
    assert len(submap.to_bytes(compress=False)) < n * (6 + 1 + 1) + len(submap.voxels.to_bytes()) + 200  # int16 mm coordinates


def test_far_points_use_int32_and_empty_submaps_round_trip():
    far = Submap("a", 0, 0, 0.0, 1.0, [[0, 0, 0], [80.0, 0.0, -0.0012]], [True, False], [True, True], [5, 7], VoxelGrid(0.1), 1, 0.0)
    back = Submap.from_bytes(far.to_bytes())
    np.testing.assert_allclose(back.points, far.points, atol=QUANTUM_M / 2 + 1e-6)
    assert far.to_bytes(compress=False)[7] == 4  # coordinate width
    wrap = Submap("a", 0, 0, 0.0, 1.0, [[-30, 0, 0], [30, 0, 0], [-30, 1, 0]], [True, False, True], [True] * 3, [5, 7, 9], VoxelGrid(0.1), 1, 0.0)
    assert wrap.to_bytes(compress=False)[7] == 2  # 60,000 mm steps wrap around in int16 and back
    np.testing.assert_allclose(Submap.from_bytes(wrap.to_bytes()).points, wrap.points, atol=QUANTUM_M / 2 + 1e-6)
    empty = Submap("ü", 2, 3, 0.0, 0.0, np.empty((0, 3)), [], [], [], VoxelGrid(0.1), 0, 0.0)
    back = Submap.from_bytes(empty.to_bytes())
    assert (back.robot, back.index, back.frame_index, len(back.points)) == ("ü", 2, 3, 0)


def test_format_rejects_garbage_and_unknown_versions(submap: Submap):
    data = submap.to_bytes()
    with pytest.raises(SubmapException, match="too short"):
        Submap.from_bytes(data[:10])
    with pytest.raises(SubmapException, match="magic"):
        Submap.from_bytes(b"XXXX" + data[4:])
    for version in (1, 3):  # version 1 had no classified flags
        with pytest.raises(SubmapException, match=f"version {version} is not supported"):
            Submap.from_bytes(data[:4] + struct.pack("<H", version) + data[6:])
    with pytest.raises(SubmapException, match="truncated"):
        Submap.from_bytes(data[:-5])
    with pytest.raises(SubmapException, match="trailing"):
        Submap.from_bytes(data + b"\0")
    with pytest.raises(SubmapException, match="robot name"):
        Submap.from_bytes(data[:74] + b"\xff\xfe\xfd\xfc" + data[78:])
    header = 74 + len(submap.robot.encode())
    corrupt = bytearray(data)
    corrupt[header + 4 : header + 12] = b"\xff" * 8
    with pytest.raises(SubmapException, match="corrupt"):
        Submap.from_bytes(bytes(corrupt))
