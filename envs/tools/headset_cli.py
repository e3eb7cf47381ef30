"""``viotb headset``: :func:`register` adds it to the ``viotb`` app.

Only typer and rich are imported here; the simulator loads inside the command, so ``viotb --help`` stays
fast. ``--out`` is checked before any work (a non-empty folder is refused unless ``--overwrite``) and the
outputs are written atomically (:func:`viotb.envs.tools.outdir.atomic_out_dir`), so an interrupted run
leaves nothing that looks complete.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import typer
from viotb.envs.tools.cli_common import (
    EXIT_DIVERGED,
    check_out,
    emit,
    estimator_option,
    fail,
    frontend_option,
    overwrite_option,
    progress,
    quiet_option,
    seed_option,
)


def register(app: typer.Typer) -> None:
    """Add the ``headset`` command to ``app``."""
    app.command("headset")(headset)


def headset(
    scenario: str = typer.Argument(
        ...,
        help="Headset scenario: headset-still | headset-look-around | headset-fast-turns | headset-walk | "
        "headset-crouch | headset-blank-wall | headset-dark-room (or head-*; see `viotb scenarios`).",
    ),
    estimator: str = estimator_option(),
    cameras: int = typer.Option(
        1, "--cameras", min=1, max=2, help="1 (head_cam0, default) | 2 (stereo head_cam0 + head_cam1)."
    ),
    latency_ms: float = typer.Option(20.0, "--latency-ms", min=0.0, max=200.0, help="Display latency (ms)."),
    seconds: float | None = typer.Option(
        None, "--seconds", min=0.001, help="Duration (s); default: scenario's."
    ),
    seed: int = seed_option(),
    frontend: str = frontend_option(help_text="klt (images) or sim (projected landmarks, fast)."),
    out: Path = typer.Option(
        ..., "--out", help="Output folder: TUM files, metrics.json, plots, headset.rrd."
    ),
    imu: str | None = typer.Option(
        None,
        "--imu",
        help="IMU part: icm42688-1khz (the scenario's, raw intrinsics) | icm42688-1khz-calibrated "
        "(factory-calibrated scale/misalignment) | adis16448 | bmi088 | ideal.",
    ),
    gyro_noise_inflation: float | None = typer.Option(
        None,
        "--gyro-noise-inflation",
        min=1e-3,
        help="Factor on the gyro noise density the estimator is told (default: 2 for the msckf, which "
        "estimates the gyro's scale/misalignment online; 10 for the others, covering those errors of the "
        "raw part; 1: the sensor's own density).",
    ),
    right_pixel_sigma: float | None = typer.Option(
        None,
        "--right-pixel-sigma",
        min=1e-6,
        help="msckf, stereo, klt: the pixel noise (px) cam1's observations are told (default: cam0's; "
        "cam1 is matched from cam0 every frame, so it carries cam0's error plus the match's; README: 0.2 "
        "makes the walk consistent).",
    ),
    calibrate: bool = typer.Option(
        False, "--calibrate", help="Estimate the camera-IMU time offset and extrinsics online (msckf, window)"
    ),
    time_offset_error_ms: float = typer.Option(
        0.0,
        "--time-offset-error-ms",
        min=-100.0,
        max=100.0,
        help="Tell the estimator a camera-IMU time offset this far off (ms): a sync error to diagnose.",
    ),
    no_display_filter: bool = typer.Option(
        False,
        "--no-display-filter",
        help="Render with the estimator's pose itself (metrics then equal the estimator_* ones).",
    ),
    loop_closure: bool = typer.Option(
        False, "--loop-closure", help="Loop closure beside the estimator (needs klt); loop_closures.csv."
    ),
    map_in: Path | None = typer.Option(None, "--map-in", help="Start in this saved map's frame."),
    map_out: Path | None = typer.Option(None, "--map-out", help="Save the room's map here at the end."),
    overwrite: bool = overwrite_option(),
    quiet: bool = quiet_option(),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    """Headset rig, estimator online: pose at IMU rate, prediction to display time, headset metrics.

    Exit status: 0 done; 2 bad input (the message names it); 3 the estimator diverged.
    """
    check_out(out, overwrite)
    from viotb.envs.run.headset import HEADSET_MSCKF, HeadsetOptions, run_headset
    from viotb.envs.run.headset_report import headset_result
    from viotb.envs.run.loop_glue import loop_options
    from viotb.envs.tools.headset_viz import write_headset_outputs
    from viotb.envs.tools.outdir import atomic_out_dir

    try:
        msckf = None
        if right_pixel_sigma is not None:  # checked with the other options (``headset._check``)
            msckf = replace(HEADSET_MSCKF, right_pixel_sigma_px=right_pixel_sigma)
        opts = HeadsetOptions(
            estimator=estimator,
            cameras=cameras,
            latency_s=latency_ms * 1e-3,
            seconds=seconds,
            seed=seed,
            frontend=frontend,
            imu_preset=imu,
            gyro_noise_inflation=gyro_noise_inflation,
            msckf=msckf,
            loop=loop_options(loop_closure, map_in, map_out),
            time_offset_error_s=time_offset_error_ms * 1e-3,
            online_calibration=calibrate,
            **({"display": None} if no_display_filter else {}),
        )
        with atomic_out_dir(out, overwrite) as tmp_dir, progress(f"headset {scenario}", not quiet) as report:
            run = run_headset(scenario, opts, report)
            result = headset_result(run)
            write_headset_outputs(run, result, tmp_dir)
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    result["out"] = str(out)
    emit(result, as_json, f"headset {scenario} on {estimator} ({cameras} camera(s)) -> {out}")
    if result["diverged"]:
        raise typer.Exit(code=EXIT_DIVERGED)
