"""Tests of the compiled MSCKF update kernels against their numpy references (``MsckfParams.update_kernels``).

The numpy implementation is the reference: on random views (triangulation) and on updates captured from a
short synthetic stereo flight, replayed with each front-end noise model and linearization, the compiled
path must accept and reject the same features and give the same updated mean and covariance to round-off.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
import viotb.vio.msckf as msckf_module
from stereo_world import LookAroundWorld, run_look_around
from test_triangulation import _observe, _views
from viotb.vio.msckf import MsckfEstimator, MsckfParams
from viotb.vio.msckf_update import msckf_update
from viotb.vio.triangulation import TriangulationParams, triangulate
from viotb.vio.types import ImuNoise


def _random_views(seed: int, n: int = 60, views: int = 11):
    rng = np.random.default_rng(seed)
    R_WC, p_WC = _views(rng, views)
    pts = rng.uniform([-2, -2, 3], [2, 2, 8], (n, 3))
    pts[0, 2] = -5.0  # behind the cameras
    pts[1, 2] = 500.0  # too little parallax
    xy = _observe(R_WC, p_WC, pts, rng, 0.5 / 400.0)
    xy[2, 3] += 0.05  # a 20 px outlier
    mask = rng.random((n, views)) < 0.7
    mask[:3] = True  # the outlier and the degenerate points in every view
    mask[3] = False  # no view
    mask[4, 1:] = False  # one view
    return R_WC, p_WC, np.where(mask[..., None], xy, np.nan), mask


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_triangulation_equals_the_numpy_reference(seed):
    R_WC, p_WC, xy, mask = _random_views(seed)
    # Every iteration (no early stop): both converge to the same point. Near the minimum the steps are
    # accepted by comparing costs that differ at round-off, so the converged points differ by ~1e-9
    # relative; numpy and test_triangulation's per-feature reference differ from each other as much.
    full = TriangulationParams(step_tolerance=0.0, max_iterations=20)
    ref = triangulate(R_WC, p_WC, xy, mask, full, 400.0)
    nb = triangulate(R_WC, p_WC, xy, mask, full, 400.0, kernels="numba")
    np.testing.assert_array_equal(nb.valid, ref.valid)
    assert ref.valid.sum() > 40 and not ref.valid[:5].any()
    ok = ref.valid
    np.testing.assert_allclose(nb.p_W[ok], ref.p_W[ok], rtol=1e-8, atol=0.0)
    np.testing.assert_allclose(nb.rms_error_px, ref.rms_error_px, rtol=1e-9, atol=1e-12)
    well = ref.condition_number < 1e10  # the degenerate ones' condition number is round-off over round-off
    np.testing.assert_allclose(nb.condition_number[well], ref.condition_number[well], rtol=1e-9)
    # The default stops once every step is below 1e-6 of the parameters; a last step that improves the
    # cost only at round-off may be taken by one and not the other, so the points agree to that step.
    ref_d = triangulate(R_WC, p_WC, xy, mask, TriangulationParams(), 400.0)
    nb_d = triangulate(R_WC, p_WC, xy, mask, TriangulationParams(), 400.0, kernels="numba")
    np.testing.assert_array_equal(nb_d.valid, ref_d.valid)
    np.testing.assert_allclose(nb_d.p_W[ok], ref_d.p_W[ok], rtol=1e-7, atol=0.0)


def test_update_kernels_is_validated():
    with pytest.raises(ValueError, match="update_kernels"):
        MsckfParams(update_kernels="cuda")
    with pytest.raises(ValueError, match="kernels"):
        triangulate(*_random_views(0)[:4], kernels="cuda")


@pytest.fixture(scope="module")
def captured_updates():
    """Deep copies of the MSCKF updates' inputs of a 2 s stereo look-around, the extrinsic estimated."""
    world = LookAroundWorld(np.random.default_rng(7))
    params = MsckfParams(frontend="sim", pixel_sigma_px=0.5, estimate_extrinsics=True, update_kernels="numpy")
    est = MsckfEstimator(world.calib0, ImuNoise(), params, calib_right=world.calib1)
    calls = []
    real = msckf_module.msckf_update

    def capture(*args, **kwargs):
        assert not kwargs.get("use_oldest")  # no update-gap rule here: the replay calls without it
        calls.append(copy.deepcopy(args))
        return real(*args, **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(msckf_module, "msckf_update", capture)
    try:
        run_look_around(est, world, seed=3, seconds=2.0, stereo=True)
    finally:
        mp.undo()
    assert len(calls) > 15
    return calls[5::4]


def _state_vector(st) -> np.ndarray:
    parts = [c.p_WB for c in st.clones.values()] + [c.R_WB.ravel() for c in st.clones.values()]
    return np.concatenate(parts + [np.asarray(st.p_BC, dtype=float), np.asarray(st.R_BC).ravel()])


@pytest.mark.parametrize(
    "variant",
    ["as_flown", "klt_random_walk", "mono", "first_estimates", "current", "tight_gate", "right_sigma"],
)
def test_compiled_update_equals_the_numpy_reference(captured_updates, variant):
    n_used = n_rejected = 0
    for st, db, p, chi2_table, t_s, focal_px, calib_right, focal_right_px in captured_updates:
        if variant == "klt_random_walk":
            p = replace(p, frontend="klt", klt=replace(p.klt, track_random_walk_px2_per_px=0.02))
        elif variant == "mono":
            calib_right = None
        elif variant in ("first_estimates", "current"):
            p = replace(p, update_linearization=variant)
        elif variant == "right_sigma":
            p = replace(p, right_pixel_sigma_px=1.5)  # cam1 told 3x cam0's 0.5 px
        elif variant == "tight_gate":
            p = replace(p, chi2_multiplier=0.75)  # rejects some, so the kernel's selection is exercised
        out = {}
        for kernels in ("numpy", "numba"):
            s, d = copy.deepcopy(st), copy.deepcopy(db)
            stats = msckf_update(
                s,
                d,
                replace(p, update_kernels=kernels),
                chi2_table,
                t_s,
                focal_px,
                calib_right,
                focal_right_px,
            )
            out[kernels] = (s, stats)
        (ref, ref_stats), (nb, nb_stats) = out["numpy"], out["numba"]
        for name in ("candidates", "triangulated", "used", "rejected", "rows", "inconsistent"):
            assert getattr(nb_stats, name) == getattr(ref_stats, name), name
        np.testing.assert_allclose(nb_stats.nis_per_dof_all, ref_stats.nis_per_dof_all, rtol=1e-8)
        n_used += ref_stats.used
        n_rejected += ref_stats.rejected
        # The mean moves by the update's step; the two agree to ~1e-8 of it (measured up to 1.3e-8: the
        # triangulated points differ by ~1e-9 relative, see above, and the EKF update loses digits).
        step = np.abs(_state_vector(ref) - _state_vector(st)).max()
        assert np.abs(_state_vector(nb) - _state_vector(ref)).max() <= 1e-7 * step + 1e-15
        sig = np.sqrt(np.diag(ref.cov))
        assert np.max(np.abs(nb.cov - ref.cov) / np.outer(sig, sig)) < 1e-8
    assert n_used > (10 if variant == "tight_gate" else 50)
    if variant == "tight_gate":
        assert n_rejected > 0


def test_right_row_weight_whitens_cam1_to_cam0s_sigma():
    """Cam1 rows are weighted ``(f1 / f0) (sigma_0 / sigma_1)``: residual / weight is in cam0's sigmas."""
    from viotb.vio.msckf_update import right_row_weight

    p = MsckfParams(pixel_sigma_px=0.05)
    assert right_row_weight(p, 120.0, None) == 1.0
    assert right_row_weight(p, 120.0, 180.0) == pytest.approx(1.5)
    told = replace(p, right_pixel_sigma_px=0.2)
    # A cam1 pixel error of 0.2 px (one of its sigmas) at f1 = 180 px weighs as 0.05 px (one sigma) at f0.
    err_norm = 0.2 / 180.0
    assert err_norm * right_row_weight(told, 120.0, 180.0) == pytest.approx(0.05 / 120.0)
    with pytest.raises(ValueError, match="right_pixel_sigma_px"):
        MsckfParams(right_pixel_sigma_px=0.0)
