"""The team's results of a run (thesis 4.2): each robot's trajectory by its final graph, its beliefs about its
peers, every robot's SLAM trajectory in the world frame, and each robot's final graph as g2o, key map and GTSAM
serialisation, read back by the tools they are for (evo, gtsam)."""

import csv

import gtsam
import numpy as np
import pytest
from evo.tools import file_interface
from test_slam_run import ENCOUNTER

from sim.evaluation import results_folder
from sim.evaluation.trajectory import Trajectory, trajectory_metrics
from sim.run.runner import Run
from sim.scenario import load_scenario

ROBOTS = ("lru1", "lru2")


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """tests/test_slam_run.py's encounter with a new submap every 0.3 m: each rover's 1 m drive spans four
    frames, so that its trajectory by the final graph rests on origins the graph moved after the fact."""
    run = Run(load_scenario("scenarios/spacebotcamp_outage.yaml", [*ENCOUNTER, "slam.mapping.submap_distance_m=0.3"]))
    run.execute()
    run.drain(15.0)
    out = tmp_path_factory.mktemp("team")
    return run, out, results_folder.write(run, out)


def read_tum(path) -> Trajectory:
    traj = file_interface.read_tum_trajectory_file(str(path))
    return Trajectory(traj.timestamps, np.stack(traj.poses_se3))


def test_every_file_is_written_and_evo_reads_the_trajectories(results):
    run, out, metrics = results
    assert not (out / "error.txt").exists() and metrics["status"] == "completed"
    for name in ROBOTS:
        (peer,) = (r for r in ROBOTS if r != name)
        tums = [f"{name}.slam.tum", f"{name}.slam_final.tum", f"{name}.belief.{peer}.tum", f"team/{name}.slam.world.tum"]
        tums += [f"team/{name}.slam_final.world.tum"]
        for tum in tums:
            assert len(read_tum(out / "trajectories" / tum)) > 100, tum
        for graph_file in (f"{name}.g2o", f"{name}.keys.csv", f"{name}.graph.gtsam", f"{name}.values.gtsam"):
            assert (out / "graphs" / graph_file).stat().st_size > 0, graph_file
        assert metrics["robots"][name]["graph_export"] == {"status": "ok", "vertices": run.robots[name].onboard.agent.graph.node_count()}


def test_final_trajectory_ends_at_the_final_graphs_estimate(results):
    run, out, _ = results
    for name in ROBOTS:
        onboard = run.robots[name].onboard
        log, graph = onboard.log, onboard.agent.graph
        online, final = read_tum(out / "trajectories" / f"{name}.slam.tum"), read_tum(out / "trajectories" / f"{name}.slam_final.tum")
        assert np.array_equal(final.t, online.t)
        j = int(log.frame_index[-1])
        assert j >= 3  # the drive's submaps
        v = np.linalg.solve(onboard.estimator.frame_origins[j], log.pose_first_frame[-1])  # the filter's last pose in its frame
        expected = graph.online_pose(name, j, v)  # eq. 4.6 on the final graph's origin of that frame
        assert np.allclose(final.T[-1], expected, atol=1e-6), (name, final.T[-1], expected)
        origins = onboard.estimator.frame_origins
        for T, j, T_first_body in zip(final.T, log.frame_index, log.pose_first_frame):  # and every pose before, in every frame
            assert np.allclose(T, graph.online_pose(name, int(j), np.linalg.solve(origins[j], T_first_body)), atol=1e-6)


def test_final_graph_metrics_are_those_of_the_final_trajectory(results):
    """``slam.final_graph`` scores the trajectory by the final graph (``slam_final.tum``) against the truth in the
    start frame (``gt_start.tum``), as ``slam.ate_m`` scores the online one."""
    _, out, metrics = results
    tol = 5e-6  # the TUM files hold positions to 1 um: two of them round a distance by up to about 2 um
    for name in ROBOTS:
        slam = metrics["robots"][name]["slam"]
        truth = read_tum(out / "trajectories" / f"{name}.gt_start.tum")
        final = trajectory_metrics(read_tum(out / "trajectories" / f"{name}.slam_final.tum"), truth)[0]
        online = trajectory_metrics(read_tum(out / "trajectories" / f"{name}.slam.tum"), truth)[0]
        assert slam["ate_m"]["rmse"] == pytest.approx(online["ate_m"]["rmse"], abs=tol)
        assert slam["final_graph"]["ate_m"]["rmse"] == pytest.approx(final["ate_m"]["rmse"], abs=tol)
        assert slam["final_graph"]["final_error_m"] == pytest.approx(final["final_error_m"], abs=tol)


def test_beliefs_are_the_slam_logs_rows(results):
    run, out, _ = results
    for name in ROBOTS:
        (peer,) = (r for r in ROBOTS if r != name)
        rows = np.asarray(run.robots[name].onboard.slam_log.beliefs[peer])  # [t, t of the estimate, 16 entries]
        belief = read_tum(out / "trajectories" / f"{name}.belief.{peer}.tum")
        assert np.allclose(belief.t, rows[:, 0], atol=1e-6)
        assert np.allclose(belief.T, rows[:, 2:].reshape(-1, 4, 4), atol=1e-6)


def test_team_trajectories_in_the_world_are_close_to_ground_truth(results):
    _, out, metrics = results
    for name in ROBOTS:
        truth = read_tum(out / "trajectories" / f"{name}.gt.tum")
        ate = metrics["robots"][name]["slam"]["ate_m"]["rmse"]
        online = trajectory_metrics(read_tum(out / "trajectories" / "team" / f"{name}.slam.world.tum"), truth)[0]["ate_m"]["rmse"]
        final = trajectory_metrics(read_tum(out / "trajectories" / "team" / f"{name}.slam_final.world.tum"), truth)[0]["ate_m"]["rmse"]
        assert online < ate + 1e-3, (name, online, ate)  # the same trajectory, moved rigidly into the world
        assert final < ate + 0.02, (name, final, ate)


def test_graph_files_read_back(results):
    run, out, _ = results
    for name in ROBOTS:
        graph = run.robots[name].onboard.agent.graph
        factors, initial = gtsam.readG2o(str(out / "graphs" / f"{name}.g2o"), True)
        assert initial.size() == graph.node_count() and factors.size() == graph.batch_graph().size() - 1  # the prior: FIX 0
        with (out / "graphs" / f"{name}.keys.csv").open() as f:
            keys = {int(r["id"]): int(r["key"]) for r in csv.DictReader(f)}
        estimate = graph.estimate()
        assert sorted(keys) == list(range(graph.node_count())) and sorted(keys.values()) == sorted(estimate)
        for i, key in keys.items():
            assert np.allclose(initial.atPose3(i).matrix(), estimate[key], atol=1e-12)
        values = gtsam.Values()
        values.deserialize((out / "graphs" / f"{name}.values.gtsam").read_text())
        serialised = gtsam.NonlinearFactorGraph()
        serialised.deserialize((out / "graphs" / f"{name}.graph.gtsam").read_text())
        assert serialised.size() == graph.batch_graph().size() and serialised.error(values) == pytest.approx(graph.batch_graph().error(values))
