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


# ---------------------------------------------------------------------------------------------- hardening


def _message(result) -> str:
    return " ".join(result.output.split())


@pytest.fixture(scope="module")
def hover_dataset(tmp_path_factory):
    """A 2 s hover recording made through the CLI."""
    out = tmp_path_factory.mktemp("cli") / "hover"
    _json(
        CliRunner().invoke(app, ["record", "hover", "--out", str(out), "--seconds", "2", "--quiet", "--json"])
    )
    return out


def test_eval_ground_truth_prints_strict_json_with_null_and_notes(runner, hover_dataset, tmp_path):
    out = tmp_path / "ev"
    args = ["eval", str(hover_dataset), "--estimator", "ground-truth", "--out", str(out), "--json"]
    result = runner.invoke(app, args)
    line = result.stdout.strip().splitlines()[-1]
    assert "NaN" not in line and "Infinity" not in line
    obj = _json(result)
    # A 2 s hover has no 1 m of path: the RPE is null and the notes say why (so does the NEES).
    assert obj["rpe_1m_pct"] is None and obj["nees_pos_mean"] is None
    notes = " ".join(obj["notes"])
    assert "rpe_1m_pct: null (no two evaluated poses 1 m apart" in notes and "nees_pos_mean" in notes
    assert obj["ate_posyaw_m"] < 1e-6
    assert (out / "metrics.json").exists() is False and (out / "estimate_tum.txt").is_file()


@pytest.mark.parametrize("command", ["eval", "record", "fly", "demo"])
def test_out_that_is_a_file_or_a_non_empty_folder_is_refused_before_any_work(runner, tmp_path, command):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    full = tmp_path / "full"
    full.mkdir()
    (full / "earlier.txt").write_text("x")
    lead = {
        "eval": ["eval", str(tmp_path / "no-dataset-here")],
        "record": ["record", "hover"],
        "fly": ["fly", "fly-hover", "--estimator", "ground-truth"],
        "demo": ["demo"],
    }[command]
    for out, message in ((a_file, "is an existing file"), (full, "is not empty")):
        result = runner.invoke(app, [*lead, "--out", str(out)])
        assert result.exit_code == 2, result.output
        assert f"--out {out}" in _message(result) and message in _message(result)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "full"]
    assert sorted(p.name for p in full.iterdir()) == ["earlier.txt"]


def test_demo_with_an_unknown_scenario_leaves_nothing(runner, tmp_path):
    result = runner.invoke(app, ["demo", "--scenario", "nope", "--out", str(tmp_path / "D")])
    assert result.exit_code == 2 and "unknown closed-loop scenario" in _message(result)
    assert list(tmp_path.iterdir()) == []


def test_record_overwrite_replaces_and_never_mixes(runner, hover_dataset, tmp_path):
    out = tmp_path / "rec"
    _json(runner.invoke(app, ["record", "hover", "--out", str(out), "--seconds", "1", "--json"]))
    refused = runner.invoke(app, ["record", "hover", "--out", str(out), "--seconds", "0.5"])
    assert refused.exit_code == 2 and "--overwrite" in _message(refused)
    args = ["record", "hover", "--out", str(out), "--seconds", "0.5", "--overwrite", "--json"]
    assert _json(runner.invoke(app, args))["frames"] == 11
    rows = (out / "mav0" / "cam0" / "data.csv").read_text().strip().splitlines()[1:]
    assert len(rows) == len(list((out / "mav0" / "cam0" / "data").iterdir())) == 11


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["record", "hover", "--out", "x", "--seed", "-1"], "--seed"),
        (["eval", "x", "--max-frames", "-1"], "--max-frames"),
        (["eval", "x", "--estimator", "kalman"], "unknown estimator 'kalman'; allowed: msckf, window"),
        (["eval", "x", "--frontend", "orb"], "unknown front end 'orb'; allowed: klt, sim"),
        (["eval", "x", "--imu-gap-policy", "ignore"], "unknown IMU gap policy 'ignore'"),
        (["record", "hover", "--out", "x", "--resolution", "752"], "--resolution"),
        (["record", "hover", "--out", "x", "--camera-rate", "0"], "--camera-rate"),
        (["record", "hover", "--out", "x", "--imu-rate", "-200"], "--imu-rate"),
        (["fly", "fly-hover", "--seed", "-1"], "--seed"),
    ],
)
def test_bad_options_are_named(runner, args, message):
    result = runner.invoke(app, args, env={"COLUMNS": "250"})  # one line: no box border inside the message
    assert result.exit_code == 2, result.output
    assert message in _message(result), result.output


@pytest.mark.parametrize("command", ["eval", "fly"])
def test_help_lists_the_estimators_and_front_ends(runner, command):
    text = _message(runner.invoke(app, [command, "--help"], env={"COLUMNS": "250"}))
    assert "[msckf|window|imu-only|ground-truth]" in text and "[klt|sim]" in text
    if command == "eval":
        assert "3 the estimator diverged" in text
    else:
        assert "about 10.5 s in" in text


def test_cli_choices_match_the_factory():
    from viotb.envs.data.validate import IMU_GAP_POLICIES
    from viotb.envs.tools import cli_common, cli_data
    from viotb.vio.factory import ESTIMATOR_NAMES, FRONTEND_NAMES

    assert cli_common.ESTIMATORS == ESTIMATOR_NAMES and cli_common.FRONTENDS == FRONTEND_NAMES
    assert cli_data.IMU_GAP_POLICIES == IMU_GAP_POLICIES
    from viotb.vio.msckf_params import SENSOR_MODELS

    assert cli_data.SENSOR_MODEL_CHOICES == SENSOR_MODELS


def test_short_fly_says_why_hover_rms_is_null(runner):
    args = ["fly", "fly-hover", "--estimator", "ground-truth", "--seconds", "3"]
    obj = _json(runner.invoke(app, [*args, "--json"]))
    assert obj["hover_rms_m"] is None
    assert any(n.startswith("hover_rms_m") and "mission had not started" in n for n in obj["notes"])
    console = runner.invoke(app, [*args, "--quiet"])
    assert "note: hover_rms_m" in _message(console) and "10.5 s" in _message(console)


def test_progress_lines_when_stderr_is_not_a_terminal(capsys):
    from viotb.envs.tools.cli_common import progress

    clock = iter([0.0, 1.0, 6.0, 7.0, 12.0])
    with progress("eval msckf", every_s=5.0, clock=lambda: next(clock)) as report:
        for done in (1, 2, 3, 4):
            report(done, 4)
    lines = capsys.readouterr().err.strip().splitlines()
    # At most one line per 5 s: the update at 7 s (1 s after the last line) is not printed.
    assert lines == [
        "eval msckf:  25.0 % (1 s elapsed)",
        "eval msckf:  50.0 % (6 s elapsed)",
        "eval msckf: 100.0 % (12 s elapsed)",
    ]
    with progress("quiet", enabled=False) as report:
        report(1, 1)
    assert capsys.readouterr().err == ""


def test_eval_of_a_diverging_run_exits_3_and_still_reports(runner, tmp_path):
    rec = tmp_path / "sat"
    # The +-125 deg/s gyro saturates in the aggressive manoeuvre: the filter diverges at about 3.3 s.
    _json(
        runner.invoke(app, ["record", "fail-gyro-saturation", "--out", str(rec), "--seconds", "4", "--json"])
    )
    args = [
        "eval",
        str(rec),
        "--estimator",
        "msckf",
        "--frontend",
        "sim",
        "--out",
        str(tmp_path / "ev"),
        "--json",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 3, result.output
    obj = json.loads(result.stdout.strip().splitlines()[-1])
    assert obj["diverged"] is True and obj["reason"]
    assert (tmp_path / "ev" / "estimate_tum.txt").is_file()


def test_seed_range_reads_ranges_and_lists_and_names_bad_text():
    from viotb.envs.tools.cli_common import seed_range

    assert seed_range("0-3") == [0, 1, 2, 3] and seed_range("5") == [5] and seed_range("0,3,5") == [0, 3, 5]
    with pytest.raises(ValueError, match="got 'a-b'"):
        seed_range("a-b")
