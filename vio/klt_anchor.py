"""Drift correction of KLT tracks against each track's first appearance (template anchoring).

Frame-to-frame Lucas-Kanade re-estimates a feature's position from the previous frame's estimate, so its
sub-pixel errors add up along the track: a random walk (``benchmarks/klt_track_error.py`` measures 0.025
px^2 per px of image motion on top of ~0.1 px of white error at 320x240). The filter must then model the
walk (``KltParams.track_random_walk_px2_per_px``) and a long track holds little more than a short one.

The cure is the "template update with drift correction" of Matthews, Ishikawa and Baker, "The template update
problem", IEEE TPAMI 26(6), 2004 (their strategy 3): keep the template of the track's first frame; each new
position found frame to frame is refined by aligning that first template to the new image, starting at the
frame-to-frame position; the refinement is kept only when it stays within a few pixels of the start and
the patch still matches (zero-mean normalized cross-correlation). When it fails (the view changed too
much), the frame-to-frame position is kept and the template is taken anew there.

The alignment is translation-only inverse-compositional Lucas-Kanade (Baker and Matthews, "Lucas-Kanade 20
years on: a unifying framework", IJCV 56(3), 2004, section 3.2): the template's gradients and 2x2 Gauss-Newton
Hessian are computed once when the template is taken; each iteration only samples the image. The residual is
taken between zero-mean, unit-variance patches, so an exposure change does not bias it. All tracks are
aligned at once in numpy (no per-feature Python loop).
"""

from __future__ import annotations

import cv2
import numpy as np


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at pixel coordinates (pixel centres at integers), ``cv2.remap``.

    OpenCV interpolates with weights on a 1/32 px grid (``INTER_BITS = 5``), so a sample is the bilinear
    value at the coordinate rounded to 1/32 px; borders are replicated.

    Args:
        image: Grayscale float32 image, shape (H, W).
        x: Column coordinates (px), shape (N, P).
        y: Row coordinates (px), shape (N, P).

    Returns:
        float64 samples, shape (N, P).
    """
    mx = np.ascontiguousarray(x, dtype=np.float32)
    my = np.ascontiguousarray(y, dtype=np.float32)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.astype(np.float64).reshape(x.shape)


def _normalize(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean, unit-RMS patches (N, P) and their RMS (N,) (a flat patch gets RMS 0)."""
    centred = patches - patches.mean(axis=1, keepdims=True)
    rms = np.sqrt(np.mean(centred * centred, axis=1))
    return centred / np.maximum(rms, 1e-9)[:, None], rms


class TemplateAnchors:
    """First-appearance templates of live tracks, and their alignment into a new image.

    Args:
        half_size_px: Template half side (px): the patch is ``(2 h + 1)^2`` pixels.
        iterations: Gauss-Newton iterations of the alignment.
        max_shift_px: Largest accepted distance (px) between the refined and the frame-to-frame position.
        min_zncc: Smallest accepted zero-mean normalized cross-correlation of the aligned patch.
        min_texture: Smallest template RMS (gray levels) for a template to be kept (a flat patch cannot be
            aligned).
    """

    def __init__(
        self,
        half_size_px: int = 5,
        iterations: int = 4,
        max_shift_px: float = 2.0,
        min_zncc: float = 0.85,
        min_texture: float = 4.0,
    ) -> None:
        """Create an empty template store."""
        r = np.arange(-half_size_px, half_size_px + 1, dtype=float)
        gy, gx = np.meshgrid(r, r, indexing="ij")
        self._dx, self._dy = gx.ravel(), gy.ravel()
        # One extra ring, for the central-difference gradients of the template.
        r1 = np.arange(-half_size_px - 1, half_size_px + 2, dtype=float)
        gy1, gx1 = np.meshgrid(r1, r1, indexing="ij")
        self._dx1, self._dy1 = gx1.ravel(), gy1.ravel()
        self._side1 = r1.size
        self.half = half_size_px
        self.iterations = iterations
        self.max_shift_px = max_shift_px
        self.min_zncc = min_zncc
        self.min_texture = min_texture
        self.ids = np.zeros(0, dtype=np.int64)
        self._tmpl = np.zeros((0, self._dx.size))  # normalized templates (N, P)
        self._grad = np.zeros((0, self._dx.size, 2))  # their gradients (N, P, 2)
        self._hinv = np.zeros((0, 2, 2))  # inverse Gauss-Newton Hessians (N, 2, 2)

    def _inside(self, image: np.ndarray, uv: np.ndarray, margin: float) -> np.ndarray:
        h, w = image.shape
        m = self.half + margin
        return (uv[:, 0] >= m) & (uv[:, 0] <= w - 1 - m) & (uv[:, 1] >= m) & (uv[:, 1] <= h - 1 - m)

    def take(self, image: np.ndarray, ids: np.ndarray, uv_px: np.ndarray) -> None:
        """Take (or take anew) the templates of tracks ``ids`` at pixels ``uv_px`` (N, 2) of ``image``.

        Tracks too close to the border or on flat texture get no template (they stay frame-to-frame).
        """
        ids = np.asarray(ids, dtype=np.int64)
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        image = np.asarray(image, dtype=np.float32)
        self.drop(ids)
        ok = self._inside(image, uv, 2.0)
        ids, uv = ids[ok], uv[ok]
        if len(ids) == 0:
            return
        side1 = self._side1
        big = sample_bilinear(image, uv[:, :1] + self._dx1, uv[:, 1:] + self._dy1).reshape(-1, side1, side1)
        inner = big[:, 1:-1, 1:-1].reshape(len(ids), -1)
        tmpl, rms = _normalize(inner)
        gx = 0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2]).reshape(len(ids), -1)
        gy = 0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1]).reshape(len(ids), -1)
        grad = np.stack([gx, gy], axis=2) / np.maximum(rms, 1e-9)[:, None, None]
        hess = np.einsum("npi,npj->nij", grad, grad)
        det = hess[:, 0, 0] * hess[:, 1, 1] - hess[:, 0, 1] ** 2
        keep = (rms >= self.min_texture) & (
            det > 1e-9 * np.maximum(np.trace(hess, axis1=1, axis2=2), 1.0) ** 2
        )
        if not np.any(keep):
            return
        hess, det = hess[keep], det[keep]
        hinv = np.stack([hess[:, 1, 1], -hess[:, 0, 1], -hess[:, 1, 0], hess[:, 0, 0]], axis=1).reshape(
            -1, 2, 2
        )
        self.ids = np.concatenate([self.ids, ids[keep]])
        self._tmpl = np.vstack([self._tmpl, tmpl[keep]])
        self._grad = np.concatenate([self._grad, grad[keep]])
        self._hinv = np.concatenate([self._hinv, hinv / det[:, None, None]])

    def drop(self, ids: np.ndarray) -> None:
        """Forget the templates of ``ids`` (absent ids are ignored)."""
        if len(self.ids) == 0 or len(ids) == 0:
            return
        keep = ~np.isin(self.ids, ids)
        self.ids, self._tmpl = self.ids[keep], self._tmpl[keep]
        self._grad, self._hinv = self._grad[keep], self._hinv[keep]

    def keep_only(self, ids: np.ndarray) -> None:
        """Forget every template whose track is not in ``ids`` (the tracks that ended)."""
        if len(self.ids):
            self.drop(self.ids[~np.isin(self.ids, ids)])

    def refine(self, image: np.ndarray, ids: np.ndarray, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Align the templates of ``ids`` into ``image``, starting from the frame-to-frame pixels ``uv_px``.

        Args:
            image: The new grayscale image (H, W).
            ids: Track ids (N,).
            uv_px: Frame-to-frame positions (px), shape (N, 2).

        Returns:
            ``(uv_refined (N, 2), anchored (N,) bool)``: the refined position where the alignment was
            accepted, else the input position; ``anchored`` says which.
        """
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2).copy()
        ids = np.asarray(ids, dtype=np.int64)
        anchored = np.zeros(len(ids), dtype=bool)
        if len(self.ids) == 0 or len(ids) == 0:
            return uv, anchored
        order = np.argsort(self.ids)
        pos = np.searchsorted(self.ids[order], ids)
        pos = np.clip(pos, 0, len(order) - 1)
        has = self.ids[order][pos] == ids
        which, rows = np.flatnonzero(has), order[pos[has]]
        start = uv[which]
        p = start.copy()
        tmpl, grad, hinv = self._tmpl[rows], self._grad[rows], self._hinv[rows]
        img = np.asarray(image, dtype=np.float32)
        ok = self._inside(img, p, 1.0)
        for _ in range(self.iterations):
            ok &= self._inside(img, p, 1.0)
            warped, _ = _normalize(sample_bilinear(img, p[:, :1] + self._dx, p[:, 1:] + self._dy))
            # Inverse compositional step (Baker & Matthews 2004, eq. 35): p <- p - H^-1 sum grad T (I(W) - T).
            step = np.einsum("nij,nj->ni", hinv, np.einsum("npi,np->ni", grad, warped - tmpl))
            p = np.where(ok[:, None], p - step, p)
        ok &= self._inside(img, p, 0.0)
        warped, _ = _normalize(sample_bilinear(img, p[:, :1] + self._dx, p[:, 1:] + self._dy))
        zncc = np.mean(warped * tmpl, axis=1)
        ok &= (zncc >= self.min_zncc) & (np.linalg.norm(p - start, axis=1) <= self.max_shift_px)
        uv[which[ok]] = p[ok]
        anchored[which[ok]] = True
        return uv, anchored
