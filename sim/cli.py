"""``marsyard`` command line: a thin shell over :mod:`sim.runner` and :mod:`sim.results`."""

from __future__ import annotations

import time
import traceback
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from sim.scenario import ScenarioError, dump_scenario, load_scenario

app = typer.Typer(add_completion=False, no_args_is_help=True, help="marsyard: multi-robot SLAM simulation testbed")
console = Console()
err_console = Console(stderr=True)

SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", help="override a scenario key: dotted.key=value (repeatable; robots by name: robots.lru1.route.speed_mps=0.4)"),
]


def _load(scenario: Path, overrides: list[str]):
    try:
        return load_scenario(scenario, overrides)
    except ScenarioError as exc:
        err_console.print(f"[bold red]{exc.source}: invalid scenario[/]")
        for line in exc.problems:
            err_console.print(f"  [red]-[/] {line}")
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


@app.command()
def run(
    scenario: Annotated[Path, typer.Argument(help="scenario YAML")],
    out: Annotated[Path | None, typer.Option("--out", help="results folder (default results/<name>-seed<seed>)")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="override the scenario's seed")] = None,
    set_: SetOption = None,
    progress: Annotated[bool, typer.Option(help="show the progress bar")] = True,
) -> None:
    """Run a scenario and write its results folder."""
    from sim import results
    from sim.recording import Recorder
    from sim.runner import Run

    overrides = list(set_ or []) + ([f"seed={seed}"] if seed is not None else [])
    sc = _load(scenario, overrides)
    out = out or Path("results") / f"{sc.name}-seed{sc.seed}"
    results.prepare(out, sc)
    recorder = Recorder(out / "recording.rrd", f"{sc.name}-seed{sc.seed}", sc.output.recording_image_scale) if sc.output.recording else None
    with console.status(f"building world for {sc.name} (seed {sc.seed})"):
        try:
            simulation = Run(sc, recorder)
        except Exception:
            (out / "error.txt").write_text(traceback.format_exc())
            if recorder is not None:
                recorder.close()
            err_console.print_exception()
            err_console.print(f"[red]could not set up the run; traceback in {out / 'error.txt'}[/]")
            raise typer.Exit(1) from None

    error = None
    wall_start = time.perf_counter()
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.1f}/{task.total:.0f} s sim"),
        TextColumn("RTF {task.fields[rtf]}"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[robots]}"),
        console=console,
        disable=not progress,
        transient=False,
    ) as bar:
        task = bar.add_task(sc.name, total=sc.duration_s, rtf="-", robots="")

        def report(t: float, statuses: dict[str, str]) -> None:
            wall = time.perf_counter() - wall_start
            rtf = f"{t / wall:.2f}" if wall > 0 else "-"
            robots = "  ".join(f"{name}: {state}" for name, state in statuses.items())
            bar.update(task, completed=min(t, sc.duration_s), rtf=rtf, robots=robots)

        try:
            simulation.execute(progress=report)
        except KeyboardInterrupt:
            error = "KeyboardInterrupt: run interrupted by the user\n"
        except Exception:
            error = traceback.format_exc()
    try:
        if recorder is not None:
            recorder.log_link_series(simulation.network.timeseries())
        metrics = results.write(simulation, out, error, recorder)
    finally:
        if recorder is not None:
            recorder.close()
    for line in results.summary_lines(metrics):
        console.print(line)
    if error:
        err_console.print(f"[bold red]run failed[/]: {metrics['error']} (traceback in {out / 'error.txt'}; partial results kept)")
    console.print(f"\nresults in [bold]{out}/[/]: metrics.json, topdown.png, filter_error.png, map_topdown.png, maps/, trajectories/, lanes.csv")
    if recorder is not None:
        console.print(f"look at the run: open {out / 'topdown.png'}; replay it with `rerun {out / 'recording.rrd'}`")
    if error:
        raise typer.Exit(1)


if __name__ == "__main__":
    app()
