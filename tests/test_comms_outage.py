"""Outages: scheduled per link, direction and node; windows; random outages; what
happens to messages meanwhile (store and forward in order, bounded, or drop)."""

import pytest
from comms_util import collect, make_net, send_at

LINK = {"latency_s": 0.1, "bandwidth_bps": 1e6, "mtu_bytes": 1000}


def test_store_and_forward_delivers_in_order_after_reconnect():
    env, net = make_net(defaults=LINK, outages=[{"start_s": 1.0, "end_s": 5.0, "links": ["a->b"]}])
    got = collect(env, net, "b")
    sent = []
    for i in range(10):
        send_at(env, 2.0 + 0.1 * i, lambda i=i: sent.append(net.send("a", "b", "blob", bytes(100 + i))))
    env.run(until=3.0)
    assert got == [] and [m.id for m in net.held("a")] == [m.id for m in sent]
    env.run(until=10)
    assert [d.message.id for d in got] == [m.id for m in sent]
    assert got[0].received_at == pytest.approx(5.0 + 8 * 100 / 1e6 + 0.1, rel=1e-12)
    assert net.held("a") == []


def test_a_message_cut_mid_transfer_is_resent_after_reconnect():
    env, net = make_net(defaults=LINK, outages=[{"start_s": 0.5, "end_s": 2.0, "links": ["a<->b"]}])
    got = collect(env, net, "b")
    net.send("a", "b", "blob", bytes(200_000))  # 1.6 s of serialization, cut at 0.5 s
    env.run(until=10)
    assert len(got) == 1
    assert got[0].received_at == pytest.approx(2.0 + 1.6 + 0.1, rel=1e-9)


def test_full_queue_drops_newest_and_counts_why():
    env, net = make_net(
        defaults=LINK,
        outages=[{"start_s": 0.0, "end_s": 5.0, "nodes": ["b"]}],
        kinds={"blob": {"max_queued": 4}},
    )
    got = collect(env, net, "b")
    sent = [net.send("a", "b", "blob", bytes(10)) for _ in range(10)]
    env.run(until=10)
    assert [d.message.id for d in got] == [m.id for m in sent[:4]]
    assert [net.accounting.fate(m.id) for m in sent[4:]] == ["queue_full"] * 6
    row = net.to_table()[0]
    assert row["dropped_queue_full_msgs"] == 6 and row["dropped_queue_full_bytes"] == 60


def test_full_queue_drops_oldest_for_fresh_poses():
    env, net = make_net(
        defaults=LINK,
        outages=[{"start_s": 0.0, "end_s": 5.0}],
        kinds={"pose": {"max_queued": 3, "when_full": "drop_oldest"}},
    )
    got = collect(env, net, "b")
    sent = [net.send("a", "b", "pose", bytes(50)) for _ in range(10)]
    env.run(until=10)
    assert [d.message.id for d in got] == [m.id for m in sent[-3:]]


def test_drop_policy_drops_what_cannot_go_now():
    env, net = make_net(
        defaults=LINK, kinds={"pose": {"outage": "drop"}}, outages=[{"start_s": 0.5, "end_s": 1.5}]
    )
    net.send("a", "b", "pose", bytes(100_000))  # 0.8 s on the wire: cut at 0.5 s
    late = []
    send_at(env, 0.6, lambda: late.append(net.send("a", "b", "pose", bytes(10))))
    env.run(until=5)
    table = net.to_table()[0]
    assert table["dropped_link_down_msgs"] == 1  # was on the link when it went down
    assert table["dropped_no_route_msgs"] == 1  # sent while no route existed
    assert net.accounting.fate(late[0].id) == "no_route"
    assert table["delivered_msgs"] == 0


def test_outages_are_per_direction_and_per_node_and_events_are_published():
    env, net = make_net(
        nodes=["a", "b", "c"],
        defaults=LINK,
        outages=[
            {"start_s": 1.0, "end_s": 2.0, "links": ["a->b"]},
            {"start_s": 3.0, "end_s": 4.0, "nodes": ["c"]},
        ],
    )
    events = []
    net.subscribe(events.append)
    env.run(until=1.5)
    assert not net.is_up("a", "b") and net.is_up("b", "a")
    assert net.link("a", "b").reasons() == ("outage",)
    env.run(until=3.5)
    assert net.is_up("a", "b") and net.is_up("a", "b")
    assert not any(net.is_up(x, y) for x, y in [("a", "c"), ("c", "a"), ("b", "c"), ("c", "b")])
    env.run(until=5)
    assert all(link.up for link in net.links.values())
    downs = [(e.t, e.src, e.dst) for e in events if not e.up]
    assert downs == [(1.0, "a", "b")] + [(3.0, x, y) for x, y in sorted([("a", "c"), ("b", "c"), ("c", "a"), ("c", "b")])]
    assert sum(e.up for e in events) == 5
    series = net.timeseries()
    assert series["t"][:3] == [1.0, 2.0, 3.0]
    assert series["links"]["a->b"]["up"][:3] == [False, True, True]


def test_windows_open_and_close_a_link():
    env, net = make_net(defaults=LINK, links={"a->b": {"windows": [[2.0, 3.0], [6.0, 7.0]]}})
    got = collect(env, net, "b")
    for t in (0.0, 3.5, 6.5):
        send_at(env, t, lambda: net.send("a", "b", "blob", bytes(10)))
    env.run(until=10)
    assert [round(d.received_at, 6) for d in got] == [2.10008, 6.10008, 6.60008]
    assert net.link_table()[0]["up_fraction"] == pytest.approx(0.2)


def test_random_outages_take_links_down_and_up():
    env, net = make_net(
        defaults=LINK, random_outages=[{"mean_up_s": 5.0, "mean_down_s": 2.0}], stats_interval_s=0.5
    )
    env.run(until=500)
    up = net.link_table()[0]["up_fraction"]
    assert up == pytest.approx(5 / 7, abs=0.1)
    assert len(net.accounting.link_events) > 40


def test_a_disabled_section_means_no_links():
    env, net = make_net(nodes=["a", "b", "c"], enabled=False, kinds={"pose": {"outage": "drop"}})
    net.send("a", "b", "pose", b"x")
    net.send("a", "c", "submap", b"y")
    env.run(until=5)
    assert not any(link.up for link in net.links.values())
    assert net.to_metrics()["totals"]["dropped_by_reason"]["no_route"]["msgs"] == 1
    assert [m.dst for m in net.held("a")] == ["c"]
