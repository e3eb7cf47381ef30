"""Tests of envs/tools/regress.py: passes on its baseline, fails on a degraded filter or a tight baseline."""

from __future__ import annotations

import json

import pytest
from viotb.envs.tools.regress import DEFAULT_BASELINE, compare, load_baseline, run_suite, write_baseline
from viotb.vio.keyframing import KeyframeParams
from viotb.vio.msckf import MsckfParams


@pytest.fixture(scope="module")
def hover_result():
    return run_suite(fly_case=False, only=("hover-sim",))


def _only(baseline: dict, case: str) -> dict:
    return {**baseline, "cases": {case: baseline["cases"][case]}}


def test_passes_on_committed_baseline_and_is_deterministic(hover_result):
    base = _only(load_baseline(DEFAULT_BASELINE), "hover-sim")
    rows = compare(hover_result, base)
    # The timing ratio depends on the machine's load (a benchmark, checked by `viotb regress` itself);
    # every accuracy metric must pass.
    accuracy = [r for r in rows if r["metric"] != "timing_ratio"]
    assert len(accuracy) >= 5 and all(r["ok"] for r in accuracy), accuracy
    # Same seed, same metrics up to BLAS round-off across processes (measured 1.4e-9 relative).
    for metric in ("ate_m", "final_err_m", "nees_pos"):
        assert hover_result["cases"]["hover-sim"][metric] == pytest.approx(
            base["cases"]["hover-sim"][metric], rel=1e-6
        )


def test_fails_on_degraded_filter():
    bad = run_suite(
        fly_case=False,
        only=("hover-sim",),
        params=MsckfParams(pixel_sigma_px=8.0, max_clones=4, keyframing=KeyframeParams(every_n_frames=1)),
    )
    rows = compare(bad, _only(load_baseline(DEFAULT_BASELINE), "hover-sim"))
    assert any(not r["ok"] for r in rows if r["metric"] != "timing_ratio"), rows


def test_fails_on_perturbed_baseline_and_bad_files(hover_result, tmp_path):
    path = tmp_path / "b.json"
    write_baseline(path, hover_result)
    assert all(r["ok"] for r in compare(hover_result, load_baseline(path)))
    data = json.loads(path.read_text())
    # A baseline ATE well below the run's ATE minus the absolute tolerance: the run now regresses.
    tol = data["tolerances"]["ate_m"]
    run_ate = hover_result["cases"]["hover-sim"]["ate_m"]
    assert run_ate > tol["abs"], "the hover ATE must exceed the absolute tolerance for this check"
    # compare() allows baseline + abs + rel * baseline; half the largest passing baseline must fail.
    data["cases"]["hover-sim"]["ate_m"] = 0.5 * (run_ate - tol["abs"]) / (1.0 + tol["rel"])
    path.write_text(json.dumps(data))
    rows = compare(hover_result, load_baseline(path))
    assert [r["metric"] for r in rows if not r["ok"]] == ["ate_m"]
    with pytest.raises(FileNotFoundError, match="not found"):
        load_baseline(tmp_path / "missing.json")
    path.write_text("{")
    with pytest.raises(ValueError, match="invalid JSON"):
        load_baseline(path)


def test_short_run_is_compared_on_the_short_cases_only(hover_result, tmp_path):
    from viotb.envs.tools.regress import IMAGE_CASES, case_names, regress

    base = load_baseline(DEFAULT_BASELINE)
    # The committed baseline holds the full set, image cases included.
    assert set(case_names(full=True)) <= set(base["cases"]) and set(IMAGE_CASES) <= set(base["cases"])
    assert not set(IMAGE_CASES) & set(case_names(full=False))
    rows = compare(hover_result, base, cases=("hover-sim",))
    assert {r["case"] for r in rows} == {"hover-sim"}
    assert all(r["ok"] for r in rows if r["metric"] != "timing_ratio")  # timing: load-dependent
    # Without the filter every case the run lacks fails as missing.
    missing = [r for r in compare(hover_result, base) if r["metric"] == "(missing)"]
    assert {r["case"] for r in missing} == set(base["cases"]) - {"hover-sim"}
    with pytest.raises(ValueError, match="--full"):
        regress(tmp_path / "b.json", update=True, full=False)
