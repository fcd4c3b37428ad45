"""The rerun recording of a run (``recording.rrd``), written without a viewer.

Entity layout: ``world/terrain`` (mesh coloured by the albedo), ``world/rocks``,
``world/lander``, ``world/robots/<name>`` (ground-truth pose over ``sim_time``),
``world/trajectories/<name>``, ``world/filter/<name>``, ``world/maps/<name>/...``
(global map by submap, obstacles, submap origins, rolling obstacle map) and
``cameras/<name>/<rig>/{left,depth}`` (downsampled images: the left one JPEG-compressed, depth as
uint16 millimetres). Open it with ``rerun results/<run>/recording.rrd``; its default blueprint shows the
world in 3D beside each robot's cameras, the VO inlier counts and the links.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from sim.world.camera_rig import StereoRig
from sim.world.terrain import Terrain

TIMELINE = "sim_time"
TERRAIN_MESH_CELLS = 200  # the terrain mesh is downsampled to at most this many cells a side
JPEG_QUALITY = 85  # the recording's camera images: about a tenth of the raw bytes, no visible loss at half size
DEPTH_MM_MAX = 65535  # uint16 millimetres: depth to 65.5 m (the cameras' far plane is 60 m by default)


def blueprint(robots: list[str]) -> rrb.Blueprint:
    """The views a recording opens with: the world in 3D; each robot's cameras; VO inliers and the links over time."""
    cameras = [rrb.Spatial2DView(origin=f"cameras/{robot}", name=robot) for robot in robots]
    series = [rrb.TimeSeriesView(origin="vo", name="VO inliers"), rrb.TimeSeriesView(origin="comms", name="links")]
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(origin="world", name="world"), rrb.Vertical(rrb.Grid(*cameras), *series), column_shares=[3, 2]),
        collapse_panels=True,
    )


class Recorder:
    def __init__(self, path: Path, recording_id: str, image_scale: float = 0.5):
        self.path = Path(path)
        self.image_scale = image_scale
        self.rec = rr.RecordingStream("marsyard", recording_id=recording_id)
        self.rec.save(str(self.path))
        self._tracks: dict[str, list[np.ndarray]] = {}

    def log_world(self, terrain: Terrain, world) -> None:
        """The default blueprint; terrain mesh, rocks and lander, once, as static data."""
        self.rec.send_blueprint(blueprint([robot.name for robot in world.robots]))
        heights = terrain.heights
        step = max(1, int(np.ceil((heights.shape[0] - 1) / TERRAIN_MESH_CELLS)))
        h = heights[::step, ::step]
        n_rows, n_cols = h.shape
        half = terrain.size_m / 2
        ys = -half + np.arange(n_rows) * step * terrain.resolution_m
        xs = -half + np.arange(n_cols) * step * terrain.resolution_m
        gx, gy = np.meshgrid(xs, ys)
        vertices = np.stack([gx, gy, h], axis=-1).reshape(-1, 3)
        albedo = cv2.resize(terrain.albedo, (n_cols, n_rows), interpolation=cv2.INTER_AREA)
        grey = albedo.reshape(-1).astype(np.uint8)
        colors = np.stack([grey, grey, grey], axis=-1)
        idx = np.arange(n_rows * n_cols).reshape(n_rows, n_cols)
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        triangles = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
        self.rec.log("world/terrain", rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles, vertex_colors=colors), static=True)
        if terrain.rocks:
            self.rec.log(
                "world/rocks",
                rr.Ellipsoids3D(
                    centers=[r.center for r in terrain.rocks],
                    half_sizes=[r.radii for r in terrain.rocks],
                    rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], angle=r.yaw) for r in terrain.rocks],
                    colors=[[150, 140, 130]] * len(terrain.rocks),
                    fill_mode="solid",
                ),
                static=True,
            )
        if terrain.lander is not None:
            lx, ly = terrain.lander.xy
            self.rec.log(
                "world/lander",
                rr.Boxes3D(centers=[[lx, ly, terrain.lander.base_z + 0.8]], half_sizes=[[1.2, 1.2, 0.5]], colors=[[200, 170, 60]]),
                static=True,
            )

    def log_pose(self, robot: str, t: float, pos: np.ndarray, quat_wxyz: np.ndarray) -> None:
        self.rec.set_time(TIMELINE, duration=t)
        w, x, y, z = quat_wxyz
        self.rec.log(f"world/robots/{robot}", rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=[x, y, z, w])))
        self._tracks.setdefault(robot, []).append(np.asarray(pos, dtype=np.float32))

    def log_frame(self, robot: str, rig: StereoRig, t: float, stereo) -> None:
        self.rec.set_time(TIMELINE, duration=t)
        scale = self.image_scale
        size = (max(1, int(rig.width * scale)), max(1, int(rig.height * scale)))
        left = cv2.resize(stereo.left, size, interpolation=cv2.INTER_AREA)
        base = f"cameras/{robot}/{rig.name}"
        self.rec.log(f"{base}/left", rr.Image(left).compress(jpeg_quality=JPEG_QUALITY))
        if stereo.depth is not None:
            depth = cv2.resize(stereo.depth, size, interpolation=cv2.INTER_NEAREST)
            mm = np.where(np.isfinite(depth) & (depth > 0), np.round(depth * 1000.0), 0).clip(0, DEPTH_MM_MAX).astype(np.uint16)
            self.rec.log(f"{base}/depth", rr.DepthImage(mm, meter=1000.0))

    def log_vo(self, robot: str, rig: StereoRig, result) -> None:
        """VO inlier features of a frame on its (downsampled) left image, and the inlier count."""
        self.rec.set_time(TIMELINE, duration=result.t)
        base = f"cameras/{robot}/{rig.name}"
        if len(result.keypoints):
            self.rec.log(f"{base}/left/vo_features", rr.Points2D(result.keypoints * self.image_scale, radii=1.0, colors=[[0, 255, 0]]))
        self.rec.log(f"vo/{robot}/inliers", rr.Scalars(float(result.inliers)))

    def log_filter(self, robot: str, times: np.ndarray, T_world_est: np.ndarray, position_std: np.ndarray) -> None:
        """The filter-only trajectory (drawn in the world via the robot's true start frame)
        and its position standard deviation over time."""
        self.rec.log(f"world/filter/{robot}", rr.LineStrips3D([T_world_est[:, :3, 3]], colors=[[255, 80, 80]]), static=True)
        for axis, values in zip("xyz", position_std.T):
            self.rec.send_columns(
                f"filter/{robot}/position_std_{axis}",
                indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                columns=rr.Scalars.columns(scalars=values),
            )

    def log_slam(self, robot: str, times: np.ndarray, T_world_est: np.ndarray) -> None:
        """The online SLAM trajectory (eq. 4.6), drawn in the world via the robot's true start frame."""
        self.rec.log(f"world/slam/{robot}", rr.LineStrips3D([T_world_est[:, :3, 3]], colors=[[80, 220, 80]]), static=True)

    def log_graph(self, robot: str, edges: list[tuple[str, np.ndarray, np.ndarray]], colours: dict[str, tuple[int, int, int]],
                  origins: np.ndarray, sigmas: np.ndarray) -> None:
        """A robot's final graph in the world: one layer per factor type, and the submap
        origins with their marginal position standard deviations as ellipsoids."""
        by_kind: dict[str, list] = {}
        for kind, a, b in edges:
            by_kind.setdefault(kind, []).append(np.stack([a[:3], b[:3]]))
        for kind, strips in by_kind.items():
            self.rec.log(f"world/graph/{robot}/{kind}", rr.LineStrips3D(strips, colors=[colours[kind]]), static=True)
        if len(origins):
            self.rec.log(f"world/graph/{robot}/covariance", rr.Ellipsoids3D(centers=origins, half_sizes=sigmas, colors=[[255, 170, 0]]), static=True)

    def log_map(self, robot: str, robot_number: int, points: np.ndarray, submap: np.ndarray, obstacle: np.ndarray,
                origins: np.ndarray, rolling_cells: np.ndarray) -> None:
        """A robot's global map in the world frame (via its true start frame): points
        coloured by submap (one hue per robot, shades per submap), obstacle points red,
        submap origins, and the cells of its rolling obstacle map at the end of the run."""
        hue = (0.6 + 0.31 * robot_number) % 1.0
        shade = 0.45 + 0.5 * ((submap * 0.37) % 1.0)
        hsv = np.stack([np.full(len(points), hue * 180), np.full(len(points), 200.0), 255 * shade], axis=1).astype(np.uint8)
        colors = cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0]
        base = f"world/maps/{robot}"
        self.rec.log(f"{base}/points", rr.Points3D(points[~obstacle], colors=colors[~obstacle], radii=0.02), static=True)
        self.rec.log(f"{base}/obstacles", rr.Points3D(points[obstacle], colors=[[230, 40, 40]], radii=0.025), static=True)
        self.rec.log(f"{base}/submap_origins", rr.Points3D(origins, colors=[[255, 170, 0]], radii=0.08), static=True)
        if len(rolling_cells):
            self.rec.log(f"{base}/obstacle_map", rr.Points3D(rolling_cells, colors=[[255, 0, 255]], radii=0.03), static=True)

    def log_link_event(self, event) -> None:
        """A link going up or down (``comms.LinkEvent``), as a 0/1 series per direction."""
        self.rec.set_time(TIMELINE, duration=event.t)
        self.rec.log(f"comms/{event.src}_to_{event.dst}/up", rr.Scalars(float(event.up)))

    def log_link_series(self, series: dict) -> None:
        """Sampled link throughput and queue bytes from ``Network.timeseries()``."""
        for link, values in series["links"].items():
            base = "comms/" + link.replace("->", "_to_")
            for name in ("throughput_Bps", "queue_bytes"):
                if name in values:
                    self.rec.send_columns(
                        f"{base}/{name}",
                        indexes=[rr.TimeColumn(TIMELINE, duration=series["t"])],
                        columns=rr.Scalars.columns(scalars=values[name]),
                    )

    def close(self) -> None:
        for robot, track in self._tracks.items():
            if len(track) > 1:
                self.rec.log(f"world/trajectories/{robot}", rr.LineStrips3D([np.stack(track)]), static=True)
        self.rec.flush()
        self.rec.disconnect()
