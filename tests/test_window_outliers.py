"""Tests of the window's track test (`landmark_chi2`, `LandmarkOutlierTest` of vio/window_reprojection.py).

Each landmark's whitened cost against an independent dense computation: its views' residuals from the
projection, their covariance ``I + q min(n_u, n_v)`` (the track's pixel path, a plain loop) inverted
densely; the test itself on a landmark given a gross error in one view.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2
from test_window_reprojection import (
    FOCAL_PX,
    SIGMA_PX,
    _factors,
    _problem,
    _weights,
    track_covariance,
    track_views,
)
from viotb.vio.window_factors import project
from viotb.vio.window_params import WindowParams
from viotb.vio.window_reprojection import LandmarkOutlierTest, landmark_chi2
from viotb.vio.window_solver import linearize


def _dense_costs(xs, pts, obs, R_BC, p_BC, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Per landmark ``r^T C^-1 r`` of its views (r in sigmas) and its views' count."""
    kf_i, lm_i, xy = obs
    costs, views = np.zeros(len(pts)), np.zeros(len(pts))
    for lm in range(len(pts)):
        ms = track_views(kf_i, lm_i, lm)
        R = np.stack([xs[kf_i[m]].R_WB for m in ms])
        p = np.stack([xs[kf_i[m]].p_WB for m in ms])
        r = (
            (project(R, p, np.repeat(pts[lm : lm + 1], len(ms), 0), R_BC, p_BC) - xy[ms])
            * FOCAL_PX
            / SIGMA_PX
        ).ravel()
        C = track_covariance(xy, ms, q)
        costs[lm], views[lm] = float(r @ np.linalg.solve(C, r)), len(ms)
    return costs, views


@pytest.mark.parametrize("kernels", ["numba", "numpy"])
@pytest.mark.parametrize("q", [0.0, 0.05])
def test_landmark_cost_is_each_tracks_generalized_least_squares(q, kernels):
    """White (both block kinds) and correlated noise: the cost per landmark and ``2 M - 3`` dof."""
    xs, pts, obs, R_BC, p_BC = _problem()
    w8 = dataclasses.replace(_weights(R_BC, p_BC, q), kernels=kernels)
    sys = linearize(xs, pts, _factors(obs), w8)
    cost, dof = landmark_chi2(sys.reprojection_blocks, len(pts))
    cost_ref, views = _dense_costs(xs, pts, obs, R_BC, p_BC, q)
    np.testing.assert_allclose(cost, cost_ref, rtol=1e-9)
    np.testing.assert_array_equal(dof, 2 * views - 3)
    np.testing.assert_allclose(0.5 * cost.sum(), sys.cost, rtol=1e-9)  # no prior, inside the Huber band


@pytest.mark.parametrize("q", [0.0, 0.05])
def test_a_gross_error_in_one_view_fails_the_track_test(q):
    """4 px on one view of landmark 3 (noise 0.4 px told 1 px): only that landmark fails at 95 %."""
    xs, pts, (kf_i, lm_i, xy), R_BC, p_BC = _problem(seed=2)
    m = np.nonzero(lm_i == 3)[0][1]
    xy = xy.copy()
    xy[m] += np.array([4.0, 0.0]) / FOCAL_PX
    sys = linearize(xs, pts, _factors((kf_i, lm_i, xy)), _weights(R_BC, p_BC, q))
    bad = LandmarkOutlierTest.create(np.inf, 0.95, len(xs))(sys)
    assert np.nonzero(bad)[0].tolist() == [3]
    cost, dof = landmark_chi2(sys.reprojection_blocks, len(pts))
    assert cost[3] > chi2.ppf(0.95, dof[3])
    # Without the quantile only the per-view rule applies: 4 px is 4 sigmas.
    assert np.nonzero(LandmarkOutlierTest.create(3.5, None, len(xs))(sys))[0].tolist() == [3]
    assert not LandmarkOutlierTest.create(4.5, None, len(xs))(sys).any()


@pytest.mark.parametrize("q", [0.0, 1.0, 1.5, -0.1])
def test_a_quantile_outside_the_unit_interval_is_refused(q):
    """``WindowParams.outlier_chi2`` outside (0, 1): a ValueError naming the field and the value."""
    with pytest.raises(ValueError, match=rf"outlier_chi2 must be in \(0, 1\) or None, got {q}"):
        WindowParams(outlier_chi2=q)
