"""Compiled front-end kernels (vio/frontend_kernels.py) against their numpy references (vio/klt_anchor.py)."""

from __future__ import annotations

import copy
import dataclasses

import cv2
import numpy as np
import pytest
from data_paths import EUROC_MICRO, load_repo_script
from viotb.vio.frontend import KltParams, KltTracker
from viotb.vio.frontend_kernels import sample_patch
from viotb.vio.klt_anchor import TemplateAnchors

H_PX, W_PX = 240, 320


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.uniform(0.0, 255.0, (2 * H_PX, 2 * W_PX)), (0, 0), 3.0)
    return big.astype(np.float32)


def _homography(k: int) -> np.ndarray:
    """A view that drifts, turns, stretches and tilts with the frame index ``k`` (texture -> image)."""
    return np.array(
        [
            [1.0 + 0.01 * k, 0.02 * k, 40.0 + 3.1 * k],
            [-0.015 * k, 1.0 - 0.008 * k, 30.0 + 1.7 * k],
            [2e-5 * k, -1.5e-5 * k, 1.0],
        ]
    )


def _frame(texture: np.ndarray, k: int) -> np.ndarray:
    return cv2.warpPerspective(texture, _homography(k), (W_PX, H_PX), flags=cv2.INTER_CUBIC)


@pytest.mark.parametrize("use_g", [False, True])
def test_sample_patch_is_cv2_remap_of_the_numpy_patch_grid(use_g):
    rng = np.random.default_rng(0)
    image = _texture(1)[:H_PX, :W_PX].copy()
    anchors = TemplateAnchors(5)
    n = 40
    c = rng.uniform(-3.0, 330.0, (n, 2))  # some patches over the border (replicated)
    A = np.eye(2) + rng.normal(0.0, 0.2, (n, 2, 2))
    g = rng.normal(0.0, 0.01, (n, 2)) if use_g else np.zeros((n, 2))
    ref = anchors._sample(image, c, A, g if use_g else None)
    out = np.empty((n, ref.shape[1]), dtype=np.float32)
    for k in range(n):
        sample_patch(image, c[k], A[k], g[k], use_g, anchors._r, out[k])
    # The same float32 coordinates and OpenCV 5's float32 lerp: equal on this build; float32 round-off of
    # values up to 255 elsewhere (1.5e-5 is one ulp at 255).
    np.testing.assert_allclose(out, ref, rtol=0.0, atol=1e-4)


@pytest.mark.parametrize(
    ("projective_after_px", "zncc_at_final_warp"), [(float("inf"), True), (20.0, True), (3.0, False)]
)
def test_compiled_refine_follows_the_numpy_reference_over_a_sequence(projective_after_px, zncc_at_final_warp):
    """Seven frames of a drifting homography view: affine, translation and homography fits, border losses.

    Each frame both versions start from the same templates and warps (the numpy reference's), so the
    comparison is per call: carried over frames, the float32 round-off of either (numpy sums in float32,
    the kernel in float64) would make the warps walk apart by more than one call's round-off.
    """
    texture = _texture(2)
    gx, gy = np.meshgrid(np.linspace(2.0, W_PX - 3.0, 16), np.linspace(2.0, H_PX - 3.0, 12))
    uv0 = np.stack([gx.ravel(), gy.ravel()], axis=1)
    ids = np.arange(len(uv0))
    rng = np.random.default_rng(5)
    ref = TemplateAnchors(
        5, iterations=2, projective_after_px=projective_after_px, zncc_at_final_warp=zncc_at_final_warp
    )
    ref.compiled = False
    ref.take(_frame(texture, 0), ids, uv0)
    to_texture = np.linalg.inv(_homography(0))
    n_anchored, n_projective = [], 0
    for k in range(1, 8):
        X = np.c_[uv0, np.ones(len(uv0))] @ to_texture.T @ _homography(k).T
        start = X[:, :2] / X[:, 2:] + rng.normal(0.0, 0.3, uv0.shape)  # a frame-to-frame guess
        new = copy.deepcopy(ref)
        new.compiled = True
        image = _frame(texture, k)
        uv_ref, ok_ref = ref.refine(image, ids, start)
        uv_new, ok_new = new.refine(image, ids, start)
        np.testing.assert_array_equal(ok_new, ok_ref)
        # Float32 patch coordinates: one ulp is 3e-5 px at x = 300 px, and a sum taken in another order
        # can move a coordinate by one.
        np.testing.assert_allclose(uv_new, uv_ref, rtol=0.0, atol=1e-4)
        # The warp is the slope of the positions over the patch: their tolerance over the half side (5 px)
        # for A, over its square for g.
        np.testing.assert_allclose(new._A, ref._A, rtol=0.0, atol=1e-4 / 5)
        np.testing.assert_allclose(new._g, ref._g, rtol=0.0, atol=1e-4 / 25)
        n_anchored.append(int(ok_ref.sum()))
        n_projective = int(np.sum(np.any(ref._g != 0.0, axis=1)))
    assert min(n_anchored) > 50 and n_anchored[0] > n_anchored[-1]  # many tracks held, some lost at borders
    assert (n_projective > 0) == bool(np.isfinite(projective_after_px))  # the homography fit ran


@pytest.mark.skipif(not (EUROC_MICRO / "mav0").is_dir(), reason="EuRoC micro set not found")
def test_klt_tracker_with_compiled_anchoring_keeps_the_numpy_tracks_on_euroc():
    """The whole tracker on real images (EuRoC micro 752x480, 12 frames): the same tracks.

    Here the warps are carried from frame to frame in each version, so the per-call round-off above
    (1e-4 px) adds up along a track: 3e-4 px after 12 frames on this build; 1e-3 px bounds that walk
    (a tenth of a percent of the ~0.1 px track error it would take to matter).
    """
    bench = load_repo_script("benchmarks/frontend_cost.py")
    ds, frames = bench.load_frames(EUROC_MICRO, cameras=1, max_frames=12)
    tracks = {}
    for compiled in (False, True):
        tracker = KltTracker(ds.calib.camera, KltParams(anchor_compiled=compiled))
        tracks[compiled] = [tracker.process(f, f.t_s) for f in frames]
    for ref, new in zip(tracks[False], tracks[True], strict=True):
        np.testing.assert_array_equal(new.ids, ref.ids)
        np.testing.assert_allclose(new.uv_px, ref.uv_px, rtol=0.0, atol=1e-3)
    assert len(tracks[True][-1]) > 50


@pytest.mark.skipif(not (EUROC_MICRO / "mav0").is_dir(), reason="EuRoC micro set not found")
@pytest.mark.parametrize("overlap", ["parallel_anchoring", "parallel_detection", "deferred_templates", "all"])
def test_work_in_the_worker_thread_gives_the_sequential_tracks_bit_for_bit(overlap):
    """The tracker's work in its second thread, each option alone and all three, against none of them.

    ``parallel_anchoring`` (the anchoring beside the backward pass), ``parallel_detection`` (FAST beside
    the forward pass) and ``deferred_templates`` (the template taking after the frame returns). A blank
    frame in the middle ends every track (``reset`` waits for the templates still being taken).
    """
    bench = load_repo_script("benchmarks/frontend_cost.py")
    ds, frames = bench.load_frames(EUROC_MICRO, cameras=1, max_frames=12)
    frames[6] = dataclasses.replace(frames[6], image=None)
    names = ("parallel_anchoring", "parallel_detection", "deferred_templates")
    serial = KltParams(**dict.fromkeys(names, False))
    params = {
        "serial": serial,
        "overlap": dataclasses.replace(serial, **{n: n == overlap or overlap == "all" for n in names}),
    }
    tracks = {}
    for key, kp in params.items():
        tracker = KltTracker(ds.calib.camera, kp)
        tracks[key] = [tracker.process(f, f.t_s) for f in frames]
    for seq, par in zip(tracks["serial"], tracks["overlap"], strict=True):
        np.testing.assert_array_equal(par.ids, seq.ids)
        np.testing.assert_array_equal(par.uv_px, seq.uv_px)
    assert (
        len(tracks["overlap"][6]) == 0 and len(tracks["overlap"][5]) > 50 and len(tracks["overlap"][-1]) > 50
    )


@pytest.mark.parametrize("projective", [False, True])
def test_compiled_template_taking_equals_the_numpy_reference(projective):
    """``take_templates`` against ``take_templates_numpy``: textured, flat and near-singular patches.

    The template is float32 (its mean and RMS summed in float64 here, in float32 pairwise by numpy:
    round-off of values around 1, 1e-6); the solve matrices come from those templates and from another
    inversion (Gauss-Jordan against LAPACK), so they agree to the template's round-off, not to float64's.
    """
    from viotb.vio.frontend_take_kernel import take_templates
    from viotb.vio.klt_math import take_templates_numpy

    rng = np.random.default_rng(3)
    image = _texture(4)[:H_PX, :W_PX].copy()
    image[150:200, 200:260] = 77.0  # flat: no template there
    image[20:60, 250:300] = np.tile(np.linspace(0.0, 200.0, 50, dtype=np.float32), (40, 1))  # a ramp: edge
    uv = np.concatenate(
        [rng.uniform(8.0, [W_PX - 9.0, H_PX - 9.0], (60, 2)), [[230.0, 175.0], [275.0, 40.0]]]
    )
    r = TemplateAnchors(5)._r
    args = (r, 1e-3, 1.0, projective, 4.0)
    keep_ref, tmpl_ref, J_ref, Jt_ref = take_templates_numpy(image, uv, *args)
    keep, tmpl, J, Jt = take_templates(image, uv, *args)
    np.testing.assert_array_equal(keep, keep_ref)
    assert 25 <= keep.sum() < len(uv) and not keep[-2]  # textured ones kept, the flat patch refused
    np.testing.assert_allclose(tmpl[keep], tmpl_ref[keep], rtol=0.0, atol=1e-5)
    scale = np.abs(J_ref[keep]).max(axis=-1, keepdims=True) + 1e-30
    np.testing.assert_allclose(J[keep] / scale, J_ref[keep] / scale, rtol=0.0, atol=1e-5)
    # J T sums 121 products that partly cancel: compared on the scale of its track's largest entry.
    jt_scale = np.abs(Jt_ref[keep]).max(axis=(1, 2))[:, None, None]
    np.testing.assert_allclose(Jt[keep] / jt_scale, Jt_ref[keep] / jt_scale, rtol=0.0, atol=1e-5)
    assert J.shape[2] == (8 if projective else 6)
    # The stored rows a fit does not have are zero (the alignment reads only its own rows).
    assert not np.any(J[:, 0, :4]) and not np.any(J[:, 1, 6:])


def test_template_store_holds_the_compiled_templates_for_refining():
    """``TemplateAnchors.take`` with either implementation stores templates that refine alike."""
    texture = _texture(6)
    gx, gy = np.meshgrid(np.linspace(10.0, W_PX - 11.0, 10), np.linspace(10.0, H_PX - 11.0, 8))
    uv0 = np.stack([gx.ravel(), gy.ravel()], axis=1)
    ids = np.arange(len(uv0))
    stores = {}
    for compiled in (False, True):
        a = TemplateAnchors(5, iterations=2, projective_after_px=20.0, compiled=compiled)
        a.take(_frame(texture, 0), ids, uv0)
        stores[compiled] = a
    np.testing.assert_array_equal(stores[True].ids, stores[False].ids)
    X = np.c_[uv0, np.ones(len(uv0))] @ np.linalg.inv(_homography(0)).T @ _homography(1).T
    start = X[:, :2] / X[:, 2:] + np.random.default_rng(1).normal(0.0, 0.3, uv0.shape)
    for s in stores.values():
        s.compiled = True  # the same alignment kernel, so only the templates differ
    uv_ref, ok_ref = stores[False].refine(_frame(texture, 1), ids, start)
    uv_new, ok_new = stores[True].refine(_frame(texture, 1), ids, start)
    np.testing.assert_array_equal(ok_new, ok_ref)
    assert ok_ref.sum() > 25
    np.testing.assert_allclose(uv_new, uv_ref, rtol=0.0, atol=1e-4)
