"""Evaluation of the collaborative SLAM against ground truth (thesis ch. 8, issue 6 §4).

The SLAM trajectory of a robot is what it believed about itself at each moment, its
graph's submap origin composed with its filter pose (eq. 4.6), never re-optimised
afterwards, in its map frame (its first submap origin = its filter's first frame, so
the filter-only and SLAM trajectories share ground truth). A robot's beliefs about its
peers are compared in its map frame, whose true pose is its true start frame (the filter's
first frame). Detections are compared with the true relative pose at their capture time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import to_rgb

from sim.evaluation import trajectory
from slam.lie import so3_log

FACTOR_COLOURS = {"prior": "k", "w": "tab:blue", "v": "tab:cyan", "u": "tab:olive", "d": "tab:red", "c": "tab:green", "o": "tab:purple"}
LOOP_CLOSURE_TYPES = {"d": "robot_detection", "c": "submap_match", "o": "landmark"}


def truth_at(gt_t: np.ndarray, gt_world: np.ndarray, t: float) -> np.ndarray:
    """True body pose at ``t`` (ground truth is sampled on the same clock)."""
    i = min(int(np.searchsorted(gt_t, t - 1e-6)), len(gt_t) - 1)
    return gt_world[i]


def _stats(values: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(values)), "median": float(np.median(values)), "max": float(np.max(values)), "final": float(values[-1])}


def rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(R))))


def lander_tag_pose(model, data) -> np.ndarray | None:
    """World pose of the lander's tag (the landmark's frame), or None without a lander."""
    for g in range(model.ngeom):
        if model.geom(g).name.endswith("lander_tag"):
            T = np.eye(4)
            T[:3, :3] = data.geom_xmat[g].reshape(3, 3)
            T[:3, 3] = data.geom_xpos[g]
            return T
    return None


def slam_section(
    out: Path, name: str, logs: dict, onboard, gt_world: dict[str, tuple[np.ndarray, np.ndarray]], landmark_world: np.ndarray | None, recorder
) -> dict[str, Any] | None:
    """Metrics of one robot's SLAM: its own online trajectory, its beliefs about its
    peers, its graph and its detections. ``gt_world``: robot -> (times, (N, 4, 4) world poses)."""
    agent, slog = onboard.agent, onboard.slam_log
    if not onboard.exchange:
        return None
    if len(slog.t) < 2 or not onboard.log.t:
        return {"status": "not started", "poses": len(slog.t)}
    log = logs[name]
    gt_t, gt_start, T_world_start = trajectory.truth_since(log.gt_t, log.gt_pose, onboard.log.t[0])
    t_est, T_est = np.asarray(slog.t), np.stack(slog.pose)
    trajectory.write_tum(out / "trajectories" / f"{name}.slam.tum", t_est, T_est)
    section: dict[str, Any] = {"status": "ok"}
    try:
        section.update(trajectory.trajectory_metrics(t_est, T_est, gt_t, gt_start))
    except trajectory.EvaluationError as exc:
        section = {"status": f"not evaluated: {exc}"}
    edges = [(kind, T_world_start @ _h(a), T_world_start @ _h(b)) for kind, a, b in agent.graph.edges()]
    if recorder is not None:
        recorder.log_slam(name, t_est, T_world_start[None] @ T_est)
        origins, sigmas = [], []
        for (robot, index), cov in sorted(agent.marginals.items()):
            S = agent.graph.submap_origin(robot, index)
            if S is not None:
                R = T_world_start[:3, :3] @ S[:3, :3]
                origins.append((T_world_start @ S)[:3, 3])
                sigmas.append(2 * np.sqrt(np.diag(R @ cov[3:, 3:] @ R.T)))  # axis-aligned 2-sigma extents
        colours = {k: tuple(int(255 * c) for c in to_rgb(v)) for k, v in FACTOR_COLOURS.items()}
        recorder.log_graph(name, edges, colours, np.asarray(origins).reshape(-1, 3), np.asarray(sigmas).reshape(-1, 3))
    section["beliefs"] = _beliefs(slog, gt_world, T_world_start)
    section["graph"] = _graph_metrics(agent)
    section["detections"] = _detection_metrics(name, agent, gt_world, landmark_world)
    section["_plot"] = {"edges": edges}
    return section


def _h(p: np.ndarray) -> np.ndarray:
    return np.append(np.asarray(p, float), 1.0)


def _beliefs(slog, gt_world, T_world_map: np.ndarray) -> dict[str, Any]:
    """This robot's belief about each peer: the peer's pose at the time of its latest
    estimate, in this robot's map, against truth at that time (what the graph knows),
    and against the peer's true pose at the moment of the belief (what the robot would
    act on, including the age of the estimate)."""
    out = {}
    for peer, samples in sorted(slog.beliefs.items()):
        t_peer, X_peer = gt_world[peer]
        err, yaw, err_now, age = [], [], [], []
        for t, t_est, B in samples:
            true = np.linalg.solve(T_world_map, truth_at(t_peer, X_peer, t_est))
            err.append(np.linalg.norm(B[:3, 3] - true[:3, 3]))
            yaw.append(abs(trajectory.wrap(trajectory.yaw_of(B[:3, :3]) - trajectory.yaw_of(true[:3, :3]))))
            now = np.linalg.solve(T_world_map, truth_at(t_peer, X_peer, t))
            err_now.append(np.linalg.norm(B[:3, 3] - now[:3, 3]))
            age.append(t - t_est)
        out[peer] = {
            "known_since_s": float(samples[0][0]),
            "samples": len(samples),
            "position_error_m": _stats(np.asarray(err)),
            "yaw_error_deg": _stats(np.degrees(yaw)),
            "position_error_now_m": _stats(np.asarray(err_now)),
            "estimate_age_s": _stats(np.asarray(age)),
        }
    return out


def _graph_metrics(agent) -> dict[str, Any]:
    graph, stats = agent.graph, agent.stats
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
        "isam2_update_ms": {"mean": float(times.mean()), "max": float(times.max())} if times.size else None,
        "covariance_ms": {"mean": float(cov.mean()), "max": float(cov.max())} if cov.size else None,
        "messages_received": dict(stats.received),
        "duplicates_ignored": stats.duplicates,
        "submaps_received": len(agent.peer_submaps),
    }


def detection_truth(name: str, d, gt_world, landmark_world: np.ndarray | None) -> np.ndarray | None:
    """The true pose of a detection's target in the detector's body frame at its time
    (None for a landmark when the run has none)."""
    t_own, X_own = gt_world[name]
    if d.target.startswith("landmark:"):
        if landmark_world is None:
            return None
        target = landmark_world
    else:
        t_peer, X_peer = gt_world[d.target]
        target = truth_at(t_peer, X_peer, d.t)
    return np.linalg.solve(truth_at(t_own, X_own, d.t), target)


def _detection_metrics(name: str, agent, gt_world, landmark_world: np.ndarray | None) -> dict[str, Any]:
    """Each detection against the true pose of its target in the detector's body frame."""
    stats = agent.stats
    out: dict[str, Any] = {
        "markers_seen": stats.detections_seen,
        "used": stats.detections_used,
        "rejected": dict(stats.detections_rejected),
        "unanswerable": stats.unanswerable,
    }
    trans, rot, sigma = [], [], []
    for d in agent.detections:
        true = detection_truth(name, d, gt_world, landmark_world)
        if true is None:
            continue
        trans.append(np.linalg.norm(d.T_detector_target[:3, 3] - true[:3, 3]))
        rot.append(rotation_deg(d.T_detector_target[:3, :3].T @ true[:3, :3]))
        sigma.append(np.sqrt(np.trace(d.cov[3:, 3:]) / 3))
    if trans:
        trans, sigma = np.asarray(trans), np.asarray(sigma)
        out["position_error_m"] = {"median": float(np.median(trans)), "max": float(trans.max())}
        out["rotation_error_deg"] = {"median": float(np.median(rot)), "max": float(np.max(rot))}
        out["predicted_position_sigma_m"] = {"median": float(np.median(sigma))}
        out["distance_m"] = {"min": float(min(d.distance_m for d in agent.detections)), "max": float(max(d.distance_m for d in agent.detections))}
    return out


def plot_slam(robots_metrics: dict[str, Any], paths_world: dict[str, np.ndarray], path: Path) -> None:
    """Per robot: filter-only and SLAM position error over time (top) and its final graph
    drawn top-down over the true paths, edges coloured by factor type (bottom)."""
    names = [n for n, m in robots_metrics.items() if (m.get("slam") or {}).get("error_over_time")]
    if not names:
        return
    fig, axes = plt.subplots(2, len(names), figsize=(6 * len(names), 10), dpi=100, squeeze=False)
    for col, name in enumerate(names):
        m = robots_metrics[name]
        s, f = m["slam"], m.get("filter") or {}
        ax = axes[0, col]
        if f.get("error_over_time"):
            ax.plot(
                f["error_over_time"]["t"], f["error_over_time"]["position_m"], color="tab:gray", label=f"filter only: ATE {f['ate_m']['rmse']:.2f} m"
            )
        ax.plot(s["error_over_time"]["t"], s["error_over_time"]["position_m"], color="tab:red", label=f"SLAM online: ATE {s['ate_m']['rmse']:.2f} m")
        ax.set_title(f"{name}: position error in its map frame (online, unaligned)")
        ax.set_xlabel("simulated time [s]")
        ax.set_ylabel("error [m]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax = axes[1, col]
        for robot, xyz in paths_world.items():
            ax.plot(xyz[:, 0], xyz[:, 1], color="0.75", lw=1)
            ax.annotate(robot, xyz[0, :2], fontsize=7, color="0.5")
        seen = set()
        for kind, a, b in s["_plot"]["edges"]:
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
