"""Each robot's map in the results folder (thesis 5.2.2; docs/mapping.md).

::

    maps/<robot>.ply            global point cloud of the robot's map (binary PLY, map frame): x y z,
                                grey colour, intensity, obstacle flag, classified flag, robot number,
                                submap index
    maps/<robot>.voxels.npz     merged log-odds voxel grid (``slam.voxels.VoxelGrid.to_arrays``)
    maps/<robot>.occupied.ply   centres of its occupied voxels (map frame)
    map_topdown.png             per robot: map points by height, obstacles, submap origins, true path

The map frame is the robot's first local frame (gravity-aligned start pose). With the
graph the map holds every submap the robot has, its peers' included, placed by its
graph; without it, its own submaps placed by chaining the filter's frame switches.
``metrics.json`` gets ``robots.<name>.map``: submap count, sizes and partition reasons,
map size, ``T_world_map`` (from the true start pose, for evaluation only) and the map
quality of :mod:`sim.evaluation.map_quality` in the world frame (``quality``: the map as
the robot holds it, so its obstacle scores carry its localisation error too), and
``classification``: the obstacle scores of the robot's own submaps, each placed on its true
origin, which measure the obstacle classification (thesis 5.1.1) alone. Map points seen on
or beside another robot (within its ``body_radius_m`` of its true path while the submap
was built, plus the classification window) are left out of both obstacle scores and counted. The section reads a
:class:`sim.evaluation.inputs.MapInput`; what the top-down plot draws comes back apart,
as a :class:`MapPlot`.

The files are read with Open3D's tensor API (``open3d.t.io.read_point_cloud``) and numpy
(fields and loading in docs/mapping.md, "Map files"): every PLY property has a type that
reader keeps (float, double, uchar, int; it skips short, ushort, char and uint). Open3D's
legacy reader (``open3d.io.read_point_cloud``) keeps only positions, normals and colours,
so the grey value is written as colour too (red = green = blue = intensity). The header
comments ``robot <number> <name>`` name the robot numbers. The grid goes to ``.npz`` as
exact arrays rather than in ``VoxelGrid.to_bytes``, the network encoding, which quantises
log-odds to int8 and needs marsyard to read; ``VoxelGrid.from_voxels`` rebuilds the grid
from the arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from sim.evaluation import trajectory
from sim.evaluation.inputs import MapInput, TeamTruth
from sim.evaluation.map_quality import MapQualityParams, ObstacleScore, map_quality, score_obstacles
from sim.world.terrain import Terrain
from slam.globalmap import Composition, GlobalMap
from slam.submap import Submap
from slam.voxels import VoxelGrid


@dataclass(frozen=True, eq=False)
class MapPlot:
    """What the top-down plot draws of one robot's map, in the world frame."""

    points: np.ndarray  # (n, 3)
    obstacle: np.ndarray  # (n,) bool
    origins: np.ndarray  # (k, 3) submap origins
    obstacles: ObstacleScore  # of the map as held: true, false and missed obstacle cells


def compose(robot_map: MapInput) -> tuple[dict, Composition, list[str], Any]:
    """The robot's global map from its placed submaps and its active one: poses by
    submap key, the point cloud (points, obstacle flags, intensities, submap labels (robot
    number, submap index), classified flags), the robot names the numbers stand for, and
    the voxel grid.
    With the graph, the team's map: every submap the robot holds (its peers' included)
    on the graph's submap origins; without it, its own submaps on its filter's chained
    frame switches (:func:`sim.evaluation.inputs.map_input` places them)."""
    cfg = robot_map.mapping
    gmap = GlobalMap(point_resolution_m=cfg.point_resolution_m, voxel_resolution_m=cfg.voxel_resolution_m)
    poses = {}
    for submap, origin in robot_map.placed:
        gmap.set_submap(submap)
        poses[submap.key] = origin
    cloud = gmap.compose(poses, current=robot_map.current)
    voxels = gmap.voxel_grid(poses, current=robot_map.current)
    names = gmap.robots(robot_map.current[0] if robot_map.current else None)
    return poses, cloud, names, voxels


def map_section(
    out: Path, name: str, robot_map: MapInput | None, truth: TeamTruth, terrain: Terrain, recorder=None, robot_number: int = 0
) -> tuple[dict[str, Any], MapPlot | None]:
    """Write the robot's map files (and into the recording, if given); return its ``map``
    metrics and what the top-down plot draws of it."""
    if robot_map is None or robot_map.start_t is None:
        return {"status": "no mapping" if robot_map is None else "not started"}, None
    poses, cloud, names, voxels = compose(robot_map)
    points, obstacle, labels = cloud.points, cloud.obstacle, cloud.labels
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
    write_map_files(out / "maps", name, cloud, names, voxels)
    if len(points) == 0:
        section["quality"] = None
        return section, None
    T_world_map = trajectory.truth_since(truth.of(name), robot_map.start_t).T_world_start
    section["T_world_map"] = T_world_map.tolist()
    world = points @ T_world_map[:3, :3].T + T_world_map[:3, 3]
    submaps = [s for s, _ in robot_map.placed] + ([robot_map.current[0]] if robot_map.current else [])
    submap_of = _submap_of(labels, names, submaps)
    params = MapQualityParams(obstacle=robot_map.obstacle)
    quality = map_quality(world, obstacle, terrain, params, on_robots(world, submap_of, submaps, truth, params), cloud.classified)
    section["quality"] = quality.metrics()
    classification = own_submaps_on_truth(name, robot_map, truth, terrain)
    section["classification"] = classification.metrics() if classification is not None else None
    cells = robot_map.image_cells
    section["classification_images"] = cells.metrics(terrain) if cells is not None and cells.images else None
    origins = np.array([T_world_map @ T for T in poses.values()]).reshape(-1, 4, 4)[:, :3, 3]
    if recorder is not None:
        # the rolling obstacle map lives in the odometry frame (= the map frame) and has no
        # heights: its cells are drawn at the robot's final height
        rolling = robot_map.rolling
        cells = rolling.cell_centers()[rolling.obstacles]
        cells_world = np.column_stack([cells, np.zeros(len(cells))]) @ T_world_map[:3, :3].T + T_world_map[:3, 3]
        cells_world[:, 2] = (T_world_map @ robot_map.T_map_body)[2, 3]
        recorder.log_map(name, robot_number, world, labels[:, 1], obstacle, origins, cells_world)
    return section, MapPlot(world, obstacle, origins, quality.obstacles)


def on_robots(world: np.ndarray, submap_of: np.ndarray, submaps: list[Submap], truth: TeamTruth, params: MapQualityParams) -> np.ndarray:
    """Points (n, 3, world) seen on or beside another robot than their submap's own (point i
    is in ``submaps[submap_of[i]]``): within its ``body_radius_m`` of its true position at
    some time while the submap was built, plus :attr:`MapQualityParams.robot_margin_m`.
    The static truth holds no robots, so such points cannot be scored against it. (A
    robot that moved during the submap takes the ground along its path out of the scores, too.)"""
    margin = params.robot_margin_m
    out = np.zeros(len(world), bool)
    order = np.argsort(submap_of, kind="stable")
    bounds = np.searchsorted(submap_of[order], np.arange(len(submaps) + 1))
    for k, submap in enumerate(submaps):
        idx = order[bounds[k] : bounds[k + 1]]
        for robot, path in truth.robots.items():
            during = (path.t >= submap.t_start - 0.5) & (path.t <= submap.t_end + 0.5)
            if robot == submap.robot or len(idx) == 0 or not during.any():
                continue
            d, _ = cKDTree(path.positions[during, :2]).query(world[idx, :2])
            out[idx] |= d < truth.body_radius_m[robot] + margin
    return out


def _submap_of(labels: np.ndarray, names: list[str], submaps: list[Submap]) -> np.ndarray:
    """Index into ``submaps`` of each point's submap from its compose label (robot number in
    ``names``, submap index)."""
    table = {key: k for k, key in enumerate(s.key for s in submaps)}
    lut = np.array([table[(names[r], i)] for r, i in np.unique(labels, axis=0)], dtype=np.int64).reshape(-1)
    _, inverse = np.unique(labels, axis=0, return_inverse=True)
    return lut[inverse.ravel()]


def own_submaps_on_truth(name: str, robot_map: MapInput, truth: TeamTruth, terrain: Terrain) -> ObstacleScore | None:
    """Obstacle scores of the robot's own submaps (finished and active), each placed on its
    true origin (:func:`sim.evaluation.trajectory.frame_origins_truth`) and merged as the
    robot merges its map: the classification (thesis 5.1.1) without the localisation error."""
    origins = trajectory.frame_origins_truth(robot_map.start_t, robot_map.switch_times, truth.of(name))
    finished = [s for s in robot_map.own_submaps if s.frame_index in origins]
    active = robot_map.current[0] if robot_map.current is not None and robot_map.current[0].robot == name else None
    current = (active, origins[active.frame_index]) if active is not None and active.frame_index in origins else None
    if not finished and current is None:
        return None
    cfg = robot_map.mapping
    gmap = GlobalMap(point_resolution_m=cfg.point_resolution_m, voxel_resolution_m=cfg.voxel_resolution_m)
    for submap in finished:
        gmap.set_submap(submap)
    cloud = gmap.compose({s.key: origins[s.frame_index] for s in finished}, current=current)
    if len(cloud.points) == 0:
        return None
    own = finished + ([active] if current is not None else [])
    world = np.asarray(cloud.points, float)
    params = MapQualityParams(obstacle=robot_map.obstacle)
    on = on_robots(world, _submap_of(cloud.labels, [name], own), own, truth, params)
    return score_obstacles(world, cloud.obstacle, terrain, params, on, cloud.classified)


def _share(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def write_map_files(maps: Path, name: str, cloud: Composition, names: list[str], voxels: VoxelGrid) -> None:
    """The robot's map files in ``maps`` (thesis 5.2.2), from its composed map (:func:`compose`): the point cloud
    (``<name>.ply``: grey colour, intensity, obstacle flag, classified flag, robot number in ``names``, submap
    index), the voxel grid (``<name>.voxels.npz``, :meth:`slam.voxels.VoxelGrid.to_arrays`) and its occupied
    voxels' centres (``<name>.occupied.ply``)."""
    maps.mkdir(parents=True, exist_ok=True)
    i = cloud.intensity
    fields = {"red": i, "green": i, "blue": i, "intensity": i}
    fields |= {"obstacle": cloud.obstacle.astype(np.uint8), "classified": cloud.classified.astype(np.uint8)}
    fields |= {"robot": cloud.labels[:, 0].astype(np.uint8), "submap": cloud.labels[:, 1].astype(np.int32)}
    write_ply(maps / f"{name}.ply", cloud.points, fields, tuple(f"robot {number} {robot}" for number, robot in enumerate(names)))
    np.savez_compressed(maps / f"{name}.voxels.npz", **voxels.to_arrays())
    write_ply(maps / f"{name}.occupied.ply", voxels.occupied_centers(), {})


#: PLY property types that Open3D's tensor reader (``open3d.t.io.read_point_cloud``, 0.20) keeps; it skips short,
#: ushort, char and uint properties
_PLOT_CELL_M = 0.1  # cells of the top-down map plot: those of the voxel grid (thesis 5.1.2)
_PLY_TYPES = {np.dtype(np.float32): "float", np.dtype(np.float64): "double", np.dtype(np.uint8): "uchar", np.dtype(np.int32): "int"}


def write_ply(path: Path, points: np.ndarray, fields: dict[str, np.ndarray], comments: tuple[str, ...] = ()) -> None:
    """Binary little-endian PLY of float32 points with extra per-point properties (float32, float64, uint8 or
    int32) and header ``comments``."""
    points = np.asarray(points, dtype=np.float32)
    columns = [("x", points[:, 0]), ("y", points[:, 1]), ("z", points[:, 2])] + [(k, np.asarray(v)) for k, v in fields.items()]
    for k, v in columns:
        if v.dtype not in _PLY_TYPES:
            raise ValueError(f"PLY property {k!r} has dtype {v.dtype}; allowed: {', '.join(str(t) for t in _PLY_TYPES)}")
    dtype = np.dtype([(k, v.dtype.newbyteorder("<")) for k, v in columns])
    rows = np.empty(len(points), dtype=dtype)
    for k, v in columns:
        rows[k] = v
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {len(points)}"]
    header += [f"property {_PLY_TYPES[v.dtype]} {k}" for k, v in columns]
    header.append("end_header\n")
    path.write_bytes("\n".join(header).encode() + rows.tobytes())


def plot_maps(maps: dict[str, dict], plots: dict[str, MapPlot | None], truth: TeamTruth, terrain: Terrain, path: Path) -> None:
    """Top-down view of every robot's map in the world frame: points by height; obstacle
    cells as scored against the truth: true (flagged and true), false (flagged only) and
    missed (true cells the map saw but did not flag)."""
    import matplotlib.pyplot as plt

    robots = [name for name, plot in plots.items() if plot is not None]
    if not robots:
        return
    fig, axes = plt.subplots(1, len(robots), figsize=(6 * len(robots), 5.5), squeeze=False)
    half = terrain.size_m / 2
    for ax, name in zip(axes[0], robots):
        world, obstacle, origins = plots[name].points, plots[name].obstacle, plots[name].origins
        lo, hi = np.percentile(world[:, 2], [2, 98])  # robust colour range: points on other robots stand far above
        # the points as an image of their mean height per cell: it looks as a scatter of the points did, but two
        # panels of a 629,000-point Etna map draw in 1.1-1.3 s instead of 31-35 s (docs/architecture.md, "Rendering cost")
        bins = max(1, math.ceil(terrain.size_m / _PLOT_CELL_M))
        ground = world[~obstacle]
        area = ((-half, half), (-half, half))
        sums, _, _ = np.histogram2d(ground[:, 0], ground[:, 1], bins=bins, range=area, weights=ground[:, 2])
        counts, _, _ = np.histogram2d(ground[:, 0], ground[:, 1], bins=bins, range=area)
        with np.errstate(invalid="ignore", divide="ignore"):
            height = np.where(counts > 0, sums / counts, np.nan)
        sc = ax.imshow(height.T, origin="lower", extent=(-half, half, -half, half), cmap="viridis", vmin=lo, vmax=hi, interpolation="nearest")
        score = plots[name].obstacles
        cells = ((score.tp_xy, "blue", "true obstacle"), (score.fp_xy, "red", "false obstacle"), (score.missed_xy, "orange", "missed obstacle"))
        for xy, colour, label in cells:
            ax.scatter(xy[:, 0], xy[:, 1], c=colour, s=1.5, marker="s", label=f"{label} ({len(xy)} cells)", rasterized=True)
        gt = truth.of(name).positions
        ax.plot(gt[:, 0], gt[:, 1], "k-", lw=1, label="true path")
        ax.plot(origins[:, 0], origins[:, 1], "^", color="orange", mec="k", ms=7, label="submap origins")
        q = maps[name]["quality"]
        ax.set_title(
            f"{name}: {maps[name]['submaps']} submaps, accuracy median {100 * q['accuracy']['median_m']:.1f} cm, "
            f"completeness {100 * q['completeness']['share']:.0f} %\nobstacle precision {_share(q['obstacles']['precision'])}, "
            f"recall {_share(q['obstacles']['recall'])}",
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
