"""The results folder of a run.

::

    scenario.yaml               resolved scenario (defaults filled in, tag ids assigned)
    metrics.json                every number of the run (runtime, routes, stereo, lanes)
    trajectories/<robot>.gt.tum ground-truth body pose in the world frame (TUM: t x y z qx qy qz qw)
    sensors/<robot>.npz         IMU (measured, true, true biases) and wheel odometry samples
    stereo_depth_error.csv      SGBM depth against rendered ground truth, per robot, rig, range
    lanes.csv                   per robot and stage: jobs, drops, queueing delay, compute time
    comms_flows.csv             per (src, dst, kind): bytes offered, delivered, dropped by reason, latency
    comms_links.csv             per link: wire bytes, retransmissions, up fraction, queue occupancy
    routes.csv                  every waypoint of every robot with its outcome
    topdown.png                 terrain, rocks, lander, trajectories and waypoint outcomes
    maps/, map_topdown.png      each robot's global map and its top-down view (see sim.evaluation.maps)
    recording.rrd               rerun recording (see sim.run.recording)
    error.txt                   only when the run failed: the traceback

A failed run still writes everything it produced up to the failure.
"""

from __future__ import annotations

import csv
import json
import traceback
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LightSource

from sim.evaluation import loop_closures, maps, online_slam, trajectory
from sim.run.runner import Run
from sim.scenario import Scenario, dump_scenario

STEREO_SUMMARY_BINS = ("2-4m", "4-6m")  # the 2-6 m band the acceptance test uses


def prepare(out: Path, scenario: Scenario) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.yaml").write_text(dump_scenario(scenario))


def write(run: Run, out: Path, error: str | None = None, recorder=None) -> dict[str, Any]:
    """Write every result file of ``run`` into ``out``; return the metrics dict. With a
    ``recorder`` (still open), the evaluated trajectories go into the recording too."""
    out.mkdir(parents=True, exist_ok=True)
    if error is not None:
        (out / "error.txt").write_text(error)
    robots_metrics: dict[str, Any] = {}
    depth_rows, lane_rows, route_rows = [], [], []
    gt_world = {
        n: (np.asarray(r.log.gt_t), np.stack([trajectory.pose_matrix(p) for p in r.log.gt_pose]))
        for n, r in run.robots.items() if r.log.gt_pose
    }
    landmark_world = online_slam.lander_tag_pose(run.world.model, run.world.data)
    for name, runtime in run.robots.items():
        log, robot = runtime.log, runtime.robot
        _write_tum(out / "trajectories" / f"{name}.gt.tum", log.gt_t, log.gt_pose)
        _write_sensors(out / "sensors" / f"{name}.npz", log)
        stereo = {}
        for rig in robot.stereo_rigs:
            acc = log.depth_error.get(rig.name)
            if acc is None:
                continue
            depth_rows += acc.rows(name, rig.name)
            stereo[rig.name] = acc.summary(STEREO_SUMMARY_BINS)
        stages = runtime.lane.stats(run.sim_time)
        lane_rows += stages
        waypoints = [_waypoint_row(name, wp) for wp in robot.waypoints]
        route_rows += waypoints
        counts = {s: sum(w["status"] == s for w in waypoints) for s in ("reached", "failed", "pending")}
        filter_section = map_metrics = slam_metrics = None
        if runtime.onboard is not None:
            slam_metrics = _guarded(
                out, f"SLAM evaluation of {name}", online_slam.slam_section,
                out, name, {n: r.log for n, r in run.robots.items()}, runtime.onboard, gt_world, landmark_world, recorder,
            )
            filter_section = _guarded(out, f"filter evaluation of {name}", _filter_section, out, name, log, runtime.onboard, recorder)
            map_metrics = _guarded(
                out, f"map evaluation of {name}", maps.map_section,
                out, name, log, runtime.onboard, run.terrain, recorder, list(run.robots).index(name),
            )
        robots_metrics[name] = {
            "preset": robot.cfg.preset,
            "final_status": robot.status,
            "distance_m": _path_length(log.gt_pose),
            "route": {"waypoints": len(waypoints), **counts},
            "camera_frames": log.frames,
            "stereo": stereo,
            "filter": filter_section,
            "slam": slam_metrics,
            "map": map_metrics,
            "lane": {
                "utilization": runtime.lane.utilization(run.sim_time),
                "stages": {row["stage"]: {k: v for k, v in row.items() if k not in ("robot", "stage")} for row in stages},
            },
        }
    _write_csv(out / "stereo_depth_error.csv", depth_rows)
    _write_csv(out / "lanes.csv", lane_rows)
    _write_csv(out / "routes.csv", route_rows)
    _write_csv(out / "comms_flows.csv", run.network.to_table())
    _write_csv(out / "comms_links.csv", run.network.link_table())
    comms = run.network.to_metrics()
    comms["raw_equivalent_Bps"] = run.raw_equivalent_load()
    closures = _guarded(out, "loop closure evaluation", loop_closures.loop_closure_section, run, gt_world, landmark_world)
    metrics = {
        "scenario": run.scenario.name,
        "seed": run.scenario.seed,
        "status": "failed" if error else "completed",
        "error": error.strip().splitlines()[-1] if error else None,
        "runtime": runtime_metrics(run),
        "robots": robots_metrics,
        "comms": comms,
        "loop_closures": closures,
    }
    if run.scenario.output.topdown_png:
        plot_topdown(run, out / "topdown.png")
        if any(m.get("filter") for m in robots_metrics.values()):
            plot_filter_errors(robots_metrics, out / "filter_error.png")
        online_slam.plot_slam(robots_metrics, {n: T[:, :3, 3] for n, (_, T) in gt_world.items()}, out / "slam.png")
        robot_maps = {name: m["map"] for name, m in robots_metrics.items() if m.get("map")}
        paths = {name: np.stack(r.log.gt_pose)[:, :3] for name, r in run.robots.items() if r.log.gt_pose}
        maps.plot_maps(robot_maps, paths, run.terrain, out / "map_topdown.png")
    for m in robots_metrics.values():  # series went into the plot; keep metrics.json scalar-sized
        if m.get("map"):
            m["map"].pop("_plot", None)
        if m.get("slam"):
            m["slam"].pop("_plot", None)
            m["slam"].pop("error_over_time", None)
        if m.get("filter"):
            m["filter"].pop("error_over_time", None)
            m["filter"].get("nees_roll_pitch_velocity", {}).pop("series", None)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default))
    return metrics


def _guarded(out: Path, what: str, section, *args) -> dict[str, Any] | None:
    """An evaluation section; if it raises, its status says so and the traceback goes to
    error.txt: an evaluation bug must not cost the run's other results."""
    try:
        return section(*args)
    except Exception as exc:
        with (out / "error.txt").open("a") as f:
            f.write(f"{what} failed:\n{traceback.format_exc()}\n")
        return {"status": f"{what} failed: {type(exc).__name__}: {exc}"}


def _filter_section(out: Path, name: str, log, onboard, recorder) -> dict[str, Any] | None:
    """Filter-only trajectory against ground truth in the robot's start frame (issue 4 §4)."""
    est = onboard.log
    if len(est.t) < 2:
        return {"status": "not started", "poses": len(est.t)}
    gt_t, gt_start, T_world_start = trajectory.truth_since(log.gt_t, log.gt_pose, est.t[0])  # the filter's first frame
    T_est = np.stack(est.pose_first_frame)
    if recorder is not None:
        recorder.log_filter(name, np.asarray(est.t), T_world_start[None] @ T_est, np.stack(est.position_std))
    trajectory.write_tum(out / "trajectories" / f"{name}.gt_start.tum", gt_t, gt_start)
    trajectory.write_tum(out / "trajectories" / f"{name}.filter.tum", np.asarray(est.t), T_est)
    section: dict[str, Any] = {"status": "ok"}
    try:
        section.update(trajectory.trajectory_metrics(np.asarray(est.t), T_est, gt_t, gt_start))
    except trajectory.EvaluationError as exc:
        section = {"status": f"not evaluated: {exc}"}
    section["nees_roll_pitch_velocity"] = trajectory.nees_report(
        np.stack(est.observable), np.stack(est.observable_true), np.stack(est.observable_cov)
    )
    bias, bias_true = np.stack(est.bias), np.stack(est.bias_true)
    section["bias_error"] = {
        "accel_initial_mps2": float(np.linalg.norm(bias_true[0, :3] - bias[0, :3])),
        "accel_final_mps2": float(np.linalg.norm(bias_true[-1, :3] - bias[-1, :3])),
        "gyro_initial_dps": float(np.degrees(np.linalg.norm(bias_true[0, 3:] - bias[0, 3:]))),
        "gyro_final_dps": float(np.degrees(np.linalg.norm(bias_true[-1, 3:] - bias[-1, 3:]))),
    }
    vo = onboard.estimator.vo_stats
    section["vo"] = {"frames": vo.frames, "ok": vo.ok, "applied": vo.applied, "rejected_by_gate": vo.rejected, "failures": vo.failures}
    section["frame_switches"] = len(onboard.estimator.switches)
    return section


def plot_filter_errors(robots_metrics: dict[str, Any], path: Path) -> None:
    """Filter-only position and yaw error over time, one line per robot."""
    fig, (ax_p, ax_y, ax_n) = plt.subplots(3, 1, figsize=(9, 8), sharex=True, dpi=110)
    for name, m in robots_metrics.items():
        f = m.get("filter") or {}
        series = f.get("error_over_time")
        if not series:
            continue
        label = f"{name}: final {f['final_error_m']:.2f} m ({f['final_error_percent_of_distance']:.2f} % of {f['distance_m']:.0f} m)"
        ax_p.plot(series["t"], series["position_m"], label=label)
        ax_y.plot(series["t"], series["yaw_deg"], label=name)
        nees = f["nees_roll_pitch_velocity"]
        ax_n.plot(series["t"][: len(nees["series"])], nees["series"], lw=0.6, label=f"{name}: mean {nees['mean']:.1f}")
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
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def runtime_metrics(run: Run) -> dict[str, Any]:
    parts = dict(sorted(run.timers.seconds.items()))
    accounted = sum(parts.values())
    parts["other"] = max(0.0, run.wall_s - accounted)
    return {
        "wall_s": run.wall_s,
        "sim_s": run.sim_time,
        "real_time_factor": run.sim_time / run.wall_s if run.wall_s > 0 else None,
        "parts_s": parts,
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


def _path_length(poses: list[np.ndarray]) -> float:
    if len(poses) < 2:
        return 0.0
    xyz = np.stack(poses)[:, :3]
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())


def _write_tum(path: Path, times: list[float], poses: list[np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        for t, p in zip(times, poses):
            x, y, z, qw, qx, qy, qz = p
            f.write(f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} {qx:.8f} {qy:.8f} {qz:.8f} {qw:.8f}\n")


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
            f"{name}: {m['final_status']}, {m['distance_m']:.1f} m, waypoints {route['reached']}/{route['waypoints']} reached"
            + (f", {route['failed']} failed" if route["failed"] else "")
            + (f"; {stereo} (2-6 m)" if stereo else "")
            + _filter_summary(m.get("filter"))
            + _slam_summary(m.get("slam"))
        )
    return lines

