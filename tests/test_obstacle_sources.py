"""sim.tools.obstacle_sources on rendered views with known rocks (sim.tools.rocky_scene)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.evaluation.image_classification import MappedImage
from sim.tools.obstacle_sources import ObstacleSources, markdown
from slam.lie import se3, so3_exp
from slam.obstacles import ObstacleParams, classify_depth


@pytest.fixture(scope="module")
def reports():
    """Eight views of the LRU's mast camera around a circle among 300 rocks, scored by a
    robot that classified each on its true pose and by one whose believed pose is pitched
    3 deg off."""
    from sim.tools.rocky_scene import RockyScene

    scene = RockyScene(seed=5, rocks=300)
    pitched = se3(so3_exp([math.radians(3.0), 0.0, 0.0]), np.zeros(3))  # about the camera's x axis
    sources = {"true": ObstacleSources(), "pitched": ObstacleSources()}
    try:
        for k in range(8):
            a = 2 * math.pi * k / 8
            _, depth, true_depth, T = scene.view_with_true_depth(scene.head_pose((4 * math.cos(a), 4 * math.sin(a)), a + math.pi / 2))
            for name, believed in (("true", T), ("pitched", T @ pitched)):
                flags = classify_depth(depth, scene.calibration, believed, ObstacleParams()).pixel_obstacles
                sources[name].add(MappedImage("lru", k, depth, flags, T, [], true_depth, scene.calibration, ObstacleParams()))
        return {name: s.report(scene.terrain)["lru"] for name, s in sources.items()}
    finally:
        scene.close()


def test_as_run_equals_the_true_pose_only_when_the_robot_knew_its_pose(reports):
    """The three scorings share the truth: a robot that classified on its true pose scores
    as the reclassification on the true pose; one 3 deg off flags other cells."""
    exact, pitched = reports["true"], reports["pitched"]
    scores = {k: v for k, v in exact["as_run"].items() if k != "false_cells_near_robot"}
    assert scores == exact["true_pose"]
    assert pitched["true_pose"] == exact["true_pose"]
    assert pitched["as_run"]["flagged_cells"] != exact["as_run"]["flagged_cells"]
    assert exact["true_pose"]["precision"] > 0.9 and exact["true_pose"]["true_cells_seen"] > 50, exact


def test_true_depth_is_the_criterion_against_the_truth(reports):
    """On rendered depth the classification flags only true obstacles and misses the steps
    within eq. 5.4's error allowance (h_max + Δd): the missed step cells' true height
    difference lies just above h_max; the split comes from the true surface."""
    report = reports["true"]
    true_depth = report["true_depth"]
    assert true_depth["true_cells_seen"] > 50 and true_depth["precision"] > 0.95, report
    missed = true_depth["missed"]
    assert missed["cells"] == true_depth["missed_cells"] > 0
    assert 0 <= missed["steep_drop_only"] < missed["cells"]
    assert 0.15 < missed["step_h_diff_median_m"] < 0.25, missed
    assert report["images"] == 8 and report["images_without_true_depth"] == 0
    assert report["as_run"]["false_cells_near_robot"] == 0  # no other robot in the views
    assert "| lru |" in markdown({"lru": report})
