"""Filter state with named covariance blocks (the open_vins ``Type`` / ``StateHelper`` idea).

The error state is ordered by blocks: ``imu`` (15) first, then the optional IMU intrinsics
``imu_intr_gyro`` / ``imu_intr_accel`` (9 each, :mod:`viotb.vio.imu_intrinsics`; propagated with the IMU
block), the optional calibration blocks ``extrinsic`` (6: ``[dphi_BC, dp_BC]``) and ``time_offset`` (1),
then one 6-dof block per pose clone (``[dtheta, dp]``, oldest first) and one 3-dof block per SLAM
landmark (``slam@<id>``: ``dp_f`` in W, :mod:`viotb.vio.slam_features`), in the order they were added.
Rotations use the right (body-frame) perturbation ``R = R_hat Exp(dtheta)``; every other quantity is
additive. The IMU block is ordered ``[dtheta, dp, dv, dbg, dba]`` (:class:`viotb.vio.types.StateEstimate`).

The covariance is owned by :class:`State` and changes only through the module functions below
(``ekf_propagate``, ``ekf_update``, ``augment_clone``, ``marginalize``), as open_vins' ``StateHelper`` is the
only friend of its ``State``. Other modules read it through :func:`marginal_covariance` and named blocks.
The blocks' nominal values are the records of :mod:`viotb.vio.state_values` (re-exported here).

First-estimate Jacobians (FEJ; Huang, Mourikis, Roumeliotis, "A First-Estimates Jacobian EKF for improving
SLAM consistency", ISER 2008 / IJRR 2010; open_vins ``fej.dox``): the IMU keeps the values it had right after
its last propagation (``imu_fej``) and each clone keeps the values it was cloned with. The propagator
evaluates its Jacobians there; the MSCKF update evaluates them at the current estimates and projects out
the four unobservable directions (global position and yaw) taken at the clones' first estimates
(observability-constrained EKF, Hesch et al., TRO 2014; see ``MsckfParams.update_linearization``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from viotb.vio.imu_intrinsics import ImuIntrinsics
from viotb.vio.lie import exp_so3, exp_so3_batch
from viotb.vio.state_values import ClonePose, ImuValues, SlamLandmark

IMU_DIM = 15
CLONE_DIM = 6
EXTRINSIC_DIM = 6
IMU_BLOCK = "imu"
EXTRINSIC_BLOCK = "extrinsic"
TIME_OFFSET_BLOCK = "time_offset"

# Offsets of the sub-blocks of the IMU error state [dtheta, dp, dv, dbg, dba].
THETA, POS, VEL, BG, BA = 0, 3, 6, 9, 12


@dataclass(frozen=True)
class Block:
    """A contiguous piece of the error state.

    Attributes:
        name: Block name (``"imu"``, ``"extrinsic"``, ``"time_offset"`` or ``"clone@<t>"``).
        offset: First index in the error state / covariance.
        size: Error-state dimension.
    """

    name: str
    offset: int
    size: int

    @property
    def indices(self) -> slice:
        """Slice of this block in the covariance."""
        return slice(self.offset, self.offset + self.size)


class State:
    """IMU state, optional calibration and a window of pose clones, with their joint covariance.

    Args:
        t_s: Time (s, IMU clock) of the IMU state.
        imu: Initial nominal IMU state.
        imu_cov: Covariance of ``[dtheta, dp, dv, dbg, dba]``, shape (15, 15).
        R_BC: Camera-to-body rotation, shape (3, 3).
        p_BC: Camera origin in B (m), shape (3,).
        time_offset_s: ``t_imu = t_cam + time_offset_s``.
        extrinsic_cov: If given, shape (6, 6): the extrinsic is estimated online with this prior.
        time_offset_var_s2: If given (s^2): the time offset is estimated online with this prior variance.
        intrinsics: If given, the IMU intrinsics (copied); its estimated blocks get ``intrinsics_cov``.
        intrinsics_cov: Prior covariance of the intrinsic blocks, shape (intrinsics.dim, intrinsics.dim).
    """

    def __init__(
        self,
        t_s: float,
        imu: ImuValues,
        imu_cov: np.ndarray,
        R_BC: np.ndarray,
        p_BC: np.ndarray,
        time_offset_s: float = 0.0,
        extrinsic_cov: np.ndarray | None = None,
        time_offset_var_s2: float | None = None,
        intrinsics: ImuIntrinsics | None = None,
        intrinsics_cov: np.ndarray | None = None,
    ) -> None:
        """Create the state with the IMU block and the requested calibration blocks."""
        imu_cov = np.asarray(imu_cov, dtype=float)
        if imu_cov.shape != (IMU_DIM, IMU_DIM):
            raise ValueError(f"imu_cov must have shape (15, 15), got {imu_cov.shape}")
        if not np.all(np.isfinite(imu_cov)):
            raise ValueError("imu_cov must be finite")
        self.t_s = float(t_s)
        self.imu = imu.copy()
        self.imu_fej = imu.copy()
        self.R_BC = np.array(R_BC, dtype=float)
        self.p_BC = np.array(p_BC, dtype=float)
        self.time_offset_s = float(time_offset_s)
        self.clones: dict[float, ClonePose] = {}
        self.landmarks: dict[int, SlamLandmark] = {}
        self._blocks: dict[str, Block] = {IMU_BLOCK: Block(IMU_BLOCK, 0, IMU_DIM)}
        diag = [imu_cov]
        self.intrinsics = None if intrinsics is None else intrinsics.copy()
        if intrinsics is not None and intrinsics.dim:
            for name in intrinsics.block_names():
                self._blocks[name] = Block(name, self._dim_blocks(), 9)
            diag.append(np.asarray(intrinsics_cov, dtype=float).reshape(intrinsics.dim, intrinsics.dim))
        if extrinsic_cov is not None:
            self._blocks[EXTRINSIC_BLOCK] = Block(EXTRINSIC_BLOCK, self._dim_blocks(), EXTRINSIC_DIM)
            diag.append(np.asarray(extrinsic_cov, dtype=float).reshape(EXTRINSIC_DIM, EXTRINSIC_DIM))
        if time_offset_var_s2 is not None:
            self._blocks[TIME_OFFSET_BLOCK] = Block(TIME_OFFSET_BLOCK, self._dim_blocks(), 1)
            diag.append(np.array([[float(time_offset_var_s2)]]))
        self._cov = scipy.linalg.block_diag(*diag)
        self._cov = 0.5 * (self._cov + self._cov.T)

    def _dim_blocks(self) -> int:
        return sum(b.size for b in self._blocks.values())

    @property
    def dim(self) -> int:
        """Error-state dimension."""
        return self._cov.shape[0]

    @property
    def propagated_dim(self) -> int:
        """Size of the leading ``[imu, intrinsics]`` part that the IMU propagation transforms."""
        return IMU_DIM + (0 if self.intrinsics is None else self.intrinsics.dim)

    @property
    def cov(self) -> np.ndarray:
        """Read-only view of the full covariance, shape (dim, dim)."""
        view = self._cov.view()
        view.flags.writeable = False
        return view

    def block(self, name: str) -> Block:
        """The block called ``name`` (ValueError listing the blocks if absent)."""
        try:
            return self._blocks[name]
        except KeyError:
            raise ValueError(f"no state block {name!r}; blocks are {list(self._blocks)}") from None

    def has_block(self, name: str) -> bool:
        """Whether a block called ``name`` exists."""
        return name in self._blocks

    @property
    def blocks(self) -> tuple[Block, ...]:
        """All blocks in covariance order."""
        return tuple(self._blocks.values())

    @staticmethod
    def clone_name(t_s: float) -> str:
        """Block name of the clone at camera time ``t_s``."""
        return f"clone@{t_s:.9f}"

    def clone_block(self, t_s: float) -> Block:
        """Block of the clone at camera time ``t_s``."""
        return self.block(self.clone_name(t_s))

    @staticmethod
    def landmark_name(feature_id: int) -> str:
        """Block name of the SLAM landmark of track ``feature_id``."""
        return f"slam@{int(feature_id)}"

    def landmark_block(self, feature_id: int) -> Block:
        """Block of the SLAM landmark of track ``feature_id``."""
        return self.block(self.landmark_name(feature_id))

    @property
    def clone_times(self) -> np.ndarray:
        """Clone camera times (s), oldest first, shape (K,)."""
        return np.fromiter(self.clones.keys(), dtype=float, count=len(self.clones))

    def is_finite(self) -> bool:
        """True when every value and the covariance are finite."""
        imu = self.imu
        vals = [imu.R_WB, imu.p_WB, imu.v_WB, imu.gyro_bias_rad_s, imu.accel_bias_m_s2]
        intr_ok = self.intrinsics is None or self.intrinsics.is_finite()
        return bool(all(np.all(np.isfinite(v)) for v in vals) and np.all(np.isfinite(self._cov)) and intr_ok)

    # Internal helpers used by the module functions below ------------------------------------------------
    def _set_cov(self, cov: np.ndarray) -> None:
        self._cov = 0.5 * (cov + cov.T)

    def _boxplus(self, dx: np.ndarray) -> None:
        """Apply an error-state correction ``dx`` (dim,) to every block."""
        imu = self.imu
        imu.R_WB = imu.R_WB @ exp_so3(dx[THETA : THETA + 3])
        imu.p_WB = imu.p_WB + dx[POS : POS + 3]
        imu.v_WB = imu.v_WB + dx[VEL : VEL + 3]
        imu.gyro_bias_rad_s = imu.gyro_bias_rad_s + dx[BG : BG + 3]
        imu.accel_bias_m_s2 = imu.accel_bias_m_s2 + dx[BA : BA + 3]
        if self.intrinsics is not None:
            self.intrinsics.boxplus(dx[IMU_DIM : self.propagated_dim])
        if EXTRINSIC_BLOCK in self._blocks:
            o = self._blocks[EXTRINSIC_BLOCK].offset
            self.R_BC = self.R_BC @ exp_so3(dx[o : o + 3])
            self.p_BC = self.p_BC + dx[o + 3 : o + 6]
        if TIME_OFFSET_BLOCK in self._blocks:
            self.time_offset_s += float(dx[self._blocks[TIME_OFFSET_BLOCK].offset])
        if self.clones:  # all clones at once: one stacked Rodrigues, one stacked product (the same 3x3 GEMMs)
            clones = list(self.clones.items())
            o = np.array([self._blocks[self.clone_name(t)].offset for t, _ in clones])[:, None] + np.arange(3)
            R_new = np.stack([c.R_WB for _, c in clones]) @ exp_so3_batch(dx[o])
            p_new = np.stack([c.p_WB for _, c in clones]) + dx[o + 3]
            for k, (_, clone) in enumerate(clones):
                clone.R_WB, clone.p_WB = R_new[k], p_new[k]
        for fid, lm in self.landmarks.items():
            o = self._blocks[self.landmark_name(fid)].offset
            lm.p_W = lm.p_W + dx[o : o + 3]
            if lm.track_bias.size:
                lm.track_bias = lm.track_bias + dx[o + 3 : o + 3 + lm.track_bias.size].reshape(-1, 2)


def marginal_covariance(state: State, blocks: list[Block] | tuple[Block, ...]) -> np.ndarray:
    """Joint covariance of ``blocks`` in the given order, shape (sum of sizes, sum of sizes) (a copy)."""
    idx = np.concatenate([np.arange(b.offset, b.offset + b.size) for b in blocks])
    return state._cov[np.ix_(idx, idx)].copy()


def ekf_propagate(state: State, phi_imu: np.ndarray, q_imu: np.ndarray) -> None:
    """Propagate the covariance with the transition ``phi_imu`` and noise ``q_imu`` (d, d) of the IMU part.

    ``d = state.propagated_dim`` (the IMU block and the intrinsics after it). ``P_II <- Phi P_II Phi^T + Q``,
    ``P_IX <- Phi P_IX`` (the other blocks are static; open_vins ``StateHelper::EKFPropagation``).
    """
    d = state.propagated_dim
    if phi_imu.shape != (d, d) or q_imu.shape != (d, d):
        raise ValueError(f"ekf_propagate: Phi {phi_imu.shape} / Q {q_imu.shape} must be ({d}, {d})")
    P = state._cov.copy()
    P[:d, :] = phi_imu @ P[:d, :]
    P[:, :d] = P[:, :d] @ phi_imu.T
    P[:d, :d] += q_imu
    state._set_cov(P)


def ekf_update(state: State, H: np.ndarray, r: np.ndarray, R: np.ndarray | float) -> np.ndarray:
    """EKF update with a full-width Jacobian; returns the applied correction ``dx`` (dim,).

    ``S = H P H^T + R``, ``K = P H^T S^-1``, ``P <- P - K S K^T`` followed by symmetrization (the symmetric
    form; open_vins ``StateHelper::EKFUpdate``), then ``x <- x boxplus K r``.

    Args:
        state: The state (modified in place).
        H: Measurement Jacobian, shape (m, dim).
        r: Residual ``z - h(x_hat)``, shape (m,).
        R: Measurement noise covariance, shape (m, m), or a scalar variance for ``R = sigma^2 I``.

    Raises:
        ValueError: on shape mismatches or a non-positive-definite innovation covariance.
    """
    H = np.atleast_2d(H)
    m = H.shape[0]
    if H.shape[1] != state.dim or r.shape != (m,):
        raise ValueError(f"ekf_update: H {H.shape} and r {r.shape} do not match state dim {state.dim}")
    P = state._cov
    PHt = P @ H.T
    S = H @ PHt
    if np.isscalar(R) or np.ndim(R) == 0:
        S[np.diag_indices(m)] += float(R)
    else:
        S += R
    # LAPACK's Cholesky directly: what scipy.linalg.cho_factor / cho_solve call, without their wrappers.
    c, info = scipy.linalg.lapack.dpotrf(S, lower=1, clean=0)
    if info != 0:
        raise ValueError(f"ekf_update: innovation covariance is not positive definite (dpotrf info {info})")
    K_t, info = (np.zeros((0, P.shape[0])), 0) if m == 0 else scipy.linalg.lapack.dpotrs(c, PHt.T, lower=1)
    if info != 0:  # K_t (m, dim) = S^-1 H P
        raise ValueError(f"ekf_update: dpotrs argument {-info} is invalid")
    dx = K_t.T @ r
    state._set_cov(P - PHt @ K_t)
    state._boxplus(dx)
    return dx


def augment_clone(state: State, t_cam_s: float, omega_B_rad_s: np.ndarray | None = None) -> Block:
    """Clone the current IMU pose as a new block keyed by camera time ``t_cam_s``.

    The clone error equals the IMU pose error; with an online time offset, the clone is the pose at the true
    time ``t_cam + t_d`` so it also depends on ``dt_d`` through ``[omega_B; v_WB]`` (right perturbation:
    ``R(t + dt) = R Exp(omega dt)``, ``p(t + dt) = p + v dt``), as open_vins ``StateHelper::augment_clone``.

    Args:
        state: The state (modified in place); the IMU must already be propagated to ``t_cam + t_d``.
        t_cam_s: Camera timestamp (s), the clone key; must be newer than every clone.
        omega_B_rad_s: Bias-corrected angular rate at the clone time (needed with an online time offset).

    Returns:
        The new clone block.
    """
    if t_cam_s in state.clones or (state.clones and t_cam_s <= next(reversed(state.clones))):
        raise ValueError(f"augment_clone: clone time {t_cam_s} is not newer than the last clone")
    n = state.dim
    J = np.zeros((CLONE_DIM, n))
    J[0:3, THETA : THETA + 3] = np.eye(3)
    J[3:6, POS : POS + 3] = np.eye(3)
    if TIME_OFFSET_BLOCK in state._blocks:
        if omega_B_rad_s is None:
            raise ValueError("augment_clone: omega_B_rad_s is required with an online time offset")
        o = state._blocks[TIME_OFFSET_BLOCK].offset
        J[0:3, o] = omega_B_rad_s
        J[3:6, o] = state.imu.v_WB
    P = state._cov
    JP = J @ P
    new = np.empty((n + CLONE_DIM, n + CLONE_DIM))
    new[:n, :n] = P
    new[n:, :n] = JP
    new[:n, n:] = JP.T
    new[n:, n:] = JP @ J.T
    state._set_cov(new)
    block = Block(State.clone_name(t_cam_s), n, CLONE_DIM)
    state._blocks[block.name] = block
    state.clones[float(t_cam_s)] = ClonePose(
        float(t_cam_s),
        state.imu.R_WB.copy(),
        state.imu.p_WB.copy(),
        state.imu.R_WB.copy(),
        state.imu.p_WB.copy(),
    )
    return block


def marginalize(state: State, block: Block) -> None:
    """Remove ``block`` and its rows/columns of the covariance (open_vins ``StateHelper::marginalize``)."""
    if block.name == IMU_BLOCK:
        raise ValueError("marginalize: the IMU block cannot be marginalized")
    current = state.block(block.name)
    keep = np.r_[0 : current.offset, current.offset + current.size : state.dim]
    state._cov = state._cov[np.ix_(keep, keep)]
    del state._blocks[current.name]
    offset = 0
    for name, b in list(state._blocks.items()):
        state._blocks[name] = Block(name, offset, b.size)
        offset += b.size
    if current.name.startswith("clone@"):
        t = next(t for t in state.clones if State.clone_name(t) == current.name)
        del state.clones[t]
    elif current.name.startswith("slam@"):
        del state.landmarks[int(current.name[5:])]


def augment_landmark(
    state: State,
    feature_id: int,
    p_W: np.ndarray,
    cov_x_l: np.ndarray,
    cov_l_l: np.ndarray,
    last_xy: np.ndarray,
) -> Block:
    """Append a SLAM landmark block (open_vins ``StateHelper::initialize_invertible``).

    Args:
        state: The state (modified in place).
        feature_id: Track id (must not be a landmark already).
        p_W: Landmark position (m) in W, shape (3,); also its first estimate. Its walk states start at 0.
        cov_x_l: Cross-covariance of the existing error state with the block, shape (dim, 3 + 2 B).
        cov_l_l: Covariance of the block ``[dp_f, db]``, shape (3 + 2 B, 3 + 2 B).
        last_xy: The observations the walk was last clocked at, shape (B, 2).
    """
    n, size = state.dim, cov_l_l.shape[0]
    if feature_id in state.landmarks or cov_x_l.shape != (n, size) or size != 3 + np.size(last_xy):
        raise ValueError(f"augment_landmark: feature {feature_id} exists or shapes {cov_x_l.shape}, {size}")
    new = np.empty((n + size, n + size))
    new[:n, :n] = state._cov
    new[:n, n:] = cov_x_l
    new[n:, :n] = cov_x_l.T
    new[n:, n:] = cov_l_l
    state._set_cov(new)
    block = Block(State.landmark_name(feature_id), n, size)
    state._blocks[block.name] = block
    p, xy = np.array(p_W, dtype=float), np.array(last_xy, dtype=float).reshape(-1, 2)
    state.landmarks[int(feature_id)] = SlamLandmark(int(feature_id), p, p.copy(), np.zeros_like(xy), xy)
    return block


def add_diagonal_noise(state: State, indices: np.ndarray, var: np.ndarray) -> None:
    """Add process noise ``var`` (same shape as ``indices``) to the covariance diagonal at ``indices``."""
    state._cov[indices, indices] += var


def marginalize_oldest_clone(state: State) -> float | None:
    """Marginalize the oldest clone; returns its time, or None when there is no clone."""
    if not state.clones:
        return None
    t = next(iter(state.clones))
    marginalize(state, state.clone_block(t))
    return t


def is_psd(state: State, tol: float = 1e-12) -> bool:
    """True when the covariance is symmetric positive semi-definite (Cholesky of ``P + tol I``)."""
    P = state._cov
    if not np.all(np.isfinite(P)):
        return False
    P_tol = P.copy()
    P_tol[np.diag_indices_from(P_tol)] += tol  # P + tol I (the off-diagonal zeros added nothing)
    try:
        np.linalg.cholesky(P_tol)
    except np.linalg.LinAlgError:
        return False
    return True


def set_imu_fej(state: State) -> None:
    """Record the current IMU values as the first estimates (after each propagation)."""
    state.imu_fej = state.imu.copy()


def read_init_record(init: object) -> tuple[float, ImuValues, np.ndarray]:
    """Read an ``InitResult``-like record (t_s, R_WB, p_WB, v_WB, biases, cov_diag) with clear errors.

    An optional ``sigma_yaw_rad`` (finite) sets the variance of ``dtheta`` about world z (the yaw gauge) and
    removes that direction from the given orientation variances.

    Returns:
        ``(t_s, values, cov)``: the time (s), the IMU state and the 15x15 covariance (StateEstimate order
        ``[dtheta, dp, dv, dbg, dba]``; diagonal but for the orientation block with ``sigma_yaw_rad``).

    Raises:
        ValueError: A missing field, a wrong shape, a non-finite value or a non-positive variance.
    """
    names = ("R_WB", "p_WB", "v_WB", "gyro_bias_rad_s", "accel_bias_m_s2", "cov_diag")
    shapes = ((3, 3), (3,), (3,), (3,), (3,), (15,))
    try:
        t_s = float(init.t_s)  # type: ignore[attr-defined]
        arrays = [np.array(getattr(init, name), dtype=float) for name in names]
    except AttributeError as exc:
        raise ValueError(f"initialize: the init record lacks a field ({exc})") from None
    for name, arr, shape in zip(names, arrays, shapes, strict=True):
        if arr.shape != shape:
            raise ValueError(f"initialize: {name} must have shape {shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"initialize: {name} is not finite: {arr.tolist()}")
    vals, cov_diag = ImuValues(*arrays[:5]), arrays[5]
    if np.any(cov_diag <= 0.0):
        raise ValueError(f"initialize: cov_diag must be positive, got {cov_diag.tolist()}")
    cov = np.diag(cov_diag)
    sigma_yaw = float(getattr(init, "sigma_yaw_rad", float("nan")))
    if np.isfinite(sigma_yaw):
        if sigma_yaw <= 0.0:
            raise ValueError(f"initialize: sigma_yaw_rad must be > 0, got {sigma_yaw}")
        # The body-frame error dtheta has its yaw part along u = R_WB^T z_W: project it out of the tilt
        # variances and give it the gauge's sigma.
        u = vals.R_WB.T @ np.array([0.0, 0.0, 1.0])
        tilt = np.eye(3) - np.outer(u, u)
        cov[0:3, 0:3] = tilt @ cov[0:3, 0:3] @ tilt + sigma_yaw**2 * np.outer(u, u)
    return t_s, vals, cov
