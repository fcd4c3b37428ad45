"""Evaluation of the collaborative SLAM against ground truth (thesis ch. 8; docs/slam.md).

The SLAM trajectory of a robot is what it believed about itself at each moment, its
graph's submap origin composed with its filter pose (eq. 4.6), never re-optimised
afterwards, in its map frame (its first submap origin = its filter's first frame, so
the filter-only and SLAM trajectories share ground truth). A robot's beliefs about its
peers are compared in its map frame, whose true pose is its true start frame (the filter's
first frame). Detections are compared with the true relative pose at their capture time.
The section reads a :class:`sim.evaluation.inputs.SlamInput`; what ``slam.png`` draws
besides the metrics comes back as a :class:`SlamPlot`. It writes the robot's trajectories
(:func:`write_trajectories`): online, by its final graph, its beliefs about its peers, and
its own in the world, where the team's trajectories share one frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import to_rgb

from sim.evaluation import trajectory
from sim.evaluation.inputs import SlamInput, TeamTruth
from sim.evaluation.statistics import StatisticsType, statistics
from sim.evaluation.trajectory import ErrorOverTime
from slam.lie import rotation_angle, se3_inv, so3_log, wrap_angle, yaw_of

if TYPE_CHECKING:
    from slam.agent import DetectionRecord
    from slam.graph import MultiRobotGraph

FACTOR_COLOURS = {"prior": "k", "w": "tab:blue", "v": "tab:cyan", "u": "tab:olive", "d": "tab:red", "c": "tab:green", "o": "tab:purple"}
LOOP_CLOSURE_TYPES = {"d": "robot_detection", "c": "submap_match", "o": "landmark"}
BELIEF_STATISTICS = (StatisticsType.MEAN, StatisticsType.MEDIAN, StatisticsType.MAX, StatisticsType.FINAL)
MEAN_MAX = (StatisticsType.MEAN, StatisticsType.MAX)
MEDIAN_MAX = (StatisticsType.MEDIAN, StatisticsType.MAX)


@dataclass(frozen=True, eq=False)
class SlamPlot:
    """What ``slam.png`` draws of one robot besides its metrics."""

    error_over_time: ErrorOverTime | None  # None when its trajectory could not be evaluated
    edges: list[tuple[str, np.ndarray, np.ndarray]]  # (factor kind, one end, the other) in the world, via the true start


def slam_section(out: Path, name: str, slam: SlamInput | None, truth: TeamTruth, recorder=None) -> tuple[dict[str, Any] | None, SlamPlot | None]:
    """Metrics of one robot's SLAM: its own online trajectory, the same times by the final
    graph (``final_graph``: every loop closure applied to the whole trajectory, also those
    that came after a pose was used), its beliefs about its peers, its graph and its
    detections; and what ``slam.png`` draws of it. Writes its trajectory's TUM file (and
    into the recording, if given). None without the graph."""
    if slam is None:
        return None, None
    estimate = slam.estimate
    if len(estimate) < 2 or slam.start_t is None:
        return {"status": "not started", "poses": len(estimate)}, None
    start = trajectory.truth_since(truth.of(name), slam.start_t)
    T_world_start = start.T_world_start
    write_trajectories(out / "trajectories", name, slam, T_world_start)
    section: dict[str, Any] = {"status": "ok"}
    error_over_time = None
    try:
        metrics, error_over_time = trajectory.trajectory_metrics(estimate, start.trajectory)
        section.update(metrics)
    except trajectory.EvaluationError as exc:
        section = {"status": f"not evaluated: {exc}"}
    try:
        section["final_graph"], _ = trajectory.trajectory_metrics(slam.final_estimate, start.trajectory)
    except trajectory.EvaluationError as exc:
        section["final_graph"] = {"status": f"not evaluated: {exc}"}
    edges = [(kind, T_world_start @ _h(a), T_world_start @ _h(b)) for kind, a, b in slam.graph.edges()]
    if recorder is not None:
        _record(recorder, name, slam, T_world_start, edges)
    origins_true = trajectory.frame_origins_truth(slam.start_t, slam.switch_times, truth.of(name))
    section["origin_consistency"] = origin_consistency(slam.graph, name, origins_true)
    section["beliefs"] = _beliefs(slam.beliefs, truth, T_world_start)
    section["graph"] = _graph_metrics(slam)
    section["detections"] = _detection_metrics(name, slam, truth)
    return section, SlamPlot(error_over_time, edges)


def write_trajectories(folder: Path, name: str, slam: SlamInput, T_world_start: np.ndarray) -> None:
    """A robot's SLAM trajectories as TUM files in ``folder`` (the results folder's
    ``trajectories/``): in its map frame ``<name>.slam.tum`` (online, eq. 4.6),
    ``<name>.slam_final.tum`` (the same times by the final graph) and
    ``<name>.belief.<peer>.tum`` (its belief about each peer, stamped with the time it held
    it: the peer's latest pose estimate on the peer's submap origin as the graph held it
    then, :meth:`slam.agent.Agent.belief`); and both of its own in the world, through its
    true start frame ``T_world_start``, so that the team's trajectories share one frame:
    ``team/<name>.slam.world.tum``, ``team/<name>.slam_final.world.tum``."""
    trajectory.write_tum(folder / f"{name}.slam.tum", slam.estimate)
    trajectory.write_tum(folder / f"{name}.slam_final.tum", slam.final_estimate)
    for peer, rows in sorted(slam.beliefs.items()):
        a = np.asarray(rows)
        trajectory.write_tum(folder / f"{name}.belief.{peer}.tum", trajectory.Trajectory(a[:, 0], a[:, 2:].reshape(-1, 4, 4)))
    for kind, own in (("slam", slam.estimate), ("slam_final", slam.final_estimate)):
        trajectory.write_tum(folder / "team" / f"{name}.{kind}.world.tum", trajectory.Trajectory(own.t, T_world_start[None] @ own.T))


def _record(recorder, name: str, slam: SlamInput, T_world_start: np.ndarray, edges: list) -> None:
    """The online trajectory and the final graph, in the world via the true start."""
    recorder.log_slam(name, slam.estimate.t, T_world_start[None] @ slam.estimate.T)
    origins, sigmas = [], []
    for (robot, index), cov in sorted(slam.marginals.items()):
        S = slam.graph.submap_origin(robot, index)
        if S is not None:
            R = T_world_start[:3, :3] @ S[:3, :3]
            origins.append((T_world_start @ S)[:3, 3])
            sigmas.append(2 * np.sqrt(np.diag(R @ cov[3:, 3:] @ R.T)))  # axis-aligned 2-sigma extents
    colours = {k: tuple(int(255 * c) for c in to_rgb(v)) for k, v in FACTOR_COLOURS.items()}
    recorder.log_graph(name, edges, colours, np.asarray(origins).reshape(-1, 3), np.asarray(sigmas).reshape(-1, 3))


def _h(p: np.ndarray) -> np.ndarray:
    return np.append(np.asarray(p, float), 1.0)


def _beliefs(beliefs: dict[str, Any], truth: TeamTruth, T_world_map: np.ndarray) -> dict[str, Any]:
    """This robot's belief about each peer (rows ``[t, t of the estimate, the pose's 16 entries]``,
    :class:`sim.run.onboard.SlamLog`): the peer's pose at the time of its latest
    estimate, in this robot's map, against truth at that time (what the graph knows),
    and against the peer's true pose at the moment of the belief (what the robot would
    act on, including the age of the estimate)."""
    out = {}
    for peer, samples in sorted(beliefs.items()):
        peer_truth = truth.robots[peer]
        err, yaw, err_now, age = [], [], [], []
        for row in samples:
            t, t_est, B = row[0], row[1], row[2:].reshape(4, 4)
            true = np.linalg.solve(T_world_map, peer_truth.at(t_est))
            err.append(np.linalg.norm(B[:3, 3] - true[:3, 3]))
            yaw.append(abs(wrap_angle(yaw_of(B[:3, :3]) - yaw_of(true[:3, :3]))))
            now = np.linalg.solve(T_world_map, peer_truth.at(t))
            err_now.append(np.linalg.norm(B[:3, 3] - now[:3, 3]))
            age.append(t - t_est)
        out[peer] = {
            "known_since_s": float(samples[0][0]),
            "samples": len(samples),
            "position_error_m": statistics(err, BELIEF_STATISTICS),
            "yaw_error_deg": statistics(np.degrees(yaw), BELIEF_STATISTICS),
            "position_error_now_m": statistics(err_now, BELIEF_STATISTICS),
            "estimate_age_s": statistics(age, BELIEF_STATISTICS),
        }
    return out


def origin_consistency(graph: MultiRobotGraph, name: str, origins_true: dict[int, np.ndarray]) -> dict[str, Any]:
    """How well ``graph`` knows its own uncertainty: each of robot ``name``'s submap origins
    ``s_k`` after the first, relative to the first (``s_0^-1 s_k``, whose covariance is what
    the matcher's pairing, eq. 6.1-6.4, and an explorer's revisits judge by), against the
    true origins ``origins_true`` (frame index -> world pose). ``position_nees``: the NEES of
    its position (3 dof, the translation part of the right perturbation, with the graph's
    joint-marginal covariance, :meth:`slam.graph.MultiRobotGraph.relative_covariances`) and
    ``yaw_nees`` of its heading (1 dof: the rotation error about the gravity-aligned origin's
    z axis); ``step_position_nees``: the same for each origin relative to the one before
    (``s_(k-1)^-1 s_k``, one frame switch's span). Steps that fit while the whole chain does not
    mean errors that repeat from step to step, which independent frame-switch factors (eq. 4.6)
    cannot represent. ``last``: the latest origin's predicted sigmas (position: largest axis)
    and true errors. A graph whose covariances fit its errors has means near 3 and 1."""
    S0 = graph.submap_origin(name, 0)
    indices = sorted(k for k in origins_true if k > 0 and graph.submap_origin(name, k) is not None)
    if S0 is None or 0 not in origins_true or not indices:
        return {"status": "fewer than two submap origins"}
    present = set(indices) | {0}
    chain = [(0, k) for k in indices]
    steps = [(k - 1, k) for k in indices if k - 1 in present]
    try:
        covs = graph.relative_covariances([((name, a), (name, b)) for a, b in chain + steps])
    except (RuntimeError, ValueError) as exc:  # gtsam: no marginals of this estimate
        return {"status": f"not evaluated: {exc}"}

    def relative_errors(pairs):
        errors, cov, yaw, yaw_var = [], [], [], []
        for a, b in pairs:
            if ((name, a), (name, b)) not in covs:
                continue
            C = covs[((name, a), (name, b))]
            est = se3_inv(graph.submap_origin(name, a)) @ graph.submap_origin(name, b)
            true = se3_inv(origins_true[a]) @ origins_true[b]
            errors.append(est[:3, :3].T @ (true[:3, 3] - est[:3, 3]))
            cov.append(C[3:, 3:])
            yaw.append(so3_log(est[:3, :3].T @ true[:3, :3])[2])
            yaw_var.append(C[2, 2])
        return np.array(errors), np.array(cov), np.array(yaw)[:, None], np.array(yaw_var)[:, None, None]

    errors, cov, yaw, yaw_var = relative_errors(chain)
    if not len(errors):
        return {"status": "no covariances"}
    report, _ = trajectory.nees_report(errors, np.zeros_like(errors), cov, angle_dims=0)
    yaw_report, _ = trajectory.nees_report(yaw, np.zeros_like(yaw), yaw_var, angle_dims=1)
    step_errors, step_cov, _, _ = relative_errors(steps)
    step_report = trajectory.nees_report(step_errors, np.zeros_like(step_errors), step_cov, angle_dims=0)[0] if len(step_errors) else None
    return {
        "status": "ok",
        "origins": len(errors),
        "position_nees": report,
        "yaw_nees": yaw_report,
        "step_position_nees": step_report,
        "last": {
            "sigma_m": float(np.sqrt(np.linalg.eigvalsh(cov[-1])[-1])),
            "error_m": float(np.linalg.norm(errors[-1])),
            "yaw_sigma_deg": float(np.degrees(np.sqrt(yaw_var[-1, 0, 0]))),
            "yaw_error_deg": float(np.degrees(yaw[-1, 0])),
        },
    }


def _graph_metrics(slam: SlamInput) -> dict[str, Any]:
    graph, stats = slam.graph, slam.stats
    counts = graph.factor_counts()
    times = np.asarray(graph.update_times) * 1e3
    cov = np.asarray(stats.covariance_s) * 1e3
    return {
        "nodes": graph.node_count(),
        "factors": counts,
        "pending_factors": graph.pending_count(),
        "connected_robots": graph.connected_robots(),
        "loop_closures": {label: counts.get(kind, 0) for kind, label in LOOP_CLOSURE_TYPES.items()},
        "isam2_updates": len(times),
        "isam2_update_ms": statistics(times, MEAN_MAX) if times.size else None,
        "covariance_ms": statistics(cov, MEAN_MAX) if cov.size else None,
        # iSAM2 failures the graph recovered from (slam.graph.GraphRecovery) and the factors they left out
        "recoveries": {
            "count": len(graph.recoveries),
            "events": [
                {"t": r.t, "update": r.update, "error": r.error, "variable": r.variable, "action": r.action, "dropped": list(r.dropped)}
                for r in graph.recoveries
            ],
        },
        "dropped_factors": {"count": len(graph.dropped_factors()), "factors": graph.dropped_factors()},
        # robust option of the measured factors; with gnc its outlier classifications (slam.graph.GncRun)
        "robust": graph.params.robust.value,
        "gnc": _gnc_metrics(graph.gnc_runs, graph.rejected_factors()),
        "marginal_failures": stats.marginal_failures,
        "messages_received": dict(stats.received),
        "duplicates_ignored": stats.duplicates,
        "submaps_received": slam.submaps_received,
    }


def _gnc_metrics(runs: list, rejected: list[str]) -> dict[str, Any]:
    """GNC runs (count, failures, wall time), the measured factors rejected at the end, re-admissions."""
    wall = np.asarray([r.wall_s for r in runs]) * 1e3
    return {
        "runs": len(runs),
        "failures": sum(r.error is not None for r in runs),
        "wall_ms": statistics(wall, MEAN_MAX) if wall.size else None,
        "rejections": sum(r.newly_rejected for r in runs),
        "readmissions": sum(r.readmitted for r in runs),
        "bridges_kept": sum(r.bridges for r in runs),
        "rejected": {"count": len(rejected), "factors": rejected},
    }


def detection_truth(name: str, d: DetectionRecord, truth: TeamTruth) -> np.ndarray | None:
    """The true pose of a detection's target in the detector's body frame at its time
    (None for a landmark when the run has none)."""
    if d.target.startswith("landmark:"):
        if truth.landmark is None:
            return None
        target = truth.landmark
    else:
        target = truth.robots[d.target].at(d.t)
    return np.linalg.solve(truth.robots[name].at(d.t), target)


def _detection_metrics(name: str, slam: SlamInput, truth: TeamTruth) -> dict[str, Any]:
    """Each detection against the true pose of its target in the detector's body frame."""
    stats = slam.stats
    out: dict[str, Any] = {
        "markers_seen": stats.detections_seen,
        "used": stats.detections_used,
        "rejected": dict(stats.detections_rejected),
        "unanswerable": stats.unanswerable,
    }
    trans, rot, sigma = [], [], []
    for d in slam.detections:
        true = detection_truth(name, d, truth)
        if true is None:
            continue
        trans.append(np.linalg.norm(d.T_detector_target[:3, 3] - true[:3, 3]))
        rot.append(float(np.degrees(rotation_angle(d.T_detector_target[:3, :3].T @ true[:3, :3]))))
        sigma.append(np.sqrt(np.trace(d.cov[3:, 3:]) / 3))
    if trans:
        out["position_error_m"] = statistics(trans, MEDIAN_MAX)
        out["rotation_error_deg"] = statistics(rot, MEDIAN_MAX)
        out["predicted_position_sigma_m"] = statistics(sigma, (StatisticsType.MEDIAN,))
        out["distance_m"] = statistics([d.distance_m for d in slam.detections], (StatisticsType.MIN, StatisticsType.MAX))
    return out


def plot_slam(
    robots_metrics: dict[str, Any],
    slam_plots: dict[str, SlamPlot | None],
    filter_errors: dict[str, ErrorOverTime | None],
    truth: TeamTruth,
    path: Path,
) -> None:
    """Per robot: filter-only and SLAM position error over time (top) and its final graph
    drawn top-down over the true paths, edges coloured by factor type (bottom)."""
    names = [n for n, p in slam_plots.items() if p is not None and p.error_over_time is not None]
    if not names:
        return
    fig, axes = plt.subplots(2, len(names), figsize=(6 * len(names), 10), dpi=100, squeeze=False)
    for col, name in enumerate(names):
        m = robots_metrics[name]
        s, f = m["slam"], m.get("filter") or {}
        ax = axes[0, col]
        if (filter_error := filter_errors.get(name)) is not None:
            ax.plot(filter_error.t, filter_error.position_m, color="tab:gray", label=f"filter only: ATE {f['ate_m']['rmse']:.2f} m")
        slam_error = slam_plots[name].error_over_time
        ax.plot(slam_error.t, slam_error.position_m, color="tab:red", label=f"SLAM online: ATE {s['ate_m']['rmse']:.2f} m")
        ax.set_title(f"{name}: position error in its map frame (online, unaligned)")
        ax.set_xlabel("simulated time [s]")
        ax.set_ylabel("error [m]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax = axes[1, col]
        for robot, true_path in truth.robots.items():
            xyz = true_path.positions
            ax.plot(xyz[:, 0], xyz[:, 1], color="0.75", lw=1)
            ax.annotate(robot, xyz[0, :2], fontsize=7, color="0.5")
        seen = set()
        for kind, a, b in slam_plots[name].edges:
            label = None if kind in seen else kind
            seen.add(kind)
            ax.plot([a[0], b[0]], [a[1], b[1]], color=FACTOR_COLOURS.get(kind, "k"), lw=1.5 if kind in LOOP_CLOSURE_TYPES else 0.8, label=label)
        g = s["graph"]
        ax.set_title(f"{name}'s graph: {g['nodes']} nodes, " + ", ".join(f"{k} {v}" for k, v in sorted(g["factors"].items())), fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m] (world, via true start)")
        if seen:
            ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
