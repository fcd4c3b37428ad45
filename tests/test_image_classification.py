"""sim.evaluation.image_classification: which pixels of a mapped image count as seen on another robot."""

from __future__ import annotations

import numpy as np

from sim.evaluation.image_classification import ImageCells
from sim.evaluation.map_quality import MapQualityParams
from slam.obstacles import ObstacleParams, classified_pixels, classify_depth
from slam.stereo import StereoCalibration, depth_to_points

CAL = StereoCalibration(focal_px=300.0, cx=159.5, cy=119.5, baseline_m=0.09, width=320, height=240)
# a level camera 1 m up looking along world +x (OpenCV axes: x right, y down, z forward)
T_WORLD_CAM = np.eye(4)
T_WORLD_CAM[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
T_WORLD_CAM[:3, 3] = [0.0, 0.0, 1.0]
ROBOT = (np.array([2.0, 0.0]), 0.4)  # another robot 2 m ahead


def _image():
    """A robot's face 2 m ahead that stereo placed 0.8 m too near (out of its surroundings),
    the top rows sky; every second column flagged."""
    true_depth = np.full((CAL.height, CAL.width), 2.0, np.float32)
    true_depth[:20] = np.inf
    depth = np.where(np.isinf(true_depth), np.nan, true_depth - 0.8).astype(np.float32)
    obstacle = np.zeros(depth.shape, bool)
    obstacle[:, ::2] = True
    return depth, obstacle, true_depth


def test_pixels_that_saw_a_robot_are_left_out_wherever_stereo_placed_them():
    depth, obstacle, true_depth = _image()
    by_measured, by_truth = ImageCells(CAL, ObstacleParams()), ImageCells(CAL, ObstacleParams())
    by_measured.add(depth, obstacle, T_WORLD_CAM, [ROBOT])
    by_truth.add(depth, obstacle, T_WORLD_CAM, [ROBOT], true_depth)
    assert by_measured.pixels_on_robots == 0  # placed 1.2 m ahead: 0.8 m from the robot's centre

    reach = ROBOT[1] + MapQualityParams().robot_margin_m
    with np.errstate(invalid="ignore"):  # the sky's infinite true depths become NaN points
        true_xy = (depth_to_points(true_depth, CAL).reshape(-1, 3) @ T_WORLD_CAM[:3, :3].T + T_WORLD_CAM[:3, 3])[:, :2]
        on = (np.hypot(*(true_xy - ROBOT[0]).T) < reach).reshape(depth.shape) & np.isfinite(depth)
    assert 0 < on.sum() < np.isfinite(depth).sum()  # the robot's face, not the whole view nor the sky
    assert by_truth.pixels_on_robots == on.sum()
    assert by_truth.obstacle_pixels_on_robots == (on & obstacle).sum()
    # the classification's own mask of the pixels it read, as the run passes it, is the same
    read = classify_depth(depth, CAL, T_WORLD_CAM, ObstacleParams()).pixel_classified
    np.testing.assert_array_equal(read, classified_pixels(depth, CAL, ObstacleParams()))
    given = ImageCells(CAL, ObstacleParams())
    given.add(depth, obstacle, T_WORLD_CAM, [ROBOT], true_depth, seen=read)
    assert given.pixels_on_robots == on.sum() and np.array_equal(np.concatenate(given._seen), np.concatenate(by_truth._seen))
    # with no robot about, the true depth changes nothing
    alone = ImageCells(CAL, ObstacleParams())
    alone.add(depth, obstacle, T_WORLD_CAM, [], true_depth)
    assert alone.pixels_on_robots == 0
