"""The window's reduced systems: Schur elimination of the landmarks and Cholesky solves.

:func:`schur_reduce` eliminates the landmarks from a :class:`viotb.vio.window_solver.LinearSystem` (its
landmark blocks by the compiled :func:`viotb.vio.window_kernels.landmark_products` and one BLAS product, or
by numpy, the reference); :func:`pose_index`, :func:`coupled_index` and :func:`block_index` index its entries.

The reduced keyframe system ``S`` is symmetric and, damped or
with the prior, positive definite: a Cholesky factor costs a third of the LU ``np.linalg.solve`` factors and
``potri`` inverts it from that factor (the covariances of :class:`viotb.vio.window_nis.WindowMarginals`) in
about half the work of ``np.linalg.inv``. Where ``S`` is not numerically positive definite (a diverging
window) both fall back to numpy's LU, so what happened before still happens (a singular ``S`` raises
``LinAlgError``). The values agree with LU to round-off (``tests/test_window_reprojection.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import lapack
from viotb.vio.window_factors import NX
from viotb.vio.window_kernels import landmark_products


def spd_solve(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``S^-1 b`` for symmetric ``S`` (D, D) and ``b`` (D,) or (D, K): Cholesky, else ``np.linalg.solve``."""
    c, info = lapack.dpotrf(S, lower=False, clean=False, overwrite_a=False)
    if info != 0:
        return np.linalg.solve(S, b)
    x, info = lapack.dpotrs(c, b, lower=False)
    return x if info == 0 else np.linalg.solve(S, b)


def spd_inverse(S: np.ndarray) -> np.ndarray:
    """``S^-1`` (D, D), symmetric, of a symmetric ``S``: Cholesky, else ``np.linalg.inv``."""
    c, info = lapack.dpotrf(S, lower=False, clean=False, overwrite_a=False)
    if info != 0:
        return np.linalg.inv(S)
    inv, info = lapack.dpotri(c, lower=False)
    if info != 0:
        return np.linalg.inv(S)
    upper = np.triu(inv)
    return upper + np.triu(inv, 1).T


def pose_index(n_kf: int) -> np.ndarray:
    """Indices of the ``[dtheta, dp]`` entries of ``n_kf`` keyframes in the stacked error state, (6 n_kf,)."""
    return (np.arange(n_kf)[:, None] * NX + np.arange(6)[None, :]).ravel()


def block_index(idx: np.ndarray) -> tuple[slice, slice] | tuple[np.ndarray, np.ndarray]:
    """``H[block_index(idx)]`` is ``H[np.ix_(idx, idx)]``: slices where ``idx`` is a contiguous range.

    The same entries, and faster than fancy indexing.
    """
    if len(idx) and idx[-1] - idx[0] == len(idx) - 1 and np.all(np.diff(idx) == 1):
        s = slice(int(idx[0]), int(idx[-1]) + 1)
        return s, s
    return np.ix_(idx, idx)


def coupled_index(sys: Any) -> np.ndarray:
    """Entries of the system that the landmarks couple to (the rows of ``E``): poses, then calibration."""
    n_kf = (sys.E.shape[1] - sys.n_calib) // 6
    if not sys.n_calib:
        return pose_index(n_kf)
    return np.concatenate([pose_index(n_kf), n_kf * NX + np.arange(sys.n_calib)])


def schur_reduce(
    sys: Any, lam: float, compiled: bool | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eliminate the landmarks (Schur complement) from the system damped by ``lam`` (relative to diagonal).

    ``compiled`` (None: ``sys.compiled``): the landmark blocks by
    :func:`viotb.vio.window_kernels.landmark_products`, then one product; else by numpy (the reference).

    Returns:
        ``(S (N NX, N NX), g_red (N NX,), H_ll^-1 (L, 3, 3))``.
    """
    N6 = sys.E.shape[1]
    H = sys.H + lam * np.diag(np.diag(sys.H))
    H_ll = sys.H_ll + lam * np.einsum("lii->li", sys.H_ll)[:, :, None] * np.eye(3) + 1e-9 * np.eye(3)
    pidx = coupled_index(sys)
    if sys.compiled if compiled is None else compiled:
        B, E_flat, H_ll_inv, Bg = landmark_products(sys.E, np.ascontiguousarray(H_ll), sys.g_l)
        P, g = B @ E_flat.T, sys.g.copy()
        if sys.n_calib:
            H[np.ix_(pidx, pidx)] -= P
        else:  # the pose entries as a strided view of H
            n_kf = len(g) // NX
            H.reshape(n_kf, NX, n_kf, NX)[:, :6, :, :6] -= P.reshape(n_kf, 6, n_kf, 6)
        g[pidx] -= Bg
        return H, g, H_ll_inv
    H_ll_inv = np.linalg.inv(H_ll)
    EH = sys.E @ H_ll_inv
    L = len(H_ll_inv)
    EH_flat = np.swapaxes(EH, 0, 1).reshape(N6, 3 * L)
    S = H.copy()
    S[np.ix_(pidx, pidx)] -= EH_flat @ np.swapaxes(sys.E, 0, 1).reshape(N6, 3 * L).T
    g = sys.g.copy()
    g[pidx] -= EH_flat @ sys.g_l.ravel()
    return S, g, H_ll_inv
