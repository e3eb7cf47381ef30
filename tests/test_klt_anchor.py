"""Template anchoring of KLT tracks (vio/klt_anchor.py): closed-form shifts, exposure changes, rejection."""

from __future__ import annotations

import cv2
import numpy as np
from viotb.vio.camera import PinholeCamera
from viotb.vio.frontend import KltParams, KltTracker
from viotb.vio.klt_anchor import TemplateAnchors
from viotb.vio.types import CameraFrame


def _texture(seed: int, shape=(240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0.0, 255.0, shape), (0, 0), 2.0)


def _shifted(image: np.ndarray, shift_px: np.ndarray) -> np.ndarray:
    """``image`` moved by ``shift_px`` (x, y), bicubic (an interpolator other than the refiner's bilinear)."""
    M = np.float32([[1.0, 0.0, shift_px[0]], [0.0, 1.0, shift_px[1]]])
    return cv2.warpAffine(image, M, image.shape[::-1], flags=cv2.INTER_CUBIC)


def test_refine_recovers_a_subpixel_shift_under_an_exposure_change():
    rng = np.random.default_rng(0)
    image = _texture(1)
    uv = rng.uniform(30.0, 200.0, (60, 2))
    ids = np.arange(60)
    anchors = TemplateAnchors(affine_after_px=0.0)  # affine even for the tracks that moved under 3 px
    anchors.take(image, ids, uv)
    shift = np.array([0.37, -0.81])
    start = uv + shift + rng.uniform(-1.0, 1.0, uv.shape)  # a frame-to-frame guess up to 1 px off
    refined, anchored = anchors.refine(1.3 * _shifted(image, shift) + 10.0, ids, start)
    assert anchored.mean() > 0.95
    # Bilinear against bicubic resampling and cv2.remap's 1/32 px weights: well under a tenth of a pixel.
    assert np.abs(refined[anchored] - (uv[anchored] + shift)).max() < 0.1
    np.testing.assert_array_equal(refined[~anchored], start[~anchored])
    # By default a track within 3 px of its template is aligned in translation only: as accurate here.
    default = TemplateAnchors()
    default.take(image, ids, uv)
    near, flagged = default.refine(1.3 * _shifted(image, shift) + 10.0, ids, start)
    assert flagged.mean() > 0.95
    assert np.abs(near[flagged] - (uv[flagged] + shift)).max() < 0.1


def test_refine_rejects_a_patch_that_no_longer_matches_and_ignores_unknown_ids():
    anchors = TemplateAnchors(affine_after_px=0.0)
    uv = np.array([[100.0, 100.0], [150.0, 120.0]])
    anchors.take(_texture(2), np.array([4, 7]), uv)
    other = _texture(3)  # another texture: nothing there looks like the templates
    start = np.vstack([uv, [[60.0, 60.0]]])
    refined, anchored = anchors.refine(other, np.array([4, 7, 99]), start)
    assert not anchored.any()
    np.testing.assert_array_equal(refined, start)
    anchors.keep_only(np.array([7]))
    np.testing.assert_array_equal(anchors.ids, [7])


def test_tracker_with_anchors_follows_a_translating_texture():
    camera = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    base = _texture(4, (300, 400))
    frames = []
    for k in range(25):
        offset = np.array([40.0 + 1.37 * k, 30.0 + 0.61 * k])  # the window slides: points move by -offset
        M = np.float32([[1.0, 0.0, -offset[0]], [0.0, 1.0, -offset[1]]])
        frames.append((offset, cv2.warpAffine(base, M, (320, 240), flags=cv2.INTER_CUBIC).astype(np.uint8)))
    errors = {}
    for anchor in (False, True):
        trk = KltTracker(camera, KltParams(anchor_templates=anchor))
        first: dict[int, np.ndarray] = {}
        err = []
        for k, (offset, img) in enumerate(frames):
            tracks = trk.process(CameraFrame(t_s=0.05 * k, image=img), 0.05 * k)
            for tid, uv in zip(tracks.ids, tracks.uv_px, strict=True):
                world = uv + offset
                if int(tid) not in first:
                    first[int(tid)] = world
                err.append(np.linalg.norm(world - first[int(tid)]))
        errors[anchor] = float(np.sqrt(np.mean(np.square(err))))
    # A pure translation: every track should stay on its texture point; anchoring must not be worse.
    assert errors[True] < 0.15
    assert errors[True] <= errors[False] + 0.02


def test_affine_anchor_follows_a_patch_stretched_by_zoom():
    """A zoom stretches every patch, as a wide-angle pinhole does towards its edges.

    The true point of a feature first seen at ``u0`` in a frame zoomed by ``s0`` is ``c + (s / s0) (u0 - c)``.
    """
    camera = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    base = _texture(5)
    centre = np.array([159.5, 119.5])
    frames = []
    for k in range(30):
        s = 1.0 + 0.025 * k  # up to 1.7x
        M = np.float32([[s, 0.0, (1.0 - s) * centre[0]], [0.0, s, (1.0 - s) * centre[1]]])
        frames.append((s, cv2.warpAffine(base, M, (320, 240), flags=cv2.INTER_CUBIC).astype(np.uint8)))
    rms = {}
    for anchor in (False, True):
        trk = KltTracker(camera, KltParams(anchor_templates=anchor))
        first: dict[int, tuple[float, np.ndarray]] = {}
        err = []
        for k, (s, img) in enumerate(frames):
            tracks = trk.process(CameraFrame(t_s=0.05 * k, image=img), 0.05 * k)
            for tid, uv in zip(tracks.ids, tracks.uv_px, strict=True):
                s0, u0 = first.setdefault(int(tid), (s, uv.copy()))
                truth = centre + (s / s0) * (u0 - centre)
                err.append(np.linalg.norm(uv - truth))
        rms[anchor] = float(np.sqrt(np.mean(np.square(err))))
    assert rms[True] < 0.5 * rms[False]
    assert rms[True] < 0.2


def _per_track_reference(image, tmpl_image, uv0, start, iterations=4, half=6, damping=1e-3, affine=True):
    """One track at a time, as Baker & Matthews (2004, sec. 3.2) write it: SD images, Hessian, a solve a step.

    Independent of ``TemplateAnchors``' batching and its folded ``J = H^-1 SD^T``; only the bilinear sampler
    is shared. Returns the final centre (2,) and linear warp (2, 2).
    """
    from viotb.vio.klt_anchor import sample_bilinear

    r = np.arange(-half, half + 1, dtype=float)
    gy, gx = np.meshgrid(r, r, indexing="ij")
    dx, dy = gx.ravel(), gy.ravel()

    def patch(img, c, A):
        x = c[0] + A[0, 0] * dx + A[0, 1] * dy
        y = c[1] + A[1, 0] * dx + A[1, 1] * dy
        return sample_bilinear(img, x[None], y[None])[0].astype(float)

    def normalized(v):
        v = v - v.mean()
        return v / np.sqrt(np.mean(v * v)), np.sqrt(np.mean(v * v))

    T, rms = normalized(patch(tmpl_image, uv0, np.eye(2)))
    gxs = 0.5 * (
        patch(tmpl_image, uv0 + [1.0, 0.0], np.eye(2)) - patch(tmpl_image, uv0 - [1.0, 0.0], np.eye(2))
    )
    gys = 0.5 * (
        patch(tmpl_image, uv0 + [0.0, 1.0], np.eye(2)) - patch(tmpl_image, uv0 - [0.0, 1.0], np.eye(2))
    )
    gxs, gys = gxs / rms, gys / rms
    sd = np.stack([gxs * dx, gys * dx, gxs * dy, gys * dy, gxs, gys], axis=1)  # (P, 6)
    if not affine:
        sd = sd[:, 4:]
    H = sd.T @ sd
    H += damping * np.diag(np.diag(H))  # translation only: the translation block of the damped 6x6 matrix
    c, A = np.asarray(start, dtype=float).copy(), np.eye(2)
    for _ in range(iterations):
        w, _ = normalized(patch(image, c, A))
        dp = np.linalg.solve(H, sd.T @ (w - T))
        if affine:
            inv = np.linalg.inv(np.eye(2) + np.array([[dp[0], dp[2]], [dp[1], dp[3]]]))
            t = dp[4:]
        else:
            inv, t = np.eye(2), dp
        A = A @ inv
        c = c - A @ t
    return c, A


def test_batched_alignment_equals_the_per_track_reference():
    """All tracks aligned at once (one remap, folded solve matrices) = each aligned alone by the book."""
    rng = np.random.default_rng(7)
    image0 = _texture(8).astype(np.float32)
    centre = np.array([159.5, 119.5])
    M = np.array([[1.04, 0.02, 0.0], [-0.015, 0.97, 0.0]])
    M[:, 2] = centre - M[:, :2] @ centre + [0.6, -0.4]  # a small affine change about the centre, shifted
    image1 = cv2.warpAffine(image0, M, (320, 240), flags=cv2.INTER_CUBIC)
    uv0 = rng.uniform(40.0, 200.0, (40, 2)) * [1.3, 1.0]
    truth = uv0 @ M[:, :2].T + M[:, 2]
    start = truth + rng.uniform(-0.5, 0.5, uv0.shape)
    for affine in (True, False):
        anchors = TemplateAnchors(affine_after_px=0.0 if affine else 1e9, min_zncc=-1.0, max_shift_px=1e9)
        ids = np.arange(len(uv0))
        anchors.take(image0, ids, uv0)
        refined, anchored = anchors.refine(image1, ids, start)
        assert anchored.all()
        ref = np.array(
            [
                _per_track_reference(image1, image0, u, s, affine=affine)[0]
                for u, s in zip(uv0, start, strict=True)
            ]
        )
        # The same arithmetic up to round-off (float32 patches; cv2.remap rounds to 1/32 px).
        np.testing.assert_allclose(refined, ref, atol=1e-4)
        # And the alignment did its job: an affine fit lands on the truth within bilinear resampling error.
        if affine:
            assert np.sqrt(np.mean(np.sum((refined - truth) ** 2, axis=1))) < 0.05


def test_a_failed_anchoring_ends_the_track_unless_told_otherwise():
    """``anchor_min_zncc`` above 1 refuses every refinement: each track's anchoring fails every frame."""
    camera = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    base = _texture(6, (300, 400))
    frames = []
    for k in range(4):
        M = np.float32([[1.0, 0.0, -40.0 - 1.1 * k], [0.0, 1.0, -30.0]])
        frames.append(cv2.warpAffine(base, M, (320, 240), flags=cv2.INTER_CUBIC).astype(np.uint8))
    seen = {}
    for ends in (False, True):
        trk = KltTracker(camera, KltParams(anchor_min_zncc=1.01, anchor_fail_ends_track=ends))
        ids = [
            set(trk.process(CameraFrame(t_s=0.05 * k, image=im), 0.05 * k).ids.tolist())
            for k, im in enumerate(frames)
        ]
        seen[ends] = ids
    # Kept: the tracks of the first frame go on (frame-to-frame, their templates taken anew each frame).
    assert len(seen[False][0] & seen[False][-1]) > 0.8 * len(seen[False][0])
    # Ended: no id lives past the frame after its start; the positions go on under new ids.
    assert not seen[True][0] & seen[True][2]
    assert len(seen[True][2]) > 0.8 * len(seen[False][2])


def test_zncc_of_the_last_samples_accepts_as_the_final_warp_and_moves_nothing():
    """``zncc_at_final_warp=False`` tests the last iteration's samples: the same warps, the same verdicts.

    A sub-pixel shift with a small affine change (the step of the last iteration is tiny): every track
    lands where the extra final remap would have it, and the refusals of a foreign texture stay refusals.
    """
    rng = np.random.default_rng(11)
    image0 = _texture(12).astype(np.float32)
    M = np.float32([[1.03, 0.01, 0.7], [-0.01, 0.98, -0.45]])
    image1 = cv2.warpAffine(image0, M, (320, 240), flags=cv2.INTER_CUBIC)
    uv0 = rng.uniform(30.0, 200.0, (80, 2)) * [1.3, 1.0]
    start = uv0 @ M[:, :2].T + M[:, 2] + rng.uniform(-0.7, 0.7, uv0.shape)
    ids = np.arange(len(uv0))
    out = {}
    for final in (True, False):
        anchors = TemplateAnchors(affine_after_px=0.0, zncc_at_final_warp=final)
        anchors.take(image0, ids, uv0)
        out[final] = anchors.refine(image1, ids, start)
        refused, flags = anchors.refine(_texture(13).astype(np.float32), ids, start)
        assert not flags.any()
        np.testing.assert_array_equal(refused, start)
    assert out[True][1].mean() > 0.95
    np.testing.assert_array_equal(out[True][1], out[False][1])
    np.testing.assert_array_equal(out[True][0], out[False][0])


def test_anchored_tracks_skip_the_backward_pass_and_keep_the_checked_positions():
    """``fb_check_anchored=False``: the anchoring's ZNCC test replaces the forward-backward check.

    On a clean shift both settings keep the same tracks at the same positions (the anchoring refines the
    same forward result); on a frame of another texture the anchoring (then the backward pass of the
    refused tracks, and RANSAC) still drops over 90 % of the tracks.
    """
    camera = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    base = _texture(14, (300, 400))
    frames = []
    for k in range(6):
        M = np.float32([[1.0, 0.0, -40.0 - 1.7 * k], [0.0, 1.0, -30.0 + 0.9 * k]])
        frames.append(cv2.warpAffine(base, M, (320, 240), flags=cv2.INTER_CUBIC).astype(np.uint8))
    frames.append(np.clip(_texture(15), 0, 255).astype(np.uint8))
    runs = {}
    for checked in (True, False):
        trk = KltTracker(camera, KltParams(fb_check_anchored=checked))
        runs[checked] = [
            trk.process(CameraFrame(t_s=0.05 * k, image=im), 0.05 * k) for k, im in enumerate(frames)
        ]
    for a, b in zip(runs[True][:-1], runs[False][:-1], strict=True):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_allclose(a.uv_px, b.uv_px, atol=1e-4)
    first, last = runs[False][-2], runs[False][-1]
    assert np.isin(last.ids, first.ids).mean() < 0.1
