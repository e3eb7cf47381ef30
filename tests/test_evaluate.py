"""Tests of envs/data/evaluate.py on bad and awkward datasets: ground truth, gaps, late IMU, atomic output."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from viotb.envs.data.evaluate import EvalOptions, evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.tools.outdir import OutDirError


@pytest.fixture(scope="module")
def hover(tmp_path_factory) -> Path:
    """A 3 s hover recording (61 frames, 601 IMU samples)."""
    out = tmp_path_factory.mktemp("rec") / "hover"
    record_scenario("hover", out, seed=0, seconds=3.0)
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _imu_rows(ds: Path) -> tuple[list[str], list[str]]:
    lines = (ds / "mav0" / "imu0" / "data.csv").read_text().splitlines(keepends=True)
    return lines[:1], lines[1:]


def _siblings(path: Path) -> list[str]:
    return sorted(p.name for p in path.parent.iterdir()) if path.parent.exists() else []


def test_ground_truth_estimator_runs_and_says_why_nees_is_missing(hover, tmp_path):
    result = evaluate_dataset(hover, tmp_path / "ev", EvalOptions(estimator="ground-truth"))
    assert result["ate_posyaw_m"] < 1e-6 and result["estimated_frames"] == result["frames"] == 61
    assert np.isnan(result["nees_pos_mean"])
    assert any("nees_pos_mean" in n and "covariance" in n for n in result["notes"])
    assert (tmp_path / "ev" / "estimate_tum.txt").is_file()


def test_ground_truth_estimator_without_ground_truth_names_the_file_and_writes_nothing(hover, tmp_path):
    ds = _copy(hover, tmp_path / "nogt")
    shutil.rmtree(ds / "mav0" / "state_groundtruth_estimate0")
    with pytest.raises(ValueError, match="state_groundtruth_estimate0"):
        evaluate_dataset(ds, tmp_path / "ev", EvalOptions(estimator="ground-truth"))
    assert not (tmp_path / "ev").exists() and not [n for n in _siblings(tmp_path / "ev") if "partial" in n]


def test_imu_gap_is_refused_by_default_naming_file_lines_and_times(hover, tmp_path):
    ds = _copy(hover, tmp_path / "gap")
    header, rows = _imu_rows(ds)
    (ds / "mav0" / "imu0" / "data.csv").write_text("".join(header + rows[:200] + rows[400:]))  # 1 s hole
    with pytest.raises(ValueError) as info:
        evaluate_dataset(ds, tmp_path / "ev", EvalOptions(estimator="ground-truth"))
    message = str(info.value)
    assert (
        "imu0/data.csv, lines 201-202" in message
        and "1.005 s without IMU samples (t 0.9950 s to 2.0000 s)" in message
    ), message
    assert "--imu-gap-policy bridge" in message
    assert not (tmp_path / "ev").exists()
    bridged = evaluate_dataset(
        ds, tmp_path / "ev", EvalOptions(estimator="ground-truth", imu_gap_policy="bridge")
    )
    (gap,) = bridged["imu_gaps"]
    assert (gap["line0"], gap["line1"], gap["samples_inserted"]) == (201, 202, 200)
    assert any("bridged" in n for n in bridged["notes"])


def test_imu_starting_after_the_first_image_skips_and_counts_those_frames(hover, tmp_path):
    ds = _copy(hover, tmp_path / "late")
    header, rows = _imu_rows(ds)
    (ds / "mav0" / "imu0" / "data.csv").write_text("".join(header + rows[200:]))  # IMU from t = 1 s
    result = evaluate_dataset(ds, tmp_path / "ev", EvalOptions(estimator="ground-truth"))
    assert result["frames_skipped_before_imu"] == 20  # frames at 0.00 .. 0.95 s
    assert result["frames"] == result["estimated_frames"] == 41
    assert any("20 frame(s) before the first IMU sample (t 1.0000 s) skipped" in n for n in result["notes"])
    # The filter cannot initialize statically here (the hover is still only until 1.5 s): that is reported.
    late = evaluate_dataset(ds, tmp_path / "ev2", EvalOptions(estimator="msckf", frontend="sim"))
    assert late["frames_skipped_before_imu"] == 20 and late["frames_without_estimate"] == late["frames"] == 41
    assert any("41 of 41 processed frame(s) gave no estimate" in n for n in late["notes"])
    assert "ate_posyaw_m" in result


def test_out_dir_is_checked_before_any_work_and_never_mixed(hover, tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(OutDirError, match="existing file"):  # before the (missing) dataset is read
        evaluate_dataset(tmp_path / "missing", a_file, EvalOptions(estimator="ground-truth"))
    out = tmp_path / "ev"
    out.mkdir()
    (out / "old_run.txt").write_text("earlier")
    with pytest.raises(OutDirError, match="not empty"):
        evaluate_dataset(hover, out, EvalOptions(estimator="ground-truth"))
    evaluate_dataset(hover, out, EvalOptions(estimator="ground-truth"), overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["estimate_tum.txt", "groundtruth_tum.txt"]


def test_interrupted_eval_leaves_nothing_and_keeps_the_previous_run(hover, tmp_path):
    out = tmp_path / "ev"
    evaluate_dataset(hover, out, EvalOptions(estimator="ground-truth"))
    before = (out / "estimate_tum.txt").read_text()

    def interrupt(done: float, total: float) -> None:
        if done >= 10:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        evaluate_dataset(
            hover, out, EvalOptions(estimator="ground-truth", max_frames=20), interrupt, overwrite=True
        )
    assert (out / "estimate_tum.txt").read_text() == before
    assert _siblings(out) == ["ev"]
    with pytest.raises(KeyboardInterrupt):
        evaluate_dataset(hover, tmp_path / "new", EvalOptions(estimator="ground-truth"), interrupt)
    assert _siblings(out) == ["ev"]


def test_negative_max_frames_is_refused():
    with pytest.raises(ValueError, match="max_frames must be an integer >= 0, got -1"):
        EvalOptions(max_frames=-1)
