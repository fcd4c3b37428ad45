"""The team-size benchmark's scenarios and its growth exponents (sim/tools/team_bench.py)."""

import math

import numpy as np

from sim.scenario import load_scenario
from sim.tools.team_bench import growth, team_scenario


def test_teams_are_valid_scenarios_whose_rovers_keep_apart():
    for n in (1, 2, 4, 8):
        scenario = load_scenario(team_scenario(n, 30.0, seed=1))
        assert [r.name for r in scenario.robots] == [f"lru{k + 1}" for k in range(n)]
        paths = [np.array([r.start.xy] + [w.xy for w in r.route.waypoints]) for r in scenario.robots]
        for a in range(n):
            for b in range(a + 1, n):
                gap = min(np.linalg.norm(p - q) for p in paths[a] for q in paths[b])
                assert gap > 2.0, (n, a, b, gap)  # corners of different rovers' loops stay apart


def test_growth_exponents():
    rows = [
        {"robots": 1, "wall_s_per_sim_s": {"linear": 0.1, "square": 0.01, "flat": 0.2}},
        {"robots": 8, "wall_s_per_sim_s": {"linear": 0.8, "square": 0.64, "flat": 0.2}},
    ]
    e = growth(rows)
    assert math.isclose(e["linear"], 1.0) and math.isclose(e["square"], 2.0) and math.isclose(e["flat"], 0.0, abs_tol=1e-12)
