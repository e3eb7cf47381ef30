"""Tests of vio/keyframing.py: the keyframe rule the MSCKF and the window share."""

import numpy as np
import pytest
from viotb.vio.frontend import Tracks
from viotb.vio.keyframing import KeyframeParams, KeyframeSelector, compensated_parallax_px, shared_motion_px
from viotb.vio.lie import exp_so3


def _tracks(ids, uv_px) -> Tracks:
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    return Tracks(0.0, 0.0, np.asarray(ids, dtype=np.int64), uv / 400.0, uv)


def test_shared_motion_is_per_common_id_in_id_order():
    ref = _tracks([5, 1, 9], [[0, 0], [10, 0], [0, 0]])
    now = _tracks([9, 1, 7], [[0, 4], [13, 4], [1, 1]])
    np.testing.assert_allclose(shared_motion_px(ref, now), [5.0, 4.0])  # ids 1 then 9


def test_first_frame_parallax_shared_fraction_and_every_n_rules():
    sel = KeyframeSelector(KeyframeParams(every_n_frames=4, min_parallax_px=3.0))
    ids = np.arange(10)
    base = _tracks(ids, np.zeros((10, 2)))
    assert sel.is_keyframe(base)  # no reference yet
    sel.accept(base)
    small = _tracks(ids, np.full((10, 2), 1.0))  # 1.4 px median
    assert not sel.is_keyframe(small)
    assert sel.is_keyframe(_tracks(ids, np.full((10, 2), 3.0)))  # 4.2 px >= 3 px
    assert sel.is_keyframe(_tracks(ids[:4], np.zeros((4, 2))))  # fewer than half still tracked
    sel.skip()
    sel.skip()
    assert not sel.is_keyframe(small)
    sel.skip()
    assert sel.is_keyframe(small)  # the 4th frame since the keyframe
    sel.forget_reference()
    assert sel.is_keyframe(small)


def test_estimators_keep_their_keyframe_defaults():
    from viotb.vio.msckf import MsckfParams
    from viotb.vio.window import WindowParams

    assert MsckfParams().keyframing == KeyframeParams(every_n_frames=6, min_parallax_px=3.0)
    assert WindowParams().keyframing == KeyframeParams(
        every_n_frames=3, min_parallax_px=10.0, rotation_compensated=True
    )


def _view(points_C: np.ndarray, ids: np.ndarray, focal_px: float) -> Tracks:
    xy = points_C[:, :2] / points_C[:, 2:3]
    return Tracks(0.0, 0.0, ids, xy, xy * focal_px)


def test_compensated_parallax_removes_rotation_and_keeps_translation():
    """Compensated parallax: zero for a rotation, the raw motion for a translation, its part for both.

    Rotated camera: pixels move > 20 px; rotated and translated: the motion in the current camera between the
    points and the same points without the translation.
    """
    rng = np.random.default_rng(0)
    p_Cr = np.column_stack([rng.uniform(-1, 1, (40, 2)), rng.uniform(2, 5, 40)])  # in the reference camera
    ids = np.arange(40)
    f = 200.0
    ref = _view(p_Cr, ids, f)
    R_CrCn = exp_so3(np.array([0.05, -0.12, 0.08]))  # current camera's rotation in the reference camera
    rotated = _view(p_Cr @ R_CrCn, ids, f)  # p_Cn = R_CrCn^T p_Cr
    assert np.median(shared_motion_px(ref, rotated)) > 20.0
    np.testing.assert_allclose(compensated_parallax_px(ref, rotated, R_CrCn, f), 0.0, atol=1e-9)
    t_CrCn = np.array([0.1, 0.0, 0.02])
    moved = _view(p_Cr - t_CrCn, ids, f)
    np.testing.assert_allclose(
        compensated_parallax_px(ref, moved, np.eye(3), f), shared_motion_px(ref, moved)
    )
    both = _view((p_Cr - t_CrCn) @ R_CrCn, ids, f)
    # What is left is the translation's motion seen in the current camera: the points against the same points
    # without the translation (the depth changes by the baseline, so the point does not reduce to a bearing).
    spun = _view(p_Cr @ R_CrCn, ids, f)
    np.testing.assert_allclose(
        compensated_parallax_px(ref, both, R_CrCn, f),
        np.linalg.norm(both.uv_px - spun.uv_px, axis=1),
        atol=1e-9,
    )


def test_rotation_compensated_selector_ignores_a_spin_and_needs_the_rotation():
    """A spin that moves every pixel ~30 px is no keyframe when compensated (it is without); no R -> error."""
    rng = np.random.default_rng(1)
    p_Cr = np.column_stack([rng.uniform(-1, 1, (30, 2)), rng.uniform(2, 5, 30)])
    ids = np.arange(30)
    ref = _view(p_Cr, ids, 200.0)
    R = exp_so3(np.array([0.0, 0.15, 0.0]))
    spun = _view(p_Cr @ R, ids, 200.0)
    plain = KeyframeSelector(KeyframeParams(every_n_frames=10, min_parallax_px=10.0))
    comp = KeyframeSelector(
        KeyframeParams(every_n_frames=10, min_parallax_px=10.0, rotation_compensated=True)
    )
    for sel in (plain, comp):
        sel.accept(ref)
    assert plain.is_keyframe(spun)
    assert not comp.is_keyframe(spun, R, 200.0)
    with pytest.raises(ValueError, match="rotation_compensated"):
        comp.is_keyframe(spun)
