"""Online estimator health monitor that names the failure modes of the lesson's debugging catalog.

The monitor runs beside any :class:`~viotb.vio.types.Estimator`: it sees every IMU sample and, after each
camera frame, the estimator's :class:`~viotb.vio.types.HealthStatus` and :class:`StateEstimate`. It raises
named conditions, whose catalog, thresholds and measurements are in :mod:`viotb.vio.health_conditions`.

The replay that feeds it IMU samples and frames in timestamp order is ``viotb.envs.run.replay`` (vio/ does not
run data: it is told it).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.spatial.transform import Rotation
from viotb.vio.health_conditions import CONDITION_NAMES, Condition, HealthParams
from viotb.vio.types import (
    GRAVITY_M_S2,
    CalibrationDrift,
    HealthStatus,
    ImuSample,
    StateEstimate,
)

__all__ = ["CONDITION_NAMES", "Condition", "HealthMonitor", "HealthParams"]


class _SlidingWindow:
    """Rows ``x`` (fixed width) stamped ``t`` over the last ``window_s`` seconds, kept as contiguous arrays.

    The monitor reads its windows at every IMU sample; arrays (rather than deques of tuples rebuilt into
    arrays on each read) keep that read free of Python loops.
    """

    def __init__(self, window_s: float, width: int) -> None:
        self._window_s = float(window_s)
        self._t = np.empty(256)
        self._x = np.empty((256, width))
        self._start = 0
        self._end = 0

    def append(self, t: float, row: np.ndarray) -> None:
        """Add a row and drop the rows older than ``t - window_s`` (those with time ``< t - window_s``)."""
        self.extend(np.array([t], dtype=float), np.asarray(row, dtype=float)[None])

    def extend(self, t: np.ndarray, rows: np.ndarray) -> None:
        """Add rows (times ``t`` increasing, shape (K,); rows (K, width)) and drop the expired ones."""
        k = len(t)
        if k == 0:
            return
        while self._end + k > len(self._t):
            n = self._end - self._start
            if 2 * (n + k) > len(self._t):  # more than half full: grow, else compact in place
                self._t = np.concatenate([self._t, np.empty(len(self._t))])
                self._x = np.concatenate([self._x, np.empty_like(self._x)])
            self._t[:n] = self._t[self._start : self._end]
            self._x[:n] = self._x[self._start : self._end]
            self._start, self._end = 0, n
        self._t[self._end : self._end + k] = t
        self._x[self._end : self._end + k] = rows
        self._end += k
        self._start += int(np.searchsorted(self.t, float(t[-1]) - self._window_s, side="left"))

    def __len__(self) -> int:
        return self._end - self._start

    @property
    def t(self) -> np.ndarray:
        """Times (s), shape (N,), increasing."""
        return self._t[self._start : self._end]

    @property
    def x(self) -> np.ndarray:
        """Rows, shape (N, width)."""
        return self._x[self._start : self._end]


class HealthMonitor:
    """Watches an estimator stream and names the lesson's failure modes (see the module docstring).

    Args:
        params: Thresholds.
    """

    def __init__(self, params: HealthParams | None = None) -> None:
        """Create an empty monitor."""
        self.params = params if params is not None else HealthParams()
        self._conditions: dict[str, Condition] = {}
        self._active: set[str] = set()
        self._imu = _SlidingWindow(self.params.excitation_window_s, 7)  # [gyro_B, accel_B, |gyro_B|]
        self._accel_W = _SlidingWindow(self.params.excitation_window_s, 3)
        self._attitude: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None  # t, R_WB, b_g, b_a
        self._first_imu_t: float | None = None
        self._last_imu_t: float | None = None
        self._n_saturated = 0
        self._first_saturated_t: float | None = None
        self._unexcited_since: float | None = None
        self._excitation_ok = True
        self._speed_m_s = 0.0
        self._poor_frames = 0
        self._sync: deque[tuple[float, float, float]] = deque(maxlen=self.params.speed_window_frames)
        self._initialized = False
        self._init_checked = False
        self._last_used_t: float | None = None
        # IMU samples not yet in the world-acceleration window; the first ``_n_in_imu`` of them are already in
        # the IMU window (:meth:`_flush_imu_window`).
        self._pending: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._n_in_imu = 0
        # Samples of earlier frames with the attitude they are rotated by, whose world accelerations wait
        # for the test that reads them (:meth:`_defer_accel`), oldest first.
        self._deferred: list[tuple[tuple[float, np.ndarray, np.ndarray, np.ndarray], list]] = []
        self._next_check_t: float | None = None

    # ------------------------------------------------------------------ inputs
    def observe_imu(self, sample: ImuSample) -> None:
        """Feed one IMU sample (saturation count now; the excitation test every ``excitation_check_s``).

        Samples are buffered and enter the excitation windows in batches (vectorized) when a test reads them
        and before each frame, so the result is the per-sample one at a fraction of the cost.
        """
        p = self.params
        t = float(sample.t_s)
        gyro = np.asarray(sample.gyro_B_rad_s, dtype=float)
        if self._first_imu_t is None:
            self._first_imu_t = t
        self._last_imu_t = t
        self._pending.append((t, gyro, np.asarray(sample.accel_B_m_s2, dtype=float)))
        if sample.saturated:
            self._n_saturated += 1
            if self._first_saturated_t is None:
                self._first_saturated_t = t
            if self._n_saturated >= p.min_saturated_samples:
                self._raise(
                    "imu_saturation",
                    self._first_saturated_t,
                    f"{self._n_saturated} saturated samples, first at t={self._first_saturated_t:.3f} s "
                    f"(gyro {np.array2string(gyro, precision=2)} rad/s)",
                )
        if self._next_check_t is None or t >= self._next_check_t:
            self._check_excitation(t)
            self._next_check_t = t + p.excitation_check_s
        if not self._initialized and t - self._first_imu_t > p.init_timeout_s:
            self._raise(
                "initialization_failure",
                t,
                f"no estimate after {t - self._first_imu_t:.1f} s of IMU data (timeout {p.init_timeout_s} s)",
            )

    def observe_frame(self, t_s: float, health: HealthStatus, estimate: StateEstimate | None) -> None:
        """Feed the estimator's status and estimate after one camera frame (``t_s`` on the IMU clock)."""
        p = self.params
        valid = estimate is not None and all(np.all(np.isfinite(x)) for x in (estimate.v_WB, estimate.R_WB))
        if valid:
            self._defer_accel()  # this estimate replaces the attitude the buffered samples are rotated by
        else:
            self._flush_imu()
        self._active = {n for n in self._active if n in ("insufficient_excitation", "imu_saturation")}
        if not self._excitation_ok:
            self._active.add("insufficient_excitation")
        # Feature poverty.
        if health.initialized and health.tracked_features < p.min_tracked_features:
            self._poor_frames += 1
        else:
            self._poor_frames = 0
        if self._poor_frames >= p.poverty_frames:
            self._raise(
                "feature_poverty",
                t_s,
                f"{health.tracked_features} tracked features (< {p.min_tracked_features}) for "
                f"{self._poor_frames} frames",
            )
        if valid:
            self._speed_m_s = float(np.linalg.norm(estimate.v_WB))
            self._attitude = (
                float(estimate.t_s),
                np.array(estimate.R_WB, dtype=float),
                np.array(estimate.gyro_bias_rad_s, dtype=float),
                np.array(estimate.accel_bias_m_s2, dtype=float),
            )
        # Initialization.
        if estimate is not None and not self._init_checked:
            self._init_checked = True
            self._initialized = True
            self._check_init(t_s, estimate)
        # Divergence.
        self._check_divergence(t_s, health, estimate)
        # Time offset / extrinsic.
        if estimate is not None:
            self._check_sync(t_s, health, estimate)
        if health.calibration is not None:
            self._check_calibration(t_s, health.calibration)

    # ------------------------------------------------------------------ outputs
    def report(self) -> list[Condition]:
        """All conditions raised so far, in order of first appearance."""
        return sorted(self._conditions.values(), key=lambda c: c.t_s_first)

    def active(self) -> set[str]:
        """Names of the conditions raised at the latest frame (or IMU sample, for IMU-only conditions)."""
        return set(self._active)

    def first_time(self, name: str) -> float | None:
        """Time (s) ``name`` was first raised, or None."""
        c = self._conditions.get(name)
        return None if c is None else c.t_s_first

    # ------------------------------------------------------------------ checks
    def _raise(self, name: str, t_s: float, evidence: str) -> None:
        self._active.add(name)
        if name not in self._conditions:
            self._conditions[name] = Condition(name, float(t_s), evidence)

    def _flush_imu_window(self) -> None:
        """Move the buffered IMU samples into the IMU window ``[gyro_B, accel_B, |gyro_B|]``.

        They stay buffered for the world-acceleration window, which :meth:`_flush_imu` fills.
        """
        new = self._pending[self._n_in_imu :]
        if not new:
            return
        self._n_in_imu = len(self._pending)
        gyro = np.array([s[1] for s in new])
        rows = np.hstack([gyro, np.array([s[2] for s in new]), np.linalg.norm(gyro, axis=1)[:, None]])
        self._imu.extend(np.array([s[0] for s in new]), rows)

    def _defer_accel(self) -> None:
        """At a frame whose estimate replaces the attitude: defer the world accelerations of the buffer.

        The buffered samples enter the IMU window now and wait, with the attitude they are rotated by, for
        the world-acceleration window (:meth:`_flush_imu`). Segments that lie wholly before the window are
        dropped (the window would drop their rows).
        """
        self._flush_imu_window()
        pending, self._pending, self._n_in_imu = self._pending, [], 0
        if self._attitude is None or not pending:
            return
        self._deferred.append((self._attitude, pending))
        lo = pending[-1][0] - self.params.excitation_window_s
        while self._deferred[0][1][-1][0] < lo:
            self._deferred.pop(0)

    def _flush_imu(self) -> None:
        """Move the buffered IMU samples into both windows, with their world accelerations.

        The deferred segments first (each with its own attitude), then the samples since the latest frame.
        """
        for attitude, samples in self._deferred:
            self._accel_from(attitude, samples)
        self._deferred = []
        pending = self._pending
        if not pending:
            return
        self._flush_imu_window()
        self._pending, self._n_in_imu = [], 0
        if self._attitude is not None:
            self._attitude = self._accel_from(self._attitude, pending)

    def _accel_from(
        self, attitude: tuple[float, np.ndarray, np.ndarray, np.ndarray], samples: list
    ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Add the samples' world accelerations to the window; return the attitude propagated through them.

        The attitude is propagated from the latest estimate with each sample's gyro over the interval ending
        at it (``R <- R Exp((gyro - b_g) dt)``), as one sample at a time would. A batch never spans two
        estimates (a frame that replaces the estimate closes it), so the batched values are the per-sample
        ones.

        Args:
            attitude: ``(t_s, R_WB (3, 3), b_g (3,), b_a (3,))`` the samples start from.
            samples: ``(t_s, gyro_B (3,), accel_B (3,))`` in time order.
        """
        t = np.array([s[0] for s in samples])
        gyro = np.array([s[1] for s in samples])
        accel = np.array([s[2] for s in samples])
        t_att, R_WB, b_g, b_a = attitude
        prev = np.maximum.accumulate(np.concatenate([[t_att], t]))[:-1]
        dt = np.maximum(t - prev, 0.0)
        steps = Rotation.from_rotvec((gyro - b_g) * dt[:, None]).as_matrix()
        R_all = np.empty_like(steps)
        for i in range(len(t)):
            R_WB = R_WB @ steps[i]
            R_all[i] = R_WB
        a_W = np.einsum("nij,nj->ni", R_all, accel - b_a) - np.array([0.0, 0.0, GRAVITY_M_S2])
        self._accel_W.extend(t, a_W)
        return (max(t_att, float(t[-1])), R_WB, b_g, b_a)

    def _accel_window_full(self, t: float) -> bool:
        """Whether the world-acceleration window, flushed now (newest sample ``t``), spans the test's window.

        The flush drops the rows older than ``t - excitation_window_s``; its first row is the first kept row
        of the window, else the first kept deferred or buffered sample (buffered samples enter only once
        there is an attitude). So the test is decided without the flush.
        """
        p = self.params
        lo = t - p.excitation_window_s
        times = self._accel_W.t
        i = int(np.searchsorted(times, lo, side="left"))
        if i < len(times):
            first = float(times[i])
        else:  # the deferred segments' samples, then the buffered ones (they enter with an attitude)
            # A segment's last sample is its newest: look into the first segment that reaches ``lo``.
            segments = [samples for _, samples in self._deferred]
            if self._attitude is not None and self._pending:
                segments.append(self._pending)
            seg = next((samples for samples in segments if samples[-1][0] >= lo), None)
            first = None if seg is None else next(s[0] for s in seg if s[0] >= lo)
            if first is None:
                return False
        return t - first >= 0.99 * p.excitation_window_s

    def _world_accel_rms(self) -> float:
        """RMS over the window of the norms of the block-mean world accelerations (m/s^2)."""
        t, a = self._accel_W.t, self._accel_W.x
        block = np.floor((t - t[0]) / self.params.excitation_block_s).astype(int)
        starts = np.concatenate([[0], np.flatnonzero(np.diff(block)) + 1])  # blocks are contiguous runs
        counts = np.diff(np.append(starts, len(t)))
        means = np.add.reduceat(a, starts, axis=0) / counts[:, None]
        return float(np.sqrt(np.mean(np.sum(means**2, axis=1))))

    def _check_excitation(self, t: float) -> None:
        """The excitation test at ``t`` (the newest sample).

        The flag needs the platform moving, a low gyro norm and a low world acceleration: each is computed
        only when the ones before it hold (the buffered samples enter the windows then), which decides the
        same as computing all three.
        """
        p = self.params
        if not self._accel_window_full(t):
            return
        low = moving = self._speed_m_s > p.min_excitation_speed_m_s
        if moving:
            self._flush_imu_window()
            gyro_norm = float(np.mean(self._imu.x[:, 6]))
            low = gyro_norm < p.min_gyro_norm_rad_s
        if low:
            self._flush_imu()
            accel_rms = self._world_accel_rms()
            low = accel_rms < p.min_accel_m_s2
        if not (low and moving):
            self._unexcited_since = None
            self._excitation_ok = True
            self._active.discard("insufficient_excitation")
            return
        if self._unexcited_since is None:
            self._unexcited_since = t
        if t - self._unexcited_since >= p.excitation_hold_s:
            self._excitation_ok = False
            self._raise(
                "insufficient_excitation",
                t,
                f"world acceleration RMS {accel_rms:.3f} m/s^2 (< {p.min_accel_m_s2}) and gyro norm "
                f"{gyro_norm:.3f} rad/s (< {p.min_gyro_norm_rad_s}) over {p.excitation_window_s} s at "
                f"{self._speed_m_s:.2f} m/s: scale unobservable, a scale error grows the position error "
                "with distance",
            )

    def _check_init(self, t_s: float, est: StateEstimate) -> None:
        p = self.params
        if len(self._imu):
            accel = self._imu.x[:, 3:6]
            g_norm = float(np.mean(np.linalg.norm(accel, axis=1)))
            # Only meaningful when the window was still (std small): then |a| should read 9.81.
            still = float(np.max(np.std(accel, axis=0))) < 0.5
            if still and abs(g_norm - GRAVITY_M_S2) > p.gravity_norm_tol_m_s2:
                self._raise(
                    "initialization_failure",
                    t_s,
                    f"gravity norm at init {g_norm:.3f} m/s^2 differs from {GRAVITY_M_S2} by more than "
                    f"{p.gravity_norm_tol_m_s2}",
                )
        bg = float(np.linalg.norm(est.gyro_bias_rad_s))
        if bg > p.max_init_gyro_bias_rad_s:
            self._raise(
                "initialization_failure",
                t_s,
                f"initial gyro bias {bg:.3f} rad/s beyond {p.max_init_gyro_bias_rad_s} rad/s",
            )

    def _check_divergence(self, t_s: float, health: HealthStatus, est: StateEstimate | None) -> None:
        p = self.params
        if health.diverged:
            self._raise("divergence", t_s, f"estimator reports divergence: {health.reason}")
            return
        if est is None:
            return
        finite = all(np.all(np.isfinite(x)) for x in (est.R_WB, est.p_WB, est.v_WB, est.cov))
        if not finite:
            self._raise("divergence", t_s, "non-finite value in the estimate or covariance")
            return
        sigma = float(np.sqrt(max(np.max(np.diag(est.cov_position_W_m2)), 0.0)))
        if sigma > p.max_position_sigma_m:
            self._raise("divergence", t_s, f"position sigma {sigma:.2f} m beyond {p.max_position_sigma_m} m")
        moving = self._speed_m_s > p.min_sync_speed_m_s
        if self._last_used_t is None or health.updated_features > 0 or not moving:
            self._last_used_t = t_s
        elif health.tracked_features >= p.min_tracked_features and t_s - self._last_used_t > p.max_unused_s:
            self._raise(
                "divergence",
                t_s,
                f"{health.tracked_features} features tracked but none used in an update for "
                f"{t_s - self._last_used_t:.1f} s at {self._speed_m_s:.2f} m/s: the images do not fit the "
                "state",
            )

    def _check_sync(self, t_s: float, health: HealthStatus, est: StateEstimate) -> None:
        p = self.params
        gated = health.updated_features + health.chi2_rejections
        nis = float(getattr(health, "nis_per_dof_all", float("nan")))
        if gated < p.sync_min_features or not np.isfinite(nis):
            return
        w = float(np.linalg.norm(est.omega_B_rad_s))
        v = float(np.linalg.norm(est.v_WB))
        self._sync.append((nis, w, v))
        if len(self._sync) < p.speed_window_frames:
            return
        arr = np.array(self._sync)
        mean_nis = float(np.mean(arr[:, 0])) / p.nis_per_dof_expected
        mean_w, mean_v = float(np.mean(arr[:, 1])), float(np.mean(arr[:, 2]))
        moving = mean_v > p.min_sync_speed_m_s or mean_w > p.min_sync_rate_rad_s
        if mean_nis <= p.max_nis_per_dof or not moving:
            return
        self._raise(
            "time_sync_or_extrinsic_suspected",
            t_s,
            f"mean NIS per dof {mean_nis:.2f} (> {p.max_nis_per_dof}; relative to the expected "
            f"{p.nis_per_dof_expected:.3g}) over {len(arr)} updates while moving "
            f"(mean {mean_v:.2f} m/s, {mean_w:.2f} rad/s); correlation with angular speed "
            f"{_pearson(arr[:, 0], arr[:, 1]):.2f}, with linear speed {_pearson(arr[:, 0], arr[:, 2]):.2f}; "
            "to tell which, calibrate both online (MsckfParams.estimate_time_offset and "
            "estimate_extrinsics): the one that moves is named time_offset_miscalibrated or "
            "extrinsic_miscalibrated",
        )

    def _check_calibration(self, t_s: float, c: CalibrationDrift) -> None:
        p = self.params
        k = p.calib_min_sigmas
        dt, sig_t = c.time_offset_s, c.time_offset_sigma_s
        if np.isfinite(dt) and abs(dt) > max(p.min_time_offset_change_s, k * sig_t):
            self._raise(
                "time_offset_miscalibrated",
                t_s,
                f"online calibration moved the camera-IMU time offset by {dt * 1e3:+.2f} ms (sigma "
                f"{sig_t * 1e3:.2f} ms, limits {p.min_time_offset_change_s * 1e3:.1f} ms and {k:g} sigma)",
            )
        for what, d, sig, lim, unit, scale in (
            (
                "rotation",
                c.rotation_BC_rad,
                c.rotation_sigma_rad,
                p.min_rotation_change_rad,
                "deg",
                np.rad2deg(1.0),
            ),
            (
                "translation",
                c.translation_BC_m,
                c.translation_sigma_m,
                p.min_translation_change_m,
                "cm",
                100.0,
            ),
        ):
            d, sig = np.asarray(d, dtype=float), np.asarray(sig, dtype=float)
            if not np.all(np.isfinite(d)):
                continue
            z = float(np.max(np.abs(d) / np.maximum(sig, 1e-12)))
            if float(np.linalg.norm(d)) > lim and z > k:
                self._raise(
                    "extrinsic_miscalibrated",
                    t_s,
                    f"online calibration moved the camera-IMU {what} by "
                    f"{np.array2string(d * scale, precision=2)} {unit} (largest {z:.1f} sigma, limits "
                    f"{lim * scale:.2f} {unit} and {k:g} sigma)",
                )


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation (0 when either input is constant)."""
    sa, sb = float(np.std(a)), float(np.std(b))
    if sa < 1e-12 or sb < 1e-12:
        return 0.0
    return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))
