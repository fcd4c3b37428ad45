from concurrent.futures import Future

import pytest
import simpy

from sim.run.lanes import ComputeModel, Device, Lane, Priority
from sim.scenario import ComputeConfig


def make_lane(env, cores=1, fpga=False, max_queue=10, **cfg):
    return Lane(env, "r", cores=cores, fpga=fpga, compute=ComputeModel(ComputeConfig(**cfg)), max_queue=max_queue)


def test_job_result_appears_after_modelled_cost():
    env = simpy.Environment()
    lane = make_lane(env, stages={"stereo_s": 0.25})
    seen = []
    lane.submit("stereo", lambda: 42, lambda result, t: seen.append((result, t)))
    env.run()
    assert seen == [(42, pytest.approx(0.25))]


def test_a_job_holds_its_core_for_the_stages_its_result_says_it_ran():
    """A matching attempt that reached the ICP costs matching plus ICP, one that stopped
    before it matching alone (thesis 8.4); measured, the wall time already holds both."""
    env = simpy.Environment()
    lane = make_lane(env, stages={"matching_s": 3.0, "icp_s": 2.0})
    done = []
    icp = lambda result: ("icp",) if result == "refined" else ()  # noqa: E731
    lane.submit("matching", lambda: "refined", lambda r, t: done.append((r, t)), extra_stages=icp)
    lane.submit("matching", lambda: "no hypothesis", lambda r, t: done.append((r, t)), extra_stages=icp)
    env.run()
    assert done == [("refined", pytest.approx(5.0)), ("no hypothesis", pytest.approx(8.0))]
    measured = ComputeModel(ComputeConfig(model="measured", measured_scale=2.0))
    assert measured.cost("matching", 0.5) == 1.0 and measured.extra_cost(("icp",)) == 0.0


def test_work_beside_the_loop_holds_the_stage_cost_then_the_stages_its_result_names():
    """Offloaded work (a future, as ImagePipeline.background returns): the job holds its stage's
    cost, takes the result when that is up, then holds the stages it names; a real-time job
    that preempts it in between delays the finish by its own cost."""
    env = simpy.Environment()
    lane = make_lane(env, stages={"matching_s": 3.0, "icp_s": 2.0, "vo_s": 0.5})
    future, resolved, done = Future(), [], []

    def resolve(f):
        resolved.append(env.now)
        return f.result()

    lane.resolve = resolve
    icp = lambda result: ("icp",) if result == "refined" else ()  # noqa: E731
    lane.submit("matching", lambda: future, lambda r, t: done.append((r, t)), priority=Priority.BACKGROUND, extra_stages=icp)
    env.run(until=1.0)
    future.set_result("refined")
    lane.submit("vo", lambda: "delta", lambda r, t: done.append((r, t)))  # preempts the attempt at 1.0
    env.run()
    assert resolved == [pytest.approx(3.5)]
    assert done == [("delta", pytest.approx(1.5)), ("refined", pytest.approx(5.5))]


def test_jobs_queue_on_one_core_and_priorities_order_them():
    env = simpy.Environment()
    lane = make_lane(env, stages={"stereo_s": 1.0})
    done = []
    lane.submit("stereo", lambda: "a", lambda r, t: done.append((r, t)))
    # both wait behind "a"; the real-time one goes first although submitted later
    lane.submit("stereo", lambda: "bg", lambda r, t: done.append((r, t)), priority=Priority.BACKGROUND)
    lane.submit("stereo", lambda: "rt", lambda r, t: done.append((r, t)))
    env.run()
    assert done == [("a", 1.0), ("rt", 2.0), ("bg", 3.0)]
    row = lane.stats(3.0)[0]
    assert row["completed"] == 3 and row["queue_delay_max_s"] == pytest.approx(2.0)
    assert lane.utilization(3.0)[Device.CPU] == pytest.approx(1.0)


def test_full_realtime_queue_drops_new_jobs():
    env = simpy.Environment()
    lane = make_lane(env, max_queue=1, stages={"stereo_s": 1.0})
    results = [lane.submit("stereo", lambda: None) for _ in range(4)]
    env.run()
    # one runs, one waits, the other two are dropped
    assert [r is None for r in results] == [False, False, True, True]
    row = lane.stats(2.0)[0]
    assert (row["submitted"], row["completed"], row["dropped"]) == (4, 2, 2)


def test_fpga_runs_beside_the_cpu_and_falls_back_when_absent():
    env = simpy.Environment()
    lane = make_lane(env, fpga=True, stages={"stereo_s": 1.0})
    ends = []
    lane.submit("stereo", lambda: None, lambda r, t: ends.append(t), device=Device.FPGA)
    lane.submit("stereo", lambda: None, lambda r, t: ends.append(t), device=Device.CPU)
    env.run()
    assert ends == [1.0, 1.0]
    assert make_lane(simpy.Environment()).device_for(Device.FPGA) == Device.CPU


def test_measured_model_scales_wall_time():
    env = simpy.Environment()
    lane = make_lane(env, model="measured", measured_scale=1000.0)
    total = []
    lane.submit("stereo", lambda: sum(range(200000)), lambda r, t: total.append(t))
    env.run()
    (wall_s,) = lane._stages["stereo"].column("wall_s")
    assert wall_s > 0
    assert total[0] == pytest.approx(wall_s * 1000.0)


def test_unknown_stage_is_named():
    with pytest.raises(KeyError, match="known stages"):
        ComputeModel(ComputeConfig()).cost("teleport", 0.0)


def test_realtime_job_preempts_a_long_background_job():
    """A 5 s background job (submap matching) on one core is preempted by a real-time job
    submitted meanwhile, and finishes later by the real-time job's compute time."""
    env = simpy.Environment()
    lane = make_lane(env, stages={"matching_s": 5.0, "strapdown_s": 0.01})
    done = []
    lane.submit("matching", lambda: "match", lambda r, t: done.append((r, t)), priority=Priority.BACKGROUND)
    env.run(until=1.0)
    lane.submit("strapdown", lambda: "imu", lambda r, t: done.append((r, t)))
    env.run()
    assert done[0] == ("imu", pytest.approx(1.01))
    assert done[1] == ("match", pytest.approx(5.01))
    assert lane.utilization(5.01)[Device.CPU] == pytest.approx(1.0)


def test_a_background_job_preempted_in_the_instant_it_gets_the_core_queues_again():
    """A background job granted the only core and, before it resumes, preempted by a real-time
    job submitted in the same instant (an IMU sample's strapdown beside a background
    job): it runs after the real-time job instead of failing the run."""
    env = simpy.Environment()
    lane = make_lane(env, stages={"pairing_s": 0.3, "strapdown_s": 0.01})
    done = []

    def both():
        yield env.timeout(1.0)
        lane.submit("pairing", lambda: "goal", lambda r, t: done.append((r, t)), priority=Priority.BACKGROUND)
        lane.submit("strapdown", lambda: "imu", lambda r, t: done.append((r, t)))

    env.process(both())
    env.run()
    assert done == [("imu", pytest.approx(1.01)), ("goal", pytest.approx(1.31))]
    # and preempted again when re-granted: a second real-time job in the instant the first ends
    env = simpy.Environment()
    lane = make_lane(env, stages={"pairing_s": 0.3, "strapdown_s": 0.01})
    done = []

    def imu1_done(r, t):
        done.append((r, t))
        lane.submit("strapdown", lambda: "imu2", lambda r2, t2: done.append((r2, t2)))

    def three():
        yield env.timeout(1.0)
        lane.submit("pairing", lambda: "goal", lambda r, t: done.append((r, t)), priority=Priority.BACKGROUND)
        lane.submit("strapdown", lambda: "imu1", imu1_done)

    env.process(three())
    env.run()
    assert [r for r, _ in done] == ["imu1", "imu2", "goal"]
    assert done[-1][1] == pytest.approx(1.32)


def test_busy_counts_waiting_and_running_jobs_per_priority_until_their_results():
    env = simpy.Environment()
    lane = make_lane(env, max_queue=1, stages={"stereo_s": 1.0, "pairing_s": 1.0})
    seen = []
    lane.submit("stereo", lambda: None, lambda r, t: seen.append((t, lane.busy(Priority.REALTIME), lane.busy())))
    lane.submit("pairing", lambda: None, priority=Priority.BACKGROUND)
    lane.submit("stereo", lambda: None)
    lane.submit("stereo", lambda: None)  # dropped: never busy
    assert lane.busy(Priority.REALTIME) and lane.busy(Priority.BACKGROUND)
    env.run(until=1.5)
    assert seen == [(1.0, True, True)]  # the second real-time job waits, so does the background one
    env.run(until=2.5)
    assert not lane.busy(Priority.REALTIME) and lane.busy(Priority.BACKGROUND) and lane.busy()
    env.run()
    assert not lane.busy()
