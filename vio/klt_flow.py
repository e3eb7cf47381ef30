"""Options of OpenCV's pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) shared by the KLT front ends.

``calcOpticalFlowPyrLK`` always returns a per-point error, and without a flag it computes it in one more
pass over every point's window at level 0, after the iterations (``LKTrackerInvoker`` in OpenCV's
``lkpyramid.cpp``). That pass also clears the status of a point whose final position lies beyond the
padded image: ``floor(x - (w - 1) / 2) < -w`` or ``>= cols`` (and the same in y), i.e. more than about
half a window outside. With :data:`LK_NO_ERROR_PASS` the error is the minimum eigenvalue already computed
for the status test and the pass is skipped; the positions are the same bit for bit and only those far
outside points keep status 1. Every caller here refuses such points by its own test (inside the image
with a border, or back within a pixel of a point inside the image), so the tracks do not change
(``tests/test_klt_flow.py``).
"""

from __future__ import annotations

import cv2

LK_NO_ERROR_PASS = cv2.OPTFLOW_LK_GET_MIN_EIGENVALS
"""``calcOpticalFlowPyrLK`` flag: the error output is the minimum eigenvalue, no error pass (see above)."""
