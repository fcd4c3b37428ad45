"""``marsyard`` command line: a thin shell over :mod:`sim.run.runner` and :mod:`sim.evaluation.results_folder`."""

from __future__ import annotations

import datetime
import importlib.metadata
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.traceback import Traceback
from typer.core import TyperCommand

from sim.scenario import Scenario, ScenarioError, dump_scenario, load_scenario

app = typer.Typer(add_completion=False, no_args_is_help=True, help="marsyard: multi-robot SLAM simulation testbed")
console = Console()
err_console = Console(stderr=True)

SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", help="override a scenario key: dotted.key=value (repeatable; robots by name: robots.lru1.route.speed_mps=0.4)"),
]


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"marsyard {importlib.metadata.version('marsyard')}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_print_version, is_eager=True, help="print the installed version and exit")
    ] = False,
) -> None:
    """Options before the command (``marsyard --version``)."""


def _load(scenario: Path, overrides: list[str]):
    try:
        return load_scenario(scenario, overrides)
    except ScenarioError as exc:
        err_console.print(f"[bold red]{escape(exc.source)}: invalid scenario[/]")
        for line in exc.problems:  # escaped: a problem quotes the user's text, whose [brackets] are no markup
            err_console.print(f"  [red]-[/] {escape(line)}")
        raise typer.Exit(2) from None


@app.command()
def validate(
    scenario: Annotated[Path, typer.Argument(help="scenario YAML")],
    set_: SetOption = None,
    show: Annotated[bool, typer.Option("--show", help="print the resolved scenario")] = False,
) -> None:
    """Check a scenario and say what is wrong with it, key by key."""
    sc = _load(scenario, set_ or [])
    if show:
        console.print(dump_scenario(sc), markup=False)
    robots = ", ".join(f"{r.name} ({r.preset})" for r in sc.robots)
    console.print(f"[green]ok[/]: {scenario} - {sc.name}, seed {sc.seed}, {sc.duration_s:g} s, robots: {robots}")


class _RichRunProgress:
    """``marsyard run``'s view of a run: a spinner while building, then a progress bar."""

    def __init__(self, show_bar: bool):
        self.show_bar = show_bar

    @contextmanager
    def building(self, sc: Scenario):
        with console.status(f"building world for {sc.name} (seed {sc.seed})"):
            yield

    @contextmanager
    def simulating(self, sc: Scenario):
        wall_start = time.perf_counter()
        with Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.completed:.1f}/{task.total:.0f} s sim"),
            TextColumn("RTF {task.fields[rtf]}"),
            TimeElapsedColumn(),
            TextColumn("{task.fields[robots]}"),
            console=console,
            disable=not self.show_bar,
            transient=False,
        ) as bar:
            task = bar.add_task(sc.name, total=sc.duration_s, rtf="-", robots="")

            def report(t: float, statuses: dict[str, str]) -> None:
                wall = time.perf_counter() - wall_start
                rtf = f"{t / wall:.2f}" if wall > 0 else "-"
                robots = "  ".join(f"{name}: {state}" for name, state in statuses.items())
                bar.update(task, completed=min(t, sc.duration_s), rtf=rtf, robots=robots)

            yield report


@app.command()
def run(
    scenario: Annotated[Path, typer.Argument(help="scenario YAML")],
    out: Annotated[Path | None, typer.Option("--out", help="results folder (default results/<name>-seed<seed>)")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="override the scenario's seed")] = None,
    set_: SetOption = None,
    progress: Annotated[bool, typer.Option(help="show the progress bar")] = True,
) -> None:
    """Run a scenario and write its results folder."""
    from sim.evaluation import results_folder
    from sim.run.run_folder import RunSetupError, run_to_folder

    overrides = list(set_ or []) + ([f"seed={seed}"] if seed is not None else [])
    sc = _load(scenario, overrides)
    out = out or Path("results") / f"{sc.name}-seed{sc.seed}"
    try:
        metrics = run_to_folder(sc, out, _RichRunProgress(progress))
    except RunSetupError as exc:
        cause = exc.__cause__
        err_console.print(Traceback.from_exception(type(cause), cause, cause.__traceback__))
        err_console.print(f"[red]could not set up the run; traceback in {exc.error_file}[/]")
        raise typer.Exit(1) from None
    failed = metrics["status"] == "failed"
    for line in results_folder.summary_lines(metrics):
        console.print(line)
    if failed:
        err_console.print(f"[bold red]run failed[/]: {metrics['error']} (traceback in {out / 'error.txt'}; partial results kept)")
    files = "metrics.json, topdown.png, filter_error.png, slam.png, map_topdown.png, maps/, trajectories/, lanes.csv"
    console.print(f"\nresults in [bold]{out}/[/]: {files}")
    if sc.output.recording:
        console.print(f"look at the run: open {out / 'topdown.png'}; replay it with `rerun {out / 'recording.rrd'}`")
    if failed:
        raise typer.Exit(1)


def _load_batch(batch_file: Path, overrides: list[str], seeds: int | None):
    from sim.batch.spec import BatchError, check, load_batch

    try:
        batch = load_batch(batch_file, overrides, seeds)
    except BatchError as exc:
        err_console.print(f"[bold red]{escape(exc.source)}: invalid batch file[/]")
        for line in exc.problems:
            err_console.print(f"  [red]-[/] {escape(line)}")
        raise typer.Exit(2) from None
    failing = check(batch)
    for problem in failing:
        err_console.print(f"[bold red]variant {problem.variant}: invalid scenario[/]" + (f" (robots {problem.robots})" if problem.robots else ""))
        err_console.print(f"  overrides: {' '.join(problem.overrides)}", markup=False, highlight=False)
        for line in problem.problems:
            err_console.print(f"  [red]-[/] {escape(line)}")
    if failing:
        err_console.print(f"[bold red]{len(failing)} of {len(batch.variants)} variants invalid; nothing was run[/]")
        raise typer.Exit(2)
    return batch


class _BatchCommand(TyperCommand):
    """``--ray`` takes an optional ADDRESS: a bare ``--ray`` (not followed by ``auto``,
    ``host:port`` or ``ray://...``) means a local Ray started for the batch."""

    def parse_args(self, ctx, args: list[str]) -> list[str]:
        args = list(args)
        for i in [i for i, a in enumerate(args) if a == "--ray"][::-1]:
            following = args[i + 1] if i + 1 < len(args) else ""
            if not (following == "auto" or ":" in following):
                args.insert(i + 1, "local")
        return super().parse_args(ctx, args)


@app.command(cls=_BatchCommand)
def batch(
    batch_file: Annotated[Path, typer.Argument(help="batch YAML (see sim/batch/spec.py)")],
    out: Annotated[Path | None, typer.Option("--out", help="batch folder (default results/batches/<name>)")] = None,
    workers: Annotated[
        int | None, typer.Option("--workers", min=1, help="runs at a time (default: CPU count; with --ray ADDRESS: the cluster's CPUs)")
    ] = None,
    ray: Annotated[
        str | None,
        typer.Option(
            "--ray", metavar="[ADDRESS]", help="run as Ray tasks: on a local Ray, or on the cluster at ADDRESS (auto, host:port, ray://host:port)"
        ),
    ] = None,
    resume: Annotated[bool, typer.Option("--resume", help="skip runs the index already has an outcome for")] = False,
    retry_failed: Annotated[bool, typer.Option("--retry-failed", help="resume, and run failed, crashed and timed-out runs again")] = False,
    check_only: Annotated[bool, typer.Option("--check", help="only validate every variant's scenario")] = False,
    set_: SetOption = None,
    seeds: Annotated[int | None, typer.Option("--seeds", min=1, help="only the first N seeds")] = None,
) -> None:
    """Run a Monte-Carlo batch (seeds x variants), then write its tables, plots and report."""
    from rich.progress import MofNCompleteColumn, SpinnerColumn

    from sim.batch import execute, report

    spec = _load_batch(batch_file, set_ or [], seeds)
    runs = spec.specs()
    if check_only:
        console.print(f"[green]ok[/]: {batch_file} - {len(spec.variants)} variants x {len(spec.config.seed_list())} seeds = {len(runs)} runs")
        for v in spec.variants:
            console.print(
                f"  {v.name}: {' '.join(v.overrides) or '(base scenario)'}" + (f" robots {list(v.robots)}" if v.robots else ""),
                markup=False,
                highlight=False,
            )
        return
    out = out or Path("results") / "batches" / spec.config.name
    index, todo = execute.plan(spec, out, resume, retry_failed)
    where = "local process pool" if ray is None else "local Ray" if ray == "local" else f"Ray cluster {ray}"
    console.print(f"{spec.config.name}: {len(runs)} runs, {len(todo)} to do ({where}) -> {out}/")
    counts = {"completed": 0, "not completed": 0}
    started = time.monotonic()
    with Progress(
        SpinnerColumn(),
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[counts]}"),
        TimeElapsedColumn(),
        TextColumn("ETA {task.fields[eta]}"),
        console=console,
    ) as bar:
        task = bar.add_task(spec.config.name, total=len(runs), completed=len(runs) - len(todo), counts="", eta="-")

        def finished(run: execute.RunSpec, outcome: execute.Outcome) -> None:
            ok = outcome.status == "completed"
            counts["completed" if ok else "not completed"] += 1
            mark = "[green]ok[/]" if ok else f"[red]{outcome.status}[/]"
            bar.console.print(f"{mark} {run.id} ({outcome.wall_s or 0:.0f} s)" + ("" if ok else f": {outcome.error}"))
            done = sum(counts.values())  # ETA: this session's wall time per finished run, all workers together
            eta = datetime.timedelta(seconds=round((time.monotonic() - started) / done * (len(todo) - done)))
            bar.update(task, advance=1, counts=f"{counts['completed']} ok, {counts['not completed']} not", eta=eta)

        try:
            execute.execute(
                index, todo, workers=workers, use_ray=ray is not None, ray_address=None if ray in (None, "local") else ray, on_finish=finished
            )
        except KeyboardInterrupt:
            bar.stop()
            err_console.print(f"[bold red]interrupted[/]: runs in progress are pending again; continue with `marsyard batch {batch_file} --resume`")
            raise typer.Exit(130) from None
    report_path = report.write_report(out)
    statuses = [r["status"] for r in index.runs.values()]
    console.print(f"{statuses.count('completed')}/{len(statuses)} runs completed; index {out / execute.INDEX}; report {report_path}")
    if statuses.count("completed") < len(statuses):
        raise typer.Exit(1)


@app.command("marker-lut")
def marker_lut(
    scenario: Annotated[Path, typer.Argument(help="scenario YAML: its robots' cameras and marker sizes")],
    force: Annotated[bool, typer.Option("--force", help="rebuild tables that exist")] = False,
    distances: Annotated[int, typer.Option("--distances", min=3, help="grid size in distance")] = 30,
    angles: Annotated[int, typer.Option("--angles", min=3, help="grid size in view angle")] = 23,
) -> None:
    """Build the marker error lookup tables (thesis 6.2.3) a scenario needs, under assets/marker_lut/."""
    from sim.tools import marker_lut as ml

    sc = _load(scenario, [])
    t0 = time.perf_counter()
    written = ml.build_for_scenario(sc, force, distances, angles, log=console.print)
    console.print(f"{len(written)} table(s) written to {ml.LUT_DIR} in {time.perf_counter() - t0:.0f} s")


@app.command()
def report(
    batch_dir: Annotated[Path, typer.Argument(help="a batch folder (holds index.json)")],
    metric: Annotated[list[str] | None, typer.Option("--metric", help="metric to summarise and plot (repeatable; default: the batch file's)")] = None,
) -> None:
    """Regenerate a batch's tables, plots and report.md from its run folders."""
    from sim.batch import report

    try:
        path = report.write_report(batch_dir, metric or None)
    except FileNotFoundError as exc:
        err_console.print(f"[red]{exc}[/]")
        raise typer.Exit(2) from None
    console.print(f"report: {path}")


@app.command()
def regress(
    update: Annotated[bool, typer.Option("--update", help="write the baselines from this run (on purpose: commit them with the change)")] = False,
    only: Annotated[list[str] | None, typer.Option("--only", help="canonical scenario name (repeatable; default: all)")] = None,
    baselines: Annotated[
        Path | None, typer.Option("--baselines", help="folder with regress.yaml and the baselines (default results/baselines)")
    ] = None,
    out: Annotated[Path, typer.Option("--out", help="where the runs go")] = Path("results/regress"),
    workers: Annotated[int, typer.Option("--workers", min=1, help="runs at a time")] = 2,
) -> None:
    """Run the canonical scenarios and compare tracked metrics with the committed baselines (exit 1 if worse)."""
    from rich.table import Table

    from sim.batch import regress as rg

    directory = baselines or rg.BASELINES
    try:
        config = rg.load_config(directory)
        names = rg.select(config, only)
    except rg.RegressError as exc:
        err_console.print(f"[red]{exc}[/]")
        raise typer.Exit(2) from None
    have = [n for n in names if (directory / f"{n}.json").is_file()]
    if not update and len(have) < len(names):
        missing = [n for n in names if n not in have]
        err_console.print(f"[red]no baseline for {missing} in {directory}; write one with `marsyard regress --update --only NAME`[/]")
        raise typer.Exit(2)
    with console.status(f"running {', '.join(names)} into {out}/"):
        outcomes = rg.run(config, names, out, workers)
    for run_id, outcome in outcomes.items():
        console.print(f"{run_id}: {outcome.status} ({outcome.wall_s or 0:.0f} s)" + (f": {outcome.error}" if outcome.error else ""))
    checks = rg.evaluate(config, directory, have, out)
    shown = [c for c in checks if c.verdict != "ok"]
    if shown:
        table = Table(title="tracked metrics off their baselines (limit: max(relative x baseline, absolute))")
        for column in ("scenario", "seed", "metric", "baseline", "current", "change", "limit", "verdict"):
            table.add_column(column, no_wrap=column in ("scenario", "metric"))
        style = {"worse": "red", "missing": "red", "failed": "red", "better": "green", "new": "cyan"}
        for c in shown:
            change = f"{c.current - c.baseline:+.4g}" if isinstance(c.current, float | int) and c.baseline is not None else ""
            table.add_row(
                c.name, str(c.seed), c.metric, _num(c.baseline), _num(c.current), change, _num(c.limit), f"[{style[c.verdict]}]{c.verdict}[/]"
            )
        (console if console.is_terminal else Console(width=160)).print(table)  # logs: metric names unwrapped
    verdicts = [c.verdict for c in checks]
    console.print(
        ", ".join(f"{verdicts.count(v)} {v}" for v in ("ok", "better", "new", "worse", "missing", "failed") if verdicts.count(v))
        or "nothing compared"
    )
    if update:
        try:
            for path in rg.update(config, directory, names, out):
                console.print(f"wrote baseline {path}")
        except rg.RegressError as exc:
            err_console.print(f"[red]{exc}[/]")
            raise typer.Exit(1) from None
    elif any(c.failing for c in checks):
        err_console.print("[bold red]regression[/]: tracked metrics worse than their baselines allow (table above)")
        raise typer.Exit(1)


def _num(value) -> str:
    if value is None:
        return "-"
    return f"{value:.4g}" if isinstance(value, float | int) else str(value)


if __name__ == "__main__":
    app()
