"""Regression tests on trajectory error: the committed baselines hold, a worsened copy fails."""

import json
import shutil

import pytest
from typer.testing import CliRunner

from sim.batch import regress
from sim.cli import app

pytestmark = pytest.mark.regression
CONFIG = regress.load_config()
FAST = [name for name, c in CONFIG.scenarios.items() if c.fast]
SLOW = [name for name, c in CONFIG.scenarios.items() if not c.fast]


def test_verdicts_follow_direction_tolerance_and_presence():
    tracked = [
        regress.Tracked(pattern="robots.*.ate", worse="higher", relative=0.1, absolute=0.01),
        regress.Tracked(pattern="robots.*.closures.*", worse="lower", relative=0.2, absolute=1),
    ]
    baseline = {"robots.a.ate": 1.0, "robots.b.ate": 0.001, "robots.a.closures.c": 5, "robots.a.closures.d": 10, "robots.gone.ate": 0.5}
    run = {
        "robots": {
            "a": {"ate": 1.2, "closures": {"c": 3, "d": 10, "e": 2}, "untracked": 9.0},
            "b": {"ate": 0.009},  # within the absolute floor of 0.01
            "new": {"ate": 0.3},
        }
    }
    verdicts = {c.metric: c.verdict for c in regress.compare("x", 1, baseline, run, tracked)}
    assert verdicts == {
        "robots.a.ate": "worse",  # +0.2 > 10 % of 1.0
        "robots.b.ate": "ok",
        "robots.a.closures.c": "worse",  # fewer loop closures: 5 -> 3, limit max(1.0, 1)
        "robots.a.closures.d": "ok",
        "robots.a.closures.e": "new",
        "robots.new.ate": "new",
        "robots.gone.ate": "missing",
    }
    assert regress.compare("x", 1, {"robots.a.ate": 1.0}, {"robots": {"a": {"ate": 0.5}}}, tracked)[0].verdict == "better"


def test_fast_baselines_hold_and_a_worsened_copy_fails(tmp_path):
    worse = tmp_path / "baselines"
    shutil.copytree(regress.BASELINES, worse)
    for name in FAST:  # pretend the filter used to be twice as good
        path = worse / f"{name}.json"
        baseline = json.loads(path.read_text())
        for values in baseline["seeds"].values():
            for key in [k for k in values if k.endswith(".filter.ate_m.rmse")]:
                values[key] /= 2
        path.write_text(json.dumps(baseline))
    runs = tmp_path / "runs"
    result = CliRunner().invoke(app, ["regress", "--baselines", str(worse), "--out", str(runs)] + [a for n in FAST for a in ("--only", n)])
    assert result.exit_code == 1, result.output
    assert "worse" in result.output and "regression" in result.output
    failing = {c.metric for c in regress.evaluate(CONFIG, worse, FAST, runs) if c.failing}
    assert failing and all(m.endswith(".filter.ate_m.rmse") for m in failing), failing

    checks = regress.evaluate(CONFIG, regress.BASELINES, FAST, runs)  # the same runs against the committed baselines
    assert not [c for c in checks if c.failing], [c for c in checks if c.verdict != "ok"]
    assert any(c.metric.endswith(".filter.ate_m.rmse") and c.verdict == "ok" for c in checks)


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_slow_baselines_hold(tmp_path, name):
    outcomes = regress.run(CONFIG, [name], tmp_path)
    assert all(o.status == "completed" for o in outcomes.values()), outcomes
    checks = regress.evaluate(CONFIG, regress.BASELINES, [name], tmp_path)
    assert not [c for c in checks if c.failing], [c for c in checks if c.verdict != "ok"]
