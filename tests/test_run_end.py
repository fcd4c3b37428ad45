"""The end of a run (docs/matching.md, "The end of a run"): once every route is done, the
robots rest with their sensors off while the last submaps are finished and matched and
queued jobs and messages complete."""

import numpy as np
import pytest

from sim.run.runner import Run
from sim.scenario import ScenarioError, load_scenario

# The rock field's two rovers, 20 m apart, each on a 2.5 m leg (about 10 s): one submap each.
SHORT = [
    "duration_s=60",
    "output.recording=false",
    "output.topdown_png=false",
    "robots.lru1.route.waypoints=[[-7.5, -5]]",
    "robots.lru2.route.waypoints=[[7.5, -5]]",
]


@pytest.fixture(scope="module")
def drained():
    """The run, and the robots' true positions every 0.5 s."""
    run = Run(load_scenario("scenarios/rock_field_revisit.yaml", SHORT))
    states = []
    run.execute(progress=lambda t, _: states.append((t, {n: rt.robot.pose()[0].copy() for n, rt in run.robots.items()})), progress_every_s=0.5)
    return run, states


def test_the_run_drains_after_the_routes_and_ends_when_no_work_is_left(drained):
    run, _ = drained
    assert all(rt.robot.finished for rt in run.robots.values())
    assert 5 < run.mission_s < 30 and run.drain_end == "idle"
    assert run.mission_s < run.sim_time < run.scenario.duration_s
    for name, rt in run.robots.items():
        onboard, agent = rt.onboard, rt.onboard.agent
        # the active submap was finished at the end, sent, and prepared by both robots' pairing
        assert onboard.partitions[-1][0] >= run.mission_s and onboard.partitions[-1][1] == "end"
        assert onboard.mapper.builder.images == 0
        last = onboard.mapper.submaps[-1].key
        for peer in run.robots.values():
            held = peer.onboard.agent.matcher.queue
            assert last in held.prepared or last in held.unsuitable, (name, peer.robot.name)
        assert not rt.lane.busy() and not agent.dirty and not agent.matcher.has_work
    assert run.messages_in_flight() == 0
    lru2 = run.robots["lru2"].onboard.agent
    assert ("lru1", run.robots["lru1"].onboard.mapper.submaps[-1].index) in lru2.peer_submaps


def test_the_robots_rest_and_nothing_is_sensed_while_draining(drained):
    run, states = drained
    after = [poses for t, poses in states if t > run.mission_s + 1e-9]
    assert len(after) >= 2
    for name in run.robots:
        assert all(np.array_equal(poses[name], after[0][name]) for poses in after)
        log, onboard = run.robots[name].log, run.robots[name].onboard
        assert max(log.gt_t) <= run.mission_s and max(log.imu_t) <= run.mission_s and max(onboard.log.t) <= run.mission_s


def test_drain_s_validates():
    assert load_scenario("scenarios/quickstart.yaml").drain_s > 0
    with pytest.raises(ScenarioError, match="drain_s"):
        load_scenario("scenarios/quickstart.yaml", ["drain_s=-1"])


def test_a_second_partition_at_the_end_does_not_repeat_the_frame_switch(drained):
    """With the sensors off the filter no longer propagates: a partition at the end right
    after another one (an image mapped in between) would switch the frame again with a
    zero covariance, which the graph refuses. The end's partition is skipped then."""
    run, _ = drained
    onboard = run.robots["lru1"].onboard
    est, builder = onboard.estimator, onboard.mapper.builder
    assert est.switches[-1].t >= est.filter.t  # the end's switch was the filter's last step
    rig = onboard.vo_rig
    shape = (rig.height, rig.width)
    builder.integrate(np.full(shape, 2.0, np.float32), np.eye(4), np.zeros(shape, bool), np.zeros(shape, np.uint8),
                      run.sim_time, classified=np.ones(shape, bool))
    assert builder.images == 1
    switches, partitions = len(est.switches), len(onboard.partitions)
    assert onboard._end_submap(run.sim_time) == []
    assert len(est.switches) == switches and len(onboard.partitions) == partitions
