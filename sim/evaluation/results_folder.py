"""The results folder of a run.

::

    scenario.yaml               resolved scenario (defaults filled in, tag ids assigned)
    metrics.json                every number of the run (runtime, routes, stereo, lanes)
    trajectories/<robot>.gt.tum ground-truth body pose in the world frame (TUM: t x y z qx qy qz qw)
    trajectories/<robot>.gt_start.tum, .filter.tum
                                ground truth and the filter alone in the robot's start frame
    trajectories/<robot>.slam.tum, .slam_final.tum
                                its SLAM trajectory in its map frame (= its start frame): online
                                (eq. 4.6), and the same times by its final graph (its logged filter
                                poses on the final submap origins)
    trajectories/<robot>.belief.<peer>.tum
                                its belief about each peer over time, in its map frame, stamped
                                with the time it held it (sim.evaluation.online_slam)
    trajectories/team/<robot>.slam.world.tum, .slam_final.world.tum
                                both in the world frame through the robot's true start frame:
                                the team's trajectories in one frame
    graphs/<robot>.g2o, .keys.csv
                                its final graph as g2o (consecutive ids, robust kernels left out,
                                the anchor as FIX 0) and the map of ids to gtsam keys and variables
                                (slam.graph_export)
    graphs/<robot>.graph.gtsam, .values.gtsam
                                GTSAM's serialisation of the graph's factors and its estimate
    sensors/<robot>.npz         IMU (measured, true, true biases) and wheel odometry samples
    stereo_depth_error.csv      SGBM depth against rendered ground truth, per robot, rig, range
    lanes.csv                   per robot and stage: jobs, drops, queueing delay, compute time
    comms_flows.csv             per (src, dst, kind): bytes offered, delivered, dropped by reason, latency
    comms_links.csv             per link: wire bytes, retransmissions, up fraction, queue occupancy
    routes.csv                  every waypoint of every robot with its outcome
    topdown.png                 terrain, rocks, lander, trajectories and waypoint outcomes
    exploration.png             with ``exploration``: coverage of the target region over time, explored
                                cells by robot (see sim.evaluation.exploration)
    maps/, map_topdown.png      each robot's global map (<robot>.ply points, <robot>.voxels.npz voxel grid,
                                <robot>.occupied.ply) and its top-down view (see sim.evaluation.maps)
    recording.rrd               rerun recording (see sim.run.recording)
    error.txt                   only when the run failed: the traceback

A failed run still writes everything it produced up to the failure.

:func:`write` reads each section's typed input from the run (:mod:`sim.evaluation.inputs`),
evaluates it under its own guard, and keeps what the plots draw (the ``*Plot`` data
classes) apart from the metrics, so that ``metrics.json`` holds the metrics alone.
"""

from __future__ import annotations

import csv
import json
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LightSource

from sim.evaluation import exploration, inputs, loop_closures, maps, online_slam, trajectory
from sim.evaluation.navigation import navigation_metrics
from sim.evaluation.trajectory import ErrorOverTime
from sim.run.faults import fault_metrics
from sim.run.runner import Run
from sim.scenario import Scenario, dump_scenario
from sim.world.calibration_errors import CalibrationError
from slam import graph_export
from slam.graph import MultiRobotGraph

STEREO_SUMMARY_BINS = ("2-4m", "4-6m")  # the 2-6 m band tests/test_run.py holds stereo depth to


def prepare(out: Path, scenario: Scenario) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.yaml").write_text(dump_scenario(scenario))


def write(run: Run, out: Path, error: str | None = None, recorder=None) -> dict[str, Any]:
    """Write every result file of ``run`` into ``out``; return the metrics dict. With a
    ``recorder`` (still open), the evaluated trajectories go into the recording too."""
    out.mkdir(parents=True, exist_ok=True)
    if error is not None:
        (out / "error.txt").write_text(error)
    truth = inputs.team_truth(run)
    robots = {name: _robot_results(run, out, name, truth, recorder) for name in run.robots}
    _write_tables(run, out, list(robots.values()))
    comms = _comms_metrics(run)
    closures, _ = _guarded(out, "loop closure evaluation", lambda: (loop_closures.loop_closure_section(inputs.closure_inputs(run), truth), None))
    metrics = {
        "scenario": run.scenario.name,
        "seed": run.scenario.seed,
        "status": "failed" if error else "completed",
        "error": error.strip().splitlines()[-1] if error else None,
        "runtime": runtime_metrics(run),
        "robots": {name: r.metrics for name, r in robots.items()},
        "comms": comms,
        "loop_closures": closures,
    }
    explore = run.scenario.exploration
    if explore is not None:
        metrics["exploration"], explored = _guarded(
            out, "exploration evaluation", lambda: exploration.exploration_section(explore.region, explore.cell_m, inputs.explorer_inputs(run), truth)
        )
        if explored is not None and run.scenario.output.topdown_png:
            exploration.plot_exploration(explored, truth, out / "exploration.png")
    if run.scenario.output.topdown_png:
        _write_plots(run, out, robots, truth)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default))
    return metrics


@dataclass(frozen=True, eq=False)
class FilterPlot:
    """What ``filter_error.png`` and ``slam.png`` draw of one robot's filter."""

    error_over_time: ErrorOverTime | None  # None when its trajectory could not be evaluated
    nees: np.ndarray  # NEES of roll, pitch and body velocity per logged estimate
    t: np.ndarray  # the logged estimates' times


@dataclass(frozen=True, eq=False)
class RobotPlots:
    """What the plots draw of one robot besides its metrics (None: nothing to draw)."""

    filter: FilterPlot | None = None
    slam: online_slam.SlamPlot | None = None
    map: maps.MapPlot | None = None


@dataclass(frozen=True, eq=False)
class _RobotResults:
    """One robot's part of the results: its ``metrics.json`` entry, its plot data and its
    rows of the CSV tables."""

    metrics: dict[str, Any]
    plots: RobotPlots
    depth_rows: list[dict[str, Any]]
    lane_rows: list[dict[str, Any]]
    route_rows: list[dict[str, Any]]


def _robot_results(run: Run, out: Path, name: str, truth: inputs.TeamTruth, recorder) -> _RobotResults:
    """Write one robot's files and evaluate it: ground truth, sensors, stereo, lane, route
    and, with its onboard stack, its filter, SLAM and map."""
    runtime = run.robots[name]
    log, robot = runtime.log, runtime.robot
    trajectory.write_tum(out / "trajectories" / f"{name}.gt.tum", truth.of(name))
    _write_sensors(out / "sensors" / f"{name}.npz", log)
    stereo, depth_rows = _stereo(name, runtime)
    stages = runtime.lane.stats(run.sim_time)
    waypoints = [_waypoint_row(name, wp) for wp in robot.waypoints]
    counts = {s: sum(w["status"] == s for w in waypoints) for s in ("reached", "failed", "pending")}
    sections, plots = _evaluate_onboard(run, out, name, truth, recorder)
    metrics = {
        "preset": robot.cfg.preset,
        "final_status": robot.status,
        "distance_m": trajectory.path_length(truth.of(name)),
        "route": {"waypoints": len(waypoints), **counts},
        "navigation": navigation_metrics(robot, run.collisions.of(name), np.asarray(log.guidance_t), np.asarray(log.guidance_xy), truth.of(name)),
        "camera_frames": log.frames,
        "stereo": stereo,
        "imaging": _imaging(log),
        "calibration": _calibration(run.calibration_errors[name], robot.stereo_rigs),
        **sections,
        "faults": fault_metrics(runtime.onboard, runtime.faults, run.sim_time),  # injected failures (sim/run/faults.py)
        # samples in which the odometry's encoder check left a wheel out (sim/world/sensors.py)
        "wheel_odometry_outvoted_samples": runtime.odometry.outvoted_samples if runtime.odometry is not None else None,
        "health": inputs.health_report(runtime.onboard, run.mission_s) if runtime.onboard is not None else None,
        "lane": {
            "utilization": runtime.lane.utilization(run.sim_time),
            "stages": {row["stage"]: {k: v for k, v in row.items() if k not in ("robot", "stage")} for row in stages},
        },
    }
    return _RobotResults(metrics, plots, depth_rows, stages, waypoints)


def _stereo(name: str, runtime) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Per stereo rig its depth error summary (2-6 m), and the rows of ``stereo_depth_error.csv``."""
    stereo, rows = {}, []
    for rig in runtime.robot.stereo_rigs:
        acc = runtime.log.depth_error.get(rig.name)
        if acc is None:
            continue
        rows += acc.rows(name, rig.name)
        stereo[rig.name] = acc.summary(STEREO_SUMMARY_BINS)
    return stereo, rows


def _imaging(log) -> dict[str, Any]:
    """Per stereo rig with a camera model (sim/world/imaging.py): the exposure and gain
    its auto exposure chose, and the share of the left image's pixels at full well."""
    out = {}
    for rig, rows in log.exposure.items():
        a = np.asarray(rows, dtype=float)
        out[rig] = {
            "exposure_ms": {"median": 1e3 * float(np.median(a[:, 0])), "min": 1e3 * float(a[:, 0].min()), "max": 1e3 * float(a[:, 0].max())},
            "gain": {"median": float(np.median(a[:, 1])), "max": float(a[:, 1].max())},
            "saturated_share": {"mean": float(a[:, 2].mean()), "max": float(a[:, 2].max())},
            "frames_over_1_percent_saturated": int(np.count_nonzero(a[:, 2] > 0.01)),
        }
    return out


def _calibration(errors: CalibrationError, rigs) -> dict[str, Any]:
    """The calibration errors drawn for a robot (sim/world/calibration_errors.py), per rig:
    the right camera's rotation as disparity offset coefficients (px), baseline and focal
    scales, and the lens distortion's RMS over the image per camera and of the disparity
    error it causes (left less right shift along x, px); the pan-tilt encoders' offsets and
    the camera-IMU time offset (ms, the pairs taken after their stamps)."""
    out: dict[str, Any] = {
        "pan_offset_deg": float(np.degrees(errors.pan_offset_rad)),
        "tilt_offset_deg": float(np.degrees(errors.tilt_offset_rad)),
        "camera_imu_time_offset_ms": errors.time_offset_s * 1e3,
    }
    for rig in rigs:
        e = errors.rigs[rig.name]
        lens = e.lens_distortions(rig)
        out[rig.name] = {
            "disparity_offset_coefficients_px": e.disparity_offset_coefficients_px(rig).tolist(),
            "baseline_scale": e.baseline_scale,
            "focal_scale": e.focal_scale,
            "lens_distortion_rms_px": [0.0, 0.0] if lens is None else [float(np.sqrt((d.shift**2).sum(axis=0).mean())) for d in lens],
            "lens_disparity_error_rms_px": 0.0 if lens is None else float(np.sqrt(np.mean((lens[0].shift[0] - lens[1].shift[0]) ** 2))),
        }
    return out


def _evaluate_onboard(run: Run, out: Path, name: str, truth: inputs.TeamTruth, recorder) -> tuple[dict[str, Any], RobotPlots]:
    """The ``filter``, ``slam`` and ``map`` sections of a robot (None without an onboard
    stack), each read from the run and evaluated under its own guard, and their plot data."""
    onboard = run.robots[name].onboard
    if onboard is None:
        return {"filter": None, "slam": None, "map": None, "graph_export": None}, RobotPlots()
    slam, slam_plot = _guarded(
        out, f"SLAM evaluation of {name}", lambda: online_slam.slam_section(out, name, inputs.slam_input(onboard), truth, recorder)
    )
    filter_section, filter_plot = _guarded(
        out, f"filter evaluation of {name}", lambda: _filter_section(out, name, inputs.filter_input(onboard), truth.of(name), recorder)
    )
    offset = ((filter_section or {}).get("vo") or {}).get("disparity_offset")
    if offset is not None:  # the truth beside the robot's estimate
        truth_c = run.calibration_errors[name].rigs[onboard.vo_rig.name].disparity_offset_coefficients_px(onboard.vo_rig)
        offset["true_px"], offset["true_coefficients_px"] = float(truth_c[1]), truth_c.tolist()
    robot_map, map_plot = _guarded(
        out,
        f"map evaluation of {name}",
        lambda: maps.map_section(
            out, name, inputs.map_input(onboard, run.robots[name].image_cells), truth, run.terrain, recorder, list(run.robots).index(name)
        ),
    )
    graph_files, _ = _guarded(out, f"graph export of {name}", lambda: (_export_graph(out, name, inputs.final_graph(onboard)), None))
    return {"filter": filter_section, "slam": slam, "map": robot_map, "graph_export": graph_files}, RobotPlots(filter_plot, slam_plot, map_plot)


def _export_graph(out: Path, name: str, graph: MultiRobotGraph | None) -> dict[str, Any] | None:
    """The robot's final graph under ``graphs/`` (:mod:`slam.graph_export`); None without one."""
    if graph is None:
        return None
    folder = out / "graphs"
    folder.mkdir(parents=True, exist_ok=True)
    vertices = graph_export.write_g2o(graph, folder / f"{name}.g2o")
    graph_export.write_keys(vertices, folder / f"{name}.keys.csv")
    graph_export.write_gtsam(graph, folder / f"{name}.graph.gtsam", folder / f"{name}.values.gtsam")
    return {"status": "ok", "vertices": len(vertices)}


def _write_tables(run: Run, out: Path, robots: list[_RobotResults]) -> None:
    _write_csv(out / "stereo_depth_error.csv", [row for r in robots for row in r.depth_rows])
    _write_csv(out / "lanes.csv", [row for r in robots for row in r.lane_rows])
    _write_csv(out / "routes.csv", [row for r in robots for row in r.route_rows])
    _write_csv(out / "comms_flows.csv", run.network.to_table())
    _write_csv(out / "comms_links.csv", run.network.link_table())


def _comms_metrics(run: Run) -> dict[str, Any]:
    comms = run.network.to_metrics()
    comms["raw_equivalent_Bps"] = run.raw_equivalent_load()
    return comms


def _write_plots(run: Run, out: Path, robots: dict[str, _RobotResults], truth: inputs.TeamTruth) -> None:
    """topdown.png, filter_error.png, slam.png and map_topdown.png."""
    metrics = {name: r.metrics for name, r in robots.items()}
    plots = {name: r.plots for name, r in robots.items()}
    plot_topdown(run, out / "topdown.png")
    if any(m.get("filter") for m in metrics.values()):
        plot_filter_errors(metrics, {name: p.filter for name, p in plots.items()}, out / "filter_error.png")
    filter_errors = {name: p.filter.error_over_time if p.filter else None for name, p in plots.items()}
    online_slam.plot_slam(metrics, {name: p.slam for name, p in plots.items()}, filter_errors, truth, out / "slam.png")
    robot_maps = {name: m["map"] for name, m in metrics.items() if m.get("map")}
    maps.plot_maps(robot_maps, {name: p.map for name, p in plots.items()}, truth, run.terrain, out / "map_topdown.png")


def _guarded(out: Path, what: str, evaluate: Callable[[], tuple[Any, Any]]) -> tuple[Any, Any]:
    """An evaluation section, ``evaluate() -> (metrics, plot data)``; if it raises, its
    status says so, it has no plot data and the traceback goes to error.txt: an
    evaluation bug must not cost the run's other results."""
    try:
        return evaluate()
    except Exception as exc:
        with (out / "error.txt").open("a") as f:
            f.write(f"{what} failed:\n{traceback.format_exc()}\n")
        return {"status": f"{what} failed: {type(exc).__name__}: {exc}"}, None


def _filter_section(
    out: Path, name: str, filt: inputs.FilterInput, truth: trajectory.Trajectory, recorder
) -> tuple[dict[str, Any], FilterPlot | None]:
    """Filter-only trajectory against ground truth in the robot's start frame (thesis
    4.1; docs/estimation.md), and what the plots draw of it. ``truth``: the robot's
    ground truth in the world."""
    est = filt.estimate
    if len(est) < 2:
        return {"status": "not started", "poses": len(est)}, None
    start = trajectory.truth_since(truth, est.t[0])  # the filter's first frame
    if recorder is not None:
        recorder.log_filter(name, est.t, start.T_world_start[None] @ est.T, filt.position_std)
    trajectory.write_tum(out / "trajectories" / f"{name}.gt_start.tum", start.trajectory)
    trajectory.write_tum(out / "trajectories" / f"{name}.filter.tum", est)
    section: dict[str, Any] = {"status": "ok"}
    error_over_time = None
    try:
        metrics, error_over_time = trajectory.trajectory_metrics(est, start.trajectory)
        section.update(metrics)
    except trajectory.EvaluationError as exc:
        section = {"status": f"not evaluated: {exc}"}
    section["nees_roll_pitch_velocity"], nees = trajectory.nees_report(filt.observable, filt.observable_true, filt.observable_cov)
    for key, dims, angles in (("nees_roll_pitch", slice(0, 2), 2), ("nees_velocity", slice(2, 5), 0)):  # which part is off
        section[key] = trajectory.nees_report(filt.observable[:, dims], filt.observable_true[:, dims], filt.observable_cov[:, dims, dims], angles)[0]
    bias, bias_true = filt.bias, filt.bias_true
    section["bias_error"] = {
        "accel_initial_mps2": float(np.linalg.norm(bias_true[0, :3] - bias[0, :3])),
        "accel_final_mps2": float(np.linalg.norm(bias_true[-1, :3] - bias[-1, :3])),
        "gyro_initial_dps": float(np.degrees(np.linalg.norm(bias_true[0, 3:] - bias[0, 3:]))),
        "gyro_final_dps": float(np.degrees(np.linalg.norm(bias_true[-1, 3:] - bias[-1, 3:]))),
    }
    section["vo"] = {**filt.vo, "rejected_by_gate": filt.vo["rejections_by_reason"].get("gate", 0), "deltas_against_truth": filt.vo_deltas}
    section["zero_velocity"] = {**filt.rest, **_rest_against_truth(filt.rest["intervals"], truth)}
    section["frame_switches"] = filt.frame_switches
    return section, FilterPlot(error_over_time, nees, est.t)


def _rest_against_truth(intervals: list[list[float]], truth: trajectory.Trajectory, moving_mps: float = 0.01) -> dict[str, Any]:
    """The zero-velocity updates judged by the true speed (world frame, finite differences
    of the ground truth): its maximum inside the rest intervals, and how long the robot
    was updated as resting while it truly moved faster than ``moving_mps``."""
    if len(truth) < 2 or not intervals:
        return {"true_speed_max_mps": None, "moving_s": 0.0}
    t, p = truth.t, truth.T[:, :3, 3]
    dt = np.diff(t)
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.where(dt > 0, dt, np.inf)
    mid = 0.5 * (t[1:] + t[:-1])
    inside = np.zeros(len(mid), bool)
    for a, b in intervals:
        inside |= (mid >= a) & (mid <= b)
    if not inside.any():
        return {"true_speed_max_mps": None, "moving_s": 0.0}
    return {"true_speed_max_mps": float(speed[inside].max()), "moving_s": float(dt[inside & (speed > moving_mps)].sum())}


def plot_filter_errors(robots_metrics: dict[str, Any], plots: dict[str, FilterPlot | None], path: Path) -> None:
    """Filter-only position and yaw error over time, one line per robot."""
    fig, (ax_p, ax_y, ax_n) = plt.subplots(3, 1, figsize=(9, 8), sharex=True, dpi=110)
    drawn = False
    for name, m in robots_metrics.items():
        f = m.get("filter") or {}
        plot = plots.get(name)
        if plot is None or plot.error_over_time is None:
            continue
        drawn = True
        series = plot.error_over_time
        pct = f["final_error_percent_of_distance"]
        share = f"{pct:.2f} % of {f['distance_m']:.0f} m" if pct is not None else f"{f['distance_m']:.2f} m travelled"
        label = f"{name}: final {f['final_error_m']:.2f} m ({share})"
        ax_p.plot(series.t, series.position_m, label=label)
        ax_y.plot(series.t, series.yaw_deg, label=name)
        nees = f["nees_roll_pitch_velocity"]
        ax_n.plot(plot.t, plot.nees, lw=0.6, label=f"{name}: mean {nees['mean']:.1f}")
    if robots_metrics:
        any_nees = next(
            (f["nees_roll_pitch_velocity"] for m in robots_metrics.values() if (f := m.get("filter")) and "nees_roll_pitch_velocity" in f),
            None,
        )
        if any_nees:
            for bound in any_nees["interval_95"]:
                ax_n.axhline(bound, color="k", ls="--", lw=0.8)
    ax_p.set_ylabel("position error [m]")
    ax_y.set_ylabel("yaw error [deg]")
    ax_n.set_ylabel("NEES roll, pitch, v (5 dof)")
    ax_n.set_yscale("log")
    ax_n.set_xlabel("simulated time [s]")
    ax_p.set_title("local reference filter alone, in each robot's start frame (unaligned)")
    for ax in (ax_p, ax_y, ax_n):
        ax.grid(alpha=0.3)
        if drawn:
            ax.legend(fontsize=7)
    if not drawn:
        ax_p.text(0.5, 0.5, "no filter estimate: the run ended before any robot's filter started", transform=ax_p.transAxes, ha="center")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def runtime_metrics(run: Run) -> dict[str, Any]:
    parts = dict(sorted(run.timers.seconds.items()))
    accounted = sum(parts.values())
    parts["other"] = max(0.0, run.wall_s - accounted)
    background = dict(sorted(run.images.timers.seconds.items())) if run.images.threaded else {}
    return {
        "wall_s": run.wall_s,
        "sim_s": run.sim_time,
        "drain_s": run.sim_time - run.mission_s,  # after every route was done (docs/matching.md, "The end of a run")
        "drain_end": run.drain_end,
        "real_time_factor": run.sim_time / run.wall_s if run.wall_s > 0 else None,
        "parts_s": parts,  # the run loop's thread; "waiting": blocked on the image pipeline (sim/run/pipeline.py)
        "image_thread_s": background,  # the pipeline's threads (empty when inline)
        "memory": run.memory.metrics(),  # resident set size over simulated time (sim/run/memory.py)
    }


def _waypoint_row(robot: str, wp) -> dict[str, Any]:
    return {
        "robot": robot,
        "index": wp.index,
        "x": wp.xy[0],
        "y": wp.xy[1],
        "status": wp.status,
        "reached_t": wp.reached_t,
        "reason": wp.reason if wp.status != "pending" else "run ended before the robot got there",
    }


def _write_sensors(path: Path, log) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)

    def arr(rows, width):
        return np.stack(rows) if rows else np.zeros((0, width))

    np.savez_compressed(
        path,
        imu_t=np.asarray(log.imu_t),
        imu=arr(log.imu, 6),
        imu_true=arr(log.imu_true, 6),
        imu_bias=arr(log.imu_bias, 6),
        odom_t=np.asarray(log.odom_t),
        odom=arr(log.odom, 3),
    )


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    if not rows:
        path.write_text("")
        return
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot serialise {type(value).__name__}")


WAYPOINT_STYLE = {"reached": ("o", "#2ca02c"), "failed": ("X", "#d62728"), "pending": ("o", "#7f7f7f")}


def plot_topdown(run: Run, path: Path) -> None:
    """Hill-shaded terrain with rocks, lander, trajectories and waypoint outcomes."""
    terrain = run.terrain
    half = terrain.size_m / 2
    fig, ax = plt.subplots(figsize=(8.5, 8), dpi=110)
    norm = plt.Normalize(terrain.heights.min(), terrain.heights.max())
    rgb = LightSource(azdeg=315, altdeg=35).shade(
        terrain.heights, cmap=plt.cm.gist_earth, norm=norm, blend_mode="soft", dx=terrain.resolution_m, dy=terrain.resolution_m
    )
    ax.imshow(rgb, origin="lower", extent=(-half, half, -half, half))
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=plt.cm.gist_earth), ax=ax, shrink=0.6, label="terrain height [m]")
    for rock in terrain.rocks:
        ax.add_patch(plt.Circle(rock.center[:2], max(rock.radii[:2]), color="#8c564b", alpha=0.8, lw=0))
    if terrain.lander is not None:
        lx, ly = terrain.lander.xy
        ax.add_patch(plt.Rectangle((lx - 1.25, ly - 1.25), 2.5, 2.5, fill=False, ec="gold", lw=2))
        ax.annotate(f"lander (tag {terrain.lander.marker.tag_id})", (lx, ly + 1.5), color="gold", ha="center", fontsize=8)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, runtime) in enumerate(run.robots.items()):
        color = colors[i % len(colors)]
        poses = runtime.log.gt_pose
        if poses:
            xyz = np.stack(poses)
            ax.plot(xyz[:, 0], xyz[:, 1], color=color, lw=1.6, label=f"{name} ({runtime.robot.cfg.preset}): {runtime.robot.status}")
            ax.plot(*xyz[0, :2], marker="^", color=color, ms=9, mec="k")
        for wp in runtime.robot.waypoints:
            marker, wcolor = WAYPOINT_STYLE[wp.status]
            ax.plot(*wp.xy, marker=marker, color=wcolor, mec=color, mew=1.5, ms=8)
            ax.annotate(str(wp.index), wp.xy, xytext=(4, 4), textcoords="offset points", fontsize=7, color="w")
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{run.scenario.name} (seed {run.scenario.seed}): {run.sim_time:.0f} s simulated")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.8)
    ax.text(
        0.99,
        0.01,
        "waypoints: green reached, red X failed, grey pending",
        transform=ax.transAxes,
        ha="right",
        fontsize=7,
        color="w",
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _filter_summary(f: dict[str, Any] | None) -> str:
    if not f or "final_error_m" not in f:
        return ""
    pct = f["final_error_percent_of_distance"]
    return f"; filter final error {f['final_error_m']:.2f} m" + (f" ({pct:.2f} % of distance)" if pct is not None else "")


def _slam_summary(s: dict[str, Any] | None) -> str:
    if not s or "final_error_m" not in s:
        return ""
    lc = s["graph"]["loop_closures"]
    return f"; SLAM final error {s['final_error_m']:.2f} m, loop closures " + ", ".join(f"{k} {v}" for k, v in lc.items())


def _health_summary(health: dict[str, Any] | None) -> str:
    """`` (estimator lost since 123.4 s: vo lost)``; nothing while the estimator is ok."""
    if not health or health["state"] == "ok":
        return ""
    return f" (estimator {health['state']} since {health['since']:.1f} s: {health['reason']})"


def _navigation_summary(nav: dict[str, Any] | None) -> str:
    if not nav:
        return ""
    out = f", {nav['collisions']} collision{'s' * (nav['collisions'] != 1)}" if nav["collisions"] else ""
    if "guidance_error_m" in nav:
        out += f", steered by its estimate ({nav['guidance_error_m']['final']:.2f} m off at the end)"
    return out


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """Short human summary of a run for the CLI."""
    rt = metrics["runtime"]
    rtf = rt["real_time_factor"]
    lines = [f"{rt['sim_s']:.1f} s simulated in {rt['wall_s']:.1f} s wall (real-time factor {rtf:.2f})"]
    for name, m in metrics["robots"].items():
        route = m["route"]
        stereo = ", ".join(
            f"{rig} depth err {s['median_rel_error'] * 100:.1f} %" for rig, s in m["stereo"].items() if s.get("median_rel_error") is not None
        )
        lines.append(
            f"{name}: {m['final_status']}{_health_summary(m.get('health'))}, {m['distance_m']:.1f} m, "
            f"waypoints {route['reached']}/{route['waypoints']} reached"
            + (f", {route['failed']} failed" if route["failed"] else "")
            + _navigation_summary(m.get("navigation"))
            + (f"; {stereo} (2-6 m)" if stereo else "")
            + _filter_summary(m.get("filter"))
            + _slam_summary(m.get("slam"))
        )
    explored = metrics.get("exploration")
    if explored and "coverage" in explored:
        lines.append(
            f"exploration: {100 * explored['coverage']:.0f} % of the {explored['region_m2']:.0f} m^2 target region explored "
            f"({explored['explored_m2']:.0f} m^2, {explored['distance_m']:.0f} m driven)"
        )
    return lines

