"""slam.globalmap: composition of two robots' submaps at known poses, voxel-filtered union, order-independent
voxel merge, and the cache with the never-cached current submap (thesis 5.2.2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_submap import CALIB, camera_pose, integrate, render

from slam.globalmap import GlobalMap, GlobalMapException
from slam.lie import rot_z, se3
from slam.submap import Submap, SubmapBuilder, SubmapParams
from slam.voxels import VoxelState

GROUND_Z = 0.025  # the ground in the middle of a 5 cm voxel layer, not on a voxel boundary
BOX = (np.array([1.213, -0.187, 0.0]), np.array([1.613, 0.213, 0.313]))  # in the global frame, faces off the voxel planes


def pose(x: float, y: float, yaw: float) -> np.ndarray:
    return se3(rot_z(yaw), [x, y, 0.0])


T_A = pose(0.0, 0.0, 0.0)  # lru1's submap 0: the global frame itself
T_B = pose(3.0, 0.3, math.pi)  # lru2's submap 3: facing back towards lru1's start
CAMERAS_A = [(0.0, 0.0, 0.0), (0.5, 0.1, 0.0)]  # (x, y, yaw) in the submap's frame
CAMERAS_B = [(0.0, 0.0, 0.0), (0.5, -0.1, 0.1)]


def build(robot: str, T_global_submap: np.ndarray, cameras, index: int = 0) -> SubmapBuilder:
    """A builder whose images are rendered in the global frame and integrated in the submap's frame."""
    builder = SubmapBuilder(robot, SubmapParams(), CALIB)
    for _ in range(index):
        builder.finish(0.0, builder.frame_index + 1)
    for k, (x, y, yaw) in enumerate(cameras):
        T_submap_cam = camera_pose(x, y, yaw)
        depth, obstacle, intensity = render(T_global_submap @ T_submap_cam, (BOX,), ground_z=GROUND_Z)
        builder.integrate(depth, T_submap_cam, obstacle, intensity, float(k), classified=np.isfinite(depth))
    return builder


@pytest.fixture(scope="module")
def submaps() -> tuple[Submap, Submap]:
    a = build("lru1", T_A, CAMERAS_A).finish(2.0, 1)  # sees the ground at x in [1.3, 3.0]
    b = build("lru2", T_B, CAMERAS_B, index=3).finish(2.0, 5)  # at x in [0.2, 1.7]
    return a, b


def global_map(*submaps: Submap, **kw) -> GlobalMap:
    g = GlobalMap(**kw)
    for s in submaps:
        g.set_submap(s)
    return g


POSES = {("lru1", 0): T_A, ("lru2", 3): T_B}


def test_two_robots_compose_at_the_right_place(submaps):
    a, b = submaps
    g = global_map(a, b)
    c = g.compose(POSES)
    assert g.robots() == ["lru1", "lru2"]
    ground = ~c.obstacle & (c.points[:, 2] < GROUND_Z + 0.02)
    assert ground.sum() > 2000
    np.testing.assert_allclose(c.points[ground, 2], GROUND_Z, atol=1e-5)
    # the box, seen by both robots, lands where it is in the global frame, from either robot
    lo, hi = BOX
    for robot in (0, 1):
        mine = c.obstacle & (c.labels[:, 0] == robot)
        assert mine.sum() > 20
        assert np.all((c.points[mine] > lo - 0.05) & (c.points[mine] < hi + 0.05))
    # lru2's ground reaches back towards lru1's start, where lru1 did not look; labels name its submap
    b_points = c.labels[:, 0] == 1
    np.testing.assert_array_equal(np.unique(c.labels[b_points, 1]), [3])
    assert c.points[b_points, 0].min() < 0.5 < 1.25 < c.points[ground & (c.labels[:, 0] == 0), 0].min()
    # intensities are the global checkerboard, so the submaps agree where they overlap
    checker = np.where((np.floor(c.points[:, 0] / 0.2) + np.floor(c.points[:, 1] / 0.2)) % 2 == 0, 60, 200)
    inside = np.all(np.abs(c.points[:, :2] / 0.2 - np.rint(c.points[:, :2] / 0.2)) > 0.3, axis=1)  # away from square edges
    np.testing.assert_array_equal(c.intensity[ground & inside], checker[ground & inside])


def test_union_is_voxel_filtered(submaps):
    a, b = submaps
    c = global_map(a, b).compose(POSES)
    moved = np.vstack([a.points @ T_A[:3, :3].T + T_A[:3, 3], b.points @ T_B[:3, :3].T + T_B[:3, 3]])
    cells = np.unique(np.floor(moved / 0.05), axis=0)
    assert len(c.points) == len(cells) < len(a.points) + len(b.points) - 100  # the overlap is thinned
    assert len(np.unique(np.floor(c.points / 0.05), axis=0)) == len(c.points)  # one point per voxel


def test_composition_and_grid_do_not_depend_on_arrival_order(submaps):
    a, b = submaps
    g1, g2 = global_map(a, b), global_map(b, a)
    for x, y in zip(g1.compose(POSES), g2.compose(POSES)):
        np.testing.assert_array_equal(x, y)
    v1, v2 = g1.voxel_grid(POSES), g2.voxel_grid(POSES)
    for x, y in zip(v1.voxels(), v2.voxels()):
        np.testing.assert_array_equal(x, y)
    # the merged grid: occupied at the ground both robots saw, free on the rays of one of the robot's cameras
    c = g1.compose(POSES)
    ground = ~c.obstacle
    assert np.mean(v1.state(c.points[ground].astype(float)) == VoxelState.OCCUPIED) > 0.97
    for robot, T, cams in ((0, T_A, CAMERAS_A), (1, T_B, CAMERAS_B)):
        p = c.points[ground & (c.labels[:, 0] == robot)].astype(float)
        mid = [(T @ camera_pose(*cam))[:3, 3] for cam in cams]
        free = [v1.state(o + 0.5 * (p - o)) == VoxelState.FREE for o in mid]
        assert np.mean(free[0] | free[1]) > 0.97


def test_grid_merge_is_sequential_in_sorted_order(submaps):
    a, b = submaps
    expected = global_map(a).voxel_grid({("lru1", 0): T_A})
    expected.merge_transformed(b.voxels, T_B)
    got = global_map(b, a).voxel_grid(POSES)
    for x, y in zip(got.voxels(), expected.voxels()):
        np.testing.assert_array_equal(x, y)


def test_cache_hits_within_tolerance_and_recomposes_beyond(submaps):
    a, b = submaps
    g = global_map(a, b, translation_tolerance_m=0.05, rotation_tolerance_rad=math.radians(1))
    first = g.compose(POSES)
    again = g.compose({k: T.copy() for k, T in POSES.items()})
    assert (g.stats.cloud_recompositions, g.stats.cloud_hits) == (1, 1)
    np.testing.assert_array_equal(first.points, again.points)
    small = dict(POSES)
    small[("lru2", 3)] = T_B @ pose(0.04, 0.0, math.radians(0.9))  # 4 cm, 0.9 deg: within the tolerances
    np.testing.assert_array_equal(g.compose(small).points, first.points)  # the cached poses are used
    assert (g.stats.cloud_recompositions, g.stats.cloud_hits) == (1, 2)
    for moved in (T_B @ pose(0.06, 0.0, 0.0), T_B @ pose(0.0, 0.0, math.radians(1.1))):
        g.compose(POSES)
        recompositions = g.stats.cloud_recompositions
        g.compose({**POSES, ("lru2", 3): moved})
        assert g.stats.cloud_recompositions == recompositions + 1
    # recomposed with the new pose: lru2's points away from the overlap move with it (0.3 m = 6 voxels)
    shifted = g.compose({**POSES, ("lru2", 3): pose(0.3, 0.0, 0.0) @ T_B})
    only_b = first.points[(first.labels[:, 0] == 1) & (first.points[:, 0] < 0.9)]
    assert len(only_b) > 200
    gap = np.linalg.norm(only_b[:, None] + [0.3, 0, 0] - shifted.points[None], axis=2).min(axis=1)
    assert gap.max() < 1e-4
    # a new submap, or a pose that appears, recomposes
    g2 = global_map(a)
    g2.compose(POSES)
    g2.set_submap(b)
    g2.compose(POSES)
    g2.compose({("lru1", 0): T_A})
    assert (g2.stats.cloud_recompositions, g2.stats.cloud_hits) == (3, 0)


def test_grid_cache(submaps):
    a, b = submaps
    g = global_map(a, b)
    v = g.voxel_grid(POSES)
    v.merge(v)  # callers get a copy: changing it does not touch the cache
    again = g.voxel_grid(POSES)
    assert (g.stats.grid_recompositions, g.stats.grid_hits) == (1, 1)
    np.testing.assert_array_equal(again.voxels()[1], g.voxel_grid(POSES).voxels()[1])
    assert not np.array_equal(v.voxels()[1], again.voxels()[1])
    g.voxel_grid({**POSES, ("lru2", 3): pose(0.1, 0, 0) @ T_B})
    assert (g.stats.grid_recompositions, g.stats.grid_hits) == (2, 2)


def test_current_submap_is_always_fresh(submaps):
    a, b = submaps
    g = global_map(a, b)
    builder = SubmapBuilder("lru1", SubmapParams(), CALIB, frame_index=1)
    builder.finish(0.0, 2)  # lru1's submap 1 is its current one here
    T_cur = pose(-2.0, 0.0, 0.0)
    integrate(builder, camera_pose(0.0, 0.0, 0.0), 0.0)
    one = g.compose(POSES, current=(builder.current(), T_cur))
    grid_one = g.voxel_grid(POSES, current=(builder.current(), T_cur))
    integrate(builder, camera_pose(0.0, 3.0, 0.0), 1.0)  # beside the first view, which reaches y = 1.9 m at the 4 m cut
    two = g.compose(POSES, current=(builder.current(), T_cur))
    grid_two = g.voxel_grid(POSES, current=(builder.current(), T_cur))
    assert (g.stats.cloud_recompositions, g.stats.cloud_hits, g.stats.grid_recompositions, g.stats.grid_hits) == (1, 1, 1, 1)
    cur_one, cur_two = np.all(one.labels == [0, 1], axis=1), np.all(two.labels == [0, 1], axis=1)
    assert cur_one.sum() > 100 and cur_two.sum() > cur_one.sum() + 100  # the second image is in
    assert two.points[cur_two, 1].max() > 3.0 > one.points[cur_one, 1].max()
    assert len(grid_two) > len(grid_one)
    # without the current submap, the cached finished map alone
    np.testing.assert_array_equal(g.compose(POSES).points, global_map(a, b).compose(POSES).points)


def test_current_is_exactly_one_filter_over_all_points(submaps):
    a, b = submaps
    cur = build("lru3", np.eye(4), [(1.0, 0.0, 0.0)]).current()
    with_current = global_map(a, b).compose(POSES, current=(cur, np.eye(4)))
    all_stored = global_map(a, b, cur).compose({**POSES, ("lru3", 0): np.eye(4)})
    assert with_current.labels[:, 0].max() == 2
    for x, y in zip(with_current, all_stored):
        np.testing.assert_array_equal(x, y)


def test_input_errors(submaps):
    a, _ = submaps
    g = global_map(a)
    with pytest.raises(GlobalMapException, match="already set"):
        g.set_submap(a)
    with pytest.raises(GlobalMapException, match="also stored"):
        g.compose(POSES, current=(a, T_A))
    with pytest.raises(GlobalMapException, match="not rigid"):
        g.compose({("lru1", 0): np.diag([2.0, 1, 1, 1])})
    with pytest.raises(GlobalMapException, match="voxels"):
        GlobalMap(voxel_resolution_m=0.2).set_submap(a)
