"""The state observation of the viotb Gymnasium envs (:class:`~viotb.envs.gym.base.VioQuadEnv`).

Its entries and their order are the env's ``_state_layout`` (``state_names()``); every one comes from the
estimator, none from the truth.
"""

from __future__ import annotations

import numpy as np
from viotb.envs.sim.checks import all_finite
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.types import StateEstimate


def orientation_features(R_WB: np.ndarray, kind: str) -> np.ndarray:
    """Orientation as network input: ``rot6d`` = ``[R[:, 0], R[:, 1]]`` (6,) or ``quat_wxyz``, w >= 0 (4,).

    Zhou et al., "On the continuity of rotation representations in neural networks", CVPR 2019 (6D).
    """
    if kind == "rot6d":
        return np.concatenate([R_WB[:, 0], R_WB[:, 1]])
    q = rotmat_to_quat_wxyz(R_WB)
    return -q if q[0] < 0.0 else q


def state_vector_rot6d(
    est: StateEstimate,
    tracked_features: int,
    target_est_W_m: np.ndarray,
    target_v_est_W_m_s: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
) -> np.ndarray:
    """The flat state observation (float32) of an estimate, with the ``rot6d`` orientation.

    The entries of the env's concatenation of arrays, from plain floats: the position difference taken in
    floats (the same subtraction), cast to float32 and clipped to the state space by the same numpy calls, at
    about a third of the concatenation's cost per step.

    Args:
        est: The estimate (estimator frame).
        tracked_features: The estimator's tracked-feature count.
        target_est_W_m: Target position in the estimator's frame (m), shape (3,).
        target_v_est_W_m_s: Target velocity in the estimator's frame (m/s), shape (3,).
        low: Lower bounds of the state space, float32, shape (N,).
        high: Upper bounds, float32, shape (N,).
    """
    (r00, r01, _), (r10, r11, _), (r20, r21, _) = est.R_WB.tolist()
    var = est.cov.diagonal().tolist()
    target = target_est_W_m.tolist()
    values = [
        *(p - t for p, t in zip(est.p_WB.tolist(), target, strict=True)),
        *est.v_WB.tolist(),
        r00, r10, r20, r01, r11, r21,
        *est.omega_B_rad_s.tolist(),
        *target,
        *target_v_est_W_m_s.tolist(),
        *var[3:9],
        float(tracked_features),
    ]  # fmt: skip
    vec = np.array(values, dtype=np.float32)
    if not all_finite(vec.tolist()):  # after the cast: a float64 beyond float32's range reads inf
        vec = np.nan_to_num(vec, nan=0.0, posinf=1e6, neginf=-1e6)
    return np.minimum(np.maximum(vec, low, out=vec), high, out=vec)
