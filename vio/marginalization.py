"""Schur-complement marginalization into a linear prior.

Leutenegger et al. IJRR 2015 sec. IV-E (OKVIS); Qin et al. TRO 2018 sec. VI-D (VINS-Mono); lesson ch. 4.

A Gauss-Newton system ``H dx = -g`` of a cost ``0.5 dx^T H dx + g^T dx`` split into kept ``r`` and
marginalized ``m`` variables::

    [H_rr H_rm] [dx_r]     [g_r]
    [H_mr H_mm] [dx_m] = - [g_m]

loses ``m`` without losing what it told us about ``r`` by eliminating it:
``H* = H_rr - H_rm H_mm^-1 H_mr`` and ``g* = g_r - H_rm H_mm^-1 g_m``. ``H*`` is the information of the
marginal Gaussian of ``r`` (its inverse is the ``r`` block of ``H^-1``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def schur_complement(
    H: np.ndarray, g: np.ndarray, marg_idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eliminate the variables ``marg_idx`` from the system ``(H, g)``.

    Args:
        H: Information (Gauss-Newton Hessian), shape (D, D), symmetric.
        g: Gradient, shape (D,).
        marg_idx: Indices of the variables to marginalize, shape (M,).

    Returns:
        ``(H_prior (D-M, D-M), g_prior (D-M,), keep_idx (D-M,))`` over the kept indices in increasing order.

    Raises:
        ValueError: when the shapes disagree or an index is out of range.
    """
    H = np.asarray(H, dtype=float)
    g = np.asarray(g, dtype=float)
    D = H.shape[0]
    if H.shape != (D, D) or g.shape != (D,):
        raise ValueError(f"schur_complement: H {H.shape} and g {g.shape} do not agree")
    marg = np.unique(np.asarray(marg_idx, dtype=np.int64))
    if len(marg) and (marg[0] < 0 or marg[-1] >= D):
        raise ValueError(f"schur_complement: marg_idx out of range 0..{D - 1}: {marg.tolist()}")
    keep = np.setdiff1d(np.arange(D), marg)
    H_mm = H[np.ix_(marg, marg)]
    H_rm = H[np.ix_(keep, marg)]
    # Symmetric eigen-decomposition inverse of H_mm (VINS-Mono's ``Marginalization``): directions with no
    # information are dropped instead of producing inf.
    w, V = np.linalg.eigh(0.5 * (H_mm + H_mm.T))
    tol = max(float(w.max(initial=0.0)), 1.0) * 1e-12
    w_inv = np.where(w > tol, 1.0 / np.where(w > tol, w, 1.0), 0.0)
    H_mm_inv = (V * w_inv) @ V.T
    K = H_rm @ H_mm_inv
    H_prior = H[np.ix_(keep, keep)] - K @ H_rm.T
    g_prior = g[keep] - K @ g[marg]
    return 0.5 * (H_prior + H_prior.T), g_prior, keep


@dataclass
class LinearPrior:
    """A linear (Gaussian) prior left by marginalization: ``0.5 dx^T H dx + g^T dx``.

    ``dx = x [-] x0`` is taken from the linearization point ``x0`` of the prior's states, which stays fixed
    (first-estimate linearization: the prior's Jacobian is never re-evaluated, Leutenegger et al. 2015
    sec. IV-E; Huang et al., first-estimates Jacobians).

    Attributes:
        H: Information, shape (D, D).
        g: Gradient at ``x0``, shape (D,).
        keys: Identifiers of the states, in the order of their blocks.
        x0: Linearization point of each state (one entry per key).
    """

    H: np.ndarray
    g: np.ndarray
    keys: list
    x0: list
