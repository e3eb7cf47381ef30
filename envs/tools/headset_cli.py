"""``viotb headset``: :func:`register` adds it to the ``viotb`` app.

Only typer and rich are imported here; the simulator loads inside the command, so ``viotb --help`` stays
fast. ``--out`` is checked before any work (a non-empty folder is refused unless ``--overwrite``) and the
outputs are written into a sibling ``.partial`` folder renamed into place at the end, so an interrupted run
leaves nothing that looks complete.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import typer
from rich.console import Console

_err = Console(stderr=True)


def register(app: typer.Typer) -> None:
    """Add the ``headset`` command to ``app``."""
    app.command("headset")(headset)


def _fail(message: str) -> None:
    _err.print(f"[red]error:[/red] {message}")
    raise typer.Exit(code=2)


def headset(
    scenario: str = typer.Argument(
        ...,
        help="Headset scenario: headset-still | headset-look-around | headset-fast-turns | headset-walk | "
        "headset-crouch | headset-blank-wall | headset-dark-room (or head-*; see `viotb scenarios`).",
    ),
    estimator: str = typer.Option("msckf", "--estimator", help="msckf | window | imu-only | ground-truth."),
    cameras: int = typer.Option(
        1, "--cameras", min=1, max=2, help="1 (head_cam0, default) | 2 (stereo head_cam0 + head_cam1)."
    ),
    latency_ms: float = typer.Option(20.0, "--latency-ms", min=0.0, max=200.0, help="Display latency (ms)."),
    seconds: float | None = typer.Option(
        None, "--seconds", min=0.001, help="Duration (s); default: scenario's."
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed (IMU, pixel noise, drops)."),
    frontend: str = typer.Option("klt", "--frontend", help="klt (images) | sim (projected landmarks, fast)."),
    out: Path = typer.Option(
        ..., "--out", help="Output folder: TUM files, metrics.json, plots, headset.rrd."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty --out."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    """Headset rig, estimator online: pose at IMU rate, prediction to display time, headset metrics."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        _fail(f"--out {out} exists and is not empty (use --overwrite)")
    from viotb.envs.run.headset import HeadsetOptions, headset_result, run_headset
    from viotb.envs.tools.headset_viz import write_headset_outputs

    opts = HeadsetOptions(
        estimator=estimator,
        cameras=cameras,
        latency_s=latency_ms * 1e-3,
        seconds=seconds,
        seed=seed,
        frontend=frontend,
    )
    partial = out.with_name(out.name + ".partial")
    try:
        with Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TimeRemainingColumn(),
            console=_err,
            transient=True,
            disable=as_json,
        ) as bar:
            task = bar.add_task(f"headset {scenario}", total=1.0)
            run = run_headset(scenario, opts, lambda d, t: bar.update(task, completed=d, total=max(t, 1)))
        result = headset_result(run)
        if partial.exists():
            shutil.rmtree(partial)
        write_headset_outputs(run, result, partial)
    except (ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    if out.exists():
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    partial.rename(out)
    result["out"] = str(out)
    if as_json:
        sys.stdout.write(json.dumps(result, allow_nan=False) + "\n")
    else:
        console = Console()
        console.print(f"[bold]headset {scenario} on {estimator} ({cameras} camera(s)) -> {out}[/bold]")
        for key, value in result.items():
            console.print(f"  {key:<24} {value}")
    if result["diverged"]:
        raise typer.Exit(code=3)
