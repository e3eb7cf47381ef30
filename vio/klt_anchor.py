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

The alignment is affine inverse-compositional Lucas-Kanade (Baker and Matthews, "Lucas-Kanade 20 years
on: a unifying framework", IJCV 56(3), 2004, section 3.2): the template's steepest-descent images and 6x6
Gauss-Newton matrix are computed once when the template is taken; each iteration only samples the image.
The residual is taken between zero-mean, unit-variance patches, so an exposure change does not bias it.
All tracks are aligned at once in numpy (no per-feature Python loop).
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
        float32 samples, shape (N, P).
    """
    mx = np.ascontiguousarray(x, dtype=np.float32)
    my = np.ascontiguousarray(y, dtype=np.float32)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(x.shape)


def _normalize(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean, unit-RMS patches (N, P) and their RMS (N,) (a flat patch gets RMS 0)."""
    centred = patches - patches.mean(axis=1, keepdims=True)
    rms = np.sqrt(np.mean(centred * centred, axis=1))
    return centred / np.maximum(rms, 1e-9)[:, None], rms


class TemplateAnchors:
    """First-appearance templates of live tracks, and their affine alignment into a new image.

    Each track keeps its template, the steepest-descent images and inverse Hessian of the affine
    inverse-compositional alignment, and the template's current linear warp ``A`` (2x2: template offsets
    to image offsets), carried from frame to frame: a wide-angle pinhole stretches a patch by up to 2x
    between the image centre and its edge, which a translation-only match follows by sliding off its
    point (README "KLT track error").

    Args:
        half_size_px: Template half side (px): the patch is ``(2 h + 1)^2`` pixels.
        iterations: Gauss-Newton iterations of the alignment.
        max_shift_px: Largest accepted distance (px) between the refined and the frame-to-frame position.
        min_zncc: Smallest accepted zero-mean normalized cross-correlation of the aligned patch.
        min_texture: Smallest template RMS (gray levels) for a template to be kept (a flat patch cannot be
            aligned).
        max_stretch: Largest accepted singular value of ``A`` (and smallest ``1 / max_stretch``).
        damping: Levenberg damping of the 6x6 Gauss-Newton matrix (relative to its diagonal).
        affine_after_px: A track closer than this to where its template was taken is aligned in
            translation only: there is no stretch to correct yet, and on a still real image (EuRoC micro,
            window estimator) the 6-parameter fit is noisier than the 2-parameter one.
    """

    def __init__(
        self,
        half_size_px: int = 6,
        iterations: int = 4,
        max_shift_px: float = 2.0,
        min_zncc: float = 0.85,
        min_texture: float = 4.0,
        max_stretch: float = 4.0,
        damping: float = 1e-3,
        affine_after_px: float = 3.0,
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
        self.max_stretch = max_stretch
        self.damping = damping
        self.affine_after_px = affine_after_px
        n_px = self._dx.size
        # Slot storage: a track's template lives in one row until its track ends (no copies per frame).
        self._slot_of: dict[int, int] = {}
        self._free: list[int] = []
        self._tmpl = np.zeros((0, n_px), dtype=np.float32)  # normalized templates (S, P)
        self._sd = np.zeros((0, n_px, 6), dtype=np.float32)  # steepest-descent images (S, P, 6)
        self._hinv = np.zeros((0, 6, 6))  # inverse Gauss-Newton matrices (S, 6, 6)
        self._hinv_t = np.zeros((0, 2, 2))  # inverses of their translation blocks (S, 2, 2)
        self._A = np.zeros((0, 2, 2))  # current linear warps (S, 2, 2)
        self._uv0 = np.zeros((0, 2))  # where each template was taken (S, 2)

    @property
    def ids(self) -> np.ndarray:
        """Ids of the tracks that have a template, sorted, shape (N,)."""
        return np.array(sorted(self._slot_of), dtype=np.int64)

    def _slots(self, n: int) -> np.ndarray:
        """``n`` free rows (the storage doubles when full)."""
        while len(self._free) < n:
            old = len(self._tmpl)
            grow = max(old, n, 64)
            self._tmpl = np.vstack([self._tmpl, np.zeros((grow, self._tmpl.shape[1]), dtype=np.float32)])
            self._sd = np.concatenate([self._sd, np.zeros((grow, *self._sd.shape[1:]), dtype=np.float32)])
            self._hinv = np.concatenate([self._hinv, np.zeros((grow, 6, 6))])
            self._hinv_t = np.concatenate([self._hinv_t, np.zeros((grow, 2, 2))])
            self._A = np.concatenate([self._A, np.zeros((grow, 2, 2))])
            self._uv0 = np.concatenate([self._uv0, np.zeros((grow, 2))])
            self._free.extend(range(old + grow - 1, old - 1, -1))
        return np.array([self._free.pop() for _ in range(n)], dtype=np.int64)

    def _inside(self, image: np.ndarray, uv: np.ndarray, margin: float) -> np.ndarray:
        h, w = image.shape
        m = self.half + margin
        return (uv[:, 0] >= m) & (uv[:, 0] <= w - 1 - m) & (uv[:, 1] >= m) & (uv[:, 1] <= h - 1 - m)

    def _inside_warped(self, image: np.ndarray, c: np.ndarray, A: np.ndarray) -> np.ndarray:
        """Whether each warped patch ``c + A @ (dx, dy)`` lies inside the image with a 1 px margin."""
        h, w = image.shape
        ex = self.half * (np.abs(A[:, 0, 0]) + np.abs(A[:, 0, 1])) + 1.0
        ey = self.half * (np.abs(A[:, 1, 0]) + np.abs(A[:, 1, 1])) + 1.0
        return (c[:, 0] >= ex) & (c[:, 0] <= w - 1 - ex) & (c[:, 1] >= ey) & (c[:, 1] <= h - 1 - ey)

    def _sample(self, image: np.ndarray, c: np.ndarray, A: np.ndarray) -> np.ndarray:
        """The image at ``c + A @ (dx, dy)`` for every template point, shape (N, P)."""
        x = c[:, :1] + A[:, 0, :1] * self._dx + A[:, 0, 1:] * self._dy
        y = c[:, 1:] + A[:, 1, :1] * self._dx + A[:, 1, 1:] * self._dy
        return sample_bilinear(image, x, y)

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
        scale = 1.0 / np.maximum(rms, 1e-9)[:, None]
        gx = 0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2]).reshape(len(ids), -1) * scale
        gy = 0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1]).reshape(len(ids), -1) * scale
        # dW/dp of W(x; p) = (I + [[p1, p3], [p2, p4]]) x + (p5, p6) at p = 0 (Baker & Matthews 2004, sec. 2).
        dx, dy = self._dx, self._dy
        sd = np.stack([gx * dx, gy * dx, gx * dy, gy * dy, gx, gy], axis=2)
        hess = np.einsum("npi,npj->nij", sd, sd)
        hess += self.damping * hess[:, np.arange(6), np.arange(6)][:, :, None] * np.eye(6)
        keep = (rms >= self.min_texture) & (np.linalg.det(hess) > 0.0)
        if not np.any(keep):
            return
        slots = self._slots(int(keep.sum()))
        self._tmpl[slots] = tmpl[keep]
        self._sd[slots] = sd[keep]
        self._hinv[slots] = np.linalg.inv(hess[keep])
        self._hinv_t[slots] = np.linalg.inv(hess[keep][:, 4:, 4:])
        self._A[slots] = np.eye(2)
        self._uv0[slots] = uv[keep]
        for tid, slot in zip(ids[keep].tolist(), slots.tolist(), strict=True):
            self._slot_of[tid] = slot

    def drop(self, ids: np.ndarray) -> None:
        """Forget the templates of ``ids`` (absent ids are ignored)."""
        for tid in np.asarray(ids, dtype=np.int64).tolist():
            slot = self._slot_of.pop(tid, None)
            if slot is not None:
                self._free.append(slot)

    def keep_only(self, ids: np.ndarray) -> None:
        """Forget every template whose track is not in ``ids`` (the tracks that ended)."""
        live = set(np.asarray(ids, dtype=np.int64).tolist())
        self.drop(np.array([tid for tid in self._slot_of if tid not in live], dtype=np.int64))

    def refine(self, image: np.ndarray, ids: np.ndarray, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Align the templates of ``ids`` into ``image``, starting from the frame-to-frame pixels ``uv_px``.

        Args:
            image: The new grayscale image (H, W).
            ids: Track ids (N,).
            uv_px: Frame-to-frame positions (px), shape (N, 2).

        Returns:
            ``(uv_refined (N, 2), anchored (N,) bool)``: the refined position where the alignment was
            accepted, else the input position; ``anchored`` says which (False: take the template anew).
        """
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2).copy()
        ids = np.asarray(ids, dtype=np.int64)
        anchored = np.zeros(len(ids), dtype=bool)
        slot_of = self._slot_of
        found = np.array([slot_of.get(tid, -1) for tid in ids.tolist()], dtype=np.int64)
        which = np.flatnonzero(found >= 0)
        rows = found[which]
        if len(rows) == 0:
            return uv, anchored
        start = uv[which]
        near = np.linalg.norm(start - self._uv0[rows], axis=1) < self.affine_after_px
        c, A = start.copy(), self._A[rows].copy()
        tmpl, sd, hinv = self._tmpl[rows], self._sd[rows], self._hinv[rows]
        hinv_near = self._hinv_t[rows[near]]  # the translation blocks' inverses of the near tracks
        img = np.asarray(image, dtype=np.float32)
        ok = self._inside_warped(img, c, A)
        for _ in range(self.iterations):
            warped, _ = _normalize(self._sample(img, c, A))
            # Inverse compositional step (Baker & Matthews 2004, eq. 35): dp = H^-1 sum SD^T (I(W) - T),
            # then W <- W o W(dp)^-1: A <- A (I + D)^-1, c <- c - A (I + D)^-1 t.
            grad = np.einsum("npi,np->ni", sd, warped - tmpl)
            dp = np.einsum("nij,nj->ni", hinv, grad)
            dp[near, :4] = 0.0  # translation only: the 2x2 block's solve
            dp[near, 4:] = np.einsum("nij,nj->ni", hinv_near, grad[near, 4:])
            inv = np.linalg.inv(np.eye(2) + dp[:, [0, 2, 1, 3]].reshape(-1, 2, 2))
            A_new = A @ inv
            c_new = c - np.einsum("nij,nj->ni", A_new, dp[:, 4:])
            A = np.where(ok[:, None, None], A_new, A)
            c = np.where(ok[:, None], c_new, c)
            ok &= self._inside_warped(img, c, A)
        warped, _ = _normalize(self._sample(img, c, A))
        zncc = np.mean(warped * tmpl, axis=1)
        sv = np.linalg.svd(A, compute_uv=False)
        ok &= (zncc >= self.min_zncc) & (np.linalg.norm(c - start, axis=1) <= self.max_shift_px)
        ok &= (sv[:, 0] <= self.max_stretch) & (sv[:, 1] >= 1.0 / self.max_stretch)
        uv[which[ok]] = c[ok]
        anchored[which[ok]] = True
        self._A[rows[ok]] = A[ok]
        return uv, anchored
