import math

import pytest
from comms_util import collect, make_net
from pydantic import ValidationError

from comms import CommsConfig, CommsError, resolve_links
from comms.config import KindPolicy, LossConfig, Preset


def test_unknown_keys_are_errors_at_every_level():
    for bad in (
        {"bandwith_bps": 1},
        {"defaults": {"latency": 1}},
        {"defaults": {"loss": {"model": "bernoulli", "rat": 0.1}}},
        {"links": {"a->b": {"latencyy_s": 1}}},
        {"kinds": {"pose": {"prio": 1}}},
        {"outages": [{"start_s": 1, "end_s": 2, "node": ["a"]}]},
    ):
        with pytest.raises(ValidationError) as info:
            CommsConfig.model_validate(bad)
        assert any(e["type"] == "extra_forbidden" for e in info.value.errors()), bad


def test_bad_values_are_errors():
    with pytest.raises(ValidationError, match="not one of"):
        CommsConfig.model_validate({"preset": "mars_orbiter"})
    with pytest.raises(ValidationError, match="a->b"):
        CommsConfig.model_validate({"links": {"a=>b": {"latency_s": 1}}})
    with pytest.raises(ValidationError, match="end_s"):
        CommsConfig.model_validate({"outages": [{"start_s": 5, "end_s": 2}]})
    with pytest.raises(ValidationError, match="window"):
        CommsConfig.model_validate({"uplink_windows": [[10, 5]]})
    with pytest.raises(ValidationError, match="gilbert_elliott needs"):
        LossConfig(model="gilbert_elliott", rate=0.1)
    with pytest.raises(ValidationError):
        CommsConfig.model_validate({"defaults": {"bandwidth_bps": 0}})


def test_unknown_node_names_are_reported_with_the_known_ones():
    cfg = CommsConfig.model_validate({"preset": None, "links": {"a->zz": {"latency_s": 1}}, "relays": ["qq"]})
    with pytest.raises(CommsError) as info:
        resolve_links(cfg, ["a", "b"])
    text = str(info.value)
    assert "'zz'" in text and "'qq'" in text and "['a', 'b']" in text


def test_spacebotcamp_preset_is_the_thesis_channel():
    cfg = CommsConfig(preset=Preset.SPACEBOTCAMP)
    assert cfg.defaults.latency_s == 2.0  # thesis 9.2: 4 s round trip
    assert cfg.defaults.bandwidth_bps == 100e6  # 100 Mbit/s
    assert cfg.ground_station == "ground"
    assert cfg.uplink_windows == []  # uplink blocked unless a scenario opens checkpoints
    links = resolve_links(cfg, ["lru1", "lru2", "ground"])
    assert links[("ground", "lru1")].windows == []
    assert links[("lru1", "ground")].windows is None
    assert links[("lru1", "lru2")].latency_s == 2.0


def test_spacebotcamp_downlink_takes_two_seconds_and_uplink_opens_only_in_its_window():
    env, net = make_net(nodes=["lru1"], preset="spacebotcamp", uplink_windows=[[10.0, 310.0]])
    assert net.nodes == ("lru1", "ground")  # the preset's ground station joins the network
    down = collect(env, net, "ground")
    up = collect(env, net, "lru1")
    net.send("lru1", "ground", "telemetry", bytes(1000))
    net.send("ground", "lru1", "command", bytes(100))  # uplink blocked: waits for the window
    env.run(until=20)
    assert down[0].latency == pytest.approx(2.0 + 8 * 1000 / 100e6, rel=1e-12)
    assert up[0].received_at == pytest.approx(10.0 + 2.0 + 8 * 100 / 100e6, rel=1e-12)


def test_preset_values_are_merged_under_the_section():
    cfg = CommsConfig.model_validate({"preset": "spacebotcamp", "defaults": {"bandwidth_bps": 2e6}})
    assert cfg.defaults.bandwidth_bps == 2e6 and cfg.defaults.latency_s == 2.0
    uhf = CommsConfig(preset="lunar_surface_uhf")
    assert uhf.defaults.range_m == 300.0 and uhf.defaults.line_of_sight
    assert uhf.defaults.loss.stationary_loss_rate() == pytest.approx(0.01)
    assert CommsConfig().preset == Preset.LAB_WIFI and CommsConfig().defaults.bandwidth_bps == 20e6


def test_dump_and_reload_is_the_same_config():
    for preset in (*Preset, None):
        cfg = CommsConfig.model_validate(
            {
                "preset": preset,
                "links": {"a<->b": {"range_m": None}, "*->b": {"latency_s": 0.5}},
                "kinds": {"submap": {"priority": 4}},
                "outages": [{"start_s": 1, "end_s": 2, "nodes": ["a"]}],
            }
        )
        again = CommsConfig.model_validate(cfg.model_dump(mode="json"))
        assert again == cfg
        assert again.links["a<->b"].model_fields_set == {"range_m"}  # 'unlimited' survives


def test_override_layers_least_to_most_specific():
    cfg = CommsConfig.model_validate(
        {
            "preset": None,
            "defaults": {"latency_s": 1.0, "range_m": 50},
            "links": {
                "a->b": {"latency_s": 4.0},  # direction beats pair, whatever the order
                "a<->b": {"latency_s": 3.0, "range_m": None},
                "*->b": {"latency_s": 2.0, "bandwidth_bps": 1e3},
            },
        }
    )
    links = resolve_links(cfg, ["a", "b", "c"])
    assert links[("a", "b")].latency_s == 4.0 and links[("a", "b")].bandwidth_bps == 1e3
    assert links[("a", "b")].range_m is None
    assert links[("b", "a")].latency_s == 3.0
    assert links[("c", "b")].latency_s == 2.0 and links[("c", "b")].range_m == 50
    assert links[("c", "a")].latency_s == 1.0


def test_kind_policies_resolve_over_kind_defaults():
    cfg = CommsConfig.model_validate({"kind_defaults": {"max_queued": 7}, "kinds": {"submap": {"priority": 9}}})
    assert cfg.kind_policy("submap").priority == 9
    assert cfg.kind_policy("submap").delivery == "reliable"  # built-in kind, thesis 3.3
    assert cfg.kind_policy("submap").max_queued == 200
    assert cfg.kind_policy("pose").priority == 0
    assert cfg.kind_policy("anything") == KindPolicy(max_queued=7)


def test_gilbert_elliott_short_form():
    loss = LossConfig(model="gilbert_elliott", rate=0.05, mean_burst_fragments=4)
    gb, bg, lg, lb = loss.gilbert_elliott()
    assert bg == 0.25 and lg == 0 and lb == 1
    assert gb / (gb + bg) == pytest.approx(0.05)
    assert math.isclose(loss.stationary_loss_rate(), 0.05)
