"""FAST corner detection with grid bucketing for :class:`viotb.vio.frontend.KltTracker` (new tracks)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from viotb.vio.camera import PinholeCamera


def detect_corners(
    fast: cv2.FastFeatureDetector,
    camera: PinholeCamera,
    p: Any,
    img: np.ndarray,
    pts: np.ndarray,
    kps: Sequence[cv2.KeyPoint] | None = None,
) -> np.ndarray:
    """New FAST corners of ``KltTracker``, bucketed on a grid and away from the tracked points.

    Args:
        fast: The FAST detector.
        camera: Intrinsics (the image border).
        p: Tracker settings, a ``KltParams`` (``max_features``, ``min_distance_px``, the grid,
            ``border_px``; not imported here: :mod:`viotb.vio.frontend` imports this module).
        img: Grayscale uint8 image (H, W).
        pts: Tracked pixels, shape (M, 2).
        kps: ``fast.detect(img)``'s corners when they were detected already (None: detect here).

    Returns:
        New corners (px), shape (N, 2) float32, strongest first, at most ``max_features - M``.
    """
    need = p.max_features - len(pts)
    if need <= 0:
        return np.zeros((0, 2), dtype=np.float32)
    if kps is None:
        kps = fast.detect(img, None)
    if not kps:
        return np.zeros((0, 2), dtype=np.float32)
    cand = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32, copy=False)
    h, w = img.shape
    inside = camera.in_image(cand.astype(float), p.border_px + 4)
    # Occupancy at min_distance resolution: reject candidates whose cell (or a neighbour) holds a feature.
    cell = max(p.min_distance_px, 1.0)
    gw, gh = int(np.ceil(w / cell)) + 2, int(np.ceil(h / cell)) + 2
    occ = np.zeros((gh, gw), dtype=bool)
    if len(pts):
        ci = np.clip((pts[:, 0] / cell).astype(int) + 1, 1, gw - 2)
        cj = np.clip((pts[:, 1] / cell).astype(int) + 1, 1, gh - 2)
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                occ[cj + dj, ci + di] = True
    ki = np.clip((cand[:, 0] / cell).astype(int) + 1, 0, gw - 1)
    kj = np.clip((cand[:, 1] / cell).astype(int) + 1, 0, gh - 1)
    ok = np.flatnonzero(inside & ~occ[kj, ki])
    cand, ki, kj = cand[ok], ki[ok], kj[ok]
    # Responses only of the candidates kept (reading a KeyPoint costs a Python call each).
    resp = np.fromiter((kps[i].response for i in ok), dtype=np.float32, count=len(ok))
    if len(cand) == 0:
        return np.zeros((0, 2), dtype=np.float32)
    # One corner per occupancy cell (the strongest), then a per-bucket quota.
    order = np.lexsort((-resp, kj * gw + ki))
    cell_id = (kj * gw + ki)[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell_id[1:] != cell_id[:-1]
    sel = order[first]
    cand, resp = cand[sel], resp[sel]
    bx = np.clip((cand[:, 0] * p.grid_cols / w).astype(int), 0, p.grid_cols - 1)
    by = np.clip((cand[:, 1] * p.grid_rows / h).astype(int), 0, p.grid_rows - 1)
    bucket = by * p.grid_cols + bx
    n_buckets = p.grid_cols * p.grid_rows
    quota = int(np.ceil(p.max_features / n_buckets))
    have = np.zeros(n_buckets, dtype=int)
    if len(pts):
        tbx = np.clip((pts[:, 0] * p.grid_cols / w).astype(int), 0, p.grid_cols - 1)
        tby = np.clip((pts[:, 1] * p.grid_rows / h).astype(int), 0, p.grid_rows - 1)
        have = np.bincount(tby * p.grid_cols + tbx, minlength=n_buckets)
    order = np.lexsort((-resp, bucket))
    b_sorted = bucket[order]
    starts = np.searchsorted(b_sorted, np.arange(n_buckets))
    rank = np.arange(len(order)) - starts[b_sorted]
    take = order[rank < np.maximum(quota - have[b_sorted], 0)]
    take = take[np.argsort(-resp[take])][:need]
    return cand[take]
