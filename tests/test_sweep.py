"""Tests of viotb.envs.tools.sweep: spec, Ray engine, report and CLI.

Spec validation, the engine's rows, resume, determinism, failing runs and timeouts, the report and the CLI.

One local Ray instance (2 CPUs) serves the module; the runs are 2.5 s hovers recorded and evaluated with the
simulated-feature front end (a few seconds each).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2
from typer.testing import CliRunner
from viotb.envs.tools.cli import app
from viotb.envs.tools.sweep import RunConfig, SpecError, parse_spec, run_config, run_sweep
from viotb.envs.tools.sweep.engine import WORKER_ENV
from viotb.envs.tools.sweep.report import nees_band, sweep_report
from viotb.envs.tools.sweep.runs import catalog

ray = pytest.importorskip("ray")

SECONDS = 2.5
DETERMINISTIC = (
    "ate_posyaw_m",
    "ate_se3_m",
    "drift_pct",
    "scale_error_pct",
    "nees_pos_mean",
    "frames",
    "estimated_frames",
    "record/path_length_m",
    "record/imu_samples",
)
"""Metrics that depend on the configuration only (not on timing)."""


def _spec(**grid) -> dict:
    fixed = {
        "scenario": "hover",
        "mode": "record-eval",
        "estimator": "msckf",
        "frontend": "sim",
        "seconds": SECONDS,
    }
    return {
        "name": "test",
        "fixed": {k: v for k, v in fixed.items() if k not in grid},
        "grid": grid,
        "seeds": [0, 1],
    }


@pytest.fixture(scope="module")
def cat():
    return catalog()


@pytest.fixture(scope="module")
def local_ray():
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        log_to_driver=False,
        logging_level="WARNING",
        object_store_memory=128 * 1024**2,
        runtime_env={"env_vars": dict(WORKER_ENV)},
    )
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def swept(local_ray, tmp_path_factory):
    """A 4-run sweep: seeds 0, 1 x update_linearization in {current_oc, bogus}; the bogus runs raise."""
    out = tmp_path_factory.mktemp("sweep")
    spec = _spec(**{"msckf.update_linearization": ["current_oc", "bogus"]})
    result = run_sweep(spec, out, workers=2)
    return spec, out, result


def test_rows_and_columns(swept):
    _, out, result = swept
    assert (result.runs, result.computed, result.skipped, result.failed) == (4, 4, 0, 2)
    df = pd.read_parquet(result.results)
    assert len(df) == 4 and df["run_id"].is_unique
    for col in (
        "run_id",
        "config_id",
        "status",
        "error",
        "seed",
        "config/scenario",
        "config/mode",
        "config/estimator",
        "config/frontend",
        "config/seconds",
        "config/msckf.update_linearization",
        "ate_posyaw_m",
        "drift_pct",
        "nees_pos_mean",
        "ms_per_frame_median",
        "record/frames",
        "wall_s",
        "host",
        "version",
        "git_commit",
        "finished_utc",
    ):
        assert col in df.columns, col
    assert sorted(df["seed"]) == [0, 0, 1, 1]
    assert df["config_id"].nunique() == 2  # two configurations, two seeds each
    ok = df[df["status"] == "ok"]
    assert (ok["config/msckf.update_linearization"] == "current_oc").all() and len(ok) == 2
    assert np.all(np.isfinite(ok["ate_posyaw_m"])) and ok["error"].isna().all()


def test_failing_run_is_a_row_and_the_others_finish(swept):
    _, _, result = swept
    df = pd.read_parquet(result.results)
    bad = df[df["config/msckf.update_linearization"] == "bogus"]
    assert (bad["status"] == "error").all() and len(bad) == 2
    assert bad["error"].str.contains("update_linearization").all()
    assert bad["ate_posyaw_m"].isna().all()


def test_resume_computes_nothing_new(swept):
    spec, out, first = swept
    again = run_sweep(spec, out, workers=2)
    assert (again.runs, again.computed, again.skipped, again.failed) == (4, 0, 4, 2)
    pd.testing.assert_frame_equal(pd.read_parquet(again.results), pd.read_parquet(first.results))


def test_same_seed_same_metrics_as_sequential_run_config(swept):
    _, _, result = swept
    df = pd.read_parquet(result.results).set_index("seed")
    ok = df[df["status"] == "ok"]
    for seed in (0, 1):
        cfg = RunConfig(
            scenario="hover",
            estimator="msckf",
            frontend="sim",
            seconds=SECONDS,
            seed=seed,
            params=(("msckf.update_linearization", "current_oc"),),
        )
        assert cfg.run_id == ok.loc[seed, "run_id"]
        metrics = run_config(cfg)
        for key in DETERMINISTIC:
            assert metrics[key] == ok.loc[seed, key], (seed, key)


def test_parameter_override_reaches_the_estimator():
    """The overrides are applied by swapping factories: a silent no-op would make sweeps meaningless."""
    base = RunConfig(scenario="hover", estimator="msckf", frontend="sim", seconds=SECONDS, seed=0)
    few = RunConfig.from_dict({**base.as_dict(), "msckf.max_features_per_update": 5})
    assert few.run_id != base.run_id and few.config_id != base.config_id
    assert run_config(few)["nees_pos_mean"] != run_config(base)["nees_pos_mean"]


def test_retry_failed_and_timeout(local_ray, tmp_path):
    spec = _spec(**{"msckf.update_linearization": ["bogus"]}) | {"seeds": [0]}
    first = run_sweep(spec, tmp_path, workers=2)
    assert (first.computed, first.failed) == (1, 1)
    retried = run_sweep(spec, tmp_path, workers=2, retry_failed=True)
    assert (retried.computed, retried.skipped, retried.failed) == (1, 0, 1)
    slow = run_sweep(
        _spec(**{"msckf.max_clones": [9]}) | {"seeds": [7]}, tmp_path / "t", workers=2, timeout_s=0.5
    )
    assert (slow.computed, slow.failed) == (1, 1)
    row = pd.read_parquet(slow.results).iloc[0]
    assert row["status"] == "timeout" and "timed out" in row["error"]


def test_refuses_a_non_sweep_folder(tmp_path):
    (tmp_path / "something.txt").write_text("x")
    with pytest.raises(FileExistsError, match="not a sweep folder"):
        run_sweep(_spec(), tmp_path)


@pytest.mark.parametrize(
    ("change", "culprit"),
    [
        ({"grid": {"msckf.max_featurs": [1]}}, "msckf.max_featurs"),
        ({"grid": {"msckf.max_clones": ["ten"]}}, "msckf.max_clones"),
        ({"grid": {"window.window_size": [2.5]}}, "window.window_size"),
        ({"grid": {"estimator": []}}, "grid.estimator: empty"),
        ({"grid": {"scenario": ["hover", "hovr"]}}, "hovr"),
        ({"grid": {"estimator": ["msckf", "ekf"]}}, "ekf"),
        ({"grid": {"imu": ["mems"]}}, "mems"),
        ({"grid": {"msckf.klt": [1]}}, "msckf.klt"),
        ({"grid": {"msckf.klt.max_features": ["many"]}}, "msckf.klt.max_features"),
        ({"grid": {"rig.wind.gust_sigma_N": [1.0]}}, "fly"),
        ({"grid": {"seed": [1]}}, "seeds"),
        ({"grid": {"severity": [1.0]}}, "severity"),
        (
            {"grid": {"estimator": ["msckf"]}, "fixed": {"estimator": "window", "scenario": "hover"}},
            "more than once",
        ),
        ({"fixed": {"mode": "fly", "scenario": "hover"}}, "hover"),
        ({"random": {"draws": 2, "axes": {"msckf.max_clones": {"uniform": [5, 12]}}}}, "msckf.max_clones"),
        ({"random": {"draws": 2, "axes": {"msckf.pixel_sigma_px": {"normal": [1, 2]}}}}, "normal"),
        ({"seeds": []}, "seeds"),
        ({"timeout": 10}, "timeout"),
    ],
)
def test_spec_errors_name_the_culprit(cat, change, culprit):
    spec = _spec()
    spec.update(change)
    with pytest.raises(SpecError, match=None) as info:
        parse_spec(spec, cat)
    assert culprit in str(info.value), str(info.value)


def test_spec_expansion_and_stable_ids(cat):
    spec = _spec(estimator=["msckf", "window"], **{"msckf.integration": ["RK4", "discrete"]})
    spec["random"] = {
        "draws": 3,
        "seed": 4,
        "axes": {"msckf.pixel_sigma_px": {"uniform": [0.5, 2.0]}, "msckf.max_clones": {"randint": [8, 15]}},
    }
    runs = parse_spec(spec, cat).expand()
    assert len(runs) == 2 * 2 * 3 * 2
    assert len({r.run_id for r in runs}) == len(runs)
    assert [r.run_id for r in parse_spec(spec, cat).expand()] == [r.run_id for r in runs]  # draws are seeded
    assert {dict(r.params)["msckf.integration"] for r in runs} == {"rk4", "discrete"}  # canonical enum values
    # 4 and 4.0 seconds are the same run (canonical floats), key order does not matter.
    a = parse_spec(_spec() | {"fixed": {**_spec()["fixed"], "seconds": 4}}, cat).expand()[0]
    b = RunConfig.from_dict(dict(reversed(list(a.as_dict().items()))) | {"seconds": 4.0})
    assert a.run_id == b.run_id


def test_nees_band_matches_chi2():
    n = 50
    band = nees_band(np.full(n, 3.0))
    assert band["inside"] and band["n"] == n
    np.testing.assert_allclose([band["low"], band["high"]], chi2.ppf([0.025, 0.975], 3 * n) / n, rtol=1e-12)
    assert not nees_band([30.0, 25.0, np.nan])["inside"]


def test_report_and_cli(swept, tmp_path):
    _, out, _ = swept
    summary = sweep_report(out, tmp_path / "report")
    assert summary["rows"] == 4 and summary["failed"] == 2
    assert {Path(p).name for p in summary["plots"]} == {"ate.png", "drift.png", "nees.png", "timing.png"}
    assert all(Path(p).stat().st_size > 0 for p in summary["plots"] + summary["tables"])
    ok = next(c for c in summary["configs"] if "current_oc" in c["label"])
    assert ok["runs"] == 2 and ok["failed"] == 0 and ok["nees"]["n"] == 2
    runner = CliRunner()
    res = runner.invoke(app, ["sweep-report", str(out), "--json"])
    assert res.exit_code == 0, res.output
    last = json.loads(res.stdout.strip().splitlines()[-1])
    assert last["rows"] == 4
    res = runner.invoke(app, ["sweep", str(out / "spec.yaml"), "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout.strip().splitlines()[-1]) == {
        "runs": 4,
        "computed": 0,
        "skipped": 4,
        "failed": 2,
        "results": str(out / "results.parquet"),
        "wall_s": pytest.approx(0, abs=60),
        "interrupted": False,
    }


def test_cli_refuses_a_bad_spec(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("fixed: {scenario: hover}\ngrid: {msckf.max_featurs: [10]}\n")
    res = CliRunner().invoke(app, ["sweep", str(bad), "--out", str(tmp_path / "out"), "--json"])
    assert res.exit_code == 2
    assert "msckf.max_featurs" in res.output
    assert not (tmp_path / "out").exists()  # checked before any work


@pytest.mark.slow
def test_smoke_example_spec(tmp_path):
    """examples/sweep-smoke.yaml through the CLI on a fresh local Ray (about a minute on two cores)."""
    spec = Path(__file__).resolve().parent.parent / "examples" / "sweep-smoke.yaml"
    res = CliRunner().invoke(app, ["sweep", str(spec), "--out", str(tmp_path), "--workers", "2", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert (out["runs"], out["computed"], out["failed"]) == (4, 4, 0)
