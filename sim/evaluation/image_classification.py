"""The obstacle classification of each mapped image, placed by its camera's true pose
(docs/mapping.md): thesis 5.1.1 alone, without the filter's pose error within a submap
that ``map.classification`` (own submaps on their true origins) still carries.

While a run maps, :class:`ImageCells` collects per robot the 2.5D cells its images saw
within the classification's range (:func:`slam.obstacles.classified_pixels`) and the
cells of their pixels flagged as obstacles, each pixel placed by the true pose of the
left camera at capture; pixels on or beside another robot (its true position at capture)
are left out and counted: those whose point is placed there, and, where the frame has
its rendered depth, those whose true point lies there (stereo places a robot's silhouette
pixels up to 0.8 m too near, out of its surroundings; docs/mapping.md). At the end the
cells are scored like a map (:func:`sim.evaluation.map_quality.score_obstacles`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.evaluation.map_quality import MapQualityParams, ObstacleScore, score_obstacles
from sim.world.terrain import Terrain
from slam.obstacles import ObstacleParams, classified_pixels
from slam.stereo import StereoCalibration, depth_to_points_at

_OFFSET = 1 << 30  # cell indices are shifted by this into non-negative 31-bit halves of one key
_COMPACT_EVERY = 64  # images between merges of the collected keys


def _keys(cells: np.ndarray) -> np.ndarray:
    return np.unique(((cells[:, 0] + _OFFSET) << 31) | (cells[:, 1] + _OFFSET))


def _cells(keys: np.ndarray) -> np.ndarray:
    return np.column_stack([(keys >> 31) - _OFFSET, (keys & ((1 << 31) - 1)) - _OFFSET])


@dataclass(frozen=True, eq=False)
class MappedImage:
    """One mapped depth image of a robot with what the simulator knows of it (for tools that
    look into the classification, e.g. ``sim.tools.obstacle_sources``)."""

    robot: str
    frame: int
    depth: np.ndarray  # the robot's stereo z-depth (m) of its VO rig's left camera
    obstacle: np.ndarray  # its per-pixel obstacle flags, classified on its believed camera pose
    T_world_cam: np.ndarray  # true pose of that camera at capture (OpenCV axes)
    others: list[tuple[np.ndarray, float]]  # the other robots' true xy and body radii at capture
    true_depth: np.ndarray | None  # the rendered z-depth of the same camera (inf: sky); None where not rendered
    calibration: StereoCalibration
    params: ObstacleParams


def world_xy(depth: np.ndarray, pixels: np.ndarray, calibration: StereoCalibration, T_world_cam: np.ndarray) -> np.ndarray:
    """World xy (n, 2) of the points of ``depth`` at the ``pixels`` mask."""
    cam = depth_to_points_at(depth, pixels, calibration).astype(float)
    return (cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3])[:, :2]


class ImageCells:
    """Seen and flagged cells of one robot's mapped images at true camera poses."""

    def __init__(self, calibration: StereoCalibration, params: ObstacleParams):
        self.calibration = calibration
        self.params = params
        self.images = 0
        self.pixels_on_robots = 0
        self.obstacle_pixels_on_robots = 0
        self._seen: list[np.ndarray] = [np.zeros(0, np.int64)]
        self._flagged: list[np.ndarray] = [np.zeros(0, np.int64)]

    def add(
        self,
        depth: np.ndarray,
        obstacle: np.ndarray,
        T_world_cam: np.ndarray,
        robots: list[tuple[np.ndarray, float]],
        true_depth: np.ndarray | None = None,
        seen: np.ndarray | None = None,
    ) -> None:
        """One mapped depth image with its per-pixel obstacle flags, the true pose of its
        camera (OpenCV axes), the other robots' true xy with their body radii (their
        surroundings are not scored, :attr:`MapQualityParams.robot_margin_m` beyond) and,
        if rendered, the camera's true z-depth (inf: sky), which tells the pixels that saw
        a robot wherever stereo placed them. ``seen``: the pixels the classification read
        (``slam.obstacles.Classification.pixel_classified``), else found again from ``depth``."""
        cal, p = self.calibration, self.params
        seen = classified_pixels(depth, cal, p) if seen is None else seen
        xy = world_xy(depth, seen, cal, T_world_cam)
        flagged = obstacle[seen]
        true_xy = None
        if true_depth is not None and robots:
            with np.errstate(invalid="ignore"):  # sky: inf depth gives inf/NaN coordinates
                true_xy = world_xy(true_depth, seen, cal, T_world_cam)
        on = np.zeros(len(xy), bool)
        margin = MapQualityParams(obstacle=p).robot_margin_m
        for centre, radius in robots:
            on |= np.hypot(*(xy - centre).T) < radius + margin
            if true_xy is not None:
                with np.errstate(invalid="ignore"):
                    on |= np.hypot(*(true_xy - centre).T) < radius + margin  # sky (inf, NaN): False
        self.images += 1
        self.pixels_on_robots += int(on.sum())
        self.obstacle_pixels_on_robots += int((on & flagged).sum())
        cells = np.floor(xy[~on] / p.resolution_m).astype(np.int64)
        self._seen.append(_keys(cells))
        self._flagged.append(_keys(cells[flagged[~on]]))
        if self.images % _COMPACT_EVERY == 0:
            self._seen = [np.unique(np.concatenate(self._seen))]
            self._flagged = [np.unique(np.concatenate(self._flagged))]

    def score(self, terrain: Terrain) -> ObstacleScore:
        """Precision and recall of the flagged cells against the true obstacle cells that
        the images saw (one cell of tolerance), as for a map."""
        seen = np.unique(np.concatenate(self._seen))
        flagged = np.isin(seen, np.concatenate(self._flagged))
        centres = (_cells(seen) + 0.5) * self.params.resolution_m
        points = np.column_stack([centres, np.zeros(len(centres))])
        return score_obstacles(points, flagged, terrain, MapQualityParams(obstacle=self.params))

    def metrics(self, terrain: Terrain) -> dict:
        score = self.score(terrain).metrics()
        score.update(images=self.images, points_on_robots=self.pixels_on_robots, obstacle_points_on_robots=self.obstacle_pixels_on_robots)
        return score
