"""``viotb fly`` and ``viotb demo``: closed-loop flights (registered on the app by :func:`register`)."""

from __future__ import annotations

from pathlib import Path

import typer
from viotb.envs.tools.cli_common import (
    check_out,
    check_seconds,
    choice_option,
    emit,
    err_console,
    estimator_option,
    fail,
    frontend_option,
    overwrite_option,
    progress,
    quiet_option,
    seed_option,
    write_json,
)
from viotb.envs.tools.cli_data import SENSOR_MODEL_CHOICES

SECONDS_HELP = (
    "Flight duration (s), ground phase included. The mission starts about 10.5 s in (estimator "
    "initialization on the ground, then a 3 s takeoff); shorter flights report hover_rms_m: null."
)


def fly(
    scenario: str = typer.Argument(..., help="Closed-loop scenario (see `viotb scenarios`)."),
    estimator: str = estimator_option(),
    seconds: float | None = typer.Option(None, "--seconds", help=SECONDS_HELP),
    seed: int = seed_option(),
    frontend: str = frontend_option(help_text="klt (rendered images) or sim (fast mode)."),
    out: Path | None = typer.Option(None, "--out", help="Write plots and metrics.json here (new/empty)."),
    calibrate: bool = typer.Option(
        False,
        "--calibrate",
        help="Estimate the camera-IMU time offset and extrinsics online (msckf or window).",
    ),
    severity: float | None = typer.Option(None, "--severity", help="Severity of a fly-fail-* scenario."),
    loop_closure: bool | None = typer.Option(
        None,
        "--loop-closure/--no-loop-closure",
        help="Loop closure; the controller gets the corrected pose (default: the scenario's, off but for "
        "fly-lights-out; with --frontend sim the camera is rendered for it).",
    ),
    sensor_model: str = choice_option(
        "default",
        "--sensor-model",
        "sensor model",
        SENSOR_MODEL_CHOICES,
        "The estimator's model of its sensors: default (1 px, the IMU as calibrated) or render (measured "
        "on these renders: MsckfParams / WindowParams.with_render_sensor_model; msckf or window on klt).",
    ),
    overwrite: bool = overwrite_option(),
    quiet: bool = quiet_option(),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Fly a closed-loop scenario with the estimator in the loop."""
    from viotb.envs.run.fly import fly as run_fly
    from viotb.envs.tools.outdir import atomic_out_dir

    check_seconds(seconds)
    if out is not None:
        check_out(out, overwrite)
    try:
        with progress(f"fly {scenario}", not quiet) as report:
            result, log = run_fly(
                scenario,
                estimator,
                seconds,
                seed,
                frontend,
                report,
                online_calibration=calibrate or None,
                severity=severity,
                loop_closure=loop_closure,
                sensor_model=sensor_model,
            )
    except ValueError as exc:
        fail(str(exc))
    if out is not None:
        from viotb.envs.tools.viz import save_plots

        with atomic_out_dir(out, overwrite) as tmp:
            result["plots"] = [str(out / p.name) for p in save_plots(log, tmp)]
            write_json(tmp / "metrics.json", result)
    emit(result, as_json, f"flew {scenario} on {estimator}")


def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Output folder (new/empty): plots, demo.rrd."),
    scenario: str = typer.Option("fly-hover", "--scenario", help="Closed-loop scenario."),
    seconds: float | None = typer.Option(None, "--seconds", help=SECONDS_HELP),
    seed: int = seed_option(),
    overwrite: bool = overwrite_option(),
    quiet: bool = quiet_option(),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """The default closed-loop VIO flight, with PNG plots and a rerun recording (written atomically)."""
    from viotb.envs.run.fly import fly as run_fly
    from viotb.envs.scenarios.registry import get_fly_scenario
    from viotb.envs.tools.outdir import atomic_out_dir
    from viotb.envs.tools.viz import RerunRecorder, save_plots

    check_seconds(seconds)
    check_out(out, overwrite)
    try:
        get_fly_scenario(scenario)  # an unknown name fails before anything is created
    except ValueError as exc:
        fail(str(exc))
    with atomic_out_dir(out, overwrite) as tmp:
        recorder = RerunRecorder(tmp / "demo.rrd")
        try:
            with progress(f"demo {scenario}", not quiet) as report:
                result, log = run_fly(scenario, "msckf", seconds, seed, "klt", report, on_tick=recorder)
        except ValueError as exc:
            fail(str(exc))
        finally:
            recorder.close()
        plots = [out / p.name for p in save_plots(log, tmp)]
        result["recording"] = str(out / "demo.rrd")
        result["plots"] = [str(p) for p in plots]
        write_json(tmp / "metrics.json", result)
    if not as_json:
        err_console().print(f"plots: {', '.join(str(p) for p in plots)}")
        err_console().print(f"recording: {out / 'demo.rrd'}  (view with: rerun {out / 'demo.rrd'})")
    emit(result, as_json, f"demo {scenario}")


def register(app: typer.Typer) -> None:
    """Add ``fly`` and ``demo`` to ``app``."""
    app.command()(fly)
    app.command()(demo)
