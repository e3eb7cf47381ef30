"""``viotb bench``'s JSON: the keys of each section and that every speed figure is positive and finite."""

import json
import math
import sys

import pytest
from viotb.envs.tools.bench import SECTIONS, run_bench
from viotb.envs.tools.bench_gym import SETUPS

FIGURES = {
    "render": (
        "render_gray_ms_320x240",
        "render_gray_ms_640x480",
        "render_depth_ms_320x240",
        "physics_steps_per_s",
    ),
    "record": ("realtime_factor_median", "realtime_factor"),
    "estimator": (
        "ms_per_frame_median",
        "ms_per_frame_p99",
        "window_ms_per_frame_median",
        "window_ms_per_frame_p99",
    ),
    "closed_loop": (
        "realtime_factor_klt_median",
        "realtime_factor_sim_median",
        "cpu_realtime_factor_klt_median",
        "cpu_realtime_factor_sim_median",
    ),
}
"""Section -> its speed figures (each must be a positive finite number)."""

GYM_FIGURES = (
    "ctrl_dt_s",
    "single_steps_per_s",
    "single_realtime_factor",
    "vector_steps_per_s",
    "vector_realtime_factor",
    "single_cpu_realtime_factor",
)
GYM_PROC_FIGURES = ("vector_cpu_realtime_factor", "vector_cpu_overhead")
"""Read from ``/proc`` (the async workers' CPU time): required on Linux."""


def _assert_figures(section: dict, keys: tuple[str, ...]) -> None:
    for key in keys:
        value = section[key]
        assert isinstance(value, float) and math.isfinite(value) and value > 0.0, (key, value)


def _check(result: dict, sections: tuple[str, ...]) -> None:
    json.dumps(result, allow_nan=False)  # strict JSON
    assert result["seconds"] > 0 and result["repeats"] >= 1
    for name in sections:
        if name == "gym":
            assert set(result["gym"]) == set(SETUPS)
            for setup in SETUPS:
                _assert_figures(result["gym"][setup], GYM_FIGURES)
                if sys.platform.startswith("linux"):
                    _assert_figures(result["gym"][setup], GYM_PROC_FIGURES)
                assert result["gym"][setup]["vector_num_envs"] == 2
        else:
            _assert_figures(result[name], FIGURES[name])
    assert set(result) == {"seconds", "repeats", *sections}


def test_bench_closed_loop_section():
    _check(run_bench(("closed_loop",), seconds=0.5, repeats=1), ("closed_loop",))


@pytest.mark.slow
def test_bench_gym_section():
    _check(run_bench(("gym",), seconds=0.5, repeats=1), ("gym",))


def test_bench_rejects_unknown_sections():
    with pytest.raises(ValueError, match="unknown bench sections"):
        run_bench(("closed_loop", "warp"))


@pytest.mark.slow
def test_bench_every_section():
    _check(run_bench(SECTIONS, seconds=2.0, repeats=1), SECTIONS)


def test_bench_record_repeats_reuse_their_folder():
    """Repeats record into one temporary folder; the second replaces the first, not stop the bench."""
    result = run_bench(("record",), seconds=0.5, repeats=2)
    _check(result, ("record",))
    assert result["record"]["realtime_factor_median"] > 0
