"""``viotb eval --imu-intrinsics / --klt-noise``: the settings reach the estimator; the result names them."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
from data_paths import EUROC_MICRO
from typer.testing import CliRunner
from viotb.envs.tools.cli import app
from viotb.vio.msckf_params import (
    RENDER_KLT_PIXEL_SIGMA_PX,
    RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX,
    MsckfParams,
)
from viotb.vio.window_params import WindowParams


def _eval(tmp_path: Path, *extra: str):
    args = ["eval", str(EUROC_MICRO), "--out", str(tmp_path / "o"), "--max-frames", "40", "--no-report", "-q"]
    return CliRunner().invoke(app, [*args, *extra])


def _result(tmp_path: Path, *extra: str) -> dict:
    """The JSON of a run that must succeed (into the same folder each time)."""
    res = _eval(tmp_path, *extra, "--json", "--overwrite")
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            ("--imu-intrinsics", "gyro", "--estimator", "imu-only"),
            "--imu-intrinsics gyro: the sensor model, KLT noise and IMU intrinsics options need the msckf or "
            "window, got 'imu-only'",
        ),
        (
            ("--klt-noise", "render", "--estimator", "ground-truth"),
            "--klt-noise render: the sensor model",
        ),
        (("--klt-noise", "render", "--frontend", "sim"), "models of the klt front end, got 'sim'"),
        (
            ("--klt-noise", "render", "--estimator", "window", "--calibrate"),
            "--klt-noise render --calibrate: the window told the render KLT noise cannot calibrate online",
        ),
        (("--sensor-model", "render", "--estimator", "window", "--calibrate"), "need white track noise"),
        (("--imu-intrinsics", "accel"), "unknown IMU intrinsics choice 'accel'"),
        (("--sensor-model", "render", "--estimator", "imu-only"), "need the msckf or window, got 'imu-only'"),
        (("--sensor-model", "render", "--frontend", "sim"), "models of the klt front end, got 'sim'"),
        (("--sensor-model", "render", "--imu-intrinsics", "gyro"), "sets the KLT noise and the IMU"),
    ],
)
def test_bad_combinations_are_refused_with_the_flag_named(tmp_path: Path, extra: tuple, message: str) -> None:
    res = _eval(tmp_path, *extra)
    assert res.exit_code == 2, res.output
    assert message in " ".join(res.output.replace("│", " ").split()), res.output


def _told(sigma_px: float, walk_px2_per_px: float, intrinsics: str, rotation_compensated: bool) -> dict:
    """The ``msckf_settings`` a result names for these settings."""
    return {
        "pixel_sigma_px": sigma_px,
        "track_random_walk_px2_per_px": walk_px2_per_px,
        "imu_intrinsics": intrinsics,
        "rotation_compensated_keyframes": rotation_compensated,
    }


def test_real_euroc_with_gyro_intrinsics_and_render_noise_reports_its_settings(tmp_path: Path) -> None:
    """On the real EuRoC micro folder: runs, initializes, and the JSON names what the filter was told."""
    out = _result(tmp_path, "--imu-intrinsics", "gyro", "--klt-noise", "render")
    told = _told(RENDER_KLT_PIXEL_SIGMA_PX, RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX, "gyro", False)
    assert out["msckf_settings"] == told
    assert out["estimated_frames"] > 0
    default = MsckfParams()
    told = _told(default.pixel_sigma_px, default.klt.track_random_walk_px2_per_px, "none", False)
    assert _result(tmp_path)["msckf_settings"] == told


def test_sensor_model_render_sets_the_measured_noise_the_imu_intrinsics_and_the_clone_spacing(
    tmp_path: Path,
) -> None:
    """``--sensor-model render`` = ``MsckfParams().with_render_sensor_model()``, named in the JSON."""
    out = _result(tmp_path, "--sensor-model", "render")
    told = _told(RENDER_KLT_PIXEL_SIGMA_PX, RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX, "gyro+accel", True)
    assert out["msckf_settings"] == told
    assert out["estimated_frames"] > 0
    p = MsckfParams().with_render_sensor_model()
    assert replace(p, imu_intrinsics="none", keyframing=MsckfParams().keyframing, max_update_gap_s=None) == (
        MsckfParams().with_render_klt_noise()
    )


def test_the_window_takes_the_render_noise_model_and_the_result_names_it(tmp_path: Path) -> None:
    """``--estimator window --klt-noise render``: 0.035 px and the track walk as generalized least squares."""
    out = _result(tmp_path, "--estimator", "window", "--klt-noise", "render")
    assert out["window_settings"] == {
        "pixel_sigma_px": RENDER_KLT_PIXEL_SIGMA_PX,
        "track_random_walk_px2_per_px": RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX,
        "imu_intrinsics": "none",
        "outlier_chi2": None,
    }
    assert out["msckf_settings"] is None and out["estimated_frames"] > 0
    told = WindowParams().with_render_klt_noise()
    assert told.track_noise and told.huber_threshold == WindowParams().huber_threshold  # gates in sigmas
    default = {
        "pixel_sigma_px": 1.0,
        "track_random_walk_px2_per_px": 0.0,
        "imu_intrinsics": "none",
        "outlier_chi2": None,
    }
    assert _result(tmp_path, "--estimator", "window")["window_settings"] == default


def test_the_window_takes_the_render_sensor_model_and_the_imu_intrinsics(tmp_path: Path) -> None:
    """``--estimator window --sensor-model render``: ``WindowParams().with_render_sensor_model()``.

    The render noise, both IMU matrices, the track test and sparser keyframes; ``--imu-intrinsics
    gyro`` alone sets only ``T_g``. Both named.
    """
    out = _result(tmp_path, "--estimator", "window", "--sensor-model", "render")
    assert out["window_settings"] == {
        "pixel_sigma_px": RENDER_KLT_PIXEL_SIGMA_PX,
        "track_random_walk_px2_per_px": RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX,
        "imu_intrinsics": "gyro+accel",
        "outlier_chi2": 0.95,
    }
    assert out["estimated_frames"] > 0
    p = WindowParams().with_render_sensor_model()
    default = WindowParams()
    told = replace(p, imu_intrinsics="none", outlier_threshold=default.outlier_threshold, outlier_chi2=None)
    assert told.keyframing.every_n_frames == 10
    assert replace(told, keyframing=default.keyframing) == default.with_render_klt_noise()
    out = _result(tmp_path, "--estimator", "window", "--imu-intrinsics", "gyro")
    assert out["window_settings"]["imu_intrinsics"] == "gyro" and out["estimated_frames"] > 0
