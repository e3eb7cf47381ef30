"""Command-line tool ``viotb`` (typer + rich).

Every command has ``--help``; ``--json`` prints one JSON object on stdout as the last line. Heavy modules
are imported inside each command so that ``viotb --help`` stays fast.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

app = typer.Typer(add_completion=False, no_args_is_help=True, help="vio-testbed: VIO in the loop.")
_err = Console(stderr=True)

ProgressFn = Callable[[float, float], None]
"""Progress callback ``(done, total)`` passed to long-running library functions."""


@contextmanager
def _progress(description: str, enabled: bool = True) -> Iterator[ProgressFn]:
    """A rich progress bar on stderr, yielded as a ``(done, total)`` callback."""
    if not enabled:
        yield lambda done, total: None
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeRemainingColumn(),
        console=_err,
        transient=True,
    ) as bar:
        task = bar.add_task(description, total=1.0)

        def update(done: float, total: float) -> None:
            bar.update(task, completed=done, total=max(total, 1e-9))

        yield update


def _emit(result: dict, as_json: bool, title: str) -> None:
    """Print a result as a table (human) or one JSON line (``--json``)."""
    if as_json:
        sys.stdout.write(json.dumps(result, default=float) + "\n")
        return
    console = Console()
    console.print(f"[bold]{title}[/bold]")
    for key, value in result.items():
        console.print(f"  {key:<24} {value}")


def _fail(message: str) -> None:
    """Print a clear error and exit with status 2."""
    _err.print(f"[red]error:[/red] {message}")
    raise typer.Exit(code=2)


@app.command()
def scenarios(as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout.")) -> None:
    """List the scenarios with one-line descriptions."""
    from viotb.envs.scenarios import list_scenarios

    items = list_scenarios()
    if as_json:
        _emit({"scenarios": items}, True, "")
        return
    console = Console()
    for item in items:
        console.print(f"[bold]{item['name']:<28}[/bold] [{item['kind']}] {item['description']}")


@app.command()
def record(
    scenario: str = typer.Argument(..., help="Scenario name (see `viotb scenarios`)."),
    out: Path = typer.Option(..., "--out", help="Output folder; a EuRoC ASL tree is written to OUT/mav0."),
    seed: int = typer.Option(0, "--seed", help="Random seed (IMU noise, pixel noise, drops)."),
    seconds: float | None = typer.Option(None, "--seconds", help="Duration (s); scenario default if unset."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Simulate a scenario open loop and write a EuRoC ASL dataset."""
    from viotb.envs.record import record_scenario

    if seconds is not None and seconds <= 0:
        _fail(f"--seconds must be positive, got {seconds}")
    try:
        with _progress(f"record {scenario}", not as_json) as progress:
            result = record_scenario(scenario, out, seed=seed, seconds=seconds, progress=progress)
    except (ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    _emit(result, as_json, f"recorded {scenario} -> {out}")


def main() -> None:
    """Entry point of the ``viotb`` console script."""
    app()


if __name__ == "__main__":
    main()
