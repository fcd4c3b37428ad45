"""Each robot's map in the results folder (thesis 5.2.2; docs/mapping.md).

::

    maps/<robot>.ply            global point cloud of the robot's map (binary PLY, map frame):
                                x y z, grey intensity, obstacle flag, robot number, submap index
    maps/<robot>.voxels         merged log-odds voxel grid (``slam.voxels.VoxelGrid.to_bytes``)
    maps/<robot>.occupied.ply   centres of its occupied voxels (map frame)
    map_topdown.png             per robot: map points by height, obstacles, submap origins, true path

The map frame is the robot's first local frame (gravity-aligned start pose). With the
graph the map holds every submap the robot has, its peers' included, placed by its
graph; without it, its own submaps placed by chaining the filter's frame switches.
``metrics.json`` gets ``robots.<name>.map``: submap count, sizes and partition reasons,
map size, ``T_world_map`` (from the true start pose, for evaluation only) and the map
quality of :mod:`sim.evaluation.map_quality` in the world frame. The section reads a
:class:`sim.evaluation.inputs.MapInput`; what the top-down plot draws comes back apart,
as a :class:`MapPlot`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim.evaluation import trajectory
from sim.evaluation.inputs import MapInput, TeamTruth
from sim.evaluation.map_quality import map_quality
from sim.world.terrain import Terrain
from slam.globalmap import GlobalMap


@dataclass(frozen=True, eq=False)
class MapPlot:
    """What the top-down plot draws of one robot's map, in the world frame."""

    points: np.ndarray  # (n, 3)
    obstacle: np.ndarray  # (n,) bool
    origins: np.ndarray  # (k, 3) submap origins


def compose(robot_map: MapInput) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, np.ndarray, Any]:
    """The robot's global map from its placed submaps and its active one: poses by
    submap key, points, obstacle flags, intensities, submap labels and the voxel grid.
    With the graph, the team's map: every submap the robot holds (its peers' included)
    on the graph's submap origins; without it, its own submaps on its filter's chained
    frame switches (:func:`sim.evaluation.inputs.map_input` places them)."""
    cfg = robot_map.mapping
    gmap = GlobalMap(point_resolution_m=cfg.point_resolution_m, voxel_resolution_m=cfg.voxel_resolution_m)
    poses = {}
    for submap, origin in robot_map.placed:
        gmap.set_submap(submap)
        poses[submap.key] = origin
    points, obstacle, intensity, labels = gmap.compose(poses, current=robot_map.current)
    voxels = gmap.voxel_grid(poses, current=robot_map.current)
    return poses, points, obstacle, intensity, labels, voxels


def map_section(
    out: Path, name: str, robot_map: MapInput | None, truth: TeamTruth, terrain: Terrain, recorder=None, robot_number: int = 0
) -> tuple[dict[str, Any], MapPlot | None]:
    """Write the robot's map files (and into the recording, if given); return its ``map``
    metrics and what the top-down plot draws of it."""
    if robot_map is None or robot_map.start_t is None:
        return {"status": "no mapping" if robot_map is None else "not started"}, None
    poses, points, obstacle, intensity, labels, voxels = compose(robot_map)
    own = robot_map.own_submaps
    sizes = [s.size_bytes for s in own]
    reasons = [r for _, r in robot_map.partitions]
    section: dict[str, Any] = {
        "status": "ok",
        "submaps": len(own) + (1 if robot_map.active_images else 0),
        "finished_submaps": len(own),
        "partitions": {str(r): reasons.count(r) for r in sorted(set(reasons))},
        "submap_bytes": {"mean": float(np.mean(sizes)), "max": int(max(sizes))} if sizes else None,
        "peer_submaps_placed": sum(robot != name for robot, _ in poses),
        "images_integrated": robot_map.images_integrated,
        "points": len(points),
        "obstacle_points": int(obstacle.sum()),
        "voxels": len(voxels),
        "occupied_voxels": len(voxels.occupied_centers()),
    }
    maps = out / "maps"
    maps.mkdir(parents=True, exist_ok=True)
    fields = {"intensity": intensity, "obstacle": obstacle.astype(np.uint8)}
    fields |= {"robot": labels[:, 0].astype(np.uint8), "submap": labels[:, 1].astype(np.uint16)}
    write_ply(maps / f"{name}.ply", points, fields)
    (maps / f"{name}.voxels").write_bytes(voxels.to_bytes())
    write_ply(maps / f"{name}.occupied.ply", voxels.occupied_centers(), {})
    if len(points) == 0:
        section["quality"] = None
        return section, None
    T_world_map = trajectory.truth_since(truth.of(name), robot_map.start_t).T_world_start
    section["T_world_map"] = T_world_map.tolist()
    world = points @ T_world_map[:3, :3].T + T_world_map[:3, 3]
    section["quality"] = map_quality(world, obstacle, terrain)
    origins = np.array([T_world_map @ T for T in poses.values()]).reshape(-1, 4, 4)[:, :3, 3]
    if recorder is not None:
        # the rolling obstacle map lives in the odometry frame (= the map frame) and has no
        # heights: its cells are drawn at the robot's final height
        rolling = robot_map.rolling
        cells = rolling.cell_centers()[rolling.obstacles]
        cells_world = np.column_stack([cells, np.zeros(len(cells))]) @ T_world_map[:3, :3].T + T_world_map[:3, 3]
        cells_world[:, 2] = (T_world_map @ robot_map.T_map_body)[2, 3]
        recorder.log_map(name, robot_number, world, labels[:, 1], obstacle, origins, cells_world)
    return section, MapPlot(world, obstacle, origins)


_PLY_TYPES = {np.dtype(np.float32): "float", np.dtype(np.uint8): "uchar", np.dtype(np.uint16): "ushort"}


def write_ply(path: Path, points: np.ndarray, fields: dict[str, np.ndarray]) -> None:
    """Binary little-endian PLY of float32 points with extra per-point properties."""
    points = np.asarray(points, dtype=np.float32)
    columns = [("x", points[:, 0]), ("y", points[:, 1]), ("z", points[:, 2])] + [(k, np.asarray(v)) for k, v in fields.items()]
    dtype = np.dtype([(k, v.dtype.newbyteorder("<")) for k, v in columns])
    rows = np.empty(len(points), dtype=dtype)
    for k, v in columns:
        rows[k] = v
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {_PLY_TYPES[v.dtype]} {k}" for k, v in columns]
    header.append("end_header\n")
    path.write_bytes("\n".join(header).encode() + rows.tobytes())


def plot_maps(maps: dict[str, dict], plots: dict[str, MapPlot | None], truth: TeamTruth, terrain: Terrain, path: Path) -> None:
    """Top-down view of every robot's map in the world frame: points by height, obstacles red."""
    import matplotlib.pyplot as plt

    robots = [name for name, plot in plots.items() if plot is not None]
    if not robots:
        return
    fig, axes = plt.subplots(1, len(robots), figsize=(6 * len(robots), 5.5), squeeze=False)
    half = terrain.size_m / 2
    for ax, name in zip(axes[0], robots):
        world, obstacle, origins = plots[name].points, plots[name].obstacle, plots[name].origins
        lo, hi = np.percentile(world[:, 2], [2, 98])  # robust colour range: points on other robots stand far above
        sc = ax.scatter(world[~obstacle, 0], world[~obstacle, 1], c=world[~obstacle, 2], s=0.5, cmap="viridis", vmin=lo, vmax=hi, rasterized=True)
        ax.scatter(world[obstacle, 0], world[obstacle, 1], c="red", s=1.5, label="obstacle points", rasterized=True)
        gt = truth.of(name).positions
        ax.plot(gt[:, 0], gt[:, 1], "k-", lw=1, label="true path")
        ax.plot(origins[:, 0], origins[:, 1], "^", color="orange", mec="k", ms=7, label="submap origins")
        q = maps[name]["quality"]
        ax.set_title(
            f"{name}: {maps[name]['submaps']} submaps, accuracy median {100 * q['accuracy']['median_m']:.1f} cm, "
            f"completeness {100 * q['completeness']['share']:.0f} %",
            fontsize=9,
        )
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper right", fontsize=7, markerscale=3)
        fig.colorbar(sc, ax=ax, label="height [m]", shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
