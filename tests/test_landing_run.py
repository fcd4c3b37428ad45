"""The hexacopter through take-off, low flight, a scan, landing and rest
(scenarios/ardea_landing.yaml), judged against ground truth: its filter alone stays
within 1 % of distance, its estimator never calls itself degraded, and the
zero-velocity updates (slam/rest.py) fire only while it truly stands (true speed below
1 cm/s) and do fire once it has landed."""

import pytest

from sim.evaluation.inputs import filter_input, team_truth
from sim.evaluation.trajectory import trajectory_metrics, truth_since
from sim.run.runner import Run
from sim.scenario import load_scenario

QUIET = ["output.recording=false", "output.topdown_png=false", "robots.*.camera.depth_ground_truth_every=0"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_ardea_lands_with_a_bounded_filter_error(seed):
    scenario = load_scenario("scenarios/ardea_landing.yaml", [*QUIET, f"seed={seed}"])
    simulation = Run(scenario)
    simulation.execute()
    ardea = simulation.robots["ardea"]
    assert ardea.robot.landed, ardea.robot.status
    estimator = ardea.onboard.estimator
    estimate = filter_input(ardea.onboard).estimate
    truth = team_truth(simulation).of("ardea")
    metrics, _ = trajectory_metrics(estimate, truth_since(truth, estimate.t[0]).trajectory)
    assert metrics["final_error_percent_of_distance"] < 1.0, metrics["final_error_m"]
    assert estimator.health.state == "ok" and all(state == "ok" for _, state, _ in estimator.health_history), estimator.health_history
    rest = estimator.rest_stats
    landed_at = max(a for a, _ in rest.intervals)
    assert rest.applied > 0 and landed_at > 20.0, rest.intervals  # it rests after the flight, not only before it
    p = truth.T[:, :3, 3]
    for a, b in rest.intervals:
        inside = (truth.t >= a) & (truth.t <= b)
        if inside.sum() > 1:  # at most 1 cm/s on average over the interval, and 5 mm of settling
            moved = p[inside].max(axis=0) - p[inside].min(axis=0)
            assert max(moved) < 0.01 * (b - a) + 0.005, (a, b, moved)
