"""slam.graph: iSAM2 against batch Levenberg-Marquardt in both topologies, unconnected chains kept pending,
arrival-order independence, loop closure and the Cauchy kernel (thesis 4.2.2, 4.2.3), input validation and
the online pose (eq. 4.6), on seeded synthetic ground truth."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np
import pytest

from slam.filter import switch_pose3_covariance
from slam.graph import FactorType, GraphException, GraphParams, MultiRobotGraph, Topology
from slam.lie import rot_z, rot_zyx, se3, se3_inv, so3_exp, so3_log
from slam.vo import adjoint

DT = 0.5
COV_V = np.diag([0.004**2] * 3 + [0.03**2] * 3)  # a filter pose v


def filter_covariance(n: int) -> np.ndarray:
    """A filter's pose covariance ``n`` steps into its frame: roll and pitch bounded (observed through
    gravity), yaw and position growing from zero at the frame's start (thesis 4.1.2)."""
    return np.diag([0.005**2] * 2 + [(0.002 * n) ** 2 + 1e-8] + [(0.01 * n) ** 2 + 1e-6] * 3)


def switch_covariance(n: int) -> np.ndarray:
    """[x, y, z, yaw] covariance of a frame switch after ``n`` steps in the frame."""
    C = filter_covariance(n)
    return np.diag([C[3, 3], C[4, 4], C[5, 5], C[2, 2]])


COV_D = np.diag([0.01**2] * 3 + [0.05**2] * 3)  # detection, landmark observation
COV_C = np.diag([0.005**2] * 3 + [0.05**2] * 3)  # submap match
# iSAM2 relinearizes a variable only once its update exceeds the threshold, and the Cauchy weights (eq. 4.11)
# change only on relinearization: converging to the batch optimum takes a small threshold and some iterations.
LOCAL, SEQ = GraphParams(relinearize_threshold=1e-6), GraphParams(topology=Topology.SEQUENTIAL, relinearize_threshold=1e-6)
CONVERGE = 20  # extra iterations


@dataclass
class Robot:
    """Ground truth of one robot in the simulator's world frame."""

    name: str
    X: dict[float, np.ndarray] = field(default_factory=dict)  # body poses by time
    frame: dict[float, int] = field(default_factory=dict)  # frame index by time
    steps: dict[float, int] = field(default_factory=dict)  # steps since the start of the frame
    per_submap: int = 8  # steps in each frame
    S: list[np.ndarray] = field(default_factory=list)  # gravity-aligned submap origins
    switch_t: list[float] = field(default_factory=list)  # time of the switch into frame j + 1


def drive(name: str, rng: np.random.Generator, x: float, y: float, yaw: float, steps: int = 40, per_submap: int = 8, yaw_rate: float = 0.0) -> Robot:
    r = Robot(name, per_submap=per_submap)
    for k in range(steps):
        t = k * DT
        z = 0.2 * math.sin(0.3 * k + x)
        roll, pitch = rng.normal(0.0, 0.03, 2)
        r.X[t] = se3(rot_zyx(roll, pitch, yaw), [x, y, z])
        if k % per_submap == 0:
            r.S.append(se3(rot_z(yaw), [x, y, z]))
            if k:
                r.switch_t.append(t)
        r.frame[t], r.steps[t] = len(r.S) - 1, k % per_submap
        x, y = x + 0.5 * math.cos(yaw) * DT, y + 0.5 * math.sin(yaw) * DT
        yaw += yaw_rate * DT + rng.normal(0.0, 0.05)
    return r


def noisy(T: np.ndarray, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return T @ gtsam.Pose3.Expmap(np.linalg.cholesky(cov) @ rng.standard_normal(6)).matrix()


def chain_inputs(r: Robot, rng: np.random.Generator) -> list[tuple]:
    """Every frame switch and filter pose of a robot, noisy, as (method, args)."""
    out = []
    for j, t in enumerate(r.switch_t):
        T = se3_inv(r.S[j]) @ r.S[j + 1]
        cov = switch_pose3_covariance(T, switch_covariance(r.per_submap))
        out.append(("add_frame_switch", (r.name, j, t, noisy(T, cov, rng), cov)))
    for t, X in r.X.items():
        j, cov = r.frame[t], filter_covariance(r.steps[t])
        out.append(("add_robot_pose", (r.name, t, j, noisy(se3_inv(r.S[j]) @ X, cov, rng), cov)))
    return out


def detection(a: Robot, b: Robot, t: float, rng: np.random.Generator, offset=(0.0, 0.0, 0.0)) -> tuple:
    T = noisy(se3_inv(a.X[t]) @ b.X[t], COV_D, rng)
    T[:3, 3] += offset
    return ("add_detection", (a.name, b.name, t, T, COV_D))


def observation(r: Robot, t: float, landmark: int, L: np.ndarray, rng: np.random.Generator) -> tuple:
    return ("add_landmark_observation", (r.name, t, landmark, noisy(se3_inv(r.X[t]) @ L, COV_D, rng), COV_D))


def match(a: Robot, i: int, b: Robot, j: int, rng: np.random.Generator) -> tuple:
    return ("add_match", (a.name, i, b.name, j, noisy(se3_inv(a.S[i]) @ b.S[j], COV_C, rng), COV_C))


def feed(graph: MultiRobotGraph, inputs: list[tuple]) -> None:
    for method, args in inputs:
        getattr(graph, method)(*args)


def pose_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation rad) between two poses."""
    D = se3_inv(A) @ B
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(np.linalg.norm(so3_log(D[:3, :3])))


def nees(graph: MultiRobotGraph, robot: str, j: int, truth: np.ndarray) -> float:
    """Squared Mahalanobis distance of a submap origin's error under its marginal covariance (6 dof)."""
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(se3_inv(graph.submap_origin(robot, j)) @ truth))
    return float(xi @ np.linalg.solve(graph.marginal_covariance(robot, j), xi))


CHI2_6 = 22.46  # 99.9 % quantile, 6 dof


def team(seed: int) -> tuple[list[Robot], list[tuple], np.random.Generator]:
    """Three robots and everything they measure: chains, detections, a landmark seen by two robots, a match."""
    rng = np.random.default_rng(seed)
    a = drive("lru1", rng, 0.0, 0.0, 0.0, yaw_rate=0.1)
    b = drive("lru2", rng, 0.0, 3.0, -0.2, yaw_rate=-0.05)
    c = drive("ardea", rng, 2.0, 1.5, 0.3)
    L = se3(rot_z(0.7), [6.0, 2.0, 0.5])
    inputs = chain_inputs(a, rng) + chain_inputs(b, rng) + chain_inputs(c, rng)
    inputs += [detection(a, b, t, rng) for t in (1.0, 7.5, 15.0)] + [detection(b, c, t, rng) for t in (4.0, 12.0)]
    inputs += [detection(c, a, 18.0, rng), observation(a, 10.0, 7, L, rng), observation(b, 16.5, 7, L, rng)]
    inputs += [match(a, 1, b, 2, rng), match(c, 0, c, 3, rng)]
    return [a, b, c], inputs, rng


def in_time_order(inputs: list[tuple]) -> list[tuple]:
    """Inputs sorted by the time they refer to (a frame switch's, a pose's, a measurement's; matches last)."""

    def t(item):
        method, args = item
        return {"add_frame_switch": args[2], "add_robot_pose": args[1], "add_detection": args[2], "add_landmark_observation": args[1]}.get(
            method, 1e9
        )

    return sorted(inputs, key=t)


def run(params: GraphParams, chunks: list[list[tuple]], extra: int) -> tuple[MultiRobotGraph, list]:
    graph, stats = MultiRobotGraph("lru1", params), []
    for chunk in chunks:
        feed(graph, chunk)
        stats.append(graph.update())
    stats.append(graph.update(extra_iterations=extra))
    return graph, stats


def split(inputs: list[tuple], n: int) -> list[list[tuple]]:
    return [list(c) for c in np.array_split(np.array(inputs, dtype=object), n)]


# ---------------------------------------------------------------------------- 1. iSAM2 == batch LM


@pytest.mark.parametrize(
    "params, extra",
    [(LOCAL, CONVERGE), (SEQ, CONVERGE), (GraphParams(cauchy_c=math.inf), 2)],
    ids=["local_reference", "sequential", "gaussian_default_threshold"],
)
def test_isam2_equals_batch_levenberg_marquardt(params, extra):
    robots, inputs, _ = team(1)
    graph, _ = run(params, split(in_time_order(inputs), 5), extra=extra)
    assert graph.pending_count() == 0 and graph.connected_robots() == ["ardea", "lru1", "lru2"]
    counts = graph.factor_counts()
    assert counts["d"] == 6 and counts["o"] == 2 and counts["c"] == 2 and counts["prior"] == 1
    if params.topology is Topology.LOCAL_REFERENCE:
        assert counts["w"] == 3 * 4 and counts["v"] == 14 and counts["u"] == 0
    else:
        assert counts["w"] == counts["v"] == 0 and counts["u"] == 3 * 4 + 14
    isam, batch = graph.estimate(), graph.batch_optimize()
    assert isam.keys() == batch.keys() and len(isam) == graph.node_count() == 15 + 14 + 1
    worst = np.max([pose_error(isam[k], batch[k]) for k in isam], axis=0)
    assert worst[0] < 1e-4 and worst[1] < 1e-4, worst
    # and the truth, in the owner's map frame, is within the estimate's marginal covariance
    M = se3_inv(robots[0].S[0])
    assert max(nees(graph, r.name, j, M @ S) for r in robots for j, S in enumerate(r.S) if (r.name, j) != ("lru1", 0)) < CHI2_6


# ---------------------------------------------------------------------------- 2. unconnected chains stay pending


def test_unconnected_robot_stays_pending_then_joins_with_its_backlog():
    robots, _, rng = team(2)
    a, b, c = robots
    graph = MultiRobotGraph("lru1")
    feed(graph, chain_inputs(c, rng))  # ardea's whole chain, nothing connecting it yet
    stats = graph.update()
    assert stats.factors_added == 1 and graph.node_count() == 1  # only the owner's prior
    feed(graph, chain_inputs(a, rng) + chain_inputs(b, rng) + [detection(a, b, 5.0, rng), detection(b, a, 12.0, rng)])
    for _ in range(3):
        graph.update()
    feed(graph, [observation(c, 6.0, 3, se3(np.eye(3), [4.0, 4.0, 0.0]), rng)])  # a landmark nobody else saw
    graph.update(extra_iterations=1)
    assert graph.connected_robots() == ["lru1", "lru2"]
    assert graph.submap_origin("ardea", 0) is None and graph.latest_submap("ardea") is None
    assert graph.robot_pose("ardea", 6.0) is None and graph.landmark(3) is None
    assert graph.online_pose("ardea", 0, np.eye(4)) is None and graph.marginal_covariance("ardea", 0) is None
    assert graph.pending_count() == 4 + 1 + 1  # ardea's switches, v of x[ardea,6], o
    assert graph.latest_submap("lru2") == 4

    feed(graph, [detection(b, c, 14.0, rng)])
    stats = graph.update(extra_iterations=2)
    assert graph.pending_count() == 0 and graph.connected_robots() == ["ardea", "lru1", "lru2"]
    assert graph.latest_submap("ardea") == 4 and graph.landmark(3) is not None
    assert stats.variables_added == 5 + 2 + 1 + 1  # s[ardea,0..4], x[ardea,6|14], x[lru2,14], l[3]
    M = se3_inv(a.S[0])
    assert max(nees(graph, "ardea", j, M @ S) for j, S in enumerate(c.S)) < CHI2_6


# ---------------------------------------------------------------------------- 3. order independence


@pytest.mark.parametrize("params", [LOCAL, SEQ], ids=["local_reference", "sequential"])
def test_late_and_out_of_order_inputs_give_the_same_estimate(params):
    _, inputs, _ = team(3)
    ordered, _ = run(params, split(in_time_order(inputs), 6), extra=CONVERGE)
    shuffled = [inputs[i] for i in np.random.default_rng(4).permutation(len(inputs))]
    late, stats = run(params, split(shuffled, 4), extra=CONVERGE)
    assert ordered.signatures() == late.signatures() and len(late.signatures()) == sum(late.factor_counts().values())
    assert ordered.node_count() == late.node_count() and late.pending_count() == 0
    for name, n in (("lru1", 5), ("lru2", 5), ("ardea", 5)):
        for j in range(n):
            dp, dr = pose_error(ordered.submap_origin(name, j), late.submap_origin(name, j))
            assert dp < 1e-5 and dr < 1e-5, (name, j, dp, dr)
    for method, args in inputs:
        if method == "add_detection":
            for robot in args[:2]:
                dp, dr = pose_error(ordered.robot_pose(robot, args[2]), late.robot_pose(robot, args[2]))
                assert dp < 1e-5 and dr < 1e-5
    removed = sum(s.factors_removed for s in stats)
    assert removed > 0 if params.topology is Topology.SEQUENTIAL else removed == 0


def test_sequential_replaces_the_odometry_factor_a_late_pose_splits():
    rng = np.random.default_rng(5)
    a, b = drive("lru1", rng, 0.0, 0.0, 0.0), drive("lru2", rng, 0.0, 2.0, 0.0)
    graph = MultiRobotGraph("lru1", SEQ)
    feed(graph, chain_inputs(a, rng) + chain_inputs(b, rng) + [detection(a, b, 1.0, rng), detection(a, b, 3.0, rng)])
    graph.update()
    before = graph.factor_counts()["u"]
    feed(graph, [detection(a, b, 2.0, rng)])  # x[lru1,2] and x[lru2,2] fall between the poses at 1 and 3
    stats = graph.update()
    assert stats.factors_removed == 2 and stats.factors_added == 4 + 1 and stats.variables_added == 2
    assert graph.factor_counts()["u"] == before + 2
    names = {sig[1] for sig in graph.signatures() if sig[0] == "u"}
    assert ("x[lru1,1.0]", "x[lru1,2.0]") in names and ("x[lru1,2.0]", "x[lru1,3.0]") in names
    assert ("x[lru1,1.0]", "x[lru1,3.0]") not in names
    # the local reference topology adds the two v factors and removes nothing
    local = MultiRobotGraph("lru1")
    feed(local, chain_inputs(a, rng) + chain_inputs(b, rng) + [detection(a, b, 1.0, rng), detection(a, b, 3.0, rng)])
    local.update()
    feed(local, [detection(a, b, 2.0, rng)])
    stats = local.update()
    assert stats.factors_removed == 0 and stats.factors_added == 3


def test_sequential_odometry_covariance_is_the_clipped_difference():
    graph = MultiRobotGraph("lru1", SEQ)
    cov1, cov2 = np.diag([1e-4] * 3 + [1e-2] * 3), np.diag([2e-4] * 3 + [5e-3] * 3)
    graph.add_robot_pose("lru1", 1.0, 0, se3(np.eye(3), [1.0, 0.0, 0.0]), cov1)
    graph.add_robot_pose("lru1", 2.0, 0, se3(np.eye(3), [2.0, 0.0, 0.0]), cov2)
    graph.add_landmark_observation("lru1", 1.0, 0, np.eye(4), COV_D)
    graph.add_landmark_observation("lru1", 2.0, 0, se3(np.eye(3), [-1.0, 0.0, 0.0]), COV_D)
    graph.update()
    factors = graph.batch_graph()
    u = next(f for f in map(factors.at, range(factors.size())) if [graph.describe(k) for k in f.keys()] == ["x[lru1,1.0]", "x[lru1,2.0]"])
    R = u.noiseModel().R()
    cov = np.linalg.inv(R.T @ R)
    assert np.allclose(np.diag(cov), [1e-4] * 3 + [1e-10] * 3, rtol=1e-6)
    assert np.allclose(u.measured().matrix(), se3(np.eye(3), [1.0, 0.0, 0.0]))


# ---------------------------------------------------------------------------- 4. loop closure and outliers


def test_landmark_loop_closure_pulls_a_drifting_online_pose_toward_truth():
    rng = np.random.default_rng(6)
    r = drive("lru1", rng, 0.0, 0.0, 0.0, steps=64, yaw_rate=2 * math.pi / 32.0)  # one circle of 5 m radius
    drift = np.random.default_rng(60)
    inputs = chain_inputs(r, drift)
    L = se3(rot_z(0.3), [0.5, -1.5, 0.2])
    graph = MultiRobotGraph("lru1")
    feed(graph, inputs + [observation(r, 0.5, 0, L, rng)])
    graph.update()
    t_end = 31.5
    j, v = r.frame[t_end], next(args[3] for m, args in inputs if m == "add_robot_pose" and args[1] == t_end)
    truth = se3_inv(r.S[0]) @ r.X[t_end]
    before, cov_before = pose_error(graph.online_pose("lru1", j, v), truth), graph.marginal_covariance("lru1", j)
    feed(graph, [observation(r, t_end, 0, L, rng)])
    graph.update(extra_iterations=2)
    after, cov_after = pose_error(graph.online_pose("lru1", j, v), truth), graph.marginal_covariance("lru1", j)
    assert before[0] > 0.2 and after[0] < 0.5 * before[0], (before, after)
    assert after[1] < before[1]
    assert np.trace(cov_after[3:, 3:]) < 0.5 * np.trace(cov_before[3:, 3:])  # the closure shrinks the submap's uncertainty
    assert graph.factor_counts()["o"] == 2 and graph.latest_submap("lru1") == j == 7


@pytest.mark.parametrize("cauchy_c, suppressed", [(3.5, True), (math.inf, False)], ids=["cauchy", "gaussian"])
def test_gross_outlier_detection_is_suppressed_by_the_cauchy_kernel(cauchy_c, suppressed):
    rng = np.random.default_rng(7)
    a, b = drive("lru1", rng, 0.0, 0.0, 0.0), drive("lru2", rng, 1.0, 3.0, 0.0)
    graph = MultiRobotGraph("lru1", GraphParams(cauchy_c=cauchy_c))
    feed(graph, chain_inputs(a, rng) + chain_inputs(b, rng) + [detection(a, b, t, rng) for t in (2.0, 8.0, 14.0)])
    graph.update(extra_iterations=5)
    inliers_only = [graph.submap_origin("lru2", j) for j in range(5)]
    feed(graph, [detection(a, b, 10.0, rng, offset=(5.0, 0.0, 0.0))])  # 100 sigma off
    graph.update(extra_iterations=5)
    shift = max(pose_error(graph.submap_origin("lru2", j), inliers_only[j])[0] for j in range(5))
    assert (shift < 0.02) is suppressed and (shift > 0.3) is not suppressed, shift


# ---------------------------------------------------------------------------- 5. validation


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda g: g.add_detection("lru1", "lru1", 1.0, np.eye(4), COV_D), "two different robots"),
        (lambda g: g.add_match("lru2", 3, "lru2", 3, np.eye(4), COV_C), "two different submaps"),
        (lambda g: g.add_detection("lru1", "lru2", 1.0, np.eye(3), COV_D), "4x4"),
        (lambda g: g.add_detection("lru1", "lru2", 1.0, np.full((4, 4), np.nan), COV_D), "finite"),
        (lambda g: g.add_detection("lru1", "lru2", 1.0, 2.0 * np.eye(4), COV_D), "rigid"),
        (lambda g: g.add_detection("lru1", "lru2", 1.0, np.eye(4), np.eye(3)), "6x6"),
        (lambda g: g.add_detection("lru1", "lru2", 1.0, np.eye(4), np.diag([1.0, 1, 1, 1, 1, -1])), "positive definite"),
        (lambda g: g.add_detection("lru1", "lru2", 1.0, np.eye(4), np.diag([1.0, 1, 1, 1, 1, np.inf])), "finite"),
        (lambda g: g.add_detection("lru1", "lru2", float("nan"), np.eye(4), COV_D), "finite float"),
        (lambda g: g.add_detection("", "lru2", 1.0, np.eye(4), COV_D), "non-empty string"),
        (lambda g: g.add_frame_switch("lru1", -1, 1.0, np.eye(4), COV_D), "int >= 0"),
        (lambda g: g.add_robot_pose("lru1", 1.0, 0.5, np.eye(4), COV_V), "int >= 0"),
        (lambda g: g.add_landmark_observation("lru1", 1.0, "lander", np.eye(4), COV_D), "landmark"),
        (lambda g: g.add_match("lru1", 0, 7, 0, np.eye(4), COV_C), "robot_b"),
        (lambda g: g.update(extra_iterations=-1), "extra_iterations"),
    ],
)
def test_invalid_input_raises(call, message):
    graph = MultiRobotGraph("lru1")
    with pytest.raises(GraphException, match=message):
        call(graph)
    assert graph.pending_count() == 1  # only the prior: nothing half-added


def test_conflicting_registrations_and_parameters_raise():
    graph = MultiRobotGraph("lru1")
    graph.add_robot_pose("lru1", 1.0, 0, np.eye(4), COV_V)
    graph.add_robot_pose("lru1", 1.0, 0, np.eye(4), COV_V)  # the same again: ignored
    with pytest.raises(GraphException, match="already registered"):
        graph.add_robot_pose("lru1", 1.0, 1, np.eye(4), COV_V)
    graph.add_frame_switch("lru1", 0, 4.0, np.eye(4), COV_V)
    with pytest.raises(GraphException, match="already registered"):
        graph.add_frame_switch("lru1", 0, 4.5, np.eye(4), COV_V)
    asymmetric = COV_V.copy()
    asymmetric[0, 1] = 1e-9
    graph.add_detection("lru1", "lru2", 1.0, np.eye(4), asymmetric)  # symmetrised, accepted
    with pytest.raises(GraphException, match="must be > 0"):
        GraphParams(cauchy_c=0.0)
    with pytest.raises(GraphException, match="relinearize_skip"):
        GraphParams(relinearize_skip=0)
    with pytest.raises(GraphException, match="owner"):
        MultiRobotGraph("")
    with pytest.raises(GraphException, match="not a variable"):
        graph.describe(gtsam.symbol("s", 99))


# ---------------------------------------------------------------------------- 6. online pose (eq. 4.6), outputs


def test_online_pose_is_submap_origin_composed_with_the_filter_pose():
    _, inputs, rng = team(8)
    graph, _ = run(LOCAL, [inputs], extra=1)
    v = noisy(se3(rot_zyx(0.02, -0.01, 0.4), [1.0, 2.0, 0.1]), COV_V, rng)
    for name in ("lru1", "lru2", "ardea"):
        for j in range(5):
            assert np.allclose(graph.online_pose(name, j, v), graph.submap_origin(name, j) @ v, rtol=0.0, atol=1e-12)
    assert np.allclose(graph.submap_origin("lru1", 0), np.eye(4), atol=1e-6)
    # a pose node with nothing but its own v factor is exactly the online pose
    graph.add_robot_pose("lru1", 99.0, 4, v, COV_V)
    graph.add_landmark_observation("lru1", 99.0, 42, np.eye(4), COV_D)
    graph.update()
    assert np.allclose(graph.robot_pose("lru1", 99.0), graph.online_pose("lru1", 4, v), atol=1e-9)
    assert np.allclose(graph.landmark(42), graph.robot_pose("lru1", 99.0), atol=1e-9)


def test_outputs_describe_the_estimate():
    _, inputs, _ = team(9)
    graph, _ = run(LOCAL, [inputs], extra=1)
    names = {graph.describe(k) for k in graph.estimate()}
    assert {"s[lru1,0]", "s[ardea,4]", "x[lru2,7.5]", "l[7]"} <= names
    sig = graph.signatures()
    assert ("prior", ("s[lru1,0]",), tuple(float(x) for x in np.eye(4)[:3].ravel())) in sig
    edges = graph.edges()
    assert len(edges) == len(sig) - 1 and {e[0] for e in edges} == {"w", "v", "d", "o", "c"}
    _, p, q = next(e for e in edges if e[0] == FactorType.MATCH)
    assert p.shape == q.shape == (3,)
    C0, C4 = graph.marginal_covariance("lru1", 0), graph.marginal_covariance("lru2", 4)
    assert C0.shape == (6, 6) and np.all(np.linalg.eigvalsh(C4) > 0) and np.trace(C4) > 100 * np.trace(C0)
    assert len(graph.update_times) == 2 and all(t > 0 for t in graph.update_times)
    assert graph.update().factors_added == 0 and len(graph.update_times) == 2  # nothing to do: iSAM2 not called
    assert graph.to_batch_values().size() == graph.node_count()


def test_relative_covariance_of_submap_origins_from_the_joint_marginals():
    """Thesis 6.1.1's relative uncertainty: along a chain s0 -> s1 -> s2 the covariance of
    s0^-1 s2 is both switches' covariances composed, and of s1^-1 s2 the second's alone."""
    g = MultiRobotGraph("a")
    T1, T2 = se3(so3_exp([0, 0, 0.7]), [2.0, 1.0, 0.1]), se3(so3_exp([0, 0, -0.4]), [1.0, -1.0, 0.0])
    C1, C2 = np.diag([1e-4, 1e-4, 4e-3, 0.01, 0.02, 0.005]), np.diag([1e-4, 1e-4, 1e-3, 0.04, 0.01, 0.002])
    g.add_frame_switch("a", 0, 1.0, T1, C1)
    g.add_frame_switch("a", 1, 2.0, T2, C2)
    g.update()
    pairs = [(("a", 1), ("a", 2)), (("a", 0), ("a", 2)), (("a", 0), ("a", 5))]
    rel = g.relative_covariances(pairs)
    np.testing.assert_allclose(rel[pairs[0]], C2, atol=1e-9)
    Ad = adjoint(np.linalg.inv(T2))
    np.testing.assert_allclose(rel[pairs[1]], Ad @ C1 @ Ad.T + C2, atol=1e-9)
    assert pairs[2] not in rel  # s5 is not in the estimate
