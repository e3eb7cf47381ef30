"""Tests of ``benchmarks/msckf_backend.py``: the replayed back end is the filter ``viotb eval`` runs.

The benchmark times the back end on captured front-end tracks. That is only a measurement of the real
filter if (a) its online pass is the computation of ``viotb eval`` (checked against
:func:`viotb.envs.data.evaluate.run_monitored`, an independent driver with the health monitor) and (b) a
replay on the captured tracks reproduces the online pass bit for bit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from data_paths import load_repo_script
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.evaluate import EvalOptions, run_monitored
from viotb.envs.data.record import record_scenario


@pytest.fixture(scope="module")
def figure8(tmp_path_factory) -> Path:
    """A 4 s figure-8 recording at 320x240 (81 frames)."""
    out = tmp_path_factory.mktemp("rec") / "figure8"
    record_scenario("figure8", out, seed=0, seconds=4.0)
    return out


def test_online_pass_is_the_eval_run_and_replays_reproduce_it(figure8):
    bench = load_repo_script("benchmarks/msckf_backend.py")
    online = bench.run_backend(figure8)
    ref = run_monitored(read_euroc(figure8), EvalOptions())
    ref_p = [np.asarray(e.p_WB) for e in ref.estimates if e is not None]
    assert len(ref_p) == len(online.estimates) > 10
    for (p, _, _), q in zip(online.estimates, ref_p, strict=True):
        np.testing.assert_array_equal(p, q)
    assert online.keyframe.sum() > 5  # updates ran
    replay = bench.run_backend(figure8, tracks=online.tracks)
    assert len(replay.estimates) == len(online.estimates)
    for a, b in zip(online.estimates, replay.estimates, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(replay.keyframe, online.keyframe)
    assert np.all(replay.frontend_ms == 0.0) and np.all(online.frontend_ms > 0.0)


def test_measure_reports_positive_finite_figures(figure8):
    bench = load_repo_script("benchmarks/msckf_backend.py")
    out = bench.measure(figure8, repeats=1)
    assert out["replay_reproduces_online_estimates"] is True
    for key in ("backend", "backend_keyframes", "backend_other_frames", "frontend_online"):
        part = out[key]
        assert part["frames"] > 0
        for name in ("median_ms", "p99_ms", "max_ms", "mean_ms"):
            assert np.isfinite(part[name]) and part[name] > 0.0, (key, name)
    n_kf, n_other = out["backend_keyframes"]["frames"], out["backend_other_frames"]["frames"]
    assert n_kf + n_other == out["backend"]["frames"]


def test_measure_times_both_kernels_and_they_fly_the_same(figure8):
    bench = load_repo_script("benchmarks/msckf_backend.py")
    out = bench.measure(figure8, repeats=1, kernels=("numba", "numpy"))
    assert out["replay_reproduces_online_estimates"] is True
    assert set(out["backend_by_kernels"]) == {"numba", "numpy"}
    assert out["backend_by_kernels"]["numba"]["sum_ratio_to_first"] == 1.0
    assert out["backend_by_kernels"]["numpy"]["backend"]["frames"] == out["backend"]["frames"]
    # The two update paths agree to round-off, so the replayed trajectories agree far below a micrometre.
    online = bench.run_backend(figure8)
    ref = bench.run_backend(figure8, tracks=online.tracks, kernels="numpy")
    assert len(ref.estimates) == len(online.estimates)
    worst = max(np.abs(a[0] - b[0]).max() for a, b in zip(online.estimates, ref.estimates, strict=True))
    assert worst < 1e-6
