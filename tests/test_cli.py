"""Tests of the ``viotb`` command line: the JSON contracts of DESIGN.md and clear errors on bad input."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner
from viotb.envs.tools.cli import app


def _json(result) -> dict:
    """The last stdout line parsed as one JSON object (the ``--json`` contract)."""
    assert result.exit_code == 0, result.output
    obj = json.loads(result.stdout.strip().splitlines()[-1])
    assert isinstance(obj, dict)
    return obj


@pytest.fixture(scope="module")
def runner() -> CliRunner:
    return CliRunner()


def test_scenarios_record_and_eval_keep_their_json_keys(runner, tmp_path):
    names = {s["name"] for s in _json(runner.invoke(app, ["scenarios", "--json"]))["scenarios"]}
    assert {"hover", "figure8", "fail-extrinsic", "fly-hover", "fly-fail-time-offset"} <= names
    rec = _json(runner.invoke(app, ["record", "figure8", "--out", str(tmp_path), "--seconds", "3", "--json"]))
    # Frames at k / 20 s for k = 0..60 and IMU samples at k / 200 s for k = 0..600 (both ends included).
    assert {"frames", "imu_samples", "path_length_m"} <= set(rec)
    assert (rec["frames"], rec["imu_samples"]) == (61, 601)
    ev_dir = tmp_path / "ev"
    ev = _json(
        runner.invoke(app, ["eval", str(tmp_path), "--estimator", "msckf", "--out", str(ev_dir), "--json"])
    )
    keys = {
        "ate_posyaw_m",
        "ate_se3_m",
        "rpe_1m_pct",
        "drift_pct",
        "scale_error_pct",
        "nees_pos_mean",
        "ms_per_frame_median",
        "frames",
        "path_length_m",
    }
    assert keys <= set(ev), sorted(set(ev))
    assert (ev_dir / "estimate_tum.txt").is_file() and (ev_dir / "groundtruth_tum.txt").is_file()


def test_fly_and_failures_keep_their_json_keys(runner, tmp_path):
    args = ["fly", "fly-hover", "--estimator", "ground-truth", "--seconds", "3", "--json"]
    fly = _json(runner.invoke(app, args))
    assert {"hover_rms_m", "max_err_m", "ate_posyaw_m", "crashed", "diverged", "realtime_factor"} <= set(fly)
    rep = _json(
        runner.invoke(app, ["failures", "--name", "fail-feature-poverty", "--out", str(tmp_path), "--json"])
    )
    (one,) = rep["failures"]
    assert one["detected"] is True and one["expected_condition"] == "feature_poverty"
    assert (tmp_path / "fail-feature-poverty_error.png").is_file() and (tmp_path / "report.json").is_file()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["record", "nope", "--out", "x"], "unknown scenario"),
        (["fly", "nope"], "unknown closed-loop scenario"),
        (["fly", "fly-hover", "--estimator", "kalman"], "unknown estimator"),
        (["fly", "fly-fail-long-loop", "--severity", "2"], "no severity knob"),
        (["failures", "--name", "fail-nope"], "unknown failure"),
        (["record", "hover", "--out", "x", "--seconds", "-1"], "--seconds must be positive"),
    ],
)
def test_bad_input_exits_nonzero_with_a_clear_message(runner, args, message):
    result = runner.invoke(app, args)
    assert result.exit_code != 0
    assert message in " ".join(result.output.split()), result.output
