"""Recovery in flight: coast on the IMU when tracking is lost, re-initialize in the air when it returns.

:class:`RecoveringEstimator` wraps any feature-based estimator of the :class:`~viotb.vio.types.Estimator`
protocol (``msckf``, ``window``) and is one itself. Three modes:

1. ``tracking``: the inner estimator runs as usual and its estimate is published. Tracking is lost when the
   inner estimator reports divergence (or fails numerically in an update), when a caller declares it lost
   (:meth:`RecoveringEstimator.declare_lost`: the runner does so on the health monitor's ``divergence``), or
   when no feature has been tracked for ``RecoveryParams.feature_loss_s`` (lights out, lens covered).
2. ``coasting``: the published state is dead reckoning (strapdown integration of the IMU with the
   covariance propagated by the same error-state model as the filters, :class:`~viotb.vio.propagator.
   Propagator`) from the last good estimate, so a closed loop keeps flying instead of stopping. A fresh
   instance of the estimator is built at once and fed the IMU and the frames, but not started: its front
   end tells when features are back.
3. Hand-over: after ``return_frames`` consecutive frames with at least ``return_min_features`` tracks, the
   fresh estimator is initialized in the air from the coasted state at that frame's time and becomes the
   inner estimator (``tracking`` again). Its own inertial initializer is switched off (its
   ``initializer`` attribute, which the feature-based estimators expose, set to None): a static solve
   would declare the hovering drone at rest (measured on a hover stream: it fires in the dark and sets the
   velocity to zero), and its world frame (yaw 0, origin at its first pose) would jump the published one.

Why seed from the coasted state rather than solve a dynamic initialization: a hover gives the dynamic
initializer nothing to observe (metric velocity and scale need acceleration, lesson ch. 6), and after an
outage of seconds the coasted state is better than any fresh solve could be: the gravity direction drifts
only by the gyro-bias error times the outage (1e-3 rad over 4 s), the velocity error grows by the tilt and
accelerometer-bias errors times the outage, and the biases are the previous filter's. The seed's
covariance is the coasted one, which carries that growth, inflated by ``cov_inflation`` (the filters'
own covariance is known to be optimistic with KLT tracks) and floored. The position is the exception: it
is unobservable to VIO, the new estimator's world frame is anchored at the coasted pose (so a controller's
setpoints keep their meaning), and like any initialization the anchor gets the gauge prior
``sigma_position_m`` (the yaw keeps its coasted sigma, about 1e-3 rad); how far the coasted pose may have
drifted is reported in :class:`RecoveryEvent.coast_position_sigma_m`, not put into the new filter (it could
not reduce it). The closed loop builds the re-initialized MSCKF with :func:`cold_start_msckf_params`
(``make_reinit``): a clone per frame, so that its first update comes before the coasted velocity error
makes its clone window inconsistent.

Velocity from a map (:meth:`RecoveringEstimator.expect_velocity_fixes`, :meth:`RecoveringEstimator.
velocity_fix`): the coast's velocity error (8-9 cm/s after 4 s dark, ``fly-lights-out``) is what a
re-initialized monocular filter cannot correct in a hover. The motion is then near constant velocity, whose
magnitude (the scale) camera and IMU do not observe; the new filter triangulates its fresh tracks on the
wrong baseline and confirms the wrong velocity (measured: error 9 cm/s, sigma 1 mm/s, NIS 1, velocity NEES
in the thousands). A loop closer that relocalizes the returning frames against the map made before the
loss measures the coasted pose's drift at each loop, and its rate is the velocity error; given one, the
coasted state takes it as an EKF velocity measurement (its tilt and accelerometer bias follow through the
coasted correlations) and the hand-over, held back for it up to ``max_wait_s`` after the features are back,
seeds the new filter with it.

A non-finite or out-of-order IMU sample still raises ``ValueError`` from :meth:`feed_imu`: a failed sensor is
not recoverable by re-initializing, and the caller stops.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.imu_prediction import LazyCovarianceEstimate, PredictionChain
from viotb.vio.initialization import InitResult
from viotb.vio.lifecycle import track_conditions
from viotb.vio.propagator import Propagator
from viotb.vio.recovery_records import (  # noqa: F401 (RECOVERABLE_ESTIMATORS, cold_start_msckf_params: re-exported)
    RECOVERABLE_ESTIMATORS,
    OdometryReset,
    RecoveryEvent,
    RecoveryParams,
    cold_start_msckf_params,
)
from viotb.vio.state import IMU_BLOCK, VEL, ImuValues, State, ekf_update, marginal_covariance
from viotb.vio.types import CameraFrame, Estimator, HealthStatus, ImuNoise, ImuSample, StateEstimate


def _reset(reason: str, before: StateEstimate, after: StateEstimate) -> OdometryReset:
    return OdometryReset(
        float(after.t_s), reason, before.R_WB.copy(), before.p_WB.copy(), after.R_WB.copy(), after.p_WB.copy()
    )


def _finite(est: StateEstimate | None) -> bool:
    return est is not None and all(np.all(np.isfinite(x)) for x in (est.R_WB, est.p_WB, est.v_WB, est.cov))


class _Coaster:
    """Dead reckoning from a start estimate: propagated to frame times, predicted to the newest IMU sample.

    The prediction past the last frame is the filters' own (:mod:`viotb.vio.imu_prediction`, as in
    :meth:`MSCKF.estimate <viotb.vio.msckf.MSCKF.estimate>`): the mean one IMU interval per new sample, the
    covariance only when an estimate's ``cov`` is read. A new chain starts whenever the coasted state changes
    (propagated to a frame, or corrected by a velocity fix: :meth:`changed`).
    """

    def __init__(self, start: StateEstimate, calib: CameraCalibration, noise: ImuNoise, history) -> None:
        self.propagator = Propagator(noise, use_fej=False)
        for s in history:
            self.propagator.feed_imu(s)
        t0 = max(float(start.t_s), float(history[0].t_s)) if history else float(start.t_s)
        vals = ImuValues(
            np.array(start.R_WB, dtype=float),
            np.array(start.p_WB, dtype=float),
            np.array(start.v_WB, dtype=float),
            np.array(start.gyro_bias_rad_s, dtype=float),
            np.array(start.accel_bias_m_s2, dtype=float),
        )
        cov = 0.5 * (start.cov + start.cov.T)
        self.state = State(t0, vals, cov, calib.R_BC, calib.p_BC, calib.time_offset_s)
        self._last_imu: ImuSample | None = history[-1] if history else None
        self._version = 0
        self._chain: PredictionChain | None = None

    def feed_imu(self, sample: ImuSample) -> None:
        self.propagator.feed_imu(sample)
        self._last_imu = sample

    def propagate_to(self, t_s: float) -> None:
        self.propagator.propagate(self.state, t_s)
        self.changed()

    def changed(self) -> None:
        """The coasted state was changed in place: later predictions start from it."""
        self._version += 1

    def estimate(self) -> StateEstimate:
        st = self.state
        t_new = self._last_imu.t_s if self._last_imu is not None else st.t_s
        chain = self._chain
        if chain is None or chain.version != self._version or chain.t_s > t_new:
            P_imu = marginal_covariance(st, [st.block(IMU_BLOCK)])
            # A copy of the values: a velocity fix changes them in place (``State._boxplus``) with no
            # propagation between, and the chain builds its first transition from them when ``cov`` is read.
            imu = st.imu.copy()
            chain = self._chain = PredictionChain(self._version, st.t_s, imu, P_imu, self.propagator)
        index, vals = chain.advance(t_new)
        omega = np.zeros(3)
        if self._last_imu is not None:
            omega = np.asarray(self._last_imu.gyro_B_rad_s, dtype=float) - vals.gyro_bias_rad_s
        return LazyCovarianceEstimate.from_chain(chain, index, vals, omega)


class RecoveringEstimator:
    """Coasts through a loss of tracking and re-initializes in the air (see the module docstring).

    Args:
        make: Builds a fresh, uninitialized estimator (called now and at each loss of tracking); it must have
            the ``frontend`` and ``initializer`` attributes of the feature-based estimators (``msckf``,
            ``window``).
        calib: Camera calibration the estimator is given (the coaster uses its time offset).
        noise: IMU noise densities (for the coasted covariance).
        params: Settings.
        make_reinit: Builds the estimators of the re-initializations (None: ``make``).

    Attributes:
        events: Every loss of tracking so far, in order.
        odometry_resets: Every jump of the published odometry so far (velocity fixes, hand-overs), in order;
            the list only grows (a consumer may keep it and read what is new).
    """

    def __init__(
        self,
        make: Callable[[], Estimator],
        calib: CameraCalibration,
        noise: ImuNoise,
        params: RecoveryParams | None = None,
        make_reinit: Callable[[], Estimator] | None = None,
    ) -> None:
        """Build the first inner estimator (tracking mode, not yet initialized)."""
        self.params = params if params is not None else RecoveryParams()
        self._make = make if make_reinit is None else make_reinit
        self._calib = calib
        self._noise = noise
        self._inner: Estimator = make()
        if not (hasattr(self._inner, "initializer") and hasattr(self._inner, "frontend")):
            raise ValueError(
                f"RecoveringEstimator: estimator {self._inner.name!r} has no front end and inertial "
                "initializer; only the feature-based estimators (msckf, window) recover"
            )
        self.name = self._inner.name
        self._mode = "tracking"
        self._history: deque[ImuSample] = deque()
        self._coaster: _Coaster | None = None
        self._candidate: Estimator | None = None
        self._health_now: HealthStatus | None = None  # overrides the inner health (coasting, hand-over)
        self._failed = ""
        self._dark_since: float | None = None
        self._back_frames = 0
        self._last_good: StateEstimate | None = None
        self._good_pending = False
        self._fix_wait_s = 0.0  # how long a hand-over waits for a velocity fix (0: none expected)
        self._back_since: float | None = None  # first frame of the current run of frames with features
        self._fixed = False  # the current coast took a velocity fix
        self.events: list[RecoveryEvent] = []
        self.odometry_resets: list[OdometryReset] = []

    # ------------------------------------------------------------------ readers
    @property
    def mode(self) -> str:
        """``"tracking"``, ``"coasting"``, or ``"failed"`` (lost with no good state to coast from)."""
        return self._mode

    @property
    def inner(self) -> Estimator:
        """The estimator in charge while tracking (a new instance after each recovery)."""
        return self._inner

    # ------------------------------------------------------------------ protocol
    def feed_imu(self, sample: ImuSample) -> None:
        """Feed the active estimators (ValueError, from them, on a non-finite or non-increasing sample)."""
        if self._mode == "coasting":
            self._coaster.feed_imu(sample)
            self._candidate.feed_imu(sample)
        else:
            self._inner.feed_imu(sample)
        h = self._history
        h.append(sample)
        while h and float(sample.t_s) - float(h[0].t_s) > self.params.history_s:
            h.popleft()

    def feed_camera(self, frame: CameraFrame) -> None:
        """Process one frame in the current mode (see the module docstring)."""
        t_imu = float(frame.t_s) + self._calib.time_offset_s
        if self._mode == "coasting":
            self._coast_frame(frame, t_imu)
            return
        if self._mode == "failed":
            self._inner.feed_camera(frame)
            return
        self._health_now = None
        try:
            self._inner.feed_camera(frame)
        except (np.linalg.LinAlgError, ArithmeticError) as exc:
            self._lose(t_imu, f"numerical failure of the estimator: {type(exc).__name__}: {exc}", False)
            return
        h = self._inner.health()
        if not h.initialized:
            return
        if h.diverged:
            self._lose(t_imu, f"estimator diverged: {h.reason}", False)
        elif h.tracked_features == 0:
            if self._dark_since is None:
                self._dark_since = t_imu
            elif t_imu - self._dark_since >= self.params.feature_loss_s - 1e-9:
                self._lose(t_imu, f"no feature tracked for {t_imu - self._dark_since:.2f} s", True)
        else:
            self._dark_since = None
            self._good_pending = h.updated_features > 0 or self._last_good is None

    def estimate(self) -> StateEstimate | None:
        """The published state: the inner estimate, or the coasted one."""
        if self._mode == "coasting":
            return self._coaster.estimate()
        est = self._inner.estimate()
        if self._good_pending and self._mode == "tracking" and _finite(est):
            self._last_good, self._good_pending = est, False
        return est

    def health(self) -> HealthStatus:
        """The inner health while tracking; ``coasting`` (not diverged) while coasting; diverged if failed."""
        if self._health_now is not None:
            return self._health_now
        return self._inner.health()

    def initialize(self, init: object) -> None:
        """Start the inner estimator from an external initial state (see the protocol)."""
        self._inner.initialize(init)

    def feed_truth(self, truth: StateEstimate) -> None:
        """Passed to the inner estimator (a no-op for the VIO estimators)."""
        self._inner.feed_truth(truth)

    def wants_excitation(self) -> bool:
        """The inner estimator's request while tracking; False while coasting."""
        return self._mode == "tracking" and self._inner.wants_excitation()

    def last_tracks_px(self) -> np.ndarray:
        """Pixels tracked in the latest frame by the front end in use."""
        if self._mode == "coasting":
            return self._candidate.last_tracks_px()
        return self._inner.last_tracks_px()

    def declare_lost(self, t_s: float, reason: str) -> None:
        """Declare tracking lost from outside (the health monitor's ``divergence``); no-op unless tracking."""
        if self._mode == "tracking" and self._inner.health().initialized:
            self._lose(float(t_s), reason, False)

    def expect_velocity_fixes(self, max_wait_s: float) -> None:
        """A map will offer velocity fixes while coasting: hold a hand-over up to ``max_wait_s`` (s) for one.

        Raises:
            ValueError: ``max_wait_s`` negative or not finite.
        """
        if not (np.isfinite(max_wait_s) and max_wait_s >= 0.0):
            raise ValueError(f"expect_velocity_fixes: max_wait_s must be >= 0 and finite, got {max_wait_s}")
        self._fix_wait_s = float(max_wait_s)

    @property
    def wants_velocity_fix(self) -> bool:
        """Coasting and no velocity fix taken yet in this coast."""
        return self._mode == "coasting" and not self._fixed

    def velocity_fix(self, dv_W_m_s: np.ndarray, cov_W_m2_s2: np.ndarray) -> bool:
        """Correct the coasted velocity by a measured error (see the module docstring); once per coast.

        Args:
            dv_W_m_s: Measured true minus coasted velocity (m/s) in the estimator's world frame, shape (3,).
            cov_W_m2_s2: Its covariance, shape (3, 3).

        Returns:
            Whether it was applied (only while coasting, once).

        Raises:
            ValueError: Wrong shapes or non-finite values.
        """
        dv, cov = np.asarray(dv_W_m_s, dtype=float), np.asarray(cov_W_m2_s2, dtype=float)
        finite = np.all(np.isfinite(dv)) and np.all(np.isfinite(cov))
        if dv.shape != (3,) or cov.shape != (3, 3) or not finite:
            raise ValueError(f"velocity_fix: dv (3,) and cov (3, 3) must be finite, got {dv} and {cov}")
        if not self.wants_velocity_fix:
            return False
        before = self._coaster.estimate()
        st = self._coaster.state
        H = np.zeros((3, st.dim))
        H[:, st.block(IMU_BLOCK).offset + VEL + np.arange(3)] = np.eye(3)
        ekf_update(st, H, dv, cov)
        self._coaster.changed()
        self._fixed = True
        self.odometry_resets.append(_reset("velocity fix", before, self._coaster.estimate()))
        return True

    # ------------------------------------------------------------------ internals
    def _fresh_candidate(self) -> Estimator:
        cand = self._make()
        cand.initializer = None  # started by the hand-over only (see the module docstring)
        for s in self._history:
            cand.feed_imu(s)
        return cand

    def _lose(self, t_s: float, reason: str, current_is_good: bool) -> None:
        """Switch to coasting from the current estimate (feature loss) or the last good one (divergence)."""
        start = None
        if current_is_good:
            start = self._inner.estimate()
        if not _finite(start):
            start = self._last_good
        self._dark_since, self._back_frames, self._good_pending = None, 0, False
        if start is None:
            self._mode, self._failed = "failed", reason
            self._health_now = HealthStatus(t_s=t_s, initialized=True, diverged=True, reason=reason)
            return
        self._coaster = _Coaster(start, self._calib, self._noise, list(self._history))
        self._candidate = self._fresh_candidate()
        self._fixed, self._back_since = False, None
        self._mode = "coasting"
        t0 = self._coaster.state.t_s
        self.events.append(RecoveryEvent(t_lost_s=t_s, reason=reason, t_coast_start_s=t0))
        self._health_now = HealthStatus(
            t_s=t_s - self._calib.time_offset_s, initialized=True, conditions=("coasting", "no_features")
        )

    def _coast_frame(self, frame: CameraFrame, t_imu: float) -> None:
        self._coaster.propagate_to(t_imu)
        try:
            self._candidate.feed_camera(frame)
        except (np.linalg.LinAlgError, ArithmeticError):
            self._candidate = self._fresh_candidate()
            self._back_frames = 0
            return
        h = self._candidate.health()
        n = h.tracked_features
        self._health_now = HealthStatus(
            t_s=frame.t_s,
            initialized=True,
            tracked_features=n,
            conditions=("coasting",) + track_conditions(n),
        )
        self._back_frames = self._back_frames + 1 if n >= self.params.return_min_features else 0
        if self._back_frames == 1:
            self._back_since = t_imu
        waiting = (
            self._fix_wait_s > 0.0
            and not self._fixed
            and self._back_since is not None
            and t_imu - self._back_since < self._fix_wait_s - 1e-9
        )
        if self._back_frames >= self.params.return_frames and not waiting:
            seed = self._seed(t_imu)
            self._candidate.initialize(seed)
            self._hand_over(t_imu, n)

    def _seed(self, t_imu: float) -> InitResult:
        """The coasted state at ``t_imu`` as an initial state (covariance per the module docstring)."""
        p = self.params
        st = self._coaster.state
        var = np.diag(marginal_covariance(st, [st.block(IMU_BLOCK)])) * p.cov_inflation
        floors = np.repeat(
            [
                p.min_sigma_tilt_rad,
                p.sigma_position_m,
                p.min_sigma_velocity_m_s,
                p.min_sigma_gyro_bias_rad_s,
                p.min_sigma_accel_bias_m_s2,
            ],
            3,
        )
        var = np.maximum(var, floors**2)
        var[3:6] = p.sigma_position_m**2
        v = st.imu
        return InitResult(
            t_s=st.t_s,
            R_WB=v.R_WB.copy(),
            p_WB=v.p_WB.copy(),
            v_WB=v.v_WB.copy(),
            gyro_bias_rad_s=v.gyro_bias_rad_s.copy(),
            accel_bias_m_s2=v.accel_bias_m_s2.copy(),
            method="recovery",
            cov_diag=var,
        )

    def _hand_over(self, t_imu: float, n: int) -> None:
        ev = self.events[-1]
        coasted = self._coaster.estimate()
        ev.t_reinit_s, ev.coast_position_sigma_m = t_imu, float(np.max(coasted.position_sigma_W_m))
        self._inner = self._candidate
        est = self._inner.estimate()
        self._last_good = est if _finite(est) else None
        if self._last_good is not None:
            self.odometry_resets.append(_reset("hand-over", coasted, est))
        self._candidate = self._coaster = None
        self._mode = "tracking"
        self._back_frames = 0
        self._health_now = HealthStatus(
            t_s=t_imu - self._calib.time_offset_s,
            initialized=True,
            tracked_features=n,
            conditions=("reinitialized",) + track_conditions(n),
        )
