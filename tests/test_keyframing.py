"""Tests of vio/keyframing.py: the keyframe rule the MSCKF and the window share."""

import numpy as np
from viotb.vio.frontend import Tracks
from viotb.vio.keyframing import KeyframeParams, KeyframeSelector, shared_motion_px


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
    assert WindowParams().keyframing == KeyframeParams(every_n_frames=3, min_parallax_px=10.0)
