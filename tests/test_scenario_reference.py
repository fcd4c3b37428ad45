"""The generated scenario reference (docs/scenario.md, assets/scenario.schema.json) is current,
and every key of the schema says what it means."""

import json
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from sim import safe_yaml
from sim.scenario import Scenario, load_scenario
from sim.tools import scenario_reference

ROOT = Path(__file__).parents[1]
SCENARIOS = sorted((ROOT / "scenarios").glob("*.yaml")) + sorted((ROOT / "scenarios" / "obstacles").glob("*.yaml"))


def _models(annotation: typing.Any, found: list[type[BaseModel]]) -> list[type[BaseModel]]:
    """Every model reachable from ``annotation``: fields, list items, dict values, union members."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        if annotation not in found:
            found.append(annotation)
            for info in annotation.model_fields.values():
                _models(info.annotation, found)
        return found
    for arg in typing.get_args(annotation):
        _models(arg, found)
    return found


def test_generated_files_are_current():
    for path, text in scenario_reference.outputs().items():
        committed = ROOT / path
        assert committed.is_file(), f"{path} is missing: run `{scenario_reference.COMMAND}`"
        assert committed.read_text(encoding="utf-8") == text, f"{path} is out of date with the schema: run `{scenario_reference.COMMAND}`"
    assert scenario_reference.main(["--check"]) == 0


def test_every_field_has_a_description():
    models = _models(Scenario, [])
    assert {"CommsConfig", "LinkOverride", "LossConfig", "DiesFault", "WrongMatchFault", "WaypointConfig"} <= {m.__name__ for m in models}
    missing = [f"{m.__module__}.{m.__name__}.{key}" for m in models for key, info in m.model_fields.items() if not (info.description or "").strip()]
    assert not missing, f"fields without a description: {missing}"
    assert all("\n" not in info.description for m in models for info in m.model_fields.values()), "a description is one line"


def test_schema_covers_every_top_level_key():
    schema = json.loads((ROOT / scenario_reference.JSON_SCHEMA).read_text(encoding="utf-8"))
    resolved = load_scenario(ROOT / "scenarios" / "quickstart.yaml").model_dump(mode="json")
    assert set(resolved) == set(Scenario.model_fields)
    assert set(schema["properties"]) == set(Scenario.model_fields)
    assert schema["additionalProperties"] is False
    assert set(schema["required"]) == {k for k, info in Scenario.model_fields.items() if info.is_required()}


def test_schema_accepts_the_scenarios_as_written_and_resolved():
    jsonschema = pytest.importorskip("jsonschema")
    validator = jsonschema.Draft202012Validator(json.loads((ROOT / scenario_reference.JSON_SCHEMA).read_text(encoding="utf-8")))
    for path in SCENARIOS:
        for what, data in [("as written", safe_yaml.load(path)), ("resolved", load_scenario(path).model_dump(mode="json"))]:
            errors = [f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(data)]
            assert not errors, f"{path.name} {what}: {errors[:3]}"
    short = safe_yaml.load(ROOT / "scenarios" / "quickstart.yaml")
    short["faults"] = [{"kind": "dies", "robot": "lru1", "at_s": 10}]
    assert validator.is_valid(short)
    short["faults"] = [{"type": "dies", "unknown_key": 1}]
    assert not validator.is_valid(short)


def test_scenario_files_name_the_schema():
    assert SCENARIOS
    for path in SCENARIOS:
        first = path.read_text().splitlines()[0]
        prefix = "# yaml-language-server: $schema="
        assert first.startswith(prefix), f"{path.name}: first line {first!r}"
        assert (path.parent / first.removeprefix(prefix)).resolve() == (ROOT / scenario_reference.JSON_SCHEMA).resolve()
