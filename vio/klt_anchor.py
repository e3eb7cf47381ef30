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
Gauss-Newton matrix are computed once when the template is taken, and folded into one ``6 x P`` matrix
``J = H^-1 SD^T`` (and ``2 x P`` for the translation-only fit), so that an iteration only samples the image
(one ``cv2.remap`` of all patches stacked) and takes one batched matrix-vector product. The residual is
taken between zero-mean, unit-variance patches, so an exposure change does not bias it. All tracks are
aligned at once in numpy (no per-feature Python loop); a track stops iterating once its step is below
``converged_px``.

A track far enough from where its template was taken (``projective_after_px``) is aligned with the
8-parameter homography instead (the same algorithm with two more steepest-descent images; Baker and
Matthews 2004, sec. 3.2 lists the homographies among the warps it applies to): an affine fit of a patch on a
foreshortened plane drifts one way as the view changes (README "KLT track bias on foreshortened planes").
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import cv2
import numpy as np
from viotb.vio.klt_math import (
    _inv_2x2,
    _normalize,
    sample_bilinear,
    singular_values_2x2,
    take_templates_numpy,
)

__all__ = ["TemplateAnchors", "sample_bilinear", "singular_values_2x2"]


class PendingTake(NamedTuple):
    """Templates being taken (:meth:`TemplateAnchors.begin_take`): tracks, pixels (N, 2), the kernel call."""

    ids: np.ndarray
    uv: np.ndarray
    compute: Callable[[], tuple]


class TemplateAnchors:
    """First-appearance templates of live tracks, and their affine alignment into a new image.

    Each track keeps its template, the Gauss-Newton solve matrices of the affine inverse-compositional
    alignment, and the template's current linear warp ``A`` (2x2: template offsets to image offsets),
    carried from frame to frame: a wide-angle pinhole stretches a patch by up to 2x between the image
    centre and its edge, which a translation-only match follows by sliding off its point (README "KLT track
    error").

    Args:
        half_size_px: Template half side (px): the patch is ``(2 h + 1)^2`` pixels.
        iterations: Largest number of Gauss-Newton iterations of the alignment.
        max_shift_px: Largest accepted distance (px) between the refined and the frame-to-frame position.
        min_zncc: Smallest accepted zero-mean normalized cross-correlation of the aligned patch.
        min_texture: Smallest template RMS (gray levels) for a template to be kept (a flat patch cannot be
            aligned).
        max_stretch: Largest accepted singular value of ``A`` (and smallest ``1 / max_stretch``).
        damping: Levenberg damping of the 6x6 Gauss-Newton matrix (relative to its diagonal).
        affine_after_px: A track closer than this to where its template was taken is aligned in
            translation only: there is no stretch to correct yet, and on a still real image (EuRoC micro,
            window estimator) the 6-parameter fit is noisier than the 2-parameter one.
        converged_px: A track stops iterating after a step that moves its centre by no more than this
            (px); 0 = always ``iterations`` steps.
        projective_after_px: A track at least this far (px) from where its template was taken is aligned
            with an 8-parameter homography (the affine warp plus the projective row ``g``); ``inf`` = never.
            An affine warp cannot follow the perspective change of a patch on a foreshortened plane: its
            least-squares fit puts the quadratic part of the warp, ``-A x (g^T x)``, into the translation,
            a shift ``~ -A E[x x^T] g`` of one sign for every track on the plane (README "KLT track bias
            on foreshortened planes").
        projective_damping: Levenberg damping of the two projective parameters (relative to their
            diagonal): each step moves ``g`` by about half its Gauss-Newton step, so that ``g``, which the
            small patch holds weakly, follows the view over a few frames (``circle`` seed 0: robust white
            sigma 0.038 px at 1e-3, 0.034 at 1).
        zncc_at_final_warp: Test the ZNCC of the patch sampled at the final warp (one more remap of all
            patches); False: the ZNCC of the last iteration's samples, at the warp before its step (after
            the first iteration that step is a small fraction of a pixel): the same warps, a remap less
            (``KltParams.anchor_zncc_at_final_warp``, off by default: README "MSCKF per frame").
        compiled: Align with the compiled kernel :func:`viotb.vio.frontend_kernels.align_templates` (one
            loop over the tracks, the same steps; positions agree with this module's numpy code, the
            reference, to round-off) and take templates with
            :func:`viotb.vio.frontend_take_kernel.take_templates` (the numpy reference:
            :func:`viotb.vio.klt_math.take_templates_numpy`); False: the numpy code.
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
        converged_px: float = 0.0,
        projective_after_px: float = float("inf"),
        projective_damping: float = 1.0,
        zncc_at_final_warp: bool = True,
        compiled: bool = True,
    ) -> None:
        """Create an empty template store."""
        r = np.arange(-half_size_px, half_size_px + 1, dtype=float)
        gy, gx = np.meshgrid(r, r, indexing="ij")
        self._dx, self._dy = gx.ravel(), gy.ravel()
        self._r = r
        self.half = half_size_px
        self.iterations = iterations
        self.max_shift_px = max_shift_px
        self.min_zncc = min_zncc
        self.min_texture = min_texture
        self.max_stretch = max_stretch
        self.damping = damping
        self.affine_after_px = affine_after_px
        self.converged_px = converged_px
        self.projective_after_px = projective_after_px
        self.projective_damping = projective_damping
        self.zncc_at_final_warp = zncc_at_final_warp
        self.compiled = compiled
        self._projective = bool(np.isfinite(projective_after_px))
        n_px = self._dx.size
        # Slot storage: a track's template lives in one row until its track ends (no copies per frame).
        self._slot_by_id = np.full(0, -1, dtype=np.int64)  # storage row of each track id, -1: none
        self._free: list[int] = []
        self._tmpl = np.zeros((0, n_px), dtype=np.float32)  # normalized templates (S, P)
        # H^-1 SD^T of the three fits (S, 3, W, P): translation (in rows 4-5), affine (rows 0-5) and
        # homography (rows 0-7; W = 8 only when it is on, else 6), zero in the rows a fit does not have.
        width = 8 if self._projective else 6
        self._J = np.zeros((0, 3, width, n_px), dtype=np.float32)
        self._J_tmpl = np.zeros((0, 3, width))  # J @ template (S, 3, W)
        self._A = np.zeros((0, 2, 2))  # current linear warps (S, 2, 2)
        self._g = np.zeros((0, 2))  # current projective rows (S, 2), 1/px; zero while affine
        self._uv0 = np.zeros((0, 2))  # where each template was taken (S, 2)
        if compiled:
            from viotb.vio.frontend_take_kernel import warm_up  # numba: not on the CLI's import path

            warm_up(half_size_px, self._projective)

    @property
    def ids(self) -> np.ndarray:
        """Ids of the tracks that have a template, sorted, shape (N,)."""
        return np.flatnonzero(self._slot_by_id >= 0).astype(np.int64)

    _STORES = ("_tmpl", "_J", "_J_tmpl", "_A", "_g", "_uv0")

    def _slots(self, n: int) -> np.ndarray:
        """``n`` free rows (the storage doubles when full)."""
        while len(self._free) < n:
            old = len(self._tmpl)
            grow = max(old, n, 64)
            for name in self._STORES:
                arr = getattr(self, name)
                setattr(self, name, np.concatenate([arr, np.zeros((grow, *arr.shape[1:]), dtype=arr.dtype)]))
            self._free.extend(range(old + grow - 1, old - 1, -1))
        taken = self._free[len(self._free) - n :][::-1]  # the last n, last first (as n pops)
        del self._free[len(self._free) - n :]
        return np.array(taken, dtype=np.int64)

    def _lookup(self, ids: np.ndarray) -> np.ndarray:
        """Storage rows of track ids (N,) (-1 where a track has no template)."""
        found = np.full(len(ids), -1, dtype=np.int64)
        known = (ids >= 0) & (ids < len(self._slot_by_id))
        found[known] = self._slot_by_id[ids[known]]
        return found

    def _inside(self, image: np.ndarray, uv: np.ndarray, margin: float) -> np.ndarray:
        h, w = image.shape
        m = self.half + margin
        return (uv[:, 0] >= m) & (uv[:, 0] <= w - 1 - m) & (uv[:, 1] >= m) & (uv[:, 1] <= h - 1 - m)

    def _inside_warped(
        self, image: np.ndarray, c: np.ndarray, A: np.ndarray, g: np.ndarray | None = None
    ) -> np.ndarray:
        """Whether each warped patch (:meth:`_sample`) lies inside the image with a 1 px margin.

        With projective rows ``g`` a patch also fails where its denominator ``1 + g^T x`` falls under 0.5
        (the warp folds over or stretches more than 2x within the patch).
        """
        h, w = image.shape
        den = np.ones(len(c)) if g is None else 1.0 - self.half * (np.abs(g[:, 0]) + np.abs(g[:, 1]))
        ex = self.half * (np.abs(A[:, 0, 0]) + np.abs(A[:, 0, 1])) / np.maximum(den, 0.5) + 1.0
        ey = self.half * (np.abs(A[:, 1, 0]) + np.abs(A[:, 1, 1])) / np.maximum(den, 0.5) + 1.0
        inside = (c[:, 0] >= ex) & (c[:, 0] <= w - 1 - ex) & (c[:, 1] >= ey) & (c[:, 1] <= h - 1 - ey)
        return inside & (den >= 0.5)

    def _sample(
        self, image: np.ndarray, c: np.ndarray, A: np.ndarray, g: np.ndarray | None = None
    ) -> np.ndarray:
        """The image at ``c + A (dx, dy) / (1 + g^T (dx, dy))`` for every template point, (N, P), one remap.

        The patch grid is separable: ``x[i, j] = (c_x + A_00 r_j) + A_01 r_i`` (and ``y`` alike), one
        broadcast sum of two (N, side) vectors per coordinate; with projective rows ``g`` (N, 2) the
        offsets are divided by the broadcast sum ``1 + g_0 r_j + g_1 r_i`` (the homography
        ``[[A, 0], [g^T, 1]]`` of template offsets to image offsets about the centre ``c``).
        """
        r = self._r
        if g is None:
            x = np.add(
                (c[:, :1] + A[:, 0, :1] * r)[:, None, :], (A[:, 0, 1:] * r)[:, :, None], dtype=np.float32
            )
            y = np.add(
                (c[:, 1:] + A[:, 1, :1] * r)[:, None, :], (A[:, 1, 1:] * r)[:, :, None], dtype=np.float32
            )
        else:
            f32 = np.float32
            den = np.add((1.0 + g[:, :1] * r)[:, None, :], (g[:, 1:] * r)[:, :, None], dtype=f32)
            x = np.add((A[:, 0, :1] * r)[:, None, :], (A[:, 0, 1:] * r)[:, :, None], dtype=f32)
            y = np.add((A[:, 1, :1] * r)[:, None, :], (A[:, 1, 1:] * r)[:, :, None], dtype=f32)
            x /= den
            y /= den
            x += c[:, :1, None].astype(f32)
            y += c[:, 1:, None].astype(f32)
        n = len(c)
        out = cv2.remap(
            image, x.reshape(n, -1), y.reshape(n, -1), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        return out.reshape(n, -1)

    def take(self, image: np.ndarray, ids: np.ndarray, uv_px: np.ndarray) -> None:
        """Take (or take anew) the templates of tracks ``ids`` at pixels ``uv_px`` (N, 2) of ``image``.

        Tracks too close to the border or on flat texture get no template (they stay frame-to-frame).
        """
        job = self.begin_take(image, ids, uv_px)
        if job is not None:
            self.end_take(job, job.compute())

    def begin_take(self, image: np.ndarray, ids: np.ndarray, uv_px: np.ndarray) -> PendingTake | None:
        """:meth:`take` in two parts: drop the old templates, and the computation to run (None: nothing).

        Returns:
            The pending take, or None: its ``compute()`` is the template kernel alone (the compiled one
            releases the GIL, so another thread can run it), and :meth:`end_take` stores its result. No
            other call may change the templates in between.
        """
        ids = np.asarray(ids, dtype=np.int64)
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        image = np.asarray(image, dtype=np.float32)
        self.drop(ids)
        ok = self._inside(image, uv, 2.0)
        ids, uv = ids[ok], np.ascontiguousarray(uv[ok])
        if len(ids) == 0:
            return None
        if self.compiled:
            from viotb.vio.frontend_take_kernel import take_templates  # numba: not on the CLI's import path
        else:
            take_templates = take_templates_numpy
        args = (self._r, self.damping, self.projective_damping, self._projective, self.min_texture)
        return PendingTake(ids, uv, functools.partial(take_templates, image, uv, *args))

    def end_take(self, job: PendingTake, result: tuple) -> None:
        """Store what :meth:`begin_take`'s ``compute()`` returned (the templates that were kept)."""
        keep, tmpl, J, J_tmpl = result
        if np.any(keep):
            self._store(job.ids[keep], job.uv[keep], tmpl[keep], J[keep], J_tmpl[keep])

    def _store(
        self, ids: np.ndarray, uv: np.ndarray, tmpl: np.ndarray, J: np.ndarray, J_tmpl: np.ndarray
    ) -> None:
        """Put new templates (N, P) and their solve matrices (N, 3, W, P), (N, 3, W) into free slots."""
        slots = self._slots(len(ids))
        self._tmpl[slots] = tmpl
        self._J[slots] = J
        self._J_tmpl[slots] = J_tmpl
        self._g[slots] = 0.0
        self._A[slots] = np.eye(2)
        self._uv0[slots] = uv
        if ids.max() >= len(self._slot_by_id):
            grow = max(int(ids.max()) + 1, 2 * len(self._slot_by_id), 256) - len(self._slot_by_id)
            self._slot_by_id = np.concatenate([self._slot_by_id, np.full(grow, -1, dtype=np.int64)])
        self._slot_by_id[ids] = slots

    def drop(self, ids: np.ndarray) -> None:
        """Forget the templates of ``ids`` (absent ids are ignored)."""
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        found = self._lookup(ids)
        have = found >= 0
        self._slot_by_id[ids[have]] = -1
        self._free.extend(found[have].tolist())

    def keep_only(self, ids: np.ndarray) -> None:
        """Forget every template whose track is not in ``ids`` (the tracks that ended)."""
        have = self.ids
        self.drop(have[~np.isin(have, np.asarray(ids, dtype=np.int64))])

    @staticmethod
    def _compose_projective(A: np.ndarray, g: np.ndarray, dp: np.ndarray) -> tuple[np.ndarray, ...]:
        """The inverse compositional update of homographies ``[[A, 0], [g^T, 1]]`` about their centres.

        ``N = [[A, 0], [g^T, 1]] H(dp)^-1`` with ``H(dp) = [[M, t], [p^T, 1]]``, ``M = I + D``, scaled to
        ``N_22 = 1``, then re-centred: the centre moves by ``delta = N[:2, 2]`` and ``T(-delta) N =
        [[N_11 - delta g'^T, 0], [g'^T, 1]]``. In closed form (Schur complement, ``u = M^-1 t``, ``w =
        M^-T p``, ``s = 1 - p^T u``, ``k = 1 - g^T u``): ``delta = -A u / k``, ``g' = s M^-T g / k - w``,
        ``A' = s A (M^-1 + u w^T / s) / k - delta g'^T``. With ``p = 0`` and ``g = 0`` this is the affine
        update of :meth:`_align`.

        Returns:
            ``(delta (N, 2) px, A (N, 2, 2), g (N, 2) 1/px)``.
        """
        Mi = _inv_2x2(np.eye(2) + dp[:, [0, 2, 1, 3]].reshape(-1, 2, 2))
        u = np.einsum("nij,nj->ni", Mi, dp[:, 4:6])
        w = np.einsum("nji,nj->ni", Mi, dp[:, 6:8])
        s = 1.0 - np.sum(dp[:, 6:8] * u, axis=1)
        k = 1.0 - np.sum(g * u, axis=1)
        delta = -np.einsum("nij,nj->ni", A, u) / k[:, None]
        g_new = (s / k)[:, None] * np.einsum("nji,nj->ni", Mi, g) - w
        tl = Mi * s[:, None, None] + u[:, :, None] * w[:, None, :]
        A_new = np.matmul(A, tl) / k[:, None, None] - delta[:, :, None] * g_new[:, None, :]
        return delta, A_new, g_new

    def _align(
        self,
        img: np.ndarray,
        c: np.ndarray,
        A: np.ndarray,
        g: np.ndarray | None,
        rows: np.ndarray,
        mode: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None]:
        """Inverse-compositional Gauss-Newton of the templates in ``rows`` from the warps ``(c, A, g)``.

        Steps (Baker & Matthews 2004, sec. 3.2, eq. 35), on the tracks still iterating:
        1. sample the image at the current warps and normalize the patches (zero mean, unit RMS);
        2. ``dp = J (I(W) - T)``, with ``J = H^-1 SD^T`` of the template (``J T`` stored); a
           translation-only track's ``J`` is its 2x2 solve's in the translation rows and zero in the
           affine rows, so its ``A`` stays as it is (``(I + 0)^-1 = I`` exactly);
        3. compose with the inverse of the step: ``A <- A (I + D)^-1``, ``c <- c - A (I + D)^-1 t``
           (the homographies: :meth:`_compose_projective`);
        4. a track whose patch leaves the image fails; one whose centre moved by no more than
           ``converged_px`` stops.

        Args:
            img: float32 image (H, W).
            c: Start centres (px), shape (N, 2).
            A: Start linear warps, shape (N, 2, 2).
            g: Start projective rows (N, 2) (1/px), or None when no track is aligned as a homography.
            rows: Storage rows of the templates, shape (N,).
            mode: The fit of each track (N,): 0 translation, 1 affine, 2 homography (only with ``g``).

        Returns:
            ``(c (N, 2), A (N, 2, 2), g (N, 2) or None, ok (N,) bool, zncc (N,) or None)``: the final
            warps, which stayed inside the image, and (``zncc_at_final_warp`` False) the ZNCC of each
            track's last samples against its template (NaN where it never iterated).
        """
        c, A = c.copy(), A.copy()
        g = None if g is None else g.copy()
        zncc = None if self.zncc_at_final_warp else np.full(len(c), np.nan)
        ok = self._inside_warped(img, c, A, g)
        idx = np.flatnonzero(ok)  # the tracks still iterating, with their warps (c_i, A_i, g_i)
        # Each track's solve matrices, one gather (a smaller fit's are zero in the rows it does not have,
        # so those parameters stay as they are).
        width = 6 if g is None else 8
        J, J_tmpl = self._J[rows[idx], mode[idx], :width], self._J_tmpl[rows[idx], mode[idx], :width]
        c_i, A_i = c[idx], A[idx]
        g_i, proj = (None, None) if g is None else (g[idx], mode[idx] == 2)
        for _ in range(self.iterations):
            if len(idx) == 0:
                break
            # 1.-2. J (w / rms - T) with w the zero-mean patch.
            w = self._sample(img, c_i, A_i, g_i)
            w -= w.mean(axis=1, keepdims=True)
            rms = np.sqrt(np.einsum("np,np->n", w, w) / w.shape[1])
            if zncc is not None:  # the normalized patch against the (normalized) template
                dot = np.einsum("np,np->n", w, self._tmpl[rows[idx]])
                zncc[idx] = dot / (w.shape[1] * np.maximum(rms, 1e-9))
            dp = np.matmul(J, w[:, :, None])[:, :, 0] / np.maximum(rms, 1e-9)[:, None] - J_tmpl
            # 3. The inverse compositional update.
            A_new = A_i @ _inv_2x2(np.eye(2) + dp[:, [0, 2, 1, 3]].reshape(-1, 2, 2))
            c_new = c_i - np.einsum("nij,nj->ni", A_new, dp[:, 4:6])
            g_new = g_i
            if g_i is not None:
                g_new = g_i.copy()
                delta, A_new[proj], g_new[proj] = self._compose_projective(A_i[proj], g_i[proj], dp[proj])
                c_new[proj] = c_i[proj] + delta
            # 4. A step that leaves the image fails the track; a small one ends its iterations.
            inside = self._inside_warped(img, c_new, A_new, g_new)
            going = inside & (np.hypot(dp[:, 4], dp[:, 5]) > self.converged_px)
            if not np.all(going):
                done = inside & ~going
                c[idx[done]], A[idx[done]] = c_new[done], A_new[done]
                ok[idx[~inside]] = False
                if g is not None:
                    g[idx[done]] = g_new[done]
                    g_new, proj = g_new[going], proj[going]
                idx, J, J_tmpl = idx[going], J[going], J_tmpl[going]
                c_new, A_new = c_new[going], A_new[going]
            c_i, A_i, g_i = c_new, A_new, g_new
        c[idx], A[idx] = c_i, A_i
        if g is not None:
            g[idx] = g_i
        return c, A, g, ok, zncc

    def _align_compiled(
        self, img: np.ndarray, start: np.ndarray, g: np.ndarray | None, rows: np.ndarray, mode: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """:meth:`_align` and the ZNCC of :meth:`refine` in the compiled kernel (same arguments).

        Returns:
            ``(c (N, 2), A (N, 2, 2), g (N, 2) or None, ok (N,) bool, zncc (N,))``.
        """
        from viotb.vio.frontend_kernels import align_templates  # numba: not at import (viotb --help)

        g_in = np.zeros((len(rows), 2)) if g is None else np.ascontiguousarray(g, dtype=float)
        c, A, g_out, ok, zncc = align_templates(
            np.ascontiguousarray(img, dtype=np.float32),
            np.ascontiguousarray(start, dtype=float),
            np.ascontiguousarray(self._A[rows]),
            g_in,
            rows.astype(np.int64),
            mode.astype(np.int64),
            self._J,
            self._J_tmpl,
            self._tmpl,
            self._r,
            int(self.iterations),
            float(self.converged_px),
            bool(self.zncc_at_final_warp),
        )
        return c, A, None if g is None else g_out, ok, zncc

    def refine(self, image: np.ndarray, ids: np.ndarray, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Align the templates of ``ids`` into ``image``, starting from the frame-to-frame pixels ``uv_px``.

        Args:
            image: The new grayscale image (H, W) (float32 avoids a conversion).
            ids: Track ids (N,).
            uv_px: Frame-to-frame positions (px), shape (N, 2).

        Returns:
            ``(uv_refined (N, 2), anchored (N,) bool)``: the refined position where the alignment was
            accepted, else the input position; ``anchored`` says which (False: take the template anew).
        """
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2).copy()
        ids = np.asarray(ids, dtype=np.int64)
        anchored = np.zeros(len(ids), dtype=bool)
        found = self._lookup(ids)
        which = np.flatnonzero(found >= 0)
        rows = found[which]
        if len(rows) == 0:
            return uv, anchored
        start = uv[which]
        img = np.asarray(image, dtype=np.float32)
        moved = np.linalg.norm(start - self._uv0[rows], axis=1)
        mode = (moved >= self.affine_after_px).astype(np.int64)
        g = None
        if self._projective:
            # A track aligned as a homography once stays one (its warp keeps its projective row).
            mode[(moved >= self.projective_after_px) | np.any(self._g[rows] != 0.0, axis=1)] = 2
            g = self._g[rows] if np.any(mode == 2) else None
        if self.compiled:
            c, A, g, ok, zncc = self._align_compiled(img, start, g, rows, mode)
        else:
            c, A, g, ok, zncc_last = self._align(img, start, self._A[rows], g, rows, mode)
        # Acceptance: the aligned patch still matches, did not slide far, and is not stretched too much.
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            return uv, anchored
        if self.compiled:
            zncc = zncc[idx]
        elif zncc_last is None:
            warped, _ = _normalize(self._sample(img, c[idx], A[idx], None if g is None else g[idx]))
            zncc = np.mean(warped * self._tmpl[rows[idx]], axis=1)
        else:
            zncc = zncc_last[idx]
        sv = singular_values_2x2(A[idx])
        ok[idx] = (zncc >= self.min_zncc) & (np.linalg.norm(c[idx] - start[idx], axis=1) <= self.max_shift_px)
        ok[idx] &= (sv[:, 0] <= self.max_stretch) & (sv[:, 1] >= 1.0 / self.max_stretch)
        uv[which[ok]] = c[ok]
        anchored[which[ok]] = True
        self._A[rows[ok]] = A[ok]
        if g is not None:
            self._g[rows[ok]] = g[ok]
        return uv, anchored
