"""Regression tests on trajectory error: canonical short runs against committed baselines.

``results/baselines/regress.yaml`` names the canonical scenarios (a scenario file,
overrides, seeds; ``fast`` ones also run in ``make test`` under the pytest marker
``regression``) and the tracked metrics: dotted patterns over ``metrics.json``
(``*`` matches one key, ``robots.*.filter.ate_m.rmse``) with the direction that is
worse and a tolerance. A value regresses when it moves the worse way by more than
``max(relative * |baseline|, absolute)``.

``results/baselines/<name>.json`` holds, per seed, the tracked values a run produced,
with the command that produced them. A tracked value missing from the baseline is
``new`` (not compared, passes); one in the baseline but missing from the run fails,
as does a run that fails.
"""

from __future__ import annotations

import fnmatch
import json
import math
import shutil
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError

from sim.batch.execute import Outcome, run_local
from sim.batch.provenance import REPO, git_state
from sim.batch.report import flatten
from sim.batch.spec import RunSpec
from sim.scenario import StrictModel

BASELINES = REPO / "results" / "baselines"
CONFIG = "regress.yaml"
FAILING = ("worse", "missing", "failed")


class RegressError(ValueError):
    """A regression config or baseline that cannot be used."""


class Tracked(StrictModel):
    pattern: str
    worse: Literal["higher", "lower"]
    relative: float = Field(..., ge=0, description="tolerated change as a fraction of the baseline value")
    absolute: float = Field(..., ge=0, description="tolerated change in the metric's unit, at least")

    def matches(self, key: str) -> bool:
        parts, want = key.split("."), self.pattern.split(".")
        return len(parts) == len(want) and all(fnmatch.fnmatchcase(p, w) for p, w in zip(parts, want))

    def limit(self, baseline: float) -> float:
        return max(self.relative * abs(baseline), self.absolute)


class Canonical(StrictModel):
    description: str = ""
    scenario: str = Field(..., description="scenario YAML, relative to the repository root")
    set: list[str] = Field(default_factory=list)
    seeds: list[int] = Field(..., min_length=1)
    fast: bool = Field(False, description="also run by `make test` (pytest marker `regression`)")
    timeout_s: float = Field(900.0, gt=0)


class RegressConfig(StrictModel):
    tracked: list[Tracked] = Field(..., min_length=1)
    scenarios: dict[str, Canonical] = Field(..., min_length=1)


def load_config(directory: Path = BASELINES) -> RegressConfig:
    path = Path(directory) / CONFIG
    try:
        return RegressConfig.model_validate(yaml.safe_load(path.read_text()))
    except (OSError, yaml.YAMLError, ValidationError) as exc:
        raise RegressError(f"{path}: {exc}") from None


def select(config: RegressConfig, only: list[str] | None) -> list[str]:
    names = list(only or config.scenarios)
    unknown = [n for n in names if n not in config.scenarios]
    if unknown:
        raise RegressError(f"no canonical scenario named {unknown}; names: {list(config.scenarios)}")
    return names


def tracked_values(metrics: dict[str, Any], tracked: list[Tracked]) -> dict[str, float]:
    """The numeric values of ``metrics`` (flattened) that some pattern tracks."""
    return {k: v for k, v in flatten(metrics).items() if _number(v) and any(t.matches(k) for t in tracked)}


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass
class Check:
    """One tracked value of one run against its baseline."""

    name: str
    seed: int
    metric: str
    baseline: float | None
    current: float | str | None
    limit: float | None
    verdict: Literal["ok", "better", "worse", "new", "missing", "failed"]

    @property
    def failing(self) -> bool:
        return self.verdict in FAILING


def compare(name: str, seed: int, baseline: dict[str, float], metrics: dict[str, Any], tracked: list[Tracked]) -> list[Check]:
    """Every tracked value of a run against the baseline's (see the module docstring)."""
    current = tracked_values(metrics, tracked)
    checks = []
    for key in sorted(set(baseline) | set(current)):
        rule = next((t for t in tracked if t.matches(key)), None)
        if rule is None:  # no longer tracked
            continue
        if key not in baseline:
            checks.append(Check(name, seed, key, None, current[key], None, "new"))
            continue
        base, limit = baseline[key], rule.limit(baseline[key])
        if key not in current:
            checks.append(Check(name, seed, key, base, None, limit, "missing"))
            continue
        bad = (current[key] - base) * (1 if rule.worse == "higher" else -1)
        verdict = "worse" if bad > limit else "better" if -bad > limit else "ok"
        checks.append(Check(name, seed, key, base, current[key], limit, verdict))
    return checks


def _spec(config: RegressConfig, name: str, seed: int) -> RunSpec:
    canonical = config.scenarios[name]
    raw = yaml.safe_load((REPO / canonical.scenario).read_text())
    return RunSpec(
        id=f"{name}/seed{seed}",
        variant=name,
        seed=seed,
        folder=f"{name}/seed{seed}",
        raw=raw,
        overrides=[*canonical.set, f"seed={seed}"],
        robots=None,
        timeout_s=canonical.timeout_s,
        base_dir=str((REPO / canonical.scenario).parent),
    )


def run(config: RegressConfig, names: list[str], out: Path, workers: int = 2) -> dict[str, Outcome]:
    """Run the canonical scenarios ``names`` (every seed) into ``out/<name>/seed<n>``, each in its own process."""
    specs = [_spec(config, name, seed) for name in names for seed in config.scenarios[name].seeds]
    outcomes: dict[str, Outcome] = {}
    for spec in specs:
        shutil.rmtree(Path(out) / spec.folder, ignore_errors=True)
    run_local(specs, Path(out), min(workers, len(specs)), lambda spec: None, lambda spec, outcome: outcomes.__setitem__(spec.id, outcome))
    return outcomes


def _metrics(out: Path, name: str, seed: int) -> tuple[dict[str, Any] | None, str | None]:
    path = Path(out) / name / f"seed{seed}" / "metrics.json"
    if not path.is_file():
        error = Path(out) / name / f"seed{seed}" / "error.txt"
        return None, error.read_text().strip().splitlines()[-1] if error.is_file() else "no metrics.json"
    metrics = json.loads(path.read_text())
    return metrics, metrics.get("error") if metrics.get("status") != "completed" else None


def evaluate(config: RegressConfig, directory: Path, names: list[str], out: Path) -> list[Check]:
    """Compare the run folders under ``out`` with the baselines in ``directory``."""
    checks = []
    for name in names:
        path = Path(directory) / f"{name}.json"
        if not path.is_file():
            raise RegressError(f"{path}: no baseline; write it with `marsyard regress --update --only {name}`")
        baseline = json.loads(path.read_text())["seeds"]
        for seed in config.scenarios[name].seeds:
            metrics, error = _metrics(out, name, seed)
            if error is not None:
                checks.append(Check(name, seed, "(run)", None, error, None, "failed"))
            if metrics is not None:
                checks += compare(name, seed, baseline.get(str(seed), {}), metrics, config.tracked)
    return checks


def update(config: RegressConfig, directory: Path, names: list[str], out: Path) -> list[Path]:
    """Write ``<name>.json`` baselines from the run folders under ``out``; nothing is
    written unless every run completed."""
    values: dict[str, dict[str, dict[str, float]]] = {}
    for name in names:
        values[name] = {}
        for seed in config.scenarios[name].seeds:
            metrics, error = _metrics(out, name, seed)
            if error is not None:
                raise RegressError(f"{name} seed {seed} did not complete ({error}); no baseline written")
            values[name][str(seed)] = tracked_values(metrics, config.tracked)
    written = []
    for name in names:
        canonical = config.scenarios[name]
        sets = " ".join(f"--set {s}" for s in canonical.set)
        baseline = {
            "name": name,
            "description": canonical.description,
            "command": f"marsyard regress --update --only {name}",
            "run_command": f"marsyard run {canonical.scenario} --seed SEED {sets}",
            "scenario": canonical.scenario,
            "set": canonical.set,
            **git_state(),
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "seeds": values[name],
        }
        path = Path(directory) / f"{name}.json"
        path.write_text(json.dumps(baseline, indent=1) + "\n")
        written.append(path)
    return written
