"""Run one scenario into its results folder: what ``marsyard run`` and every batch run share.

:func:`run_to_folder` builds the run, executes it and writes the folder of
:mod:`sim.evaluation.results_folder`; a failure during the simulation still writes everything produced so
far (``metrics.json`` says ``status: failed``). A failure while setting the run up
raises :class:`RunSetupError` after writing the traceback to ``error.txt``. With
``output.dataset: euroc`` the run writes its robots' sensor data into ``dataset/``
(:mod:`sim.run.dataset`) as it goes; its files are closed when the run ends, failed or not.
"""

from __future__ import annotations

import traceback
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any, Protocol

from sim.evaluation import results_folder
from sim.run.dataset import DATASET_FOLDER, EurocDataset
from sim.run.recording import Recorder
from sim.run.runner import ProgressCallback, Run
from sim.scenario import Scenario


class RunSetupError(RuntimeError):
    """The run could not be set up; ``__cause__`` is the original exception, its traceback is in ``error_file``."""

    def __init__(self, error_file: Path, cause: BaseException):
        self.error_file = error_file
        super().__init__(f"{type(cause).__name__}: {cause}")


class RunProgress(Protocol):
    """How a caller watches a run: a context around building it, one around simulating
    it that yields the callback :meth:`sim.run.runner.Run.execute` reports to."""

    def building(self, scenario: Scenario) -> AbstractContextManager[None]: ...

    def simulating(self, scenario: Scenario) -> AbstractContextManager[ProgressCallback | None]: ...


def run_to_folder(scenario: Scenario, out: Path, progress: RunProgress | None = None, image_workers: int | None = None) -> dict[str, Any]:
    """Run ``scenario`` and write its results folder ``out``; return the metrics dict. ``image_workers``:
    the run's image pipeline threads (``sim.run.runner.Run``; None: its default)."""
    results_folder.prepare(out, scenario)
    recorder = (
        Recorder(out / "recording.rrd", f"{scenario.name}-seed{scenario.seed}", scenario.output.recording_image_scale)
        if scenario.output.recording
        else None
    )
    dataset = EurocDataset(out / DATASET_FOLDER) if scenario.output.dataset == "euroc" else None
    with progress.building(scenario) if progress else nullcontext():
        try:
            simulation = Run(scenario, recorder, dataset, image_workers=image_workers)
        except Exception as exc:
            (out / "error.txt").write_text(traceback.format_exc())
            if recorder is not None:
                recorder.close()
            if dataset is not None:
                dataset.close()
            raise RunSetupError(out / "error.txt", exc) from exc
    error = None
    with progress.simulating(scenario) if progress else nullcontext(None) as report:
        try:
            simulation.execute(progress=report)
        except KeyboardInterrupt:
            error = "KeyboardInterrupt: run interrupted by the user\n"
        except Exception:
            error = traceback.format_exc()
    try:
        if recorder is not None:
            recorder.log_link_series(simulation.network.timeseries())
        return results_folder.write(simulation, out, error, recorder)
    finally:
        if recorder is not None:
            recorder.close()
