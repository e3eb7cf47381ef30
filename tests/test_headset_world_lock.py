"""Issue #12's look-around target on the real front end: stereo KLT on the rendered pair, raw IMU, 20 s.

Three seeds of ``headset-look-around`` (yaw +-60 deg up to 200 deg/s, in place), ``msckf`` with two
cameras and the headset's settings (``HEADSET_MSCKF``: the gyro's scale/misalignment estimated online, the
gyro noise told 2x the sensor's). The targets: world-lock ATE <= 5 mm and max error
<= 10 mm, and the position NEES within the 95 % band of its chi-square statistic; with three runs the mean
of the three per-run means is compared with ``chi2(9) / 3`` (each run's mean NEES counted as one 3-dof
draw, as the README's single-run band does). Slow: three rendered 20 s runs (~1 min each on a quiet core).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def look_around_results() -> list[dict]:
    from viotb.envs.run.headset import HeadsetOptions, run_headset
    from viotb.envs.run.headset_report import headset_result

    out = []
    for seed in SEEDS:
        opts = HeadsetOptions(estimator="msckf", cameras=2, seconds=20.0, seed=seed)
        out.append(headset_result(run_headset("headset-look-around", opts)))
    return out


@pytest.mark.slow
def test_stereo_look_around_world_lock_and_consistency(look_around_results):
    for r in look_around_results:
        assert not r["diverged"], r
        assert r["world_lock_ate_mm"] <= 5.0, r
    nees = np.mean([r["nees_pos_mean"] for r in look_around_results])
    dof = 3 * len(SEEDS)
    lo, hi = chi2.ppf([0.025, 0.975], dof) / len(SEEDS)
    assert lo <= nees <= hi, (nees, lo, hi)


@pytest.mark.slow
def test_stereo_look_around_max_error(look_around_results):
    """Measured 6.8 / 7.7 / 7.3 mm (11.1 / 8.1 / 8.6 mm without the online gyro intrinsics, 10x noise)."""
    for r in look_around_results:
        assert r["max_err_mm"] <= 10.0, r
