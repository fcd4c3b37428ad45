"""Range and line of sight from caller-supplied callbacks, and relays around cuts."""

import numpy as np
import pytest
from comms_util import collect, make_net, send_at

from comms import CommsError

LINK = {"latency_s": 0.1, "bandwidth_bps": 1e6, "mtu_bytes": 1000}


class Scene:
    """Positions the test moves, a wall the test raises."""

    def __init__(self, **xy):
        self.pos = {k: np.array([*v, 0.0]) for k, v in xy.items()}
        self.walls: set[frozenset] = set()
        self.rays = 0

    def positions(self):
        return self.pos

    def line_of_sight(self, a, b):
        self.rays += 1
        return frozenset((a, b)) not in self.walls


def test_range_cuts_and_restores_a_link_at_poll_times():
    scene = Scene(a=(0, 0), b=(10, 0))
    env, net = make_net(positions=scene.positions, defaults={**LINK, "range_m": 50}, poll_interval_s=0.5)
    got = collect(env, net, "b")
    assert net.is_up("a", "b")
    send_at(env, 1.2, lambda: scene.pos.__setitem__("b", np.array([80.0, 0, 0])))
    send_at(env, 1.7, lambda: net.send("a", "b", "blob", bytes(100)))
    send_at(env, 3.2, lambda: scene.pos.__setitem__("b", np.array([40.0, 0, 0])))
    env.run(until=10)
    downs = [(e.t, e.up, e.reasons) for e in net.accounting.link_events if (e.src, e.dst) == ("a", "b")]
    assert downs == [(1.5, False, ("range",)), (3.5, True, ())]
    assert got[0].received_at == pytest.approx(3.5 + 8 * 100 / 1e6 + 0.1, rel=1e-12)


def test_line_of_sight_cuts_and_restores_a_link():
    scene = Scene(a=(0, 0), b=(10, 0))
    env, net = make_net(
        positions=scene.positions,
        line_of_sight=scene.line_of_sight,
        defaults={**LINK, "line_of_sight": True},
        poll_interval_s=1.0,
    )
    send_at(env, 2.5, lambda: scene.walls.add(frozenset("ab")))
    send_at(env, 5.5, lambda: scene.walls.clear())
    env.run(until=4)
    assert not net.is_up("a", "b") and not net.is_up("b", "a")
    assert net.link("a", "b").reasons() == ("line_of_sight",)
    env.run(until=7)
    assert net.is_up("a", "b")
    assert scene.rays == 7  # one ray per pair per poll (t = 0..6), not one per direction


def test_nodes_without_positions_are_never_out_of_range():
    scene = Scene(a=(0, 0))
    env, net = make_net(nodes=["a", "ground"], positions=scene.positions, defaults={**LINK, "range_m": 1})
    env.run(until=2)
    assert net.is_up("a", "ground")


def test_range_without_a_positions_callback_is_an_error():
    with pytest.raises(CommsError, match="positions callback"):
        make_net(defaults={**LINK, "range_m": 50})
    with pytest.raises(CommsError, match="line_of_sight callback"):
        make_net(positions=dict, defaults={**LINK, "line_of_sight": True})


def test_a_relay_delivers_around_a_cut_link():
    # a and b cannot see each other; the lander sees both (thesis 7.2: lander forwards)
    scene = Scene(a=(0, 0), b=(20, 0), lander=(10, 10))
    scene.walls.add(frozenset("ab"))
    env, net = make_net(
        nodes=["a", "b", "lander"],
        positions=scene.positions,
        line_of_sight=scene.line_of_sight,
        defaults={**LINK, "line_of_sight": True},
        relays=["lander"],
    )
    got = collect(env, net, "b")
    assert net.route("a", "b") == ("a", "lander", "b")
    net.send("a", "b", "blob", bytes(5000))
    env.run(until=5)
    assert got[0].path == ("a", "lander", "b")
    assert got[0].latency == pytest.approx(2 * (8 * 5000 / 1e6 + 0.1), rel=1e-12)  # store and forward per hop
    row = net.to_table()[0]
    assert row["mean_hops"] == 2.0
    assert net.accounting.links[("lander", "b")].completed_msgs == 1


def test_routes_follow_link_changes():
    scene = Scene(a=(0, 0), b=(20, 0), lander=(10, 10))
    env, net = make_net(
        nodes=["a", "b", "lander"],
        positions=scene.positions,
        line_of_sight=scene.line_of_sight,
        defaults={**LINK, "line_of_sight": True},
        relays=["lander"],
        poll_interval_s=1.0,
    )
    got = collect(env, net, "b")
    assert net.route("a", "b") == ("a", "b")
    send_at(env, 0.5, lambda: scene.walls.add(frozenset("ab")))
    send_at(env, 1.5, lambda: net.send("a", "b", "blob", bytes(10)))
    send_at(env, 2.5, lambda: scene.walls.clear())
    send_at(env, 3.5, lambda: net.send("a", "b", "blob", bytes(10)))
    env.run(until=6)
    assert [d.path for d in got] == [("a", "lander", "b"), ("a", "b")]


def test_without_relays_messages_wait_for_the_direct_link():
    scene = Scene(a=(0, 0), b=(20, 0), lander=(10, 10))
    scene.walls.add(frozenset("ab"))
    env, net = make_net(
        nodes=["a", "b", "lander"],
        positions=scene.positions,
        line_of_sight=scene.line_of_sight,
        defaults={**LINK, "line_of_sight": True},
        poll_interval_s=1.0,
    )
    got = collect(env, net, "b")
    net.send("a", "b", "blob", bytes(10))
    send_at(env, 2.5, lambda: scene.walls.clear())
    env.run(until=6)
    assert net.route("a", "b") == ("a", "b")
    assert [d.path for d in got] == [("a", "b")] and got[0].received_at == pytest.approx(3.10008)


def test_a_relay_parks_messages_when_its_onward_link_is_down():
    env, net = make_net(
        nodes=["a", "b", "lander"],
        defaults=LINK,
        relays=["lander"],
        outages=[{"start_s": 0.0, "end_s": 100.0, "links": ["a<->b"]}, {"start_s": 0.11, "end_s": 3.0, "links": ["lander->b"]}],
    )
    got = collect(env, net, "b")
    net.send("a", "b", "blob", bytes(1000))  # at the lander 0.108 s; cut while it is sent on
    env.run(until=1.0)
    assert [m.dst for m in net.held("lander")] == ["b"]
    env.run(until=5)
    assert got[0].path == ("a", "lander", "b") and got[0].received_at == pytest.approx(3.108)
