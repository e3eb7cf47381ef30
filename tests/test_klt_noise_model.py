"""The KLT noise model measured on the renders: the robust fit of ``benchmarks/klt_track_error.py``, its use.

- :func:`fit_core` recovers the white sigma and the random walk per px of synthetic track errors drawn from
  that model; when 10 % of the tracks slide off their point by pixels (the tail the MSCKF gate removes) it
  stays within a bounded, upward bias and reports that tail's share.
- :meth:`MsckfParams.with_render_klt_noise` sets exactly the two measured numbers.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from data_paths import load_repo_script
from viotb.vio.msckf_params import (
    RENDER_KLT_PIXEL_SIGMA_PX,
    RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX,
    MsckfParams,
)


def _bench():
    return load_repo_script("benchmarks/klt_track_error.py")


def _tracks(rng: np.random.Generator, s_w: float, q: float, n: int, slide_share: float) -> dict:
    """Tracks as ``track_errors`` returns them: rows (frame, e_u, e_v, u, v), ``e = w_k - w_0 + walk``."""
    out = {}
    for tid in range(n):
        length = int(rng.integers(20, 80))
        step = rng.uniform(0.3, 4.0, size=length - 1)  # image motion per frame (px)
        heading = rng.uniform(0.0, 2.0 * np.pi)
        uv = np.cumsum(
            np.vstack([[160.0, 120.0], step[:, None] * [np.cos(heading), np.sin(heading)]]), axis=0
        )
        walk = np.vstack(
            [[0.0, 0.0], np.cumsum(rng.normal(size=(length - 1, 2)) * np.sqrt(q * step)[:, None], 0)]
        )
        w = rng.normal(scale=s_w, size=(length, 2))
        e = w - w[0] + walk
        if rng.random() < slide_share:  # slips off its point: 0.3 px per frame
            e += np.arange(length)[:, None] * 0.3 * np.array([1.0, -1.0])
        out[tid] = np.column_stack([np.arange(length) + tid, e, uv])
    return out


@pytest.mark.parametrize("slide_share", [0.0, 0.1])
def test_fit_core_recovers_the_white_and_walk_model(slide_share: float) -> None:
    rng = np.random.default_rng(0)
    s_w, q = 0.03, 2e-4
    fit = _bench().fit_core(_tracks(rng, s_w, q, 600, slide_share))
    if slide_share:
        # The median has a bias, not a breakdown: 10 % of sliding tracks raise the white sigma by 10-16 %
        # and the walk by 30-40 % (seeds 0-2), on the safe side.
        assert s_w < fit["white_sigma_px"] < 1.25 * s_w
        assert q < fit["rw_px2_per_px"] < 1.6 * q
        assert 0.05 < fit["tail_share"] < 0.15  # the sliding tracks (all but their first few views)
    else:
        assert fit["white_sigma_px"] == pytest.approx(s_w, rel=0.1)
        assert fit["rw_px2_per_px"] == pytest.approx(q, rel=0.2)
        assert fit["tail_share"] < 1e-3  # 5 sigma of a Gaussian: ~6e-7 per axis


def test_fit_core_without_a_walk_finds_none() -> None:
    rng = np.random.default_rng(1)
    fit = _bench().fit_core(_tracks(rng, 0.05, 0.0, 400, 0.0))
    assert fit["white_sigma_px"] == pytest.approx(0.05, rel=0.1)
    assert fit["rw_px2_per_px"] < 2e-5


def test_render_klt_noise_sets_the_measured_white_and_walk_only() -> None:
    base = MsckfParams(max_clones=9)
    p = base.with_render_klt_noise()
    assert p.pixel_sigma_px == RENDER_KLT_PIXEL_SIGMA_PX
    assert p.klt.track_random_walk_px2_per_px == RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX
    assert replace(p, pixel_sigma_px=base.pixel_sigma_px, klt=base.klt) == base
