"""The health monitor's deferred windows (vio/health.py) against the eager monitor they replaced.

The monitor fills its excitation windows only when a test reads them (the IMU window also at each frame;
the world accelerations wait, with their attitude, past frames) and computes the gyro norm and the world
acceleration only when the tests before them hold. ``_EagerMonitor`` below is
the former code, kept as the reference: it flushes every buffered sample into both windows at every
excitation check and computes both statistics there. On random streams that move, stop, rotate, lose
their estimate and jump in time, both must raise the same conditions at the same times with the same
evidence, after every call, and hold the same windows bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.vio.health import HealthMonitor, HealthParams, _SlidingWindow
from viotb.vio.types import GRAVITY_M_S2, HealthStatus, ImuSample, StateEstimate


class _EagerMonitor(HealthMonitor):
    """The monitor as it was: both windows flushed and both statistics computed at every check."""

    def __init__(self, params: HealthParams | None = None) -> None:
        super().__init__(params)
        self._imu = _SlidingWindow(self.params.excitation_window_s, 6)  # [gyro_B, accel_B]

    def observe_imu(self, sample: ImuSample) -> None:
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
            self._flush_imu()
            self._check_excitation(t)
            self._next_check_t = t + p.excitation_check_s
        if not self._initialized and t - self._first_imu_t > p.init_timeout_s:
            self._raise(
                "initialization_failure",
                t,
                f"no estimate after {t - self._first_imu_t:.1f} s of IMU data (timeout {p.init_timeout_s} s)",
            )

    def _flush_imu(self) -> None:
        if not self._pending:
            return
        t = np.array([s[0] for s in self._pending])
        gyro = np.array([s[1] for s in self._pending])
        accel = np.array([s[2] for s in self._pending])
        self._pending = []
        self._imu.extend(t, np.hstack([gyro, accel]))
        if self._attitude is None:
            return
        t_att, R_WB, b_g, b_a = self._attitude
        prev = np.maximum.accumulate(np.concatenate([[t_att], t]))[:-1]
        dt = np.maximum(t - prev, 0.0)
        steps = Rotation.from_rotvec((gyro - b_g) * dt[:, None]).as_matrix()
        R_all = np.empty_like(steps)
        for i in range(len(t)):
            R_WB = R_WB @ steps[i]
            R_all[i] = R_WB
        self._attitude = (max(t_att, float(t[-1])), R_WB, b_g, b_a)
        a_W = np.einsum("nij,nj->ni", R_all, accel - b_a) - np.array([0.0, 0.0, GRAVITY_M_S2])
        self._accel_W.extend(t, a_W)

    def _defer_accel(self) -> None:
        self._flush_imu()  # the former frame: every buffered sample into both windows at once

    def _check_excitation(self, t: float) -> None:
        p = self.params
        window_full = len(self._accel_W) > 0 and t - self._accel_W.t[0] >= 0.99 * p.excitation_window_s
        if not window_full:
            return
        gyro = self._imu.x[:, :3]
        accel_rms = self._world_accel_rms()
        gyro_norm = float(np.mean(np.linalg.norm(gyro, axis=1)))
        low = accel_rms < p.min_accel_m_s2 and gyro_norm < p.min_gyro_norm_rad_s
        moving = self._speed_m_s > p.min_excitation_speed_m_s
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


def _stream(seed: int, seconds: float = 24.0):
    """IMU samples at 200 Hz and a frame after every 10th, as ``("imu", sample)`` / ``("frame", args)``.

    Segments of a few seconds each draw a speed (below and above the 0.2 m/s of the test), a gyro rate
    (below and above 0.2 rad/s), an acceleration noise (below and above 0.1 m/s^2), a tilted attitude and
    biases; frames sometimes carry no estimate or a non-finite one, and the IMU clock sometimes jumps.
    """
    rng = np.random.default_rng(seed)
    calls, t, k = [], 0.0, 0
    seg_end, speed, rate, noise, R_WB = 0.0, 0.0, 0.0, 0.0, np.eye(3)
    while t < seconds:
        if t >= seg_end:
            seg_end = t + rng.uniform(0.5, 5.0)
            speed = float(rng.choice([0.0, 0.1, 0.5, 0.9]))
            rate = float(rng.choice([0.0, 0.05, 0.5]))
            noise = float(rng.choice([0.005, 0.05, 0.5]))
            R_WB = Rotation.from_rotvec(rng.normal(0.0, 0.2, 3)).as_matrix()
            b_g, b_a = rng.normal(0.0, 0.01, 3), rng.normal(0.0, 0.01, 3)
            if rng.random() < 0.15:
                t += rng.uniform(0.05, 2.5)  # a gap in the IMU stream
        gyro = np.array([rate, 0.0, 0.0]) + rng.normal(0.0, 0.01, 3)
        f_B = R_WB.T @ np.array([0.0, 0.0, GRAVITY_M_S2]) + rng.normal(0.0, noise, 3)
        calls.append(("imu", ImuSample(t, gyro, f_B, saturated=bool(rng.random() < 0.002))))
        if k % 10 == 0:
            u = rng.random()
            health = HealthStatus(
                t, True, int(rng.integers(0, 120)), updated_features=int(rng.integers(0, 40))
            )
            est = StateEstimate(
                t, R_WB, np.zeros(3), np.array([speed, 0.0, 0.0]), b_g, b_a, np.zeros(3), np.eye(15) * 1e-4
            )
            if u < 0.05:
                est = None
            elif u < 0.08:
                est = StateEstimate(t, np.full((3, 3), np.nan), np.zeros(3), np.full(3, np.nan))
            calls.append(("frame", (t, health, est)))
        t += 0.005
        k += 1
    return calls


class _Recorded:
    """Records every world-acceleration RMS a monitor computes, keyed by the call it was computed in."""

    def __init__(self, mon: HealthMonitor) -> None:
        self.call = 0
        self.values: dict[int, tuple[float, bytes, bytes]] = {}
        compute = mon._world_accel_rms

        def recorded() -> float:
            value = compute()
            self.values[self.call] = (value, mon._accel_W.t.tobytes(), mon._accel_W.x.tobytes())
            return value

        mon._world_accel_rms = recorded


def _state(mon: HealthMonitor) -> tuple:
    return (
        [(c.name, c.t_s_first, c.evidence) for c in mon.report()],
        sorted(mon.active()),
        mon._excitation_ok,
        mon._unexcited_since,
    )


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize(
    "params", [HealthParams(), HealthParams(min_accel_m_s2=0.3, min_gyro_norm_rad_s=0.6)]
)
def test_deferred_windows_match_the_eager_monitor(seed: int, params: HealthParams) -> None:
    fast, ref = HealthMonitor(params), _EagerMonitor(params)
    raised, unexcited = set(), set()
    rec_fast, rec_ref = _Recorded(fast), _Recorded(ref)
    for call, (kind, arg) in enumerate(_stream(seed)):
        rec_fast.call = rec_ref.call = call
        for mon in (fast, ref):
            if kind == "imu":
                mon.observe_imu(arg)
            else:
                mon.observe_frame(*arg)
        assert _state(fast) == _state(ref)
        raised |= fast.active()
        unexcited.add(fast._unexcited_since is not None)
    # Wherever the deferred monitor computes the world acceleration, it has the eager one's window and value.
    assert len(rec_fast.values) > 10
    for call, value in rec_fast.values.items():
        assert value == rec_ref.values[call]
    fast._flush_imu()
    ref._flush_imu()
    assert np.array_equal(fast._accel_W.t, ref._accel_W.t)
    assert np.array_equal(fast._accel_W.x, ref._accel_W.x)
    assert np.array_equal(fast._imu.t, ref._imu.t)
    assert np.array_equal(fast._imu.x[:, :6], ref._imu.x)
    assert np.array_equal(fast._imu.x[:, 6], np.linalg.norm(ref._imu.x[:, :3], axis=1))
    # The streams reach both outcomes of the test (the deferral skips work in one, not in the other).
    assert unexcited == {True, False}
    assert "imu_saturation" in raised
