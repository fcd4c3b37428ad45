"""slam.graph_export: a multi-robot graph (thesis 4.2) written as g2o, read back with GTSAM's readG2o and optimised
to the graph's own estimate; the robust factors' Gaussian base, the key map and GTSAM's serialisation round trips."""

from __future__ import annotations

import csv

import gtsam
import numpy as np
import pytest
from test_graph import CONVERGE, LOCAL, in_time_order, pose_error, run, split, team

from slam.graph import GraphParams, RobustKernel, Topology
from slam.graph_export import G2O_FROM_GTSAM, gaussian, vertices, write_g2o, write_gtsam, write_keys

GAUSSIAN = GraphParams(robust=RobustKernel.NONE, relinearize_threshold=1e-6)
GAUSSIAN_SEQ = GraphParams(topology=Topology.SEQUENTIAL, robust=RobustKernel.NONE, relinearize_threshold=1e-6)


def graph_of(params: GraphParams):
    _, inputs, _ = team(1)
    graph, _ = run(params, split(in_time_order(inputs), 5), extra=CONVERGE)
    assert graph.pending_count() == 0 and graph.connected_robots() == ["ardea", "lru1", "lru2"]
    return graph


@pytest.fixture(scope="module")
def cauchy():
    return graph_of(LOCAL)


@pytest.mark.parametrize("params", [GAUSSIAN, GAUSSIAN_SEQ], ids=["local_reference", "sequential"])
def test_g2o_read_by_gtsam_optimises_to_the_graphs_estimate(tmp_path, params):
    graph = graph_of(params)
    path = tmp_path / "lru1.g2o"
    verts = write_g2o(graph, path)
    factors, initial = gtsam.readG2o(str(path), True)
    estimate = graph.estimate()
    assert initial.size() == len(verts) == graph.node_count() and factors.size() == graph.batch_graph().size() - 1  # the prior: FIX 0
    for v in verts:
        assert max(pose_error(initial.atPose3(v.id).matrix(), estimate[v.key])) < 1e-12
    factors.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setRelativeErrorTol(1e-12)
    lm.setAbsoluteErrorTol(1e-12)
    lm.setMaxIterations(200)
    optimised = gtsam.LevenbergMarquardtOptimizer(factors, initial, lm).optimize()
    worst = np.max([pose_error(optimised.atPose3(v.id).matrix(), estimate[v.key]) for v in verts], axis=0)
    assert worst[0] < 1e-4 and worst[1] < 1e-4, worst  # iSAM2 against batch Levenberg-Marquardt, as tests/test_graph.py


def test_g2o_holds_each_factor_with_the_gaussian_base_of_its_robust_noise(tmp_path, cauchy):
    path = tmp_path / "lru1.g2o"
    ids = {v.key: v.id for v in write_g2o(cauchy, path)}
    lines = path.read_text().splitlines()
    assert lines.count("FIX 0") == 1 and lines[0].split()[:2] == ["VERTEX_SE3:QUAT", "0"]
    assert np.allclose([float(v) for v in lines[0].split()[2:]], [0, 0, 0, 0, 0, 0, 1], atol=1e-12)  # s[lru1,0]: the map frame
    factors, _ = gtsam.readG2o(str(path), True)
    batch = cauchy.batch_graph()
    between = [batch.at(i) for i in range(batch.size()) if isinstance(batch.at(i), gtsam.BetweenFactorPose3)]
    assert len(between) == factors.size() == batch.size() - 1
    robust = 0
    for mine, read in zip(between, (factors.at(i) for i in range(factors.size()))):
        assert [ids[k] for k in mine.keys()] == list(read.keys())
        assert read.measured().equals(mine.measured(), 1e-12)
        robust += isinstance(mine.noiseModel(), gtsam.noiseModel.Robust)
        assert not isinstance(read.noiseModel(), gtsam.noiseModel.Robust)
        expected = gaussian(mine.noiseModel()).information()
        assert np.allclose(read.noiseModel().information(), expected, rtol=1e-9, atol=0.0)
    assert robust == 6 + 2 + 2  # the Cauchy kernel on d, o and c (eq. 4.10)
    edge = next(line for line in lines if line.startswith("EDGE_SE3:QUAT")).split()
    info = np.zeros((6, 6))
    info[np.triu_indices(6)] = [float(v) for v in edge[10:]]
    assert len(edge) == 10 + 21
    first = gaussian(between[0].noiseModel()).information()
    assert np.allclose(info[:3, :3], first[3:, 3:], rtol=1e-12) and np.allclose(info[3:, 3:], first[:3, :3], rtol=1e-12)  # translation first
    assert list(G2O_FROM_GTSAM) == [3, 4, 5, 0, 1, 2]


def test_key_map_round_trips(tmp_path, cauchy):
    verts = vertices(cauchy)
    write_keys(verts, tmp_path / "lru1.keys.csv")
    with (tmp_path / "lru1.keys.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["id"]) for r in rows] == list(range(cauchy.node_count()))
    variables = cauchy.variables()
    assert {int(r["key"]) for r in rows} == set(variables)
    for r in rows:
        key = int(r["key"])
        kind, robot, index = variables[key]
        assert r["variable"] == cauchy.describe(key) and r["symbol"] == gtsam.DefaultKeyFormatter(key)
        assert (r["kind"], r["robot"]) == (kind, robot) and type(index)(r["index"]) == index
    assert rows[0]["variable"] == "s[lru1,0]"
    kinds = [r["kind"] for r in rows]
    assert kinds == sorted(kinds, key="sxl".index)  # submap origins, robot poses, landmarks
    assert [r["robot"] for r in rows[:15]] == ["lru1"] * 5 + ["ardea"] * 5 + ["lru2"] * 5  # the owner's origins first


def test_gtsam_serialisation_round_trips(tmp_path, cauchy):
    write_gtsam(cauchy, tmp_path / "lru1.graph.gtsam", tmp_path / "lru1.values.gtsam")
    factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    factors.deserialize((tmp_path / "lru1.graph.gtsam").read_text())
    values.deserialize((tmp_path / "lru1.values.gtsam").read_text())
    batch = cauchy.batch_graph()
    assert factors.size() == batch.size() and sorted(values.keys()) == sorted(cauchy.estimate())
    for key, T in cauchy.estimate().items():
        assert np.array_equal(values.atPose3(key).matrix(), T)
    assert factors.error(values) == pytest.approx(batch.error(values), rel=1e-12)
    assert sum(isinstance(factors.at(i).noiseModel(), gtsam.noiseModel.Robust) for i in range(factors.size())) == 6 + 2 + 2
