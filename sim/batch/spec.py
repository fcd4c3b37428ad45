"""Batch files: Monte-Carlo seeds x variants of one base scenario.

A batch YAML names a base scenario (path relative to the batch file), the seeds, and
what varies::

    name: topology
    scenario: ../etna_two_rovers.yaml
    seeds: 10                       # 0..9, or an explicit list [3, 7, 11]
    timeout_s: 3600                 # per run; a run past it is killed and recorded
    set: {output.recording: false}  # dotted overrides of every run
    variants:                       # labelled variants (paired over the same seeds)
      - {label: local_reference, set: {slam.graph.topology: local_reference}}
      - {label: single, robots: [lru1]}   # keep only these robots of the base scenario
    sweep:                          # a grid over dotted keys (cartesian product)
      terrain.rocks.count: [10, 40]
    baseline: local_reference       # the variant the others are compared with (default: the first)
    comparisons:                    # instead: these [variant, baseline] pairs (both variant names)
      - [local_reference, single]
    metrics: [filter.ate_m.rmse]    # what the report summarises and plots

Every variant is the product of a labelled variant (or the base scenario alone) and a
grid point of ``sweep``. Its overrides, in order: ``set``, the variant's ``set``, the
sweep values, then ``seed``; :func:`check` validates every variant's scenario with
:func:`sim.scenario.load_scenario` before anything runs.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from sim import safe_yaml
from sim.scenario import ScenarioError, StrictModel, load_scenario

LABEL_PATTERN = r"^[A-Za-z0-9_.-]+$"
#: What the report summarises when a batch file names no ``metrics``: per-robot columns
#: of the tidy table (``robots.<name>.`` dropped) and run-level ones (``comms.``, ``runtime.``).
DEFAULT_METRICS = [
    "filter.ate_m.rmse",
    "filter.final_error_percent_of_distance",
    "slam.ate_m.rmse",
    "comms.totals.offered_bytes",
    "runtime.real_time_factor",
]


class BatchError(ValueError):
    """A batch file that cannot be loaded; ``problems`` holds one readable line each."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        super().__init__(f"{source}: invalid batch file\n  " + "\n  ".join(problems))


def _check_keys(overrides: dict[str, Any]) -> dict[str, Any]:
    for key in overrides:
        if not key or any(not part for part in key.split(".")):
            raise ValueError(f"{key!r} is not a dotted scenario key")
        if key == "seed":
            raise ValueError("'seed' is set by the batch's seeds, not by overrides")
    return overrides


class VariantConfig(StrictModel):
    """A labelled variant: overrides and, optionally, the robots of the base scenario it keeps."""

    label: str = Field(..., pattern=LABEL_PATTERN)
    description: str = ""
    set: dict[str, Any] = Field(default_factory=dict)
    robots: list[str] | None = Field(None, min_length=1, description="keep only these robots of the base scenario")

    _keys = field_validator("set")(_check_keys)


class BatchConfig(StrictModel):
    """The schema of a batch YAML (see the module docstring)."""

    name: str = Field(..., pattern=LABEL_PATTERN)
    description: str = ""
    scenario: str = Field(..., description="base scenario YAML, relative to the batch file")
    seeds: int | list[int] = Field(..., description="a count n (seeds 0..n-1) or an explicit list")
    timeout_s: float | None = Field(None, gt=0, description="per-run wall-clock limit")
    set: dict[str, Any] = Field(default_factory=dict)
    variants: list[VariantConfig] = Field(default_factory=list)
    sweep: dict[str, list[Any]] = Field(default_factory=dict)
    baseline: str | None = Field(None, description="variant the others are compared with (default: the first)")
    comparisons: list[tuple[str, str]] | None = Field(
        None, min_length=1, description="[variant, baseline] pairs the report compares (default: every variant against baseline)"
    )
    metrics: list[str] = Field(default_factory=lambda: list(DEFAULT_METRICS), min_length=1)

    _set_keys = field_validator("set", "sweep")(_check_keys)

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, value: int | list[int]) -> int | list[int]:
        seeds = range(value) if isinstance(value, int) else value
        if not seeds:
            raise ValueError("at least one seed")
        if any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
            raise ValueError(f"seeds must be distinct and >= 0, got {value}")
        return value

    @field_validator("sweep")
    @classmethod
    def _sweep(cls, value: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in value.items():
            if not values:
                raise ValueError(f"sweep.{key}: needs at least one value")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> BatchConfig:
        labels = [v.label for v in self.variants]
        repeated = sorted({x for x in labels if labels.count(x) > 1})
        if repeated:
            raise ValueError(f"variant labels must be unique, repeated: {repeated}")
        for v in self.variants:
            both = sorted(set(v.set) & set(self.sweep))
            if both:
                raise ValueError(f"variant {v.label}: keys {both} are swept too; set each key in one place")
        return self

    def seed_list(self) -> list[int]:
        return list(range(self.seeds)) if isinstance(self.seeds, int) else list(self.seeds)


@dataclass(frozen=True)
class Variant:
    """One point of the batch: a name, the overrides that make it, the robots it keeps."""

    name: str
    params: dict[str, Any]  # every key this variant sets (variant and sweep), for the tables
    overrides: tuple[str, ...]
    robots: tuple[str, ...] | None


@dataclass
class RunSpec:
    """Everything a worker needs for one run; ``raw`` is the base scenario as a dict."""

    id: str
    variant: str
    seed: int
    folder: str  # relative to the batch folder
    raw: dict[str, Any] = field(repr=False)
    overrides: list[str]
    robots: list[str] | None
    timeout_s: float | None
    base_dir: str | None = None  # the base scenario's folder: relative paths in it start there

    def digest(self) -> str:
        """Identifies what the run computes, so a resumed batch redoes runs whose inputs changed."""
        text = json.dumps([self.raw, self.overrides, self.robots], sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class Batch:
    config: BatchConfig
    source: Path
    scenario_path: Path
    raw: dict[str, Any] = field(repr=False)
    variants: list[Variant]
    extra: list[str] = field(default_factory=list)  # --set from the command line, applied last

    @property
    def baseline(self) -> str:
        if self.config.baseline is not None:
            return self.config.baseline
        return self.variants[0].name

    @property
    def comparisons(self) -> list[tuple[str, str]]:
        """The (variant, baseline) pairs the report compares."""
        if self.config.comparisons is not None:
            return [tuple(pair) for pair in self.config.comparisons]
        return [(v.name, self.baseline) for v in self.variants if v.name != self.baseline]

    def specs(self) -> list[RunSpec]:
        """All runs, seed-major: an interrupted batch still has whole pairs of variants."""
        return [
            RunSpec(
                id=f"{v.name}/seed{seed}",
                variant=v.name,
                seed=seed,
                folder=f"runs/{_slug(v.name)}/seed{seed}",
                raw=self.raw,
                overrides=[*v.overrides, *self.extra, f"seed={seed}"],
                robots=list(v.robots) if v.robots else None,
                timeout_s=self.config.timeout_s,
                base_dir=str(self.scenario_path.parent),
            )
            for seed in self.config.seed_list()
            for v in self.variants
        ]


def override(key: str, value: Any) -> str:
    """A ``key=value`` override whose value YAML parses back to ``value``."""
    text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30).strip()
    return f"{key}={text.removesuffix('...').strip()}"


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=,-]", "_", name)


def _value_label(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def expand(config: BatchConfig) -> list[Variant]:
    """Labelled variants (or the base scenario alone) x the sweep's grid points."""
    common = [override(k, v) for k, v in config.set.items()]
    labelled = config.variants or [None]
    keys = list(config.sweep)
    out = []
    for variant, values in itertools.product(labelled, itertools.product(*config.sweep.values())):
        point = dict(zip(keys, values))
        parts = ([variant.label] if variant else []) + [f"{k}={_value_label(v)}" for k, v in point.items()]
        own = variant.set if variant else {}
        out.append(
            Variant(
                name=",".join(parts) or "base",
                params={**own, **point},
                overrides=tuple(common + [override(k, v) for k, v in {**own, **point}.items()]),
                robots=tuple(variant.robots) if variant and variant.robots else None,
            )
        )
    return out


def load_batch(path: str | Path, extra: list[str] | None = None, max_seeds: int | None = None) -> Batch:
    """Load and check the batch file's own schema (not yet its scenarios: :func:`check`).
    ``extra``: overrides from the command line, applied to every run after the batch's own;
    ``max_seeds``: keep only the first seeds."""
    path = Path(path)
    label = str(path)
    if not path.is_file():
        raise BatchError(label, ["is a directory, not a YAML file" if path.is_dir() else "file not found"])
    try:
        data = safe_yaml.load(path)
    except safe_yaml.YamlError as exc:
        raise BatchError(label, [str(exc)]) from None
    try:
        config = BatchConfig.model_validate(data)
    except ValidationError as exc:
        raise BatchError(label, [_describe(e) for e in exc.errors()]) from None
    if max_seeds is not None:
        config.seeds = config.seed_list()[:max_seeds]
    scenario_path = (path.parent / config.scenario).resolve()
    if not scenario_path.is_file():
        raise BatchError(label, [f"scenario: {config.scenario!r}: no such file ({scenario_path})"])
    try:
        raw = safe_yaml.load(scenario_path)
    except safe_yaml.YamlError as exc:
        raise BatchError(label, [f"scenario: {scenario_path}: {exc}"]) from None
    if not isinstance(raw, dict):
        raise BatchError(label, [f"scenario: {scenario_path}: top level must be a mapping, got {type(raw).__name__}"])
    variants = expand(config)
    names = [v.name for v in variants]
    if config.baseline is not None and config.baseline not in names:
        raise BatchError(label, [f"baseline: got {config.baseline!r}: not a variant; variants: {names}"])
    unknown = sorted({name for pair in config.comparisons or [] for name in pair} - set(names))
    if unknown:
        raise BatchError(label, [f"comparisons: {unknown} not variants; variants: {names}"])
    same = [list(pair) for pair in config.comparisons or [] if pair[0] == pair[1]]
    if same:
        raise BatchError(label, [f"comparisons: {same} compare a variant with itself"])
    return Batch(config=config, source=path, scenario_path=scenario_path, raw=raw, variants=variants, extra=list(extra or []))


def _describe(error: dict) -> str:
    where = ".".join(str(p) for p in error["loc"]) or "(top level)"
    msg = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        model = VariantConfig if "variants" in error["loc"] else BatchConfig
        return f"{where}: unknown key; allowed keys here: {', '.join(model.model_fields)}"
    if error["type"] == "missing":
        return f"{where}: required key is missing"
    shown = repr(error.get("input"))
    return f"{where}: got {shown[:77] + '...' if len(shown) > 80 else shown}: {msg}"


def scenario_dict(raw: dict[str, Any], robots: list[str] | None) -> dict[str, Any]:
    """A copy of the base scenario, keeping only ``robots`` (all if None); an unknown name raises :class:`ScenarioError`."""
    out = copy.deepcopy(raw)
    if robots is not None:
        present = [r.get("name") for r in out.get("robots") or [] if isinstance(r, dict)]
        unknown = [name for name in robots if name not in present]
        if unknown:
            raise ScenarioError("robots", [f"robots: no robot named {', '.join(map(repr, unknown))} in the base scenario; robots: {present}"])
        out["robots"] = [r for r in out["robots"] if isinstance(r, dict) and r.get("name") in robots]
    return out


@dataclass
class VariantProblem:
    variant: str
    overrides: list[str]
    robots: list[str] | None
    problems: list[str]


def check(batch: Batch) -> list[VariantProblem]:
    """Validate every variant's scenario (with the first seed); one entry per failing variant."""
    failing = []
    for spec in batch.specs()[: len(batch.variants)]:
        try:
            load_scenario(scenario_dict(spec.raw, spec.robots), spec.overrides, spec.base_dir)
        except ScenarioError as exc:
            failing.append(VariantProblem(spec.variant, spec.overrides, spec.robots, exc.problems))
    return failing
