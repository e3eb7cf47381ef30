"""``viotb sweep`` and ``viotb sweep-report``: :func:`register` adds them to the ``viotb`` app.

Only typer and rich are imported here; ray, pyarrow, pandas and the simulator load inside the commands, so
``viotb --help`` stays fast.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import typer
from rich.console import Console


def register(app: typer.Typer) -> None:
    """Add the ``sweep`` and ``sweep-report`` commands to ``app``."""
    app.command("sweep")(sweep)
    app.command("sweep-report")(sweep_report)


def sweep(
    spec: Path = typer.Argument(
        ...,
        help="Sweep spec (YAML): grid / random draws over scenario, mode "
        "(record-eval | fly), estimator, frontend, imu, severity, seconds, "
        "msckf.* / window.* / rig.* fields, and seeds; see examples/sweep-*.yaml.",
    ),
    out: Path = typer.Option(
        ...,
        "--out",
        help="Sweep folder: results.parquet, runs/ shards; resumed when it is a sweep folder already.",
    ),
    address: str | None = typer.Option(
        None,
        "--address",
        help="Join this Ray cluster (`ray start --head` "
        "prints it; 'auto' finds a local one). Default: a local instance.",
    ),
    workers: int | None = typer.Option(
        None,
        "--workers",
        min=1,
        help="Runs in flight (local: Ray's CPUs). Default: the CPU count, or the cluster's CPUs.",
    ),
    timeout: float | None = typer.Option(
        None, "--timeout", min=0.001, help="Per-run timeout (s); overrides the spec's timeout_s."
    ),
    retry_failed: bool = typer.Option(
        False, "--retry-failed", help="Run again the runs whose row has an error."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Empty --out first (start over)."),
    as_json: bool = typer.Option(
        False, "--json", help="Print JSON on stdout (runs, computed, skipped, failed, results)."
    ),
) -> None:
    """Monte-Carlo sweep as Ray tasks: one Parquet row per run, resumable (only missing runs are computed)."""
    from viotb.envs.tools.sweep.engine import SweepInterrupted, run_sweep
    from viotb.envs.tools.sweep.spec import SpecError, load_spec

    err = Console(stderr=True)
    try:
        parsed = load_spec(spec)
    except SpecError as exc:
        _fail(err, str(exc))
    try:
        with _Progress(err, parsed.name) as progress:
            result = run_sweep(
                parsed,
                out,
                workers,
                address,
                timeout_s=timeout,
                retry_failed=retry_failed,
                overwrite=overwrite,
                progress=progress,
            )
    except FileExistsError as exc:
        _fail(err, str(exc))
    except SweepInterrupted as stop:
        r = stop.result
        err.print(
            f"[yellow]interrupted[/yellow]: {r.runs - r.skipped - r.computed} runs left; the finished "
            f"rows are in {r.results} (run the same command again to resume)"
        )
        if as_json:
            sys.stdout.write(json.dumps(r.as_json()) + "\n")
        raise typer.Exit(130) from None
    if as_json:
        sys.stdout.write(json.dumps(result.as_json()) + "\n")
        return
    Console().print(
        f"[bold]sweep {parsed.name}[/bold]: {result.runs} runs, {result.computed} computed, "
        f"{result.skipped} skipped, {result.failed} failed, {result.wall_s:.1f} s -> {result.results}"
    )


def sweep_report(
    sweep_dir: Path = typer.Argument(..., help="A sweep folder (holding results.parquet)."),
    out: Path | None = typer.Option(None, "--out", help="Report folder (default SWEEP_DIR/report)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
) -> None:
    """Plots (ATE, drift, NEES against its chi-square band, timing) and a percentile table of a sweep."""
    from viotb.envs.tools.sweep.report import sweep_report as make_report

    err = Console(stderr=True)
    try:
        summary = make_report(sweep_dir, out)
    except FileNotFoundError as exc:
        _fail(err, str(exc))
    if as_json:
        sys.stdout.write(json.dumps(summary, allow_nan=False) + "\n")
        return
    console = Console()
    console.print(f"[bold]sweep report[/bold] {summary['rows']} rows, {summary['failed']} failed")
    for c in summary["configs"]:
        ate = c["stats"].get("ate_posyaw_m", {}).get("p50")
        nees = c.get("nees", {})
        line = f"  {c['label']:<40} runs {c['runs']:>4}  failed {c['failed']:>3}"
        if ate is not None:
            line += f"  ATE median {ate:.4f} m"
        if nees.get("n"):
            line += f"  ANEES {nees['anees']:.2f} [{nees['low']:.2f}, {nees['high']:.2f}]"
        console.print(line)
    console.print("  " + ", ".join(summary["plots"] + summary["tables"]))


def _fail(err: Console, message: str) -> None:
    err.print(f"[red]error:[/red] {message}")
    raise typer.Exit(code=2)


class _Progress:
    """Progress on stderr: a rich bar on a terminal, else a line every few seconds (and the last one)."""

    EVERY_S = 5.0

    def __init__(self, err: Console, name: str) -> None:
        self.err, self.name = err, name
        self.bar = None
        self.task = None
        self.last = 0.0

    def __enter__(self):
        if self.err.is_terminal:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"),
                TimeRemainingColumn(),
                console=self.err,
            )
            self.bar.__enter__()
            self.task = self.bar.add_task(f"sweep {self.name}", total=None, info="")
        return self

    def __call__(self, p) -> None:
        info = f"failed {p.failed}, running {p.running}, remaining {p.remaining}"
        if self.bar is not None:
            self.bar.update(self.task, completed=p.done, total=p.total, info=info)
            return
        now = time.monotonic()
        if now - self.last >= self.EVERY_S or p.remaining == 0:
            self.last = now
            self.err.print(f"sweep {self.name}: done {p.done}/{p.total}, {info}", highlight=False)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.__exit__(*exc)
