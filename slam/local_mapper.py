"""Local mapping of one robot (thesis 5.1): obstacle classification of every depth image,
the rolling obstacle map, and the submaps the depth is integrated into.

Pure: depth images with the filter's camera poses in, submaps out. Two frames are in
play, both gravity-aligned: the current local frame of the filter, which *is* the active
submap's origin (thesis 5.1.2: a new submap switches the filter's frame), and the
robot's odometry frame (its first local frame, switches chained), in which the rolling
obstacle map lives so that it survives submap switches (it is for local navigation and
only needs to be locally consistent). Obstacle flags are the same in both (height
differences do not change under translation and yaw).
"""

from __future__ import annotations

import cv2
import numpy as np

from slam.obstacles import Classification, ObstacleParams, RollingObstacleMap, classify_depth
from slam.stereo import StereoCalibration
from slam.submap import Submap, SubmapBuilder, SubmapParams


class LocalMapper:
    """Classification, rolling obstacle map and submap partitioning of one robot."""

    def __init__(
        self,
        robot: str,
        calibration: StereoCalibration,
        obstacle_params: ObstacleParams,
        submap_params: SubmapParams,
        rolling_map_size_m: float = 10.0,
    ):
        self.calibration = calibration
        self.obstacle_params = obstacle_params
        self.builder = SubmapBuilder(robot, submap_params, calibration)
        self.rolling = RollingObstacleMap(obstacle_params.resolution_m, rolling_map_size_m)
        self.submaps: list[Submap] = []

    def integrate(
        self, t: float, depth: np.ndarray, image: np.ndarray, T_local_body: np.ndarray, T_body_cam: np.ndarray, T_odom_local: np.ndarray
    ) -> Classification:
        """One depth image (z-depth of the rig's left camera) with its grey or RGB left image;
        the robot's pose in the current local frame, the camera on the robot, and the local
        frame in the odometry frame."""
        T_local_cam = T_local_body @ T_body_cam
        T_odom_cam = T_odom_local @ T_local_cam
        classification = classify_depth(depth, self.calibration, T_odom_cam, self.obstacle_params)
        intensity = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        self.builder.integrate(depth, T_local_cam, classification.pixel_obstacles, intensity, t, classified=classification.pixel_classified)
        self.rolling.update(classification.height_map, (T_odom_local @ T_local_body)[:2, 3])
        return classification

    @property
    def images(self) -> int:
        """Depth images integrated into all submaps so far."""
        return sum(s.images for s in self.submaps) + self.builder.images

    def partition_due(self, position_std_m: float, distance_m: float) -> str | None:
        """Why a new submap must start now (thesis 5.1.3), or None."""
        return self.builder.should_partition(position_std_m, distance_m)

    def start_submap(self, t: float, frame_index: int) -> Submap:
        """Finish the active submap; the next one coincides with local frame ``frame_index``."""
        submap = self.builder.finish(t, frame_index)
        self.submaps.append(submap)
        return submap
