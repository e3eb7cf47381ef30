"""Closed-form helpers of the template anchoring (:mod:`viotb.vio.klt_anchor`) on stacks of 2x2 matrices."""

from __future__ import annotations

import numpy as np


def _normalize(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean, unit-RMS patches (N, P) and their RMS (N,) (a flat patch gets RMS 0)."""
    centred = patches - patches.mean(axis=1, keepdims=True)
    rms = np.sqrt(np.mean(centred * centred, axis=1))
    return centred / np.maximum(rms, 1e-9)[:, None], rms


def _inv_2x2(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 2x2 matrices (N, 2, 2), closed form (the caller keeps them invertible)."""
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    out = np.empty_like(M)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = d, -b, -c, a
    return out / (a * d - b * c)[:, None, None]


def singular_values_2x2(M: np.ndarray) -> np.ndarray:
    """Singular values of a stack of 2x2 matrices (N, 2, 2), largest first, shape (N, 2), closed form.

    ``s1^2, s2^2`` are the eigenvalues of ``M^T M``: ``(f +- sqrt(f^2 - 4 det^2)) / 2`` with ``f`` the squared
    Frobenius norm.
    """
    f = np.sum(M * M, axis=(1, 2))
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    root = np.sqrt(np.maximum(f * f - 4.0 * det * det, 0.0))
    s1 = np.sqrt(0.5 * (f + root))
    return np.stack([s1, np.abs(det) / np.maximum(s1, 1e-300)], axis=1)
