"""Executing a batch: every run in its own process, on a local pool or on Ray.

The batch folder::

    index.json                  the batch and one entry per run: status, error, wall time, folder
    runs/<variant>/seed<n>/     an ordinary run folder (see :mod:`sim.evaluation.results_folder`), plus
                                worker.log: what the run's process printed

``index.json`` is rewritten after every run, so an interrupted batch loses nothing;
``resume`` skips every run the index already has an outcome for (and whose inputs did not
change, and, if it completed, whose ``metrics.json`` is still there), ``retry_failed`` runs failed, crashed and timed-out ones again.

Run statuses: ``completed``; ``failed`` (the simulation raised, or could not be set up;
what it produced is kept and ``error`` says why); ``crashed`` (the worker process died);
``timeout`` (killed after the batch's ``timeout_s``); ``pending`` (not run yet, or
interrupted).

Local pool: a ``forkserver`` that has imported the simulator and loaded its compiled kernels
once (:mod:`sim.batch.preload`) forks one fresh process per run (MuJoCo's GL contexts stay
per process), at most ``workers`` at a time.
Ray: the same function as a task with ``max_calls=1`` (a fresh worker process per run),
in a temporary folder on the worker; the folder comes back as a tar archive through the
object store, so a cluster needs no shared file system. A cluster's nodes need
marsyard's dependencies installed; this checkout's ``sim``, ``slam`` and ``comms``
travel with the job (Ray ``runtime_env`` ``py_modules``).
"""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import shutil
import signal
import tarfile
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

from sim.batch.provenance import command_line, git_state
from sim.batch.spec import Batch, RunSpec, scenario_dict

FINAL = ("completed", "failed", "crashed", "timeout")
RETRYABLE = ("failed", "crashed", "timeout")
INDEX = "index.json"


@dataclass
class Outcome:
    """What became of one run."""

    status: str
    error: str | None = None
    wall_s: float | None = None


def run_spec(spec: RunSpec, folder: Path, image_workers: int | None = None) -> Outcome:
    """Run one spec into ``folder``: load its scenario, run it, say how it went. ``image_workers``:
    the run's image pipeline threads (``sim.run.runner.Run``; None: its default)."""
    from sim.run.run_folder import RunSetupError, run_to_folder
    from sim.scenario import load_scenario

    t0 = time.perf_counter()
    try:
        scenario = load_scenario(scenario_dict(spec.raw, spec.robots), spec.overrides, spec.base_dir)
        metrics = run_to_folder(scenario, folder, image_workers=image_workers)
        outcome = Outcome(metrics["status"], metrics["error"])
    except RunSetupError as exc:
        outcome = Outcome("failed", f"setup: {exc}")
    except Exception as exc:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "error.txt").write_text(traceback.format_exc())
        outcome = Outcome("failed", f"{type(exc).__name__}: {exc}")
    outcome.wall_s = time.perf_counter() - t0
    return outcome


# --------------------------------------------------------------------------- index


def now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def read_index(batch_dir: Path) -> dict[str, Any]:
    path = Path(batch_dir) / INDEX
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no batch index here")
    return json.loads(path.read_text())


class Index:
    """The batch's ``index.json``: written whole (to a temporary file, then renamed) after every change."""

    def __init__(self, batch: Batch, out: Path, specs: list[RunSpec], previous: dict[str, Any] | None):
        self.path = out / INDEX
        old = {r["id"]: r for r in (previous or {}).get("runs", [])}
        self.header = {
            "batch": batch.config.name,
            "description": batch.config.description,
            "batch_file": str(batch.source.resolve()),
            "scenario": str(batch.scenario_path),
            "config": batch.config.model_dump(mode="json"),
            "extra_overrides": batch.extra,
            "variants": [v.name for v in batch.variants],
            "baseline": batch.baseline,
            "comparisons": [list(pair) for pair in batch.comparisons],
            "params": sorted({k for v in batch.variants for k in v.params}),
            "created": (previous or {}).get("created", now()),
            # every command that ran (part of) the batch, with the commit of its code (sim.batch.provenance)
            "invocations": [*(previous or {}).get("invocations", []), {"started": now(), "command": command_line(), **git_state()}],
        }
        self.runs: dict[str, dict[str, Any]] = {}
        for spec in specs:
            entry = {
                "id": spec.id,
                "variant": spec.variant,
                "seed": spec.seed,
                "params": next(v.params for v in batch.variants if v.name == spec.variant),
                "robots": spec.robots,
                "overrides": spec.overrides,
                "digest": spec.digest(),
                "folder": spec.folder,
                "status": "pending",
                "error": None,
                "wall_s": None,
                "started": None,
                "finished": None,
                "git_commit": None,
                "git_dirty": None,
            }
            before = old.get(spec.id)
            if before is not None and before.get("digest") == entry["digest"] and before.get("status") in FINAL and _outcome_kept(out, before):
                entry.update({k: before.get(k) for k in ("status", "error", "wall_s", "started", "finished", "git_commit", "git_dirty")})
            self.runs[spec.id] = entry

    def write(self) -> None:
        data = {**self.header, "updated": now(), "runs": list(self.runs.values())}
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data, indent=1, default=str))
        tmp.replace(self.path)

    def start(self, spec: RunSpec) -> None:
        self.runs[spec.id].update(status="running", started=now(), finished=None, error=None, wall_s=None)
        self.write()

    def finish(self, spec: RunSpec, outcome: Outcome) -> None:
        code = {k: self.header["invocations"][-1][k] for k in ("git_commit", "git_dirty")}
        self.runs[spec.id].update(status=outcome.status, error=outcome.error, wall_s=outcome.wall_s, finished=now(), **code)
        self.write()

    def interrupt(self, spec: RunSpec) -> None:
        self.runs[spec.id].update(status="pending", started=None)
        self.write()


def _outcome_kept(out: Path, run: dict[str, Any]) -> bool:
    """Whether a finished run's results are still there to report: a completed run whose
    ``metrics.json`` is gone (a fresh clone keeps only the committed ones) runs again."""
    return run.get("status") != "completed" or (out / run["folder"] / "metrics.json").is_file()


# --------------------------------------------------------------------------- executors

#: ``on_start(spec)``, ``on_finish(spec, outcome)``: how an executor reports back.
StartHook = Callable[[RunSpec], None]
FinishHook = Callable[[RunSpec, Outcome], None]


def _child(spec: RunSpec, folder: str, conn, image_workers: int | None) -> None:
    try:
        _log_to(Path(folder))
        outcome = run_spec(spec, Path(folder), image_workers)
    except BaseException as exc:  # KeyboardInterrupt included: the parent decides what it means
        outcome = Outcome("crashed", f"{type(exc).__name__}: {exc}")
    conn.send(asdict(outcome))
    conn.close()


def _collect(process, receive, elapsed: float) -> Outcome:
    """The outcome a finished child sent, or ``crashed`` if it died without one."""
    try:
        outcome = Outcome(**receive.recv()) if receive.poll() else None
    except EOFError:
        outcome = None
    process.join()
    return outcome or Outcome("crashed", f"worker process died (exit code {process.exitcode})", elapsed)


def _log_to(folder: Path) -> None:
    """Send this process's stdout and stderr to ``folder/worker.log``."""
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / "worker.log").open("w") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)


def run_local(specs: list[RunSpec], out: Path, workers: int, on_start: StartHook, on_finish: FinishHook) -> None:
    """At most ``workers`` runs at a time, each in a fresh process forked from a server
    that has imported the simulator; a run past its timeout is killed."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["sim.batch.execute", "sim.batch.preload"])
    # runs that fill the cores form their images inline: the image thread only pays where a core is spare
    # (two workers on two cores: 552 and 564 runs/h inline against 462 and 520 threaded, sim/tools/batch_bench.py)
    image_workers = 0 if workers >= (os.cpu_count() or 1) else None
    queue = list(reversed(specs))
    running: dict[Any, tuple[Any, Any, RunSpec, float]] = {}  # process sentinel -> (process, connection, spec, start)
    try:
        while queue or running:
            while queue and len(running) < workers:
                spec = queue.pop()
                receive, send = ctx.Pipe(duplex=False)
                args = (spec, str(out / spec.folder), send, image_workers)
                process = ctx.Process(target=_child, args=args, name=f"marsyard {spec.id}", daemon=True)
                on_start(spec)
                process.start()
                send.close()
                running[process.sentinel] = (process, receive, spec, time.monotonic())
            deadlines = [start + spec.timeout_s for _, _, spec, start in running.values() if spec.timeout_s]
            timeout = max(0.05, min(deadlines) - time.monotonic()) if deadlines else None
            wait([r for _, r, _, _ in running.values()] + list(running), timeout=timeout)
            for sentinel, (process, receive, spec, start) in list(running.items()):
                outcome = None
                if receive.poll() or not process.is_alive():
                    outcome = _collect(process, receive, time.monotonic() - start)
                elif spec.timeout_s and time.monotonic() - start > spec.timeout_s:
                    process.kill()
                    process.join()
                    outcome = Outcome("timeout", f"killed after the batch's timeout_s={spec.timeout_s:g}", time.monotonic() - start)
                if outcome is not None:
                    receive.close()
                    del running[sentinel]
                    on_finish(spec, outcome)
    finally:
        for process, receive, _, _ in running.values():
            process.kill()
            process.join()
            receive.close()


def _ray_task(spec: RunSpec) -> tuple[dict[str, Any], bytes]:
    """A Ray task: the run in a temporary folder, returned as an uncompressed tar."""
    with tempfile.TemporaryDirectory(prefix="marsyard-") as tmp:
        folder = Path(tmp) / "run"
        _log_to(folder)
        outcome = run_spec(spec, folder, image_workers=0)  # one CPU per task: images inline
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as tar:
            if folder.exists():
                tar.add(folder, arcname=".")
        return asdict(outcome), buffer.getvalue()


def run_ray(specs: list[RunSpec], out: Path, workers: int | None, address: str | None, on_start: StartHook, on_finish: FinishHook) -> None:
    """The runs as Ray tasks: on a local Ray with ``workers`` CPUs (``address`` None), or
    on the cluster at ``address`` (its CPUs, or ``workers`` tasks at a time)."""
    import ray

    import comms
    import sim
    import slam

    if address is None:
        ray.init(num_cpus=workers or os.cpu_count(), include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    else:  # the cluster's workers get this checkout's packages
        ray.init(address=address, logging_level="ERROR", log_to_driver=False, runtime_env={"py_modules": [sim, slam, comms]})
    try:
        capacity = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        task = ray.remote(num_cpus=1, max_calls=1, max_retries=0)(_ray_task)
        queue = list(reversed(specs))
        running: dict[Any, tuple[RunSpec, float]] = {}
        while queue or running:
            while queue and len(running) < capacity:
                spec = queue.pop()
                on_start(spec)
                running[task.remote(spec)] = (spec, time.monotonic())
            deadlines = [start + spec.timeout_s for spec, start in running.values() if spec.timeout_s]
            timeout = max(0.05, min(deadlines) - time.monotonic()) if deadlines else None
            done, _ = ray.wait(list(running), num_returns=1, timeout=timeout)
            for ref in done:
                spec, start = running.pop(ref)
                try:
                    result, archive = ray.get(ref)
                    outcome = Outcome(**result)
                    _unpack(archive, out / spec.folder)
                except Exception as exc:
                    outcome = Outcome(
                        "crashed", f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}", time.monotonic() - start
                    )
                on_finish(spec, outcome)
            for ref, (spec, start) in list(running.items()):
                if spec.timeout_s and time.monotonic() - start > spec.timeout_s:
                    ray.cancel(ref, force=True)
                    del running[ref]
                    on_finish(spec, Outcome("timeout", f"cancelled after the batch's timeout_s={spec.timeout_s:g}", time.monotonic() - start))
    finally:
        ray.shutdown()


def _unpack(archive: bytes, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r") as tar:
        tar.extractall(folder, filter="data")


# --------------------------------------------------------------------------- the batch


def plan(batch: Batch, out: Path, resume: bool = False, retry_failed: bool = False) -> tuple[Index, list[RunSpec]]:
    """The batch's index in ``out`` (carried over from an earlier one when resuming) and
    the runs still to do: all of them without ``resume``."""
    out.mkdir(parents=True, exist_ok=True)
    previous = read_index(out) if (resume or retry_failed) and (out / INDEX).is_file() else None
    specs = batch.specs()
    index = Index(batch, out, specs, previous)
    index.write()
    status = {s.id: index.runs[s.id]["status"] for s in specs}
    return index, [s for s in specs if status[s.id] not in FINAL or (retry_failed and status[s.id] in RETRYABLE)]


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM (``kill``, a cluster's scheduler) interrupts like Ctrl-C: the workers are
    ended and the runs in progress go back to ``pending``. Only the main thread can take signals."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def execute(
    index: Index,
    todo: list[RunSpec],
    *,
    workers: int | None = None,
    use_ray: bool = False,
    ray_address: str | None = None,
    on_start: StartHook | None = None,
    on_finish: FinishHook | None = None,
) -> Index:
    """Run ``todo`` into the index's batch folder (each run's folder cleared first); return the index."""
    out = index.path.parent

    def start(spec: RunSpec) -> None:
        shutil.rmtree(out / spec.folder, ignore_errors=True)
        index.start(spec)
        if on_start:
            on_start(spec)

    def finish(spec: RunSpec, outcome: Outcome) -> None:
        index.finish(spec, outcome)
        if on_finish:
            on_finish(spec, outcome)

    try:
        with _sigterm_as_interrupt():
            if use_ray:
                run_ray(todo, out, workers, ray_address, start, finish)
            else:
                run_local(todo, out, workers or os.cpu_count() or 1, start, finish)
    finally:  # an interrupted batch: what was running goes back to pending
        for spec in todo:
            if index.runs[spec.id]["status"] == "running":
                index.interrupt(spec)
    return index
