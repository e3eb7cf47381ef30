"""A stereo headset recording evaluated with one camera and with two: stereo is better at looking around.

Looking around in place, one camera sees little parallax (only the lever arm of the cameras ahead of the IMU
moves them); the second camera's 10 cm baseline triangulates every feature at once. Measured on an 8 s
``headset-look-around`` recording (seed 0), MSCKF, ATE after the 4-DOF alignment: simulated features 12.2 mm
mono against 7.6 mm stereo; KLT on the rendered images 11.9 against 8.8 mm.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner
from viotb.envs.data.evaluate import EvalOptions, evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.tools.cli import app


@pytest.fixture(scope="module")
def look_around(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("look") / "rec"
    rec = record_scenario("headset-look-around", root, seed=0, seconds=6.0)
    assert rec["cameras"] == 2
    return root


def _ate(dataset: Path, out: Path, cameras: int, frontend: str) -> dict:
    result = evaluate_dataset(dataset, out, EvalOptions(frontend=frontend, cameras=cameras))
    assert not result["diverged"], result["reason"]
    assert result["cameras"] == cameras
    return result


def test_stereo_beats_mono_on_looking_around_simulated_features(look_around: Path, tmp_path: Path) -> None:
    mono = _ate(look_around, tmp_path / "m", 1, "sim")
    stereo = _ate(look_around, tmp_path / "s", 2, "sim")
    assert stereo["ate_posyaw_m"] < 0.8 * mono["ate_posyaw_m"], (stereo["ate_posyaw_m"], mono["ate_posyaw_m"])


@pytest.mark.slow
def test_stereo_beats_mono_on_looking_around_klt(look_around: Path, tmp_path: Path) -> None:
    mono = _ate(look_around, tmp_path / "m", 1, "klt")
    stereo = _ate(look_around, tmp_path / "s", 2, "klt")
    assert stereo["ate_posyaw_m"] < 0.9 * mono["ate_posyaw_m"], (stereo["ate_posyaw_m"], mono["ate_posyaw_m"])


def test_cameras_2_on_a_mono_folder_is_refused_with_the_reason(tmp_path: Path) -> None:
    record_scenario("hover", tmp_path / "mono", seed=0, seconds=2.0)
    out = CliRunner().invoke(
        app, ["eval", str(tmp_path / "mono"), "--cameras", "2", "--out", str(tmp_path / "e"), "--json"]
    )
    assert out.exit_code == 2
    assert "cam1" in out.output and "mono" in out.output
    assert not (tmp_path / "e").exists()


def test_eval_json_says_how_many_cameras(look_around: Path, tmp_path: Path) -> None:
    out = CliRunner().invoke(
        app,
        ["eval", str(look_around), "--cameras", "2", "--frontend", "sim", "--max-frames", "40", "--no-report"]
        + ["--out", str(tmp_path / "e"), "--json", "--quiet"],
    )
    assert out.exit_code in (0, 3), out.output
    assert json.loads(out.stdout.strip().splitlines()[-1])["cameras"] == 2
