import math
import typing
from enum import Enum
from pathlib import Path

import pytest
import yaml

from sim.robots import PRESETS
from sim.scenario import (
    DetectionConfig,
    GraphConfig,
    HealthConfig,
    MappingConfig,
    MatchingConfig,
    RobotConfig,
    ScenarioError,
    SlamConfig,
    SlamParam,
    apply_overrides,
    dump_scenario,
    load_scenario,
    slam_kwargs,
)
from slam.agent import AgentParams
from slam.filter import FilterParams
from slam.graph import GraphParams, RobustKernel, Topology
from slam.health import HealthParams
from slam.local_estimator import LocalEstimator
from slam.markers import UncertaintyModel
from slam.matcher import MatcherParams, MatchMode
from slam.obstacles import ObstacleParams
from slam.rest import RestParams
from slam.submap import SubmapParams

SCENARIOS = sorted(Path(__file__).parents[1].joinpath("scenarios").glob("*.yaml"))


def minimal(**extra):
    raw = {"name": "t", "duration_s": 10, "robots": [{"name": "a", "preset": "lru"}, {"name": "b", "preset": "ardea", "start": {"xy": [3, 0]}}]}
    raw.update(extra)
    return raw


def problems(raw, overrides=None):
    with pytest.raises(ScenarioError) as info:
        load_scenario(raw, overrides)
    return info.value.problems


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.name)
def test_shipped_scenarios_validate_and_their_dump_reloads_unchanged(path):
    scenario = load_scenario(path)
    dumped = dump_scenario(scenario)
    again = load_scenario(yaml.safe_load(dumped))
    assert again.assigned_tag_ids() == scenario.assigned_tag_ids()
    assert dump_scenario(again) == dumped


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
    # two bodies in one place: the rover reaches 0.64 m from its centre, the hexacopter 0.33 m
    (line,) = problems(minimal(), ["robots.b.start.xy=[0.5, 0.6]"])
    assert "robots a and b start 0.78 m apart, inside each other: keep at least 0.97 m" in line
    assert load_scenario(minimal(), ["robots.b.start.xy=[0.6, 0.8]"]).robot("b").start.xy == (0.6, 0.8)  # 1.0 m: clear
    clash = minimal(robots=[{"name": "a", "preset": "lru", "tag_ids": [0, 1, 2]}], terrain={"lander": {"tag_id": 0}})
    assert any("already used by lander" in p for p in problems(clash))
    rover_alt = minimal(robots=[{"name": "a", "preset": "lru", "route": {"waypoints": [[1, 1, 3]]}}])
    assert any("altitude_m is for the hexacopter only; rover waypoints [0]" in p for p in problems(rover_alt))
    rover_land = minimal(robots=[{"name": "a", "preset": "lru_wide", "route": {"land": True}}])
    assert any("route.land is for the hexacopter only" in p for p in problems(rover_land))
    copter = load_scenario(minimal(robots=[{"name": "a", "preset": "ardea", "route": {"waypoints": [[1, 1, 3]], "land": True}}]))
    assert copter.robots[0].route.waypoints[0].altitude_m == 3 and copter.robots[0].marker_count == 2
    assert any("carries 2 markers, got 3" in p for p in problems(minimal(robots=[{"name": "a", "preset": "ardea", "tag_ids": [4, 5, 6]}])))
    copter_head = minimal(robots=[{"name": "a", "preset": "ardea", "route": {"head_sweep_deg": 30}}])
    assert any("route.head_sweep_deg are for rovers with a pan-tilt head" in p for p in problems(copter_head))


def test_presets_are_the_robot_registry():
    assert typing.get_args(RobotConfig.model_fields["preset"].annotation) == tuple(PRESETS)


def test_slam_keys_take_slam_defaults_and_units():
    """Keys declared with ``slam_field`` default to slam's own defaults, and the scenario
    builds slam's parameter classes from them: with defaults exactly slam's defaults."""
    assert ObstacleParams(**slam_kwargs(ObstacleParams, MappingConfig())) == ObstacleParams()
    assert SubmapParams(**slam_kwargs(SubmapParams, MappingConfig())) == SubmapParams()
    assert GraphParams(**slam_kwargs(GraphParams, GraphConfig())) == GraphParams()
    assert MatcherParams(**slam_kwargs(MatcherParams, MatchingConfig())) == MatcherParams()
    assert AgentParams(**slam_kwargs(AgentParams, GraphConfig(), DetectionConfig())) == AgentParams()
    assert HealthParams(**slam_kwargs(HealthParams, HealthConfig())) == HealthParams()
    assert RestParams(**slam_kwargs(RestParams, SlamConfig())) == RestParams()
    filter_kwargs = slam_kwargs(FilterParams, SlamConfig())
    assert filter_kwargs == {
        "gyro_scale_std": 0.001,
        "gyro_scale_correlation_s": 5.0,
        "accel_misalignment_std": pytest.approx(math.radians(0.05)),
        "extrinsic_rotation_std": pytest.approx(math.radians(0.2)),
        "extrinsic_translation_std": 0.005,
        "disparity_bias_std": 0.25,
        "focal_scale_std": 0.0,
        "keyframe_map_error": True,
    }
    assert slam_kwargs(RestParams, SlamConfig(zero_velocity=False)) == {"zero_velocity": False}
    linked = 0
    for section in (MappingConfig, GraphConfig, DetectionConfig, MatchingConfig, SlamConfig, HealthConfig):
        for key, info in section.model_fields.items():
            for param in [p for p in info.metadata if isinstance(p, SlamParam)]:
                linked += 1
                assert param.degrees == key.endswith("_deg"), key
                if isinstance(param.slam_default, Enum):  # the schema lists exactly the enum's values
                    assert typing.get_args(info.annotation) == tuple(e.value for e in type(param.slam_default)), key
    assert linked == 63
    # units and enums on the way to slam
    kwargs = slam_kwargs(ObstacleParams, MappingConfig(max_slope_deg=35.0, max_depth_error_m=0.3))
    assert kwargs["max_slope_rad"] == math.radians(35.0) and kwargs["max_error_m"] == 0.3
    assert slam_kwargs(SubmapParams, MappingConfig(max_depth_error_m=0.3))["max_depth_error_m"] == 0.3
    assert slam_kwargs(FilterParams, SlamConfig(camera_rotation_std_deg=0.5))["extrinsic_rotation_std"] == math.radians(0.5)
    agent = slam_kwargs(AgentParams, GraphConfig(pose_buffer_s=60), DetectionConfig(uncertainty="lut", max_tilt_deg=45))
    assert agent["uncertainty"] is UncertaintyModel.LUT and agent["buffer_horizon_s"] == 60
    assert agent["max_target_tilt_rad"] == math.radians(45)
    assert slam_kwargs(GraphParams, GraphConfig(topology="sequential"))["topology"] is Topology.SEQUENTIAL
    assert slam_kwargs(GraphParams, GraphConfig(robust="gnc"))["robust"] is RobustKernel.GNC
    assert slam_kwargs(MatcherParams, MatchingConfig(mode="6d"))["mode"] is MatchMode.SIX_D
    wheel = slam_kwargs(LocalEstimator.on_wheel_odometry, SlamConfig())
    assert wheel == {"speed_std": 0.03, "yaw_rate_std": 0.03, "vz_std": 0.05, "slip_std": 0.03, "slip_correlation_s": 5.0}


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


def test_robust_option_of_the_graph_is_a_validated_key():
    """``slam.graph.robust`` (thesis 4.2.3): the Cauchy kernel by default, gnc and none by ``--set``."""
    assert load_scenario(minimal()).slam.graph.robust == "cauchy" == GraphParams().robust.value
    s = load_scenario(minimal(), ["slam.graph.robust=gnc", "slam.graph.gnc_inlier_probability=0.999"])
    assert GraphParams(**slam_kwargs(GraphParams, s.slam.graph)) == GraphParams(robust=RobustKernel.GNC, gnc_inlier_probability=0.999)
    (line,) = problems(minimal(), ["slam.graph.robust=huber"])
    assert line.startswith("slam.graph.robust: got 'huber'") and "'cauchy', 'gnc' or 'none'" in line
    (line,) = problems(minimal(), ["slam.graph.gnc_inlier_probability=1"])
    assert line.startswith("slam.graph.gnc_inlier_probability: got 1")


def test_tag_ids_are_distinct_and_dump_reloads():
    s = load_scenario(minimal(terrain={"lander": {"tag_id": 1, "xy": [10, 10]}}))
    ids = s.assigned_tag_ids()
    flat = [t for v in ids.values() for t in v]
    assert len(flat) == len(set(flat)) == 5 and 1 not in flat
    again = load_scenario(yaml.safe_load(dump_scenario(s)))
    assert again.assigned_tag_ids() == ids
    assert again.model_dump(exclude={"robots"}) == s.model_dump(exclude={"robots"})


def test_missing_file_and_bad_yaml(tmp_path):
    assert problems(tmp_path / "nope.yaml") == ["file not found"]
    assert problems(tmp_path) == ["is a directory, not a YAML file"]
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed")
    assert problems(bad)[0].startswith("not valid YAML")
