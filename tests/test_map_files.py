"""The map files of the results folder (sim.evaluation.maps.write_map_files, docs/mapping.md "Map files"): a
two-robot global map (thesis 5.2.2) written and read back with Open3D's tensor and legacy APIs and numpy."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import open3d as o3d
import pytest
from test_globalmap import BOX, CAMERAS_A, CAMERAS_B, GROUND_Z, POSES, T_A, T_B, build
from test_submap import camera_pose, render

from sim.evaluation.maps import write_map_files, write_ply
from slam.globalmap import Composition, GlobalMap
from slam.voxels import VoxelGrid, VoxelState


class Written(NamedTuple):
    maps: Path
    cloud: Composition
    names: list[str]
    voxels: VoxelGrid


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """lru2's map of lru1's submap 0 and its own submap 3, both on the box, and its active submap 4 (one more image
    of the box, classified only within 2 m, placed on submap 3's origin), written as a run writes it."""
    a = build("lru1", T_A, CAMERAS_A).finish(2.0, 1)
    builder = build("lru2", T_B, CAMERAS_B, index=3)
    b = builder.finish(2.0, 5)
    T_submap_cam = camera_pose(0.2, 0.0, 0.0)
    depth, obstacle, intensity = render(T_B @ T_submap_cam, (BOX,), ground_z=GROUND_Z)
    near = np.isfinite(depth) & (depth < 2.0)
    builder.integrate(depth, T_submap_cam, obstacle & near, intensity, 3.0, classified=near)
    current = (builder.current(), T_B)
    gmap = GlobalMap()
    for submap in (a, b):
        gmap.set_submap(submap)
    cloud = gmap.compose(POSES, current=current)
    names = gmap.robots(current[0])
    voxels = gmap.voxel_grid(POSES, current=current)
    maps = tmp_path_factory.mktemp("run") / "maps"
    write_map_files(maps, "lru2", cloud, names, voxels)
    return Written(maps, cloud, names, voxels)


def test_the_map_has_every_kind_of_point(written):
    _, cloud, names, _ = written
    assert names == ["lru1", "lru2"]
    assert {tuple(label) for label in np.unique(cloud.labels, axis=0)} == {(0, 0), (1, 3), (1, 4)}
    assert cloud.obstacle.any() and not cloud.obstacle.all()
    assert len(np.unique(cloud.intensity)) > 1
    assert not np.any(cloud.obstacle & ~cloud.classified)
    unclassified = ~cloud.classified
    assert unclassified.any() and set(np.unique(cloud.labels[unclassified, 1])) == {4}  # only the active submap's far points


def test_the_point_cloud_reads_back_whole_in_open3d_tensor_api(written):
    maps, composed, _, _ = written
    points, intensity, labels = composed.points, composed.intensity, composed.labels
    cloud = o3d.t.io.read_point_cloud(str(maps / "lru2.ply")).point
    fields = {k: cloud[k].numpy() for k in cloud}
    assert {k: (v.dtype, v.shape) for k, v in fields.items()} == {
        "positions": (np.float32, (len(points), 3)),
        "colors": (np.uint8, (len(points), 3)),
        "intensity": (np.uint8, (len(points), 1)),
        "obstacle": (np.uint8, (len(points), 1)),
        "classified": (np.uint8, (len(points), 1)),
        "robot": (np.uint8, (len(points), 1)),
        "submap": (np.int32, (len(points), 1)),
    }
    np.testing.assert_array_equal(fields["positions"], points)
    np.testing.assert_array_equal(fields["colors"], np.repeat(intensity[:, None], 3, axis=1))
    np.testing.assert_array_equal(fields["intensity"][:, 0], intensity)
    np.testing.assert_array_equal(fields["obstacle"][:, 0], composed.obstacle)
    np.testing.assert_array_equal(fields["classified"][:, 0], composed.classified)
    np.testing.assert_array_equal(fields["robot"][:, 0], labels[:, 0])
    np.testing.assert_array_equal(fields["submap"][:, 0], labels[:, 1])
    header = (maps / "lru2.ply").read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert header[1] == "format binary_little_endian 1.0"
    assert [line for line in header if line.startswith("comment")] == ["comment robot 0 lru1", "comment robot 1 lru2"]


def test_the_legacy_api_keeps_positions_and_intensity_as_grey(written):
    maps, composed, _, _ = written
    cloud = o3d.io.read_point_cloud(str(maps / "lru2.ply"))
    np.testing.assert_array_equal(np.asarray(cloud.points), composed.points.astype(np.float64))
    np.testing.assert_allclose(np.asarray(cloud.colors), np.repeat(composed.intensity[:, None] / 255.0, 3, axis=1), atol=1e-12)


def test_the_voxel_grid_reads_back_exactly_with_numpy(written):
    maps, _, _, voxels = written
    with np.load(maps / "lru2.voxels.npz") as npz:
        arrays = dict(npz)
    assert {k: (v.dtype, v.shape) for k, v in arrays.items()} == {
        "indices": (np.int32, (len(voxels), 3)),
        "log_odds": (np.float32, (len(voxels),)),
        "resolution": (np.float64, ()),
        "origin": (np.float64, (3,)),
    }
    indices, log_odds = voxels.voxels()
    np.testing.assert_array_equal(arrays["indices"], indices)
    np.testing.assert_array_equal(arrays["log_odds"], log_odds)
    assert arrays["resolution"] == voxels.resolution
    centres = arrays["origin"] + (arrays["indices"] + 0.5) * arrays["resolution"]
    np.testing.assert_array_equal(centres[arrays["log_odds"] > 0], voxels.occupied_centers())
    # the convention places each voxel where the grid itself looks it up
    np.testing.assert_array_equal(voxels.log_odds(centres), arrays["log_odds"])
    states = voxels.state(centres)
    assert (states == VoxelState.OCCUPIED).any() and (states == VoxelState.FREE).any()
    np.testing.assert_array_equal(states == VoxelState.OCCUPIED, arrays["log_odds"] > 0)
    rebuilt = VoxelGrid.from_voxels(arrays["indices"], arrays["log_odds"], float(arrays["resolution"]))
    for x, y in zip(rebuilt.voxels(), voxels.voxels()):
        np.testing.assert_array_equal(x, y)


def test_the_occupied_voxels_read_back_in_open3d(written):
    maps, _, _, voxels = written
    cloud = o3d.t.io.read_point_cloud(str(maps / "lru2.occupied.ply")).point
    assert list(cloud) == ["positions"]
    np.testing.assert_array_equal(cloud["positions"].numpy(), voxels.occupied_centers().astype(np.float32))


def test_an_empty_map_writes_empty_files(tmp_path: Path):
    nothing = Composition(np.zeros((0, 3), np.float32), np.zeros(0, bool), np.zeros(0, np.uint8), np.zeros((0, 2), np.int64), np.zeros(0, bool))
    write_map_files(tmp_path, "lru1", nothing, [], VoxelGrid())
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "lru1.ply")).point
    fields = ("positions", "colors", "intensity", "obstacle", "classified", "robot", "submap")
    assert {k: cloud[k].shape[0] for k in cloud} == dict.fromkeys(fields, 0)
    with np.load(tmp_path / "lru1.voxels.npz") as npz:
        assert npz["indices"].shape == (0, 3) and npz["log_odds"].shape == (0,)


def test_write_ply_refuses_types_open3d_would_drop(tmp_path: Path):
    with pytest.raises(ValueError, match="'submap' has dtype uint16"):
        write_ply(tmp_path / "x.ply", np.zeros((1, 3)), {"submap": np.zeros(1, np.uint16)})
