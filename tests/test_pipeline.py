"""The image pipeline (sim/run/pipeline.py): work on worker threads, results in order,
failures surfaced; the marker search it skips where no marker can show."""

import threading
from concurrent.futures import Future

import pytest

from sim.run.pipeline import ImagePipeline
from sim.run.runner import Run, Timers
from sim.scenario import load_scenario
from sim.world.sensors import SensorError
from tests.test_slam_run import ENCOUNTER


def test_a_camera_s_tasks_run_in_order_on_its_worker():
    pipeline = ImagePipeline(2, Timers())
    seen: dict[int, list] = {0: [], 1: []}

    def task(worker, k):
        seen[worker].append((k, threading.current_thread().name))
        return k

    futures = [pipeline.start(k % 2, task, k % 2, k) for k in range(20)]
    assert [pipeline.result(f) for f in futures] == list(range(20))
    pipeline.close()
    for worker, calls in seen.items():
        assert [k for k, _ in calls] == list(range(worker, 20, 2))
        assert len({name for _, name in calls}) == 1  # one thread per worker
    assert seen[0][0][1] != seen[1][0][1]


def test_a_job_s_work_is_a_future_when_threaded_and_a_value_inline():
    threaded, inline = ImagePipeline(1, Timers()), ImagePipeline(0, Timers())
    work = threaded.job(0, sum, [1, 2])
    out = work()
    assert isinstance(out, Future) and threaded.result(out) == 3
    assert inline.job(0, sum, [1, 2])() == 3
    threaded.close()
    inline.close()


def test_a_failure_nobody_waits_for_is_raised():
    pipeline = ImagePipeline(1, Timers())

    def fail():
        raise ValueError("broken frame")

    pipeline.start(0, fail)
    with pytest.raises(ValueError, match="broken frame"):
        pipeline.close()


def test_the_marker_search_is_skipped_only_where_it_finds_nothing(monkeypatch):
    """Every image of two rovers scanning side by side, searched in full: wherever a marker
    is found, ``Run._markers_in_view`` said it might show; most images without one are skipped."""
    records = []
    develop = Run._develop

    def develop_and_search(self, runtime, renderer, imaging, rig, request, dark, rate):
        frame = develop(self, runtime, renderer, imaging, rig, request, dark, rate)  # inline: at capture, the state is current
        found = runtime.onboard.agent.find_markers(rig.name, rig.intrinsics, frame.left)
        records.append((self._markers_in_view(runtime.robot, rig), len(found)))
        return frame

    monkeypatch.setattr(Run, "_develop", develop_and_search)
    run = Run(load_scenario("scenarios/spacebotcamp_outage.yaml", [*ENCOUNTER, "duration_s=14"]), image_workers=0)
    run.execute()
    with_markers = [in_view for in_view, found in records if found]
    without = [in_view for in_view, found in records if not found]
    assert len(with_markers) >= 10, records
    assert all(with_markers)
    assert sum(not v for v in without) >= 0.5 * len(without), (sum(without), len(without))


def test_a_run_closes_a_renderer_a_tool_drew_with_on_the_loop_s_thread():
    """sim/tools/render_bench.py draws with a run's renderer itself; the run's close must
    release that context on this thread and the others on the worker."""
    run = Run(load_scenario("scenarios/quickstart.yaml", ["output.recording=false"]))
    renderer = next(iter(run.robots.values())).renderers[0]
    renderer.render(run.world.data)
    assert renderer.drawing_thread == threading.get_ident()
    run.close()
    assert renderer.drawing_thread is None
    with pytest.raises(SensorError, match="closed"):
        renderer.render(run.world.data)


@pytest.mark.parametrize("phase", [None, 0.0, 0.3])
def test_each_robot_s_cameras_trigger_at_its_phase_of_the_frame_period(monkeypatch, phase):
    """By default robot k of a team of n triggers k/n of a frame period after each period's
    start; ``camera.trigger_phase`` sets the fraction for all (0: in step). Frames count
    from 0 at the first trigger."""
    triggers = []
    capture = Run._capture

    def record(self, runtime, frame, now):
        triggers.append((runtime.robot.name, frame, now))
        return capture(self, runtime, frame, now)

    monkeypatch.setattr(Run, "_capture", record)
    overrides = ["duration_s=1.25", "slam.enabled=false", "output.recording=false", "output.topdown_png=false"]
    if phase is not None:
        overrides.append(f"robots.*.camera.trigger_phase={phase}")
    run = Run(load_scenario("scenarios/quickstart.yaml", overrides), image_workers=0)
    run.execute()
    names = list(run.robots)
    period = 1.0 / run.scenario.robots[0].camera.rate_hz
    for k, name in enumerate(names):
        mine = [(frame, now) for robot, frame, now in triggers if robot == name]
        offset = period * (k / len(names) if phase is None else phase)
        assert [frame for frame, _ in mine] == list(range(len(mine))) and len(mine) >= 6
        # on the last IMU sample at or before it (an IMU sample every one or two control ticks here)
        assert all(-1e-9 <= offset + frame * period - now < 2 * run.tick_s for frame, now in mine), (name, mine[:3])
