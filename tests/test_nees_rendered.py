"""Consistency of both estimators on rendered recordings (issue #13): the causes of over- and underconfidence.

On this project's renders the KLT tracks follow their points to ~0.03 px, so the default 1 px makes the
filter underconfident; told the measured noise (:meth:`MsckfParams.with_render_klt_noise`) it becomes
overconfident wherever the motion is fast, because the simulated IMU has scale-factor and misalignment
errors (the ``adis16448`` preset's 0.2 % and 0.05 deg) that the filter does not model. Estimating both
sensors' correction matrices online (``imu_intrinsics="gyro+accel"``) removes that cause.

Each test compares configurations of the same filter on the same recording, against the truth:

- the short version (default suite): one 12 s ``aggressive`` recording;
- a closed-loop hover on ``--sensor-model render`` (the whole model) against the default;
- the Monte Carlo (slow): the whole model on 40 s recordings, seeds 0-4, of issue #13's seven scenarios,
  whose mean position NEES must lie in issue #13's band [1.5, 5] (``head-look-around``, at 5.68, is a
  strict xfail);
- the window's model (:meth:`WindowParams.with_render_sensor_model`, which also estimates the IMU
  matrices): the short run and the same Monte Carlo (``hover`` and ``head-look-around`` strict xfails).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from viotb.envs.data.diagnosis import MSCKF_RENDER_NOISE_NIS_PER_DOF, expected_nis_per_dof
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.data.evaluate import evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window_params import WindowParams

RENDER = MsckfParams().with_render_klt_noise()
RENDER_IMU = replace(RENDER, imu_intrinsics="gyro+accel")
RENDER_MODEL = MsckfParams().with_render_sensor_model()
SCENARIOS = ("figure8", "circle", "aggressive", "hover", "head-fast-turns", "head-look-around", "head-walk")


def _eval(rec: Path, out: Path, msckf: MsckfParams | None, monitor: bool = False) -> dict:
    return evaluate_dataset(rec, out, EvalOptions("msckf", "klt", msckf=msckf, monitor=monitor))


@pytest.fixture(scope="module")
def aggressive_12s(tmp_path_factory) -> Path:
    """A 12 s ``aggressive`` render (seed 1), shared by the MSCKF's and the window's short tests."""
    rec = tmp_path_factory.mktemp("aggressive") / "rec"
    record_scenario("aggressive", rec, seed=1, seconds=12.0)
    return rec


def test_measured_noise_is_overconfident_on_fast_motion_until_the_imu_errors_are_estimated(
    tmp_path, aggressive_12s
):
    """12 s ``aggressive`` (seed 1): render noise alone NEES > 5; with the IMU intrinsics in [0.75, 5].

    Measured on seeds 0 / 1 / 2 (position NEES, ATE): the 1 px default 2.1 / 2.9 / 0.85, 1.5 / 1.9 / 1.2
    cm; render noise 26 / 42 / 12, 1.2 / 1.6 / 1.4 cm; and with ``gyro+accel`` 1.2 / 2.2 / 2.0, 0.50 /
    0.52 / 0.61 cm. The lower bound 0.75 is the gross-underconfidence guard of a single short run.
    """
    rec = aggressive_12s
    default = _eval(rec, tmp_path / "default", None)
    render = _eval(rec, tmp_path / "render", RENDER)
    both = _eval(rec, tmp_path / "both", RENDER_IMU)
    assert not any(m["diverged"] for m in (default, render, both))
    assert render["nees_pos_mean"] > 5.0
    assert 0.75 < both["nees_pos_mean"] < 5.0
    assert both["nees_pos_mean"] < render["nees_pos_mean"] / 4.0
    assert both["ate_posyaw_m"] < 0.6 * min(default["ate_posyaw_m"], render["ate_posyaw_m"])
    assert "--sensor-model render" in " ".join(default["notes"])  # the note on a render told 1 px
    assert "sensor-model" not in " ".join(both["notes"])
    # The whole model under the health monitor, with its own NIS reference: nothing raised on a nominal run.
    model = _eval(rec, tmp_path / "model", RENDER_MODEL, monitor=True)
    assert model["conditions"] == [] and 0.75 < model["nees_pos_mean"] < 5.0
    told_px = RENDER_MODEL.pixel_sigma_px
    assert expected_nis_per_dof("klt", told_px, 0.5, True) == MSCKF_RENDER_NOISE_NIS_PER_DOF


def test_window_told_the_render_noise_is_consistent_once_it_estimates_the_imu_matrices(
    tmp_path, aggressive_12s
):
    """The window on the same 12 s run: render noise alone NEES > 10; the whole model in [0.75, 5].

    The model (:meth:`WindowParams.with_render_sensor_model`) estimates both IMU correction matrices in the
    window (:mod:`viotb.vio.window_calib`), drops landmarks beyond 5 sigmas or failing their track's
    chi-square test and makes a keyframe at least every 10th frame. Measured on seeds 0 / 1 / 2 (position
    NEES, ATE): the 1 px default 4.0 / 4.1 / 1.1, 1.49 / 1.81 / 1.15 cm; render noise 30 / 32 / 14, 1.17 /
    1.51 / 1.37 cm; the model 2.43 / 3.99 / 1.69, 0.53 / 0.74 / 0.51 cm (orientation NEES 1.77 / 2.53 /
    2.47, from 18 / 68 / 17).
    """

    def run(name: str, window: WindowParams | None) -> dict:
        return evaluate_dataset(aggressive_12s, tmp_path / name, EvalOptions("window", "klt", window=window))

    default = run("default", None)
    render = run("render", WindowParams().with_render_klt_noise())
    model = run("model", WindowParams().with_render_sensor_model())
    assert not any(m["diverged"] for m in (default, render, model))
    assert render["nees_pos_mean"] > 10.0
    assert 0.75 < model["nees_pos_mean"] < 5.0 and model["nees_rot_mean"] < 5.0
    assert model["ate_posyaw_m"] < 0.6 * min(default["ate_posyaw_m"], render["ate_posyaw_m"])


@pytest.mark.slow
@pytest.mark.parametrize(
    "scenario",
    [
        *(s for s in SCENARIOS if s != "head-look-around"),
        pytest.param(
            "head-look-around",
            marks=pytest.mark.xfail(strict=True, reason="above the band: mean NEES 5.68 (issue #13, open)"),
        ),
    ],
)
def test_render_sensor_model_nees_monte_carlo(tmp_path, scenario):
    """5 seeds x 40 s rendered, KLT, the whole model: mean position NEES in [1.5, 5], lower ATE than defaults.

    Measured (README "Consistency per scenario", session 16), mean position NEES and mean ATE, defaults ->
    the model: ``figure8`` 0.89 -> 2.61, 2.75 -> 1.03 cm; ``circle`` 1.31 -> 2.50, 3.20 -> 1.01;
    ``aggressive`` 6.63 -> 2.73, 4.29 -> 0.82; ``hover`` 0.46 -> 1.77, 0.67 -> 0.31; ``head-fast-turns``
    0.36 -> 2.03, 1.18 -> 0.62; ``head-walk`` 2.90 -> 2.20, 4.61 -> 1.19. ``head-look-around`` 2.82 ->
    5.68 (above the band since the update-gap rule; cause not found), 10.3 -> 1.62 cm: a strict xfail.
    """
    runs, defaults = [], []
    for seed in range(5):
        rec = tmp_path / f"rec{seed}"
        record_scenario(scenario, rec, seed=seed, seconds=40.0)
        runs.append(_eval(rec, tmp_path / f"model{seed}", RENDER_MODEL))
        defaults.append(_eval(rec, tmp_path / f"default{seed}", None))
    assert not any(m["diverged"] for m in runs)
    assert 1.5 < np.mean([m["nees_pos_mean"] for m in runs]) < 5.0
    assert np.mean([m["ate_posyaw_m"] for m in runs]) < np.mean([m["ate_posyaw_m"] for m in defaults])


@pytest.mark.slow
@pytest.mark.parametrize(
    "scenario",
    [
        *(s for s in SCENARIOS if s != "hover"),
        pytest.param(
            "hover", marks=pytest.mark.xfail(strict=True, reason="just below the band: 1.27 (issue #13)")
        ),
    ],
)
def test_window_render_sensor_model_nees_monte_carlo(tmp_path, scenario):
    """The window's model on the same Monte Carlo: mean position NEES in [1.5, 5], lower ATE than defaults.

    Measured (README "Consistency per scenario", sessions 17-18), mean position NEES and mean ATE, window
    defaults -> the model: ``figure8`` 0.86 -> 1.78, 2.42 -> 0.82 cm; ``circle`` 1.49 -> 2.99, 2.74 ->
    1.34; ``aggressive`` 11.6 -> 3.42, 4.08 -> 0.89; ``head-fast-turns`` 0.41 -> 2.06, 1.53 -> 1.15;
    ``head-look-around`` 2.00 -> 2.64, 5.56 -> 0.95; ``head-walk`` 1.83 -> 2.49, 4.18 -> 1.39. ``hover``
    0.29 -> 1.27 (underconfident), 0.46 -> 0.16, is a strict xfail.
    """
    models, defaults = [], []
    for seed in range(5):
        rec = tmp_path / f"rec{seed}"
        record_scenario(scenario, rec, seed=seed, seconds=40.0)
        opts = EvalOptions("window", "klt", window=WindowParams().with_render_sensor_model())
        models.append(evaluate_dataset(rec, tmp_path / f"model{seed}", opts))
        defaults.append(evaluate_dataset(rec, tmp_path / f"default{seed}", EvalOptions("window", "klt")))
    assert not any(m["diverged"] for m in models)
    assert np.mean([m["ate_posyaw_m"] for m in models]) < np.mean([m["ate_posyaw_m"] for m in defaults])
    assert 1.5 < np.mean([m["nees_pos_mean"] for m in models]) < 5.0


def test_closed_loop_hover_on_the_render_sensor_model_holds_closer_than_on_the_default():
    """``fly-hover`` 20 s on rendered images (seed 0): hover RMS against the truth lower with ``render``.

    Measured, seeds 0 / 1: the default 1.46 / 2.91 cm, ``--sensor-model render`` 0.69 / 1.18 cm (max error
    2.4 / 3.5 -> 0.89 / 1.41 cm). The model needs the KLT front end and says so otherwise.
    """
    from viotb.envs.run.fly import fly

    default, _ = fly("fly-hover", "msckf", 20.0, 0, "klt")
    render, _ = fly("fly-hover", "msckf", 20.0, 0, "klt", sensor_model="render")
    for m in (default, render):
        assert not m["crashed"] and not m["diverged"]
    assert render["hover_rms_m"] < 0.7 * default["hover_rms_m"]
    with pytest.raises(ValueError, match="models of the klt front end, got 'sim'"):
        fly("fly-hover", "msckf", 1.0, 0, "sim", sensor_model="render")
    with pytest.raises(ValueError, match="unknown sensor model 'tuned'"):
        MsckfParams().with_sensor_model("tuned")
