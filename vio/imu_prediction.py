"""The filter's state predicted to the newest IMU sample: the mean at once, the covariance when read.

A filter's ``estimate()`` is called at every control tick (250 Hz), between camera frames, and returns the
state propagated past the filter's last frame to the newest IMU sample. The mean is needed at once (the
controller flies on it); the 15 x 15 covariance is read by fewer consumers and less often (the Gymnasium
observation once per env step, the health monitor once per frame). :class:`PredictionChain` therefore:

1. advances the mean one IMU interval per new sample (:meth:`Propagator.predict_mean`), keeping each
   interval's :class:`~viotb.vio.imu_integration.StepMean`;
2. builds the transitions ``Phi_k`` and noises ``Q_k`` only when a covariance is read, for every interval
   not yet built, in one array operation (:func:`~viotb.vio.imu_integration.step_transitions`);
3. accumulates ``Phi = Phi_k ... Phi_1`` and ``Q = Phi_k Q_(k-1) Phi_k^T + Q_k`` in the same order as the
   eager prediction did, and returns ``Phi P Phi^T + Q`` symmetrized, ``P`` the IMU block of the
   filter's covariance when the chain started (a copy: the filter may change its own afterwards).

The issue's "covariance in one batched step per control request" (issue #15); the values equal the
per-tick eager prediction (bit for bit when each tick's covariance is read, to round-off when several
intervals are batched: ``tests/test_imu_prediction.py``).
"""

from __future__ import annotations

import numpy as np
from viotb.vio.imu_intrinsics import ImuIntrinsics
from viotb.vio.imu_kernels_calls import chain_links, step_chain_totals, step_links
from viotb.vio.propagator import (
    Propagator,
    StepMean,
    discrete_noise,
    discrete_noise_batch,
    step_transition,
    step_transitions,
)
from viotb.vio.state import IMU_DIM, ImuValues
from viotb.vio.types import StateEstimate


class PredictionChain:
    """Predictions of one filter state (one filter version) to successive IMU sample times.

    Args:
        version: The filter's version counter (the owner starts a new chain when it changes).
        t_s: Time (s, IMU clock) of the filter state.
        imu: The filter's IMU state at ``t_s`` (not modified).
        P_imu: Its IMU covariance block, shape (15, 15), or with online intrinsics that of
            ``[imu, intrinsics]``, shape (15 + n, 15 + n) (copied).
        propagator: The filter's propagator (its IMU buffer and noise).
        intrinsics: The filter's online IMU intrinsics (copied), or None.
    """

    def __init__(
        self,
        version: int,
        t_s: float,
        imu: ImuValues,
        P_imu: np.ndarray,
        propagator: Propagator,
        intrinsics: ImuIntrinsics | None = None,
    ) -> None:
        """Start an empty chain at the filter state."""
        self.version = version
        self.t_s = float(t_s)
        """Time of the newest prediction (the filter state's before the first)."""
        self._vals = imu
        self._P = np.array(P_imu, dtype=float)
        self._propagator = propagator
        self._intr = None if intrinsics is None else intrinsics.copy()
        d = IMU_DIM + (0 if intrinsics is None else intrinsics.dim)
        if self._P.shape != (d, d):
            raise ValueError(f"PredictionChain: P_imu has shape {self._P.shape}, expected ({d}, {d})")
        self._links: list[StepMean | tuple[np.ndarray, np.ndarray]] = []
        self._totals: list[tuple[np.ndarray, np.ndarray]] = []
        self._covs: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        """Number of predictions made."""
        return len(self._links)

    def advance(self, t_s: float) -> tuple[int, ImuValues]:
        """Predict to ``t_s`` (not before the newest prediction) and return ``(index, values)``.

        The newest prediction is returned again when ``t_s`` equals its time (no IMU sample since).

        Raises:
            ValueError: ``t_s`` before the newest prediction (start a new chain from the filter state).
        """
        if self._links and t_s == self.t_s:
            return len(self._links) - 1, self._vals
        if self._links and t_s < self.t_s:
            raise ValueError(f"PredictionChain.advance: t_s={t_s} is before the newest prediction {self.t_s}")
        vals, link = self._propagator.predict_mean(self._vals, self.t_s, t_s, self._intr)
        self._links.append(link)
        self._vals = vals
        self.t_s = max(float(t_s), self.t_s)
        return len(self._links) - 1, vals

    def cov(self, index: int) -> np.ndarray:
        """Covariance (15, 15) of prediction ``index``: ``Phi P Phi^T + Q`` symmetrized (memoized)."""
        cov = self._covs.get(index)
        if cov is None:
            if not 0 <= index < len(self._links):
                raise IndexError(f"PredictionChain.cov: no prediction {index} (have {len(self._links)})")
            self._build_totals()
            phi_tot, q_tot = self._totals[index]
            cov = (phi_tot @ self._P @ phi_tot.T + q_tot)[:IMU_DIM, :IMU_DIM]
            cov = self._covs[index] = 0.5 * (cov + cov.T)
        return cov

    def prefetch(self, indices: list[int]) -> None:
        """Compute the covariances of predictions ``indices`` in one batch (:meth:`cov` then reads them).

        The same values as one :meth:`cov` per index: the stacked products are the per-matrix products
        (numpy's ``matmul`` multiplies each matrix of a stack as it multiplies one), the symmetrization is
        elementwise (``tests/test_imu_prediction_batch.py``).

        Raises:
            IndexError: An index with no prediction.
        """
        todo = sorted({i for i in indices if i not in self._covs})
        if not todo:
            return
        if todo[0] < 0 or todo[-1] >= len(self._links):
            bad = todo[0] if todo[0] < 0 else todo[-1]
            raise IndexError(f"PredictionChain.prefetch: no prediction {bad} (have {len(self._links)})")
        self._build_totals()
        totals = self._totals
        phi = np.array([totals[i][0] for i in todo])
        q = np.array([totals[i][1] for i in todo])
        cov = (phi @ self._P @ phi.transpose(0, 2, 1) + q)[:, :IMU_DIM, :IMU_DIM]
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
        self._covs.update(zip(todo, cov, strict=True))

    def _build_totals(self) -> None:
        """Accumulate ``(Phi, Q)`` from the filter state to every prediction made so far."""
        first = len(self._totals)
        pending = self._links[first:]
        if not pending:
            return
        steps = [link for link in pending if isinstance(link, StepMean)]
        if self._totals:
            phi_tot, q_tot = self._totals[-1]
        else:
            d = self._P.shape[0]
            phi_tot, q_tot = np.eye(d), np.zeros((d, d))
        if self._propagator.compiled and self._intr is None:
            self._build_totals_compiled(pending, steps, phi_tot, q_tot)
            return
        noise = self._propagator.noise
        built: list[tuple[np.ndarray, np.ndarray]] = []
        if len(steps) == 1 and self._intr is None:  # the per-tick read: the eager prediction's functions
            phi = step_transition(steps[0])
            built = [(phi, discrete_noise(phi, noise, steps[0].dt))]
        elif steps:
            phis = step_transitions(steps, self._intr)
            qs = discrete_noise_batch(phis, noise, np.array([s.dt for s in steps]))
            built = list(zip(phis, qs, strict=True))
        k = 0
        for link in pending:
            if isinstance(link, StepMean):
                phi, q = built[k]
                k += 1
            else:
                phi, q = link
            phi_tot, q_tot = phi @ phi_tot, phi @ q_tot @ phi.T + q
            self._totals.append((phi_tot, q_tot))

    def _build_totals_compiled(
        self,
        pending: list[StepMean | tuple[np.ndarray, np.ndarray]],
        steps: list[StepMean],
        phi_tot: np.ndarray,
        q_tot: np.ndarray,
    ) -> None:
        """:meth:`_build_totals` by the kernels: the steps' ``Phi``, ``Q`` and the running totals (15, 15)."""
        if len(steps) == len(pending):  # the common case: one kernel for the links and their chain
            phi_tots, q_tots = step_chain_totals(steps, self._propagator.noise, phi_tot, q_tot)
        else:  # spans among the steps: their (Phi, Q) as predicted, the steps' built by the kernel
            phis, qs = np.empty((len(pending), IMU_DIM, IMU_DIM)), np.empty((len(pending), IMU_DIM, IMU_DIM))
            if steps:
                built = step_links(steps, self._propagator.noise)
                mask = [isinstance(link, StepMean) for link in pending]
                phis[mask], qs[mask] = built
            for i, link in enumerate(pending):
                if not isinstance(link, StepMean):
                    phis[i], qs[i] = link
            phi_tots, q_tots = chain_links(phis, qs, phi_tot, q_tot)
        self._totals.extend(zip(phi_tots, q_tots, strict=True))


class LazyCovarianceEstimate(StateEstimate):
    """A :class:`~viotb.vio.types.StateEstimate` whose ``cov`` is computed on first read.

    Reads, compares, ``dataclasses.replace`` and pickles like the plain record (a pickle is a plain
    :class:`StateEstimate` with the covariance filled in).

    Args:
        t_s: See :class:`StateEstimate` (the mean fields, the same units and frames).
        R_WB: See :class:`StateEstimate`.
        p_WB: See :class:`StateEstimate`.
        v_WB: See :class:`StateEstimate`.
        gyro_bias_rad_s: See :class:`StateEstimate`.
        accel_bias_m_s2: See :class:`StateEstimate`.
        omega_B_rad_s: See :class:`StateEstimate`.
        cov: The covariance (15, 15), or None to compute it with ``source`` when read.
        source: ``(chain, index)``: the covariance is ``chain.cov(index)``.
    """

    def __init__(
        self,
        t_s: float,
        R_WB: np.ndarray,
        p_WB: np.ndarray,
        v_WB: np.ndarray,
        gyro_bias_rad_s: np.ndarray,
        accel_bias_m_s2: np.ndarray,
        omega_B_rad_s: np.ndarray,
        cov: np.ndarray | None = None,
        source: tuple[PredictionChain, int] | None = None,
    ) -> None:
        """Store the mean; the covariance now (``cov``) or later (``source``)."""
        if cov is None and source is None:
            raise ValueError("LazyCovarianceEstimate needs cov or source")
        put = object.__setattr__
        put(self, "t_s", t_s)
        put(self, "R_WB", R_WB)
        put(self, "p_WB", p_WB)
        put(self, "v_WB", v_WB)
        put(self, "gyro_bias_rad_s", gyro_bias_rad_s)
        put(self, "accel_bias_m_s2", accel_bias_m_s2)
        put(self, "omega_B_rad_s", omega_B_rad_s)
        put(self, "_cov", cov)
        put(self, "_source", source)

    @classmethod
    def from_chain(
        cls, chain: PredictionChain, index: int, vals: ImuValues, omega_B_rad_s: np.ndarray
    ) -> LazyCovarianceEstimate:
        """The estimate at ``chain.advance``'s ``(index, vals)``: the mean copied, the covariance when read.

        Args:
            chain: The prediction chain (its ``t_s`` is the estimate's time).
            index: The index ``chain.advance`` returned.
            vals: The values ``chain.advance`` returned (copied, so the chain may move on).
            omega_B_rad_s: Corrected body rate (rad/s), shape (3,).
        """
        return cls(
            chain.t_s,
            vals.R_WB.copy(),
            vals.p_WB.copy(),
            vals.v_WB.copy(),
            vals.gyro_bias_rad_s.copy(),
            vals.accel_bias_m_s2.copy(),
            omega_B_rad_s,
            source=(chain, index),
        )

    @property
    def cov(self) -> np.ndarray:
        """Error-state covariance of ``[dtheta, dp, dv, dbg, dba]``, shape (15, 15) (see StateEstimate)."""
        cov = self._cov
        if cov is None:
            chain, index = self._source
            cov = chain.cov(index)
            object.__setattr__(self, "_cov", cov)
            object.__setattr__(self, "_source", None)
        return cov

    @property
    def cov_ready(self) -> bool:
        """Whether the covariance has been computed (reading it costs nothing more)."""
        return self._cov is not None

    def __reduce__(self):
        """Pickle as a plain :class:`StateEstimate` (the chain stays behind)."""
        return (
            StateEstimate,
            (
                self.t_s,
                self.R_WB,
                self.p_WB,
                self.v_WB,
                self.gyro_bias_rad_s,
                self.accel_bias_m_s2,
                self.omega_B_rad_s,
                self.cov,
            ),
        )


def prefetch_covariances(estimates: list[StateEstimate]) -> None:
    """Compute the covariances of the lazy estimates among ``estimates`` in one batch per chain.

    Reading ``cov`` afterwards costs nothing more and gives the same values
    (:meth:`PredictionChain.prefetch`); plain estimates and computed covariances are skipped.
    """
    by_chain: dict[int, tuple[PredictionChain, list[int]]] = {}
    for est in estimates:
        source = getattr(est, "_source", None)
        if source is not None:
            chain, index = source
            by_chain.setdefault(id(chain), (chain, []))[1].append(index)
    for chain, indices in by_chain.values():
        chain.prefetch(indices)
