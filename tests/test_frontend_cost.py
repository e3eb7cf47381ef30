"""``benchmarks/frontend_cost.py`` on the real EuRoC micro set: deterministic digests, the MSCKF's tracker."""

from __future__ import annotations

import numpy as np
import pytest
from data_paths import EUROC_MICRO, load_repo_script
from viotb.vio.frontend import KltParams, KltTracker

pytestmark = pytest.mark.skipif(not (EUROC_MICRO / "mav0").is_dir(), reason="EuRoC micro set not found")


def test_frontend_cost_times_the_msckf_tracker_and_its_digest_is_repeatable():
    bench = load_repo_script("benchmarks/frontend_cost.py")
    ds, frames = bench.load_frames(EUROC_MICRO, cameras=1, max_frames=12)
    assert len(frames) == 12 and frames[0].image is not None
    cpu, digests, counts, starts, wall = bench.run_once(ds, frames, 1)
    assert np.all(np.isfinite(cpu)) and np.all(cpu > 0.0) and np.all(wall > 0.0)
    assert counts[-1, 0] > 50 and np.all(counts[:, 1] == 0)  # mono: no cam1 observations
    assert starts >= counts[-1, 0]
    again = bench.run_once(ds, frames, 1)[1]
    assert again == digests  # same frames, fresh tracker: the same tracks
    # The tracks are those of the MSCKF's front end with the given settings (here the defaults).
    direct = KltTracker(ds.calib.camera, KltParams())
    last = [direct.process(f, f.t_s) for f in frames][-1]
    assert len(last) == counts[-1, 0]
    # A setting that changes the tracker is passed through (fewer features: other tracks).
    fewer = bench.run_once(ds, frames, 1, {"max_features": 60})
    assert fewer[2][-1, 0] <= 60 and fewer[1] != digests
