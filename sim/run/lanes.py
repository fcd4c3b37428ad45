"""Scheduler lanes: each robot's on-board computer as SimPy resources (thesis 3.3: real-time and background work on each robot's computer).

A lane has ``cores`` CPU cores (a ``simpy.PriorityResource``) and, like the thesis's
robots (7.1), optionally an FPGA that runs dense stereo matching. Sensor data becomes
a job: the job waits for its device, runs the real code when it gets it, then holds
the device for the compute time of the lane's :class:`ComputeModel`, so its result
appears at the simulated time a robot would have it. Real-time jobs outrank
background jobs; a real-time stage whose queue is full drops the new job, as a
robot's pipeline drops frames it cannot keep up with. A real-time job preempts a
background job holding a core (``simpy.PreemptiveResource``): the background job
queues again for the rest of its compute time, as an operating system runs a
low-priority process (thesis 6.1: the matcher takes whatever processing time is free).
"""

from __future__ import annotations

import time
from collections import Counter, defaultdict
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from typing import Any

import numpy as np
import simpy

from sim.run.series import Rows
from sim.scenario import ComputeConfig


class Priority(IntEnum):
    """SimPy serves lower numbers first."""

    REALTIME = 0
    BACKGROUND = 10


class Device(StrEnum):
    CPU = "cpu"
    FPGA = "fpga"


class ComputeModel:
    """Compute time of a job: ``modeled`` (per-stage constants, thesis 8.4 defaults)
    or ``measured`` (the job's wall time on this machine times a scale factor)."""

    def __init__(self, cfg: ComputeConfig):
        self.cfg = cfg

    def cost(self, stage: str, wall_s: float) -> float:
        """Compute time of a ``stage`` job whose wall time was ``wall_s``."""
        if self.cfg.model == "measured":
            return wall_s * self.cfg.measured_scale
        return self._modelled(stage)

    def extra_cost(self, extra: tuple[str, ...]) -> float:
        """What the further stages ``extra`` that a job's own code ran add to its :meth:`cost`
        (modelled: their costs; measured: nothing, its wall time holds them)."""
        return 0.0 if self.cfg.model == "measured" else sum(self._modelled(s) for s in extra)

    def _modelled(self, stage: str) -> float:
        try:
            return getattr(self.cfg.stages, f"{stage}_s")
        except AttributeError:
            known = sorted(k.removesuffix("_s") for k in type(self.cfg.stages).model_fields)
            raise KeyError(f"no modelled cost for stage {stage!r}; known stages: {known}") from None


@dataclass
class JobRecord:
    """A job in flight; once finished, a row of its stage's :attr:`_StageQueue.done`."""

    stage: str
    device: str
    submitted: float
    started: float | None = None
    finished: float | None = None
    wall_s: float = 0.0
    compute_s: float = 0.0


#: Columns of a stage's finished jobs (:attr:`_StageQueue.done`).
DONE_COLUMNS = ("submitted", "started", "finished", "wall_s", "compute_s")


@dataclass
class _StageQueue:
    """One stage's jobs: counts, and a row per finished job (:data:`DONE_COLUMNS`) in compact rows, since a
    long run has millions of jobs."""

    device: str = Device.CPU
    waiting: int = 0
    submitted: int = 0
    dropped: int = 0
    done: Rows = field(default_factory=Rows)

    def column(self, name: str) -> np.ndarray:
        """One column of the finished jobs."""
        rows = np.asarray(self.done)
        return rows[:, DONE_COLUMNS.index(name)] if len(rows) else np.zeros(0)


class Lane:
    """One robot's computer. ``submit`` returns the SimPy process of the job, or
    ``None`` when a real-time job was dropped because its stage queue was full.

    A job's ``work`` runs when the job starts. If it returns a :class:`Future` (work handed
    to the image pipeline's worker threads, ``sim/run/pipeline.py``, e.g. through
    ``offload``), the lane takes the result through ``resolve`` when the job finishes in
    simulated time, before ``on_done``; with ``wait=False`` it hands ``on_done`` the future
    itself (a result only evaluation reads). ``extra_stages`` names, from the result, the
    stages the work ran beyond its own, whose modelled costs the job holds its device for
    after its own stage's (a matching attempt that reached the ICP): a future is resolved
    between the two, so work beside the loop runs through the stage's own cost first."""

    def __init__(
        self,
        env: simpy.Environment,
        robot: str,
        cores: int,
        fpga: bool,
        compute: ComputeModel,
        max_queue: int,
        resolve: Callable[[Future], Any] = Future.result,
        offload: Callable[[str, Callable[[], Any]], Any] = lambda _part, fn: fn(),
    ):
        self.env = env
        self.resolve = resolve
        self.offload = offload  # (part, fn): fn's result or a future of it (ImagePipeline.background)
        self.robot = robot
        self.compute = compute
        self.max_queue = max_queue
        self.devices: dict[str, simpy.PriorityResource] = {Device.CPU: simpy.PreemptiveResource(env, capacity=cores)}
        if fpga:
            self.devices[Device.FPGA] = simpy.PriorityResource(env, capacity=1)
        self.capacity = {name: res.capacity for name, res in self.devices.items()}
        self.busy_s: dict[str, float] = defaultdict(float)
        self.wall_s = 0.0
        self._stages: dict[str, _StageQueue] = defaultdict(_StageQueue)
        self._active: Counter[Priority] = Counter()  # jobs submitted and not yet done, per priority
        self.slowdown = 1.0  # compute time multiplier (a ``compute_slowdown`` fault, sim/run/faults.py)
        self.halted = False  # the computer is dead: no job starts or reports any more

    def halt(self) -> None:
        """The computer dies: jobs submitted from now on are refused (``submit`` returns None), queued ones
        never start, running ones report no result."""
        self.halted = True

    def busy(self, priority: Priority | None = None) -> bool:
        """Whether a job (of ``priority``, or of any) is waiting or running (never, once halted)."""
        if self.halted:
            return False
        return self._active[priority] > 0 if priority is not None else any(self._active.values())

    def device_for(self, preferred: str) -> str:
        """The FPGA if the lane has one and the job can use it, else the CPU."""
        return preferred if preferred in self.devices else Device.CPU

    def submit(
        self,
        stage: str,
        work: Callable[[], Any],
        on_done: Callable[[Any, float], None] | None = None,
        priority: Priority = Priority.REALTIME,
        device: str = Device.CPU,
        wait: bool = True,
        extra_stages: Callable[[Any], tuple[str, ...]] | None = None,
    ) -> simpy.Process | None:
        if self.halted:
            return None
        device = self.device_for(device)
        queue = self._stages[stage]
        record = JobRecord(stage=stage, device=device, submitted=self.env.now)
        queue.device = device
        queue.submitted += 1
        if priority == Priority.REALTIME and queue.waiting >= self.max_queue:
            queue.dropped += 1
            return None
        resource = self.devices[device]
        # requested now, so a job that finds its device free holds it at once
        request = self._request(resource, priority)
        waits = not request.triggered
        queue.waiting += waits
        self._active[priority] += 1
        process = self.env.process(self._run(resource, request, waits, queue, record, work, on_done, priority, wait, extra_stages))
        request.proc = process  # made outside the job's process: preemption must interrupt the job
        return process

    @staticmethod
    def _request(resource, priority: Priority):
        """Real-time requests preempt background users of a preemptive resource."""
        if isinstance(resource, simpy.PreemptiveResource):
            return resource.request(priority=int(priority), preempt=priority == Priority.REALTIME)
        return resource.request(priority=int(priority))

    def _acquire(self, resource, request, priority: Priority):
        """Wait until ``request`` is granted and the job resumes; a job preempted in between
        (granted, then taken by a real-time request in the same instant) queues again.
        Returns the request that holds the device."""
        while True:
            try:
                yield request
                return request
            except simpy.Interrupt:
                request = self._request(resource, priority)

    def _hold(self, resource, request, priority: Priority, seconds: float):
        """Hold the device for ``seconds`` of compute; a preempted job queues for the rest.
        Returns the request that holds the device at the end."""
        left = seconds
        while True:
            start = self.env.now
            try:
                yield self.env.timeout(left)
                return request
            except simpy.Interrupt:  # preempted by a real-time job: queue for the rest
                left -= self.env.now - start
                request = yield from self._acquire(resource, self._request(resource, priority), priority)

    def _run(
        self, resource, request, waits: bool, queue: _StageQueue, record: JobRecord, work, on_done, priority: Priority, wait: bool, extra_stages
    ):
        try:
            request = yield from self._acquire(resource, request, priority)
            queue.waiting -= waits
            if self.halted:
                return
            record.started = self.env.now
            t0 = time.perf_counter()
            result = work()
            record.wall_s = time.perf_counter() - t0
            self.wall_s += record.wall_s
            record.compute_s = self.compute.cost(record.stage, record.wall_s) * self.slowdown
            request = yield from self._hold(resource, request, priority, record.compute_s)
            if isinstance(result, Future) and (wait or extra_stages is not None):
                result = self.resolve(result)
            if extra_stages is not None:
                extra = self.compute.extra_cost(extra_stages(result)) * self.slowdown
                if extra > 0:
                    record.compute_s += extra
                    request = yield from self._hold(resource, request, priority, extra)
            record.finished = self.env.now
            self.busy_s[record.device] += record.compute_s
            queue.done.append([record.submitted, record.started, record.finished, record.wall_s, record.compute_s])
        finally:
            resource.release(request)
            self._active[priority] -= 1
        if on_done is not None and not self.halted:
            on_done(result, self.env.now)

    def stats(self, sim_time_s: float) -> list[dict[str, Any]]:
        """One row per stage: jobs, drops, queueing delay, compute time, device utilisation."""
        rows = []
        for stage, queue in sorted(self._stages.items()):
            submitted, started, finished = (queue.column(c) for c in ("submitted", "started", "finished"))
            delays, latency = started - submitted, finished - submitted
            compute, wall = queue.column("compute_s"), queue.column("wall_s")
            rows.append(
                {
                    "robot": self.robot,
                    "stage": stage,
                    "device": queue.device,
                    "submitted": queue.submitted,
                    "completed": len(queue.done),
                    "dropped": queue.dropped,
                    "queue_delay_mean_s": float(delays.mean()) if delays.size else 0.0,
                    "queue_delay_p95_s": float(np.percentile(delays, 95)) if delays.size else 0.0,
                    "queue_delay_max_s": float(delays.max()) if delays.size else 0.0,
                    "latency_mean_s": float(latency.mean()) if latency.size else 0.0,
                    "compute_mean_s": float(compute.mean()) if compute.size else 0.0,
                    "wall_mean_s": float(wall.mean()) if wall.size else 0.0,
                }
            )
        return rows

    def utilization(self, sim_time_s: float) -> dict[str, float]:
        """Busy share of each device over the run (1.0 = all its units busy all the time)."""
        if sim_time_s <= 0:
            return {name: 0.0 for name in self.devices}
        return {name: self.busy_s[name] / (sim_time_s * self.capacity[name]) for name in self.devices}
