from pathlib import Path

import pytest
import yaml

from sim.scenario import ScenarioError, apply_overrides, dump_scenario, load_scenario

SCENARIOS = sorted(Path(__file__).parents[1].joinpath("scenarios").glob("*.yaml"))


def minimal(**extra):
    raw = {"name": "t", "duration_s": 10, "robots": [{"name": "a", "preset": "lru"}, {"name": "b", "preset": "ardea"}]}
    raw.update(extra)
    return raw


def problems(raw, overrides=None):
    with pytest.raises(ScenarioError) as info:
        load_scenario(raw, overrides)
    return info.value.problems


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.name)
def test_shipped_scenarios_validate(path):
    scenario = load_scenario(path)
    assert scenario.robots


def test_unknown_key_names_path_and_allowed_keys():
    raw = minimal()
    raw["robots"][0]["route"] = {"speeed_mps": 1}
    (line,) = problems(raw)
    assert line.startswith("robots.0(a).route.speeed_mps: unknown key")
    assert "speed_mps" in line and "waypoints" in line


def test_bad_value_names_key_value_and_constraint():
    raw = minimal()
    raw["robots"][1]["camera"] = {"width": -3}
    (line,) = problems(raw)
    assert line.startswith("robots.1(b).camera.width: got -3")
    assert "greater than or equal to 32" in line


def test_bad_literal_lists_allowed_values():
    raw = minimal()
    raw["robots"][0]["preset"] = "curiosity"
    (line,) = problems(raw)
    assert "robots.0(a).preset: got 'curiosity'" in line and "'lru'" in line and "'ardea'" in line


def test_cross_field_checks():
    assert any("unique" in p for p in problems(minimal(robots=[{"name": "a", "preset": "lru"}] * 2)))
    assert any("outside the terrain" in p for p in problems(minimal(robots=[{"name": "a", "preset": "lru", "start": {"xy": [99, 0]}}])))
    clash = minimal(robots=[{"name": "a", "preset": "lru", "tag_ids": [0, 1, 2]}], terrain={"lander": {"tag_id": 0}})
    assert any("already used by lander" in p for p in problems(clash))
    rover_alt = minimal(robots=[{"name": "a", "preset": "lru", "route": {"waypoints": [[1, 1, 3]]}}])
    assert any("hexacopter only" in p for p in problems(rover_alt))


def test_set_overrides_by_name_and_index_are_validated():
    s = load_scenario(minimal(), ["robots.b.route.speed_mps=0.5", "robots.0.start.xy=[1, 2]", "seed=7"])
    assert s.robot("b").route.speed_mps == 0.5 and s.robot("a").start.xy == (1.0, 2.0) and s.seed == 7
    s = load_scenario(minimal(), ["robots.*.camera.rate_hz=10"])
    assert [r.camera.rate_hz for r in s.robots] == [10, 10]
    assert any(p.startswith("robots.0(a).route.speed_mps: got -1") for p in problems(minimal(), ["robots.a.route.speed_mps=-1"]))
    with pytest.raises(ScenarioError, match="no element named 'zz'"):
        apply_overrides(minimal(), ["robots.zz.seed=1"])
    with pytest.raises(ScenarioError, match="expected dotted.key=value"):
        apply_overrides(minimal(), ["seed"])


def test_tag_ids_are_distinct_and_dump_reloads():
    s = load_scenario(minimal(terrain={"lander": {"tag_id": 1}}))
    ids = s.assigned_tag_ids()
    flat = [t for v in ids.values() for t in v]
    assert len(flat) == len(set(flat)) == 5 and 1 not in flat
    again = load_scenario(yaml.safe_load(dump_scenario(s)))
    assert again.assigned_tag_ids() == ids
    assert again.model_dump(exclude={"robots"}) == s.model_dump(exclude={"robots"})


def test_missing_file_and_bad_yaml(tmp_path):
    assert problems(tmp_path / "nope.yaml") == ["file not found"]
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed")
    assert problems(bad)[0].startswith("not valid YAML")
