"""``viotb record`` and ``viotb eval``: datasets in, metrics out (added to the app by :func:`register`)."""

from __future__ import annotations

from pathlib import Path

import typer
from viotb.envs.tools.cli_common import (
    EXIT_DIVERGED,
    check_out,
    check_seconds,
    choice_option,
    emit,
    estimator_option,
    fail,
    frontend_option,
    overwrite_option,
    progress,
    quiet_option,
    seed_option,
)

IMU_GAP_POLICIES = ("refuse", "bridge")
"""``viotb.envs.data.validate.IMU_GAP_POLICIES`` (repeated so that ``--help`` stays fast; a test compares)."""


def parse_resolution(text: str | None) -> tuple[int, int] | None:
    """``"752x480"`` -> ``(752, 480)``; a typer error naming ``--resolution`` otherwise."""
    if text is None:
        return None
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts) or min(int(p) for p in parts) <= 0:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT in px, e.g. 752x480, got {text!r}")
    return int(parts[0]), int(parts[1])


def _positive_rate(value: float | None) -> float | None:
    if value is not None and not (0.0 < value < float("inf")):
        raise typer.BadParameter(f"must be a positive rate in Hz, got {value}")
    return value


def record(
    scenario: str = typer.Argument(..., help="Scenario name (see `viotb scenarios`)."),
    out: Path = typer.Option(..., "--out", help="Output folder (new or empty); a EuRoC ASL tree OUT/mav0."),
    seed: int = seed_option(),
    seconds: float | None = typer.Option(None, "--seconds", help="Duration (s); scenario default if unset."),
    severity: float | None = typer.Option(None, "--severity", help="Severity of a fail-* scenario."),
    resolution: str | None = typer.Option(
        None,
        "--resolution",
        callback=parse_resolution,
        help="Image size WxH in px (default 320x240; EuRoC: 752x480).",
    ),
    camera_rate: float | None = typer.Option(
        None, "--camera-rate", callback=_positive_rate, help="Camera rate (Hz; default the scenario's, 20)."
    ),
    imu_rate: float | None = typer.Option(
        None, "--imu-rate", callback=_positive_rate, help="IMU rate (Hz; default the IMU preset's, 200)."
    ),
    start_in_motion: bool = typer.Option(
        False,
        "--start-in-motion",
        help="Begin the recording mid-trajectory, moving (ground truth from there too).",
    ),
    start_at: float | None = typer.Option(
        None,
        "--start-at-s",
        min=0.0,
        help="With --start-in-motion: trajectory time (s) where the recording begins (default: 2 s "
        "after the still start).",
    ),
    overwrite: bool = overwrite_option(),
    quiet: bool = quiet_option(),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Simulate a scenario open loop and write a EuRoC ASL dataset (atomically: complete or absent).

    Size and rates are written into cam0/sensor.yaml and imu0/sensor.yaml.
    """
    from viotb.envs.data.record import default_start_in_motion_s, record_scenario

    check_seconds(seconds)
    if start_at is not None and not start_in_motion:
        fail("--start-at-s needs --start-in-motion")
    check_out(out, overwrite)
    try:
        start_at_s = None
        if start_in_motion:
            from viotb.envs.scenarios.registry import get_scenario

            start_at_s = (
                start_at if start_at is not None else default_start_in_motion_s(get_scenario(scenario))
            )
        with progress(f"record {scenario}", not quiet) as report:
            result = record_scenario(
                scenario,
                out,
                seed=seed,
                seconds=seconds,
                progress=report,
                severity=severity,
                resolution=resolution,  # type: ignore[arg-type]  (parsed by the callback)
                camera_rate_hz=camera_rate,
                imu_rate_hz=imu_rate,
                overwrite=overwrite,
                start_at_s=start_at_s,
            )
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    emit(result, as_json, f"recorded {scenario} -> {out}")


SENSOR_MODEL_CHOICES = ("default", "render")
"""``--sensor-model`` values: :data:`viotb.vio.msckf_params.SENSOR_MODELS` (its module loads the filter)."""


def eval_(
    dataset: Path = typer.Argument(..., help="EuRoC-layout folder (containing mav0/, or mav0 itself)."),
    estimator: str = estimator_option(),
    out: Path = typer.Option(
        Path("viotb_out/eval"), "--out", help="Output folder (new or empty) for the TUM files."
    ),
    frontend: str = frontend_option(help_text="klt (images) or sim (recorded landmarks, fast)."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=0, help="Stop after this many frames."),
    cameras: int = typer.Option(
        1, "--cameras", min=1, max=2, help="1 (cam0, default) | 2 (cam0 + cam1 of a stereo folder)."
    ),
    imu_gap_policy: str = choice_option(
        "refuse",
        "--imu-gap-policy",
        "IMU gap policy",
        IMU_GAP_POLICIES,
        "What to do with an IMU gap over 5 nominal periods: refuse (an error naming file, lines, times) "
        "or bridge (linear interpolation, reported in imu_gaps and notes).",
    ),
    calibrate: bool = typer.Option(
        False,
        "--calibrate",
        help="Estimate the camera-IMU time offset and extrinsics online (msckf or window).",
    ),
    imu_intrinsics: str = choice_option(
        "none",
        "--imu-intrinsics",
        "IMU intrinsics choice",
        ("none", "gyro", "gyro+accel"),
        "Estimate the IMU's scale/misalignment matrices online (msckf or window; MsckfParams / "
        "WindowParams.imu_intrinsics).",
    ),
    klt_noise: str = choice_option(
        "default",
        "--klt-noise",
        "KLT noise model",
        ("default", "render"),
        "The filter's pixel noise: default (1 px, for any camera) or render (the KLT noise measured on this "
        "project's renders, MsckfParams / WindowParams.with_render_klt_noise; msckf or window, for "
        "recordings with the right calibration).",
    ),
    sensor_model: str = choice_option(
        "default",
        "--sensor-model",
        "sensor model",
        SENSOR_MODEL_CHOICES,
        "The estimator's model of its sensors: default (1 px, the IMU as its file says: any camera) or "
        "render (measured on this project's renders: the KLT render noise, the IMU's scale/misalignment "
        "estimated online, for the msckf also rotation-compensated clones; MsckfParams / "
        "WindowParams.with_render_sensor_model; msckf or window on klt; recordings with the right "
        "calibration).",
    ),
    monitor: bool = typer.Option(True, "--monitor/--no-monitor", help="Run the health monitor (default on)."),
    write_report: bool = typer.Option(
        True, "--report/--no-report", help="Write PNGs and report.json into --out."
    ),
    rerun: bool = typer.Option(False, "--rerun", help="Also write a rerun recording OUT/eval.rrd."),
    loop_closure: bool = typer.Option(
        False, "--loop-closure", help="Loop closure beside the estimator (OUT/loop_closures.csv)."
    ),
    map_in: Path | None = typer.Option(
        None, "--map-in", help="Start in this saved loop-closure map's frame."
    ),
    map_out: Path | None = typer.Option(None, "--map-out", help="Save the loop-closure map here (.npz)."),
    overwrite: bool = overwrite_option(),
    quiet: bool = quiet_option(),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Run an estimator on a EuRoC folder: TUM trajectories, ATE/RPE/NEES/timing, the monitor's diagnosis.

    Exit status: 0 done; 2 bad input (the message names it); 3 the estimator diverged.

    A diverged run still writes and prints its results up to the divergence (diverged: true, reason).
    """
    from viotb.envs.data.evaluate import NULL_REASONS, EvalOptions, evaluate_dataset

    check_out(out, overwrite)
    if calibrate and estimator not in ("msckf", "window"):
        fail(f"--calibrate needs --estimator msckf or window: {estimator!r} has no online calibration")
    try:
        from viotb.vio.model_options import model_settings

        msckf, window = model_settings(
            estimator, frontend, sensor_model, klt_noise, imu_intrinsics, calibrate
        )
    except ValueError as exc:
        flags = (("--sensor-model", sensor_model, "default"), ("--klt-noise", klt_noise, "default"))
        flags += (("--imu-intrinsics", imu_intrinsics, "none"),)
        told = [f"{flag} {value}" for flag, value, default in flags if value != default]
        fail(f"{' '.join(told + (['--calibrate'] if calibrate else []))}: {exc}")
    try:
        from viotb.envs.run.loop_glue import loop_options

        loop = loop_options(loop_closure, map_in, map_out)
        opts = EvalOptions(
            estimator=estimator,
            frontend=frontend,
            max_frames=max_frames,
            imu_gap_policy=imu_gap_policy,
            cameras=cameras,
            monitor=monitor,
            calibrate=calibrate,
            msckf=msckf,
            window=window,
            report=write_report,
            rerun=rerun,
            loop=loop,
        )
        with progress(f"eval {estimator}", not quiet) as report:
            result = evaluate_dataset(dataset, out, opts, report, overwrite=overwrite)
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    emit(result, as_json, f"{estimator} on {dataset} -> {out}", NULL_REASONS)
    if not as_json:
        from rich.console import Console
        from viotb.envs.tools.eval_report import print_diagnosis

        print_diagnosis(Console(stderr=True), result)
    if result["diverged"]:
        raise typer.Exit(code=EXIT_DIVERGED)


def register(app: typer.Typer) -> None:
    """Add ``record`` and ``eval`` to ``app``."""
    app.command()(record)
    app.command("eval")(eval_)
