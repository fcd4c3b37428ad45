"""Scenario validation is total: every bad scenario is a :class:`ScenarioError` with one line
per problem (exit code 2 at the command line), never a traceback, a hang or a memory blow-up.

``tests/bad_scenarios/`` holds one small file per case; its first lines say what is wrong and
``# expect:`` the text its error must contain.
"""

import copy
import math
import typing
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel
from typer.testing import CliRunner

from comms.config import BASE_KINDS
from sim.batch.spec import BatchError, load_batch
from sim.cli import app
from sim.robots import PRESETS, make_robot
from sim.safe_yaml import MAX_BYTES
from sim.scenario import (
    MAX_GRID_POINTS,
    MAX_KEEP_CLEAR_DISCS,
    MAX_LINK_SAMPLES,
    Scenario,
    ScenarioError,
    load_scenario,
)
from slam.agent import MESSAGE_KINDS

HERE = Path(__file__).parent
BAD = sorted((HERE / "bad_scenarios").glob("*.yaml"))
QUICKSTART = HERE.parent / "scenarios" / "quickstart.yaml"
runner = CliRunner()


def expected(path: Path) -> str:
    for line in path.read_bytes().decode("utf-8", "replace").splitlines():
        if line.startswith("# expect:"):
            return line.removeprefix("# expect:").strip()
    raise AssertionError(f"{path.name} has no '# expect:' line")


def problems(source, overrides=None) -> list[str]:
    with pytest.raises(ScenarioError) as info:
        load_scenario(source, overrides)
    assert info.value.problems and all("\n" not in line for line in info.value.problems), info.value.problems
    return info.value.problems


@pytest.mark.parametrize("path", BAD, ids=lambda p: p.stem)
def test_bad_scenario_is_a_scenario_error_naming_the_problem(path):
    assert expected(path) in "\n".join(problems(path))


@pytest.mark.parametrize("name", ["invalid_utf8", "deep_nesting", "alias_bomb", "nan_start", "clearance_zero", "kind_typo"])
def test_validate_exits_2_without_a_traceback(name):
    result = runner.invoke(app, ["validate", str(HERE / "bad_scenarios" / f"{name}.yaml")])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and isinstance(result.exception, SystemExit)


@pytest.mark.parametrize(
    ("override", "expect"),
    [
        ("robots.0.route.waypoints=[[1,2", "expected ',' or ']'"),
        ("description=!!python/object/apply:os.system [echo hi]", "could not determine a constructor"),
        ("description={a: 1, a: 2}", "duplicate key 'a'"),
        ("robots.0.route.speed_mps=true", "true and false are no numbers"),
        ("terrain..size_m=20", "has an empty part"),
        ("faults=[{kind: dies, robot: lru9, at_s: 1}]", "no robot named 'lru9'"),
    ],
)
def test_bad_override_exits_2_naming_it(override, expect):
    result = runner.invoke(app, ["validate", str(QUICKSTART), "--set", override])
    output = " ".join(result.output.split())  # rich wraps long lines
    assert result.exit_code == 2, result.output
    assert "Traceback" not in output and expect in output
    if "robot" not in override:  # a syntax error names the override; a schema error names the key
        assert repr(override) in output


def test_files_over_the_size_limit_are_refused_unread(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_text("name: big\nduration_s: 10\ndescription: '" + "x" * MAX_BYTES + "'\n")
    assert problems(big) == [f"larger than {MAX_BYTES} bytes"]


def test_batch_check_reads_its_files_as_safely(tmp_path):
    batch = tmp_path / "batch.yaml"
    batch.write_text(f"name: b\nscenario: {HERE / 'bad_scenarios' / 'alias_bomb.yaml'}\nseeds: 1\n")
    with pytest.raises(BatchError, match=r"values \(aliases expanded\)"):
        load_batch(batch)
    batch.write_text("name: b\nname: c\n")
    with pytest.raises(BatchError, match="duplicate key 'name'"):
        load_batch(batch)


def test_numbers_are_strict_but_integers_are_floats_and_exponents_are_numbers():
    def raw():
        return {"name": "t", "duration_s": 10, "seed": 3, "robots": [{"name": "a", "preset": "lru", "start": {"xy": [1, 2]}}]}

    scenario = load_scenario(raw(), ["comms.stats_interval_s=5e-2", "comms.defaults.bandwidth_bps=2e6"])
    assert scenario.duration_s == 10.0 and isinstance(scenario.duration_s, float) and scenario.seed == 3
    assert scenario.robots[0].start.xy == (1.0, 2.0)
    assert scenario.comms.stats_interval_s == 0.05 and scenario.comms.defaults.bandwidth_bps == 2e6
    assert "Input should be a valid integer" in problems(raw(), ["robots.a.camera.width=320.0"])[0]
    assert "Input should be a valid boolean" in problems(raw(), ["output.recording=1"])[0]


def test_what_the_schema_checks_against_matches_the_robots_and_the_messages():
    for name, preset in PRESETS.items():
        cfg = load_scenario({"name": "t", "duration_s": 1, "robots": [{"name": "r", "preset": name}]}).robots[0]
        robot = make_robot(cfg, list(range(1, 1 + preset.marker_count)))
        assert tuple(rig.name for rig in robot.stereo_rigs) == preset.stereo_rig_names
        assert preset.default_vo_rig in preset.stereo_rig_names
    assert set(BASE_KINDS) == set(MESSAGE_KINDS)  # every scenario's comms.kinds starts with these


# --------------------------------------------------------------------------- fuzzing


def _dotted_keys(model: type[BaseModel], raw, prefix: str = "") -> list[str]:
    """Dotted keys of ``model``'s schema; lists of sections by their first element in ``raw``."""
    keys = []
    for name, info in model.model_fields.items():
        key = prefix + name
        keys.append(key)
        inner = _first_model(info.annotation)
        value = raw.get(name) if isinstance(raw, dict) else None
        if inner is None:
            continue
        if typing.get_origin(info.annotation) is list:
            if isinstance(value, list) and value:
                keys += _dotted_keys(inner, value[0], f"{key}.0.")
        elif typing.get_origin(info.annotation) is dict:
            keys += _dotted_keys(inner, None, f"{key}.pose.")
        else:
            keys += _dotted_keys(inner, value, f"{key}.")
    return keys


def _first_model(annotation) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _first_model(arg)
        if found is not None:
            return found
    return None


def _scaled(value, factor: float):
    """``value`` times ``factor``: numbers (integers rounded), and lists of them (coordinates); others as they are."""
    if isinstance(value, int) and not isinstance(value, bool):
        return round(value * factor)
    if isinstance(value, float):
        return value * factor
    if isinstance(value, list):
        return [_scaled(v, factor) for v in value]
    return value


def _put(raw: dict, key: str, change) -> None:
    """Set ``key`` in ``raw`` (``("set", value)``) or scale what is there (``("scale", factor)``),
    making the sections on the way mappings; skipped where an earlier mutation left a list
    without that index."""
    *parents, last = key.split(".")
    node = raw
    for part in [*parents, last]:
        if isinstance(node, list) and not (part.isdigit() and int(part) < len(node)):
            return
        where = int(part) if isinstance(node, list) else part
        if part is last:
            how, value = change
            node[where] = value if how == "set" else _scaled(node[where] if isinstance(node, list) else node.get(part), value)
            return
        child = node[where] if isinstance(node, list) else node.get(part)
        if not isinstance(child, (dict, list)):
            child = node[where] = {}
        node = child


BASE = load_scenario(QUICKSTART).model_dump(mode="json")  # every key present, with its value
KEYS = sorted(set(_dotted_keys(Scenario, BASE)))
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**20), max_value=10**20),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e-12, 1e12, 1e300, -1e300, 0.5, 2, 1000]),
    st.text(max_size=8),
)
VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3), max_leaves=8)
# half of the changes scale the value there, so that many mutated scenarios are still valid
CHANGES = st.tuples(st.just("set"), VALUES) | st.tuples(st.just("scale"), st.sampled_from([0.0, -1.0, 1e-9, 0.3, 0.9, 1.1, 3.0, 1e9]))


def _floats(value):
    if isinstance(value, float):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _floats(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _floats(v)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.sampled_from(KEYS), CHANGES), min_size=1, max_size=3))
def test_fuzzed_scenarios_load_or_fail_cleanly(mutations):
    raw = copy.deepcopy(BASE)
    for key, change in mutations:
        _put(raw, key, change)
    try:
        scenario = load_scenario(raw)
    except ScenarioError as exc:
        assert exc.problems and all(isinstance(line, str) and "\n" not in line for line in exc.problems)
        return
    # what the run's set-up relies on
    assert all(math.isfinite(x) for x in _floats(scenario.model_dump()))
    assert scenario.terrain.grid_points() <= MAX_GRID_POINTS
    assert len(scenario.keep_clear()) <= MAX_KEEP_CLEAR_DISCS
    assert scenario.duration_s / scenario.comms.stats_interval_s <= MAX_LINK_SAMPLES
    assert 1 <= round(1 / (scenario.physics.control_rate_hz * scenario.physics.timestep_s)) <= 1000
    assert set(scenario.comms.kinds) <= set(MESSAGE_KINDS)
    for robot in scenario.robots:
        preset = PRESETS[robot.preset]
        assert robot.camera.znear_m < robot.camera.zfar_m
        assert (scenario.slam.vo_rig or preset.default_vo_rig) in preset.stereo_rig_names
        assert 0 < robot.route.speed_mps <= preset.max_speed_mps
