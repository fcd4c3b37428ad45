"""Whole runs against what the simulator knows: determinism, stereo depth, network geometry."""

import numpy as np
import pytest

from sim.run.runner import Run
from sim.scenario import load_scenario

SMALL = {
    "name": "small",
    "seed": 3,
    "duration_s": 1.5,
    "terrain": {"size_m": 20, "rocks": {"count": 6}, "craters": {"count": 2}},
    "robots": [
        {"name": "rover", "preset": "lru", "start": {"xy": [-3, 0]}, "route": {"waypoints": [[2, 0]]}},
        {"name": "copter", "preset": "ardea", "start": {"xy": [-3, -3]}, "route": {"waypoints": [[2, -3]]}},
    ],
    "output": {"recording": False, "topdown_png": False},
}


def run(raw, overrides=()):
    simulation = Run(load_scenario(raw, list(overrides)))
    simulation.execute()
    return simulation


def poses(simulation, robot):
    return np.stack(simulation.robots[robot].log.gt_pose)


def test_same_seed_same_run_other_seed_other_run():
    import copy

    a, b = run(copy.deepcopy(SMALL)), run(copy.deepcopy(SMALL))
    c = run(copy.deepcopy(SMALL), ["seed=4"])
    assert np.array_equal(a.terrain.heights, b.terrain.heights)
    for robot in ("rover", "copter"):
        assert np.array_equal(poses(a, robot), poses(b, robot))
        assert np.array_equal(np.stack(a.robots[robot].onboard.log.pose_first_frame), np.stack(b.robots[robot].onboard.log.pose_first_frame))
        assert np.array_equal(np.stack(a.robots[robot].log.imu), np.stack(b.robots[robot].log.imu))
    assert not np.array_equal(a.terrain.heights, c.terrain.heights)
    assert not np.array_equal(np.stack(a.robots["rover"].log.imu), np.stack(c.robots["rover"].log.imu))


def test_inserting_a_robot_changes_no_other_robots_randomness():
    """Every robot's random streams are named by the robot (sim.seeding), not by its place in the team."""
    import copy

    bigger = copy.deepcopy(SMALL)
    bigger["robots"].insert(0, {"name": "extra", "preset": "lru", "start": {"xy": [3, 3]}})
    a, b = Run(load_scenario(copy.deepcopy(SMALL))), Run(load_scenario(bigger))
    try:
        for robot in ("rover", "copter"):
            ra, rb = a.robots[robot], b.robots[robot]
            assert ra.onboard.agent.matcher.params.seed == rb.onboard.agent.matcher.params.seed
            assert np.array_equal(ra.imu.accel_bias, rb.imu.accel_bias) and np.array_equal(ra.imu.gyro_bias, rb.imu.gyro_bias)
        assert a.robots["rover"].onboard.agent.matcher.params.seed != a.robots["copter"].onboard.agent.matcher.params.seed
    finally:
        a.close()
        b.close()


@pytest.fixture(scope="module")
def quickstart():
    # the ideal world: these bounds are the stack's without sensor and calibration errors
    # (the realistic world's figures: docs/realism.md)
    return run("scenarios/quickstart.yaml", ["duration_s=12", "output.recording=false", "output.topdown_png=false", "realism.profile=ideal"])


def test_sgbm_depth_on_rendered_terrain_under_5_percent(quickstart):
    for robot, rig in (("lru1", "head"), ("lru2", "head"), ("ardea", "down")):
        summary = quickstart.robots[robot].log.depth_error[rig].summary(("2-4m", "4-6m"))
        assert summary["frames"] >= 30
        assert summary["valid_share"] > 0.5, (robot, summary)
        assert summary["median_rel_error"] < 0.05, (robot, summary)


def test_stereo_results_arrive_after_the_modelled_fpga_time(quickstart):
    for runtime in quickstart.robots.values():
        row = {r["stage"]: r for r in runtime.lane.stats(quickstart.sim_time)}["stereo"]
        assert row["device"] == "fpga" and row["completed"] > 0
        assert row["latency_mean_s"] >= quickstart.scenario.compute.stages.stereo_s - 1e-9


def test_line_of_sight_is_cut_by_a_ridge_and_takes_the_link_down():
    flat = {"size_m": 20, "rocks": {"count": 0}, "craters": {"count": 0}}
    base = dict(SMALL, duration_s=1.2, terrain=flat, comms={"preset": "lunar_surface_uhf"})
    base["robots"] = [dict(r, route={}) for r in SMALL["robots"]]  # both parked
    open_ground = run(base)
    assert open_ground.line_of_sight("rover", "copter") and open_ground.line_of_sight("copter", "rover")
    assert open_ground.network.is_up("rover", "copter")

    wall = {"start_xy": [-3.5, -1.5], "end_xy": [-2.5, -1.5], "height_m": 4, "width_m": 0.8}
    blocked = run(dict(base, terrain=dict(flat, ridges=[wall])))
    assert not blocked.line_of_sight("rover", "copter") and not blocked.line_of_sight("copter", "rover")
    assert not blocked.network.is_up("rover", "copter")
    assert any(not e["up"] and e["link"] == "rover->copter" for e in blocked.network.timeseries()["events"])


def test_filter_drift_and_consistency_against_truth(quickstart):
    """Filter alone (IMU + VO, wheels on rovers), in the start frame, unaligned."""
    from sim.evaluation.inputs import filter_input, team_truth
    from sim.evaluation.trajectory import trajectory_metrics, truth_since

    truth = team_truth(quickstart)
    for robot in ("lru1", "ardea"):  # narrow-angle rover and the hexacopter
        rt = quickstart.robots[robot]
        estimate = filter_input(rt.onboard).estimate
        m, _ = trajectory_metrics(estimate, truth_since(truth.of(robot), estimate.t[0]).trajectory)
        assert m["distance_m"] > 2.0
        assert m["final_error_percent_of_distance"] < 2.0, (robot, m["final_error_m"], m["distance_m"])
        vo = rt.onboard.estimator.vo_stats
        assert vo.applied > 0.8 * vo.frames, (robot, vo)
        # submap partitions by distance, each a frame switch (chained into pose_first_frame above)
        expected = int(m["distance_m"] / quickstart.scenario.slam.mapping.submap_distance_m + 0.1)
        assert abs(len(rt.onboard.estimator.switches) - expected) <= 1, (robot, len(rt.onboard.estimator.switches), m["distance_m"])


def test_filter_estimates_appear_after_the_vo_latency(quickstart):
    lane = {r["stage"]: r for r in quickstart.robots["lru1"].lane.stats(quickstart.sim_time)}
    assert lane["vo"]["completed"] > 0 and lane["strapdown"]["completed"] > 1000
    stages = quickstart.scenario.compute.stages
    assert lane["stereo"]["latency_mean_s"] + lane["vo"]["latency_mean_s"] >= stages.stereo_s + stages.vo_s - 1e-9


def test_filter_nees_and_biases_against_truth(quickstart):
    """Consistency of the observable states (roll, pitch, body velocity; 5 dof, a
    consistent filter has a mean NEES of 5) and the gyro biases. Measured on this 12 s
    run (seed 1): lru1 mean 5.7 / median 4.3 / max 82, lru2 2.1 / 1.2 / 21, ARDEA 15 / 14:
    its roll stays overconfident by about 2x after the ADIS16407's 50 mg turn-on
    accelerometer bias tilted the start (docs/estimation.md). The bounds hold those
    values with a margin for other seeds; ARDEA's is a regression guard for a known
    limitation, not a claim of consistency. The rovers' maximum guards the scoring at the
    filter's own time: against the truth one IMU sample later, the jolt at the start of
    lru1's point turn (11 s) made a spike of about 960 and a mean of 9.4."""
    from sim.evaluation.trajectory import nees_report

    bounds = {"lru1": (10.0, 10.0, 200.0), "lru2": (10.0, 5.0, 200.0), "ardea": (35.0, 35.0, np.inf)}  # mean, median, max
    for robot, (mean_bound, median_bound, max_bound) in bounds.items():
        log = quickstart.robots[robot].onboard.log
        report, values = nees_report(np.stack(log.observable), np.stack(log.observable_true), np.stack(log.observable_cov))
        assert report["mean"] < mean_bound and report["median"] < median_bound, (robot, report["mean"], report["median"])
        assert values.max() < max_bound, (robot, values.max())
        bias, truth = np.stack(log.bias), np.stack(log.bias_true)
        # gyro biases from the resting start: within 0.1 deg/s all along (turn-on spread: 0.5 and 3 deg/s)
        assert np.degrees(np.abs(bias[:, 3:] - truth[:, 3:])).max() < 0.1, robot


def test_imu_samples_integrate_to_the_physics_velocity(monkeypatch):
    """The IMU averages the physics over each sample period (sim.world.sensors.InertialAverager):
    strapdown integration of the noise-free samples with the true attitude reproduces
    the velocity change, also through the rover's wheel-ground contacts; and the run
    starts with every robot resting."""
    import copy

    from slam.lie import so3_exp

    simulation = Run(load_scenario(copy.deepcopy(SMALL), ["duration_s=3", "slam.enabled=false"]))
    truth = {name: [] for name in simulation.robots}
    sample = simulation._sample

    def sample_and_record(tick, gt_every):
        sample(tick, gt_every)
        for name, rt in simulation.robots.items():
            truth[name].append((rt.robot.velocity()[0], rt.robot.rotation()))

    monkeypatch.setattr(simulation, "_sample", sample_and_record)
    simulation.execute()
    for name, rt in simulation.robots.items():
        assert np.linalg.norm(truth[name][0][0]) < 5e-3, (name, truth[name][0][0])  # settled: within the filter's 0.01 m/s prior
        imu = np.stack(rt.log.imu_true)
        v = np.stack([v for v, _ in truth[name]])
        R = [R for _, R in truth[name]]
        dt = 1.0 / rt.robot.cfg.imu.rate_hz
        v_int = v[0].copy()
        worst = 0.0
        g = simulation.world.model.opt.gravity
        for k in range(1, len(imu)):  # IMU at the control rate here: sample k is tick k
            R_mid = R[k - 1] @ so3_exp(0.5 * dt * imu[k, 3:])
            a = R_mid @ imu[k, :3] + g
            v_int += a * dt
            worst = max(worst, float(np.linalg.norm(v_int - v[k])))
        assert worst < 0.01, (name, worst)  # one instantaneous sample per period: several cm/s on the rover


def test_maps_against_the_true_terrain(quickstart, tmp_path):
    """Each robot's map (docs/mapping.md), built along its own filter poses and placed in the
    world by its true start pose, against the terrain's true surface. Measured on this
    12 s run with the 4 m mapping range: rovers median 2.2-3.2 cm, > 99.9 % of points within
    0.1 m; ARDEA median 6.4 cm, 75 % (its filter is off by 5-10 cm; 5.4 cm and 89 % with the
    thesis's 2.5 m range); completeness of the explored area 83-85 %."""
    from sim.evaluation import inputs, maps

    bounds = {"lru1": (0.04, 0.95), "lru2": (0.04, 0.95), "ardea": (0.1, 0.7)}  # median, share within 0.1 m
    truth = inputs.team_truth(quickstart)
    for robot, (median_bound, within_bound) in bounds.items():
        section, plot = maps.map_section(tmp_path, robot, inputs.map_input(quickstart.robots[robot].onboard), truth, quickstart.terrain)
        assert len(plot.points) == section["points"]
        accuracy, completeness = section["quality"]["accuracy"], section["quality"]["completeness"]
        assert accuracy["median_m"] < median_bound and accuracy["within_0_1_m"] > within_bound, (robot, accuracy)
        assert completeness["share"] > 0.6, (robot, completeness)
        header = (tmp_path / "maps" / f"{robot}.ply").read_bytes().split(b"end_header\n")[0].decode()
        assert f"element vertex {section['points']}" in header
    # ARDEA flies more than one submap distance in 12 s: every new submap switched the filter's frame
    onboard = quickstart.robots["ardea"].onboard
    assert len(onboard.mapper.submaps) == len(onboard.estimator.switches) >= 1
    assert [s.frame_index for s in onboard.mapper.submaps] == list(range(len(onboard.mapper.submaps)))
    assert all(reason == "distance" for _, reason in onboard.partitions)


def test_submap_along_true_poses_matches_the_terrain(monkeypatch):
    """Rendered SGBM depth integrated along the cameras' true poses (no filter)
    gives a submap on the true surface, limited only by stereo: measured median 2.6 cm, p95
    8.3 cm, 98.7 % within 0.1 m with the 4 m mapping range (2.0 cm, 5.5 cm and 100 % with the
    thesis's 2.5 m); occupied voxels 4.9 cm from the ground (median, 0.1 m
    voxels), the air halfway along the rays all free."""
    from sim.evaluation.map_quality import map_quality
    from sim.run.onboard import calibration
    from slam.lie import se3
    from slam.obstacles import classify_depth
    from slam.stereo import cut_far_points, depth_to_points
    from slam.submap import SubmapBuilder, SubmapParams
    from slam.voxels import VoxelState

    simulation = Run(load_scenario("scenarios/quickstart.yaml", ["duration_s=8", "output.recording=false", "output.topdown_png=false"]))
    rt = simulation.robots["lru1"]
    onboard = rt.onboard
    truth, frames = {}, []
    capture, depth_ready = onboard.capture, onboard.depth_ready

    def capture_with_truth(frame_id, now, T_body_cam):
        truth[frame_id] = se3(rt.robot.rotation(), rt.robot.pose()[0]) @ T_body_cam
        capture(frame_id, now, T_body_cam)

    def keep_depth(frame_id, now, left, right, depth):
        frames.append((frame_id, now, left, depth))
        depth_ready(frame_id, now, left, right, depth)

    monkeypatch.setattr(onboard, "capture", capture_with_truth)
    monkeypatch.setattr(onboard, "depth_ready", keep_depth)
    simulation.execute()

    calib = calibration(onboard.vo_rig)
    builder = SubmapBuilder("lru1", SubmapParams(), calib)
    for frame_id, t, left, depth in frames:
        T_world_cam = truth[frame_id]
        classification = classify_depth(depth, calib, T_world_cam)
        builder.integrate(depth, T_world_cam, classification.pixel_obstacles, left, t, classified=classification.pixel_classified)
    submap = builder.current()
    assert submap.images > 20
    accuracy = map_quality(submap.points, submap.obstacle, simulation.terrain).accuracy
    assert accuracy["median_m"] < 0.03 and accuracy["within_0_1_m"] > 0.97, accuracy
    terrain = simulation.terrain
    occupied = submap.voxels.occupied_centers()
    assert np.median(np.abs(occupied[:, 2] - terrain.height_at(occupied[:, 0], occupied[:, 1]))) < 0.06
    # halfway along the last image's rays the air is free
    frame_id, _, _, depth = frames[-1]
    T = truth[frame_id]
    seen = depth_to_points(cut_far_points(depth, calib, SubmapParams().max_depth_error_m, SubmapParams().pixel_error), calib).reshape(-1, 3)
    seen = seen[np.all(np.isfinite(seen), axis=1)] @ T[:3, :3].T + T[:3, 3]
    states = submap.voxels.state(0.5 * (seen + T[:3, 3]))
    assert np.mean(states == VoxelState.FREE) > 0.95 and np.mean(states == VoxelState.OCCUPIED) < 0.01


def test_a_failing_evaluation_costs_only_its_own_section(monkeypatch, tmp_path):
    """A bug in one robot section's evaluation is reported there and in error.txt; the
    other sections and files are still written."""
    import copy
    import json

    from sim.evaluation import maps, results_folder

    def broken(*args, **kwargs):
        raise RuntimeError("deliberately broken")

    simulation = run(copy.deepcopy(SMALL))
    monkeypatch.setattr(maps, "map_section", broken)
    results_folder.write(simulation, tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for robot in ("rover", "copter"):
        assert metrics["robots"][robot]["map"]["status"] == f"map evaluation of {robot} failed: RuntimeError: deliberately broken"
        assert "failed" not in metrics["robots"][robot]["filter"]["status"]  # the filter's section is unaffected
        assert (tmp_path / "trajectories" / f"{robot}.filter.tum").exists()
    assert "deliberately broken" in (tmp_path / "error.txt").read_text()
