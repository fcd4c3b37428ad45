"""The image pipeline: a run's images are drawn, exposed, searched for markers and
matched by SGBM on a worker thread while the run loop goes on.

Rendering (llvmpipe, ``mjr_render``/``mjr_readPixels``), OpenCV's SGBM and marker
detection release Python's GIL, so on two cores they overlap the loop's physics, filter
and mapping. Nothing in the simulation changes: the loop snapshots the scene when a pair
is captured (:meth:`sim.world.sensors.StereoRenderer.snapshot`); the worker does the
rest in submission order (each camera's tasks on one worker thread: its auto exposure
and noise draws see the same sequence as inline), and a lane job whose work was handed to the worker gets
its result when the job finishes in simulated time (:meth:`sim.run.lanes.Lane.submit`),
where the loop waits for it if the worker is behind. Work whose inputs are fixed when
its job is submitted starts on the worker then (:meth:`ImagePipeline.job`), so a pair's
SGBM follows its own drawing rather than every pair of that instant. A run gives the
same metrics threaded or inline (``tests/test_slam_run.py``).

Work that needs nothing but its inputs and whose result nobody waits for soon (submap
matching attempts, ``sim/run/onboard.py``; the scoring of mapped images against the truth,
``sim/run/runner.py``) may run on a thread of its own (:meth:`ImagePipeline.background`,
with ``background=True``), so images never queue behind it; one thread, so it runs in the
order it was started. Without it, that work runs on the loop's thread.

Inline (``workers=0``) everything runs on the loop's thread as it is asked for: the
mode for ``compute.model: measured``, whose jobs' modelled time is their own wall time.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")


class ImagePipeline:
    """``workers`` worker threads (0: inline). Each task names its worker; a camera's tasks
    all go to one (its renderer draws in one thread, its exposure and noise are sequential),
    so they run in the order they were started. ``timers`` gets the workers' wall time per
    part (the loop's own when inline); ``waited_s`` is the loop's time blocked on them."""

    def __init__(self, workers: int, timers, background: bool = False):
        self.workers = workers
        self.timers = timers
        self.waited_s = 0.0
        self._executors = [ThreadPoolExecutor(1, thread_name_prefix=f"images{k}") for k in range(workers)]
        self._background = ThreadPoolExecutor(1, thread_name_prefix="background") if workers and background else None
        self._started: deque[Future] = deque()  # to surface a failure nobody waits for

    @property
    def threaded(self) -> bool:
        return self.workers > 0

    def start(self, worker: int, fn: Callable[..., T], *args) -> Future:
        """Run ``fn(*args)`` now (inline) or on worker ``worker`` (modulo the workers), after
        everything started there before."""
        self._raise_failures()
        if self._executors:
            future = self._executors[worker % len(self._executors)].submit(fn, *args)
            self._started.append(future)
            return future
        future: Future = Future()
        future.set_result(fn(*args))
        return future

    def background(self, part: str, fn: Callable[[], T]) -> Future | T:
        """Run ``fn()`` on the background thread, after the background work started before
        it, timed as ``part`` of the workers' time; without that thread: now, returning its result."""
        self._raise_failures()
        if self._background is None:
            return fn()

        def timed() -> T:
            t0 = time.perf_counter()
            try:
                return fn()
            finally:
                self.timers.add(part, t0)

        future = self._background.submit(timed)
        self._started.append(future)
        return future

    def job(self, worker: int, fn: Callable[..., T], *args) -> Callable[[], Any]:
        """The work of a lane job whose inputs are all given now: threaded, ``fn`` starts on
        ``worker`` now and the job's work is its future (the lane takes the result when the
        job finishes; a job dropped by a full queue wasted it); inline, the job runs ``fn``
        when it starts (so ``compute.model: measured`` times it)."""
        if not self._executors:
            return lambda: fn(*args)
        future = self.start(worker, fn, *args)
        return lambda: future

    def result(self, value: Future | T) -> T:
        """``value``'s result, waiting for the worker if it is not done yet."""
        if not isinstance(value, Future):
            return value
        if not value.done():
            t0 = time.perf_counter()
            out = value.result()
            self.waited_s += time.perf_counter() - t0
            return out
        return value.result()

    def close(self, last: Callable[[int], None] | None = None) -> None:
        """Finish the workers' queues, run ``last(worker)`` on each (e.g. release its GL
        contexts; ``last(0)`` inline), stop them, and raise the first failure nobody collected."""
        if self._background is not None:
            self._background.shutdown(wait=True)
            self._background = None
        if self._executors:
            if last is not None:
                self._started.extend(executor.submit(last, k) for k, executor in enumerate(self._executors))
            for executor in self._executors:
                executor.shutdown(wait=True)
            self._executors = []
        elif last is not None:
            last(0)
        self._raise_failures()

    def _raise_failures(self) -> None:
        while self._started and self._started[0].done():
            error = self._started.popleft().exception()
            if error is not None:
                self._started.clear()
                raise error
