"""Synthetic IMU: turn-on bias, bias random walk, white noise, scale/misalignment, quantization, saturation.

Measurement model per sample k (Kalibr convention, cf. Furgale et al. "Kalibr" IMU noise model wiki;
Woodman, "An introduction to inertial navigation", 2007, sec. 4-5)::

    y_k   = clip(quantize(M (x_k) + b_k + n_k))        M = I + diag(s) + A_offdiag
    n_k   ~ N(0, (sigma_c / sqrt(dt))^2 I)             white noise, sigma_c the noise density
    b_k+1 = b_k + w_k,  w_k ~ N(0, (sigma_b sqrt(dt))^2 I)   bias random walk, sigma_b its density

``x_k`` is the true angular rate ``omega_B`` (rad/s) or specific force ``R_WB^T (a_W - g_W)`` (m/s^2) in B.
The first sample uses the turn-on bias ``b_0``; the bias advances after each sample. ``dt = 1 / rate_hz``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from viotb.envs.sim.checks import all_finite
from viotb.vio.types import ImuNoise, ImuSample, ImuSeries

_DEG = math.pi / 180.0
_G = 9.80665  # standard gravity for datasheet "g" ranges (m/s^2)
_CHUNK_SAMPLES = 65536  # samples generated per vectorized block (bounds memory on long logs)
_BLOCK_SAMPLES = 256
"""Samples' normals drawn at once for :meth:`ImuModel.measure` (one generator call per 256 samples)."""


@dataclass(frozen=True)
class ImuModelParams:
    """Parameters of :class:`ImuModel` (units in each field's name).

    Attributes:
        rate_hz: Sample rate (Hz); ``dt = 1 / rate_hz`` sets the discrete noise sigmas.
        noise: Continuous-time white-noise and random-walk densities (Kalibr convention).
        gyro_turn_on_bias_sigma_rad_s: Per-axis sigma of the gyro bias drawn at power-on (rad/s).
        accel_turn_on_bias_sigma_m_s2: Per-axis sigma of the accelerometer bias drawn at power-on (m/s^2).
        gyro_scale_sigma: Per-axis sigma of the gyro scale-factor error (fraction, 1e-3 = 1000 ppm).
        accel_scale_sigma: Per-axis sigma of the accelerometer scale-factor error (fraction).
        misalignment_sigma_rad: Sigma of each off-diagonal axis-misalignment term (rad), both sensors.
        gyro_quantization_rad_s: Gyro output step (rad/s); 0 disables quantization.
        accel_quantization_m_s2: Accelerometer output step (m/s^2); 0 disables quantization.
        gyro_range_rad_s: Gyro full-scale range (rad/s); readings are clipped to +-range.
        accel_range_m_s2: Accelerometer full-scale range (m/s^2); readings are clipped to +-range.
    """

    rate_hz: float = 200.0
    noise: ImuNoise = field(default_factory=ImuNoise)
    gyro_turn_on_bias_sigma_rad_s: float = 0.0
    accel_turn_on_bias_sigma_m_s2: float = 0.0
    gyro_scale_sigma: float = 0.0
    accel_scale_sigma: float = 0.0
    misalignment_sigma_rad: float = 0.0
    gyro_quantization_rad_s: float = 0.0
    accel_quantization_m_s2: float = 0.0
    gyro_range_rad_s: float = math.inf
    accel_range_m_s2: float = math.inf

    def __post_init__(self) -> None:
        """Validate ranges and signs."""
        if not (self.rate_hz > 0.0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"ImuModelParams.rate_hz must be positive and finite, got {self.rate_hz}")
        for name in (
            "gyro_turn_on_bias_sigma_rad_s",
            "accel_turn_on_bias_sigma_m_s2",
            "gyro_scale_sigma",
            "accel_scale_sigma",
            "misalignment_sigma_rad",
            "gyro_quantization_rad_s",
            "accel_quantization_m_s2",
        ):
            value = getattr(self, name)
            if not (value >= 0.0 and math.isfinite(value)):
                raise ValueError(f"ImuModelParams.{name} must be finite and >= 0, got {value}")
        for name in ("gyro_range_rad_s", "accel_range_m_s2"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"ImuModelParams.{name} must be > 0, got {getattr(self, name)}")

    @property
    def dt_s(self) -> float:
        """Nominal sample period (s)."""
        return 1.0 / self.rate_hz


# Bosch BMI088-like consumer MEMS part (drones, headsets): datasheet densities (gyro 0.014 deg/s/sqrtHz,
# accel 175 ug/sqrtHz at the +-24 g range) inflated for vibration, larger turn-on biases and scale errors.
_BMI088 = ImuModelParams(
    rate_hz=200.0,
    noise=ImuNoise(
        gyro_noise_density_rad_s_sqrthz=0.014 * _DEG * 2.0,
        gyro_random_walk_rad_s2_sqrthz=1.0e-4,
        accel_noise_density_m_s2_sqrthz=175e-6 * _G * 2.0,
        accel_random_walk_m_s3_sqrthz=1.0e-2,
    ),
    gyro_turn_on_bias_sigma_rad_s=1.0 * _DEG,
    accel_turn_on_bias_sigma_m_s2=0.2,
    gyro_scale_sigma=1e-2,
    accel_scale_sigma=5e-3,
    misalignment_sigma_rad=0.5 * _DEG,
    gyro_quantization_rad_s=2000.0 * _DEG / 32768.0,
    accel_quantization_m_s2=24.0 * _G / 32768.0,
    gyro_range_rad_s=2000.0 * _DEG,
    accel_range_m_s2=24.0 * _G,
)


# TDK ICM-42688-P-class consumer MEMS part as headsets carry it, sampled at 1 kHz: gyro
# 1.0e-4 rad/s/sqrtHz (~0.0057 deg/s/sqrtHz, the datasheet's 0.0028 inflated for vibration), accel
# 1.4e-3 m/s^2/sqrtHz (~140 ug), random walks 2e-5 rad/s^2/sqrtHz and 1e-3 m/s^3/sqrtHz, +-2000 deg/s
# and +-16 g (16-bit), turn-on bias sigmas 0.5 deg/s and 0.2 m/s^2.
_ICM42688 = ImuModelParams(
    rate_hz=1000.0,
    noise=ImuNoise(1.0e-4, 2.0e-5, 1.4e-3, 1.0e-3),
    gyro_turn_on_bias_sigma_rad_s=0.5 * _DEG,
    accel_turn_on_bias_sigma_m_s2=0.2,
    gyro_scale_sigma=2e-3,
    accel_scale_sigma=2e-3,
    misalignment_sigma_rad=0.1 * _DEG,
    gyro_quantization_rad_s=2000.0 * _DEG / 32768.0,
    accel_quantization_m_s2=16.0 * _G / 32768.0,
    gyro_range_rad_s=2000.0 * _DEG,
    accel_range_m_s2=16.0 * _G,
)


# Analog Devices ADIS16448 (EuRoC's VI-sensor IMU). Densities from EuRoC imu0/sensor.yaml; ranges,
# LSB sizes and misalignment from the ADIS16448 datasheet (rev. D); turn-on biases sized like the
# EuRoC V1_01 ground-truth biases (~0.02 rad/s, ~0.05 m/s^2).
_ADIS16448 = ImuModelParams(
    rate_hz=200.0,
    noise=ImuNoise(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3),
    gyro_turn_on_bias_sigma_rad_s=0.02,
    accel_turn_on_bias_sigma_m_s2=0.05,
    gyro_scale_sigma=2e-3,
    accel_scale_sigma=2e-3,
    misalignment_sigma_rad=0.05 * _DEG,
    gyro_quantization_rad_s=0.04 * _DEG,
    accel_quantization_m_s2=0.833e-3 * _G,
    gyro_range_rad_s=1000.0 * _DEG,
    accel_range_m_s2=18.0 * _G,
)


_PRESETS: dict[str, ImuModelParams] = {
    "adis16448": _ADIS16448,
    # The same densities and bias random walk with nothing else: no turn-on bias, scale, misalignment or
    # quantization. What an estimator told only the noise densities models exactly, so a recording with it
    # separates an estimator's own inconsistency from a sensor-model mismatch (benchmarks/nees_clean_data.py).
    "adis16448-white": replace(
        _ADIS16448,
        gyro_turn_on_bias_sigma_rad_s=0.0,
        accel_turn_on_bias_sigma_m_s2=0.0,
        gyro_scale_sigma=0.0,
        accel_scale_sigma=0.0,
        misalignment_sigma_rad=0.0,
        gyro_quantization_rad_s=0.0,
        accel_quantization_m_s2=0.0,
    ),
    "bmi088": _BMI088,
    # The same BMI088 configured at its most sensitive ranges (+-125 deg/s, +-3 g): finer steps, but an
    # aggressive manoeuvre saturates it (the lesson's "sudden jump" failure mode).
    "bmi088-125dps": replace(
        _BMI088,
        gyro_quantization_rad_s=125.0 * _DEG / 32768.0,
        accel_quantization_m_s2=3.0 * _G / 32768.0,
        gyro_range_rad_s=125.0 * _DEG,
        accel_range_m_s2=3.0 * _G,
    ),
    "icm42688-1khz": _ICM42688,
    # The same part after a factory calibration of its intrinsics, as headsets ship: the residual
    # scale-factor and misalignment errors a rate-table / six-position calibration leaves, 10x below the raw
    # part's. Unless the MSCKF estimates the intrinsics (MsckfParams.imu_intrinsics), these are unmodeled.
    "icm42688-1khz-calibrated": replace(
        _ICM42688, gyro_scale_sigma=2e-4, accel_scale_sigma=2e-4, misalignment_sigma_rad=0.01 * _DEG
    ),
    # Perfect sensor: no noise, no bias, no scale errors, no quantization, infinite range.
    "ideal": ImuModelParams(rate_hz=200.0, noise=ImuNoise(0.0, 0.0, 0.0, 0.0)),
}


def imu_preset_names() -> tuple[str, ...]:
    """Names accepted by :func:`imu_preset`."""
    return tuple(sorted(_PRESETS))


def imu_preset(name: str) -> ImuModelParams:
    """Parameters of a named IMU part (``adis16448``, ``bmi088``, ``ideal``).

    Raises:
        ValueError: Unknown name; the message lists the presets.
    """
    try:
        return _PRESETS[name]
    except KeyError:
        known = ", ".join(imu_preset_names())
        raise ValueError(f"unknown IMU preset {name!r}; known presets: {known}") from None


def _sensor_matrix(rng: np.random.Generator, scale_sigma: float, misalignment_sigma_rad: float) -> np.ndarray:
    """``I + diag(scale) + off-diagonal misalignment``, shape (3, 3)."""
    scale = rng.standard_normal(3) * scale_sigma
    off = rng.standard_normal(6) * misalignment_sigma_rad
    M = np.eye(3) + np.diag(scale)
    M[~np.eye(3, dtype=bool)] = off
    return M


class ImuModel:
    """Sequential IMU sensor model; all randomness comes from the injected generator.

    The constructor draws the turn-on biases, scale factors and misalignments. Each measurement then
    draws 12 normals in the order [gyro white, accel white, gyro walk, accel walk], so
    :meth:`measure` called N times and :meth:`measure_series` on N samples give identical output. Single
    samples take their normals from blocks of 256 samples drawn ahead, so the generator runs ahead of the
    samples read: give the model a generator of its own.

    Args:
        params: Sensor parameters.
        rng: Random generator (seeded by the caller).
    """

    def __init__(self, params: ImuModelParams, rng: np.random.Generator) -> None:
        """Draw the per-unit errors (turn-on bias, scale, misalignment)."""
        self._params = params
        self._rng = rng
        self._gyro_bias_rad_s = rng.standard_normal(3) * params.gyro_turn_on_bias_sigma_rad_s
        self._accel_bias_m_s2 = rng.standard_normal(3) * params.accel_turn_on_bias_sigma_m_s2
        self._M_gyro = _sensor_matrix(rng, params.gyro_scale_sigma, params.misalignment_sigma_rad)
        self._M_accel = _sensor_matrix(rng, params.accel_scale_sigma, params.misalignment_sigma_rad)
        dt = params.dt_s
        n = params.noise
        # Discrete sigmas (Kalibr): white = density / sqrt(dt); walk per step = density * sqrt(dt).
        self._sigmas = np.array(
            [
                n.gyro_noise_density_rad_s_sqrthz / math.sqrt(dt),
                n.accel_noise_density_m_s2_sqrthz / math.sqrt(dt),
                n.gyro_random_walk_rad_s2_sqrthz * math.sqrt(dt),
                n.accel_random_walk_m_s3_sqrthz * math.sqrt(dt),
            ]
        )
        self._block = np.zeros((0, 4, 3))  # scaled draws made ahead for single samples (_scaled_draws)
        self._block_next = 0

    def _scaled_draws(self, n: int) -> np.ndarray:
        """The next ``n`` samples' normals times their sigmas, shape (n, 4, 3), in the generator's order.

        A single sample (:meth:`measure`, every IMU period of the closed loop) is served from a block of
        :data:`_BLOCK_SAMPLES` drawn at once; a series takes what is left of the block, then draws the rest.
        The normals and their order are those of one ``standard_normal((n, 4, 3))`` call per sample
        (numpy's ``Generator`` keeps no state between calls), so the output does not depend on the split.
        """
        left = self._block.shape[0] - self._block_next
        if n == 1:
            if left == 0:
                self._block = self._rng.standard_normal((_BLOCK_SAMPLES, 4, 3)) * self._sigmas[None, :, None]
                self._block_next = 0
            self._block_next += 1
            return self._block[self._block_next - 1 : self._block_next]
        take = min(left, n)
        head = self._block[self._block_next : self._block_next + take]
        self._block_next += take
        if take == n:
            return head
        rest = self._rng.standard_normal((n - take, 4, 3)) * self._sigmas[None, :, None]
        return np.concatenate([head, rest]) if take else rest

    @property
    def params(self) -> ImuModelParams:
        """The sensor parameters."""
        return self._params

    @property
    def gyro_bias_rad_s(self) -> np.ndarray:
        """True gyro bias (rad/s) that the NEXT sample will carry, shape (3,) (a copy)."""
        return self._gyro_bias_rad_s.copy()

    @property
    def accel_bias_m_s2(self) -> np.ndarray:
        """True accelerometer bias (m/s^2) that the NEXT sample will carry, shape (3,) (a copy)."""
        return self._accel_bias_m_s2.copy()

    @property
    def gyro_matrix(self) -> np.ndarray:
        """Gyro scale/misalignment matrix ``I + S + A``, shape (3, 3) (a copy)."""
        return self._M_gyro.copy()

    @property
    def accel_matrix(self) -> np.ndarray:
        """Accelerometer scale/misalignment matrix ``I + S + A``, shape (3, 3) (a copy)."""
        return self._M_accel.copy()

    def measure(self, t_s: float, omega_B_true: np.ndarray, specific_force_B_true: np.ndarray) -> ImuSample:
        """One reading from the true angular rate (rad/s) and specific force (m/s^2) in B, shape (3,) each.

        A single-sample fast path of :meth:`measure_series_with_biases` (the closed loop calls it every IMU
        period): the same draws in the same order and the same floating-point operations, so the output is
        bit-identical to ``measure_series`` on the same samples (tested).

        Raises:
            ValueError: A vector that is not shape (3,) or not finite.
        """
        omega = np.asarray(omega_B_true, dtype=float)
        f = np.asarray(specific_force_B_true, dtype=float)
        if omega.shape != (3,) or f.shape != (3,):
            raise ValueError(
                "measure expects omega_B_true (3,) and specific_force_B_true (3,); "
                f"got {omega.shape}, {f.shape}"
            )
        if not all_finite(omega.tolist() + f.tolist()):
            raise ValueError("measure: omega_B_true and specific_force_B_true must be finite")
        n_g, n_a, w_g, w_a = self._scaled_draws(1)[0].tolist()
        bias_g, bias_a = self._gyro_bias_rad_s.tolist(), self._accel_bias_m_s2.tolist()
        # Same expression shapes as the series ((1, 3) @ (3, 3)) so BLAS sums in the same order; the
        # elementwise rest in plain floats, the same operations in the same order as the series' arrays.
        m_g = (omega[None] @ self._M_gyro.T)[0].tolist()
        m_a = (f[None] @ self._M_accel.T)[0].tolist()
        p = self._params
        q_g, q_a = p.gyro_quantization_rad_s, p.accel_quantization_m_s2
        gyro = [_quantize_f(x + b + n, q_g) for x, b, n in zip(m_g, bias_g, n_g, strict=True)]
        accel = [_quantize_f(x + b + n, q_a) for x, b, n in zip(m_a, bias_a, n_a, strict=True)]
        self._gyro_bias_rad_s = np.array([b + w for b, w in zip(bias_g, w_g, strict=True)])
        self._accel_bias_m_s2 = np.array([b + w for b, w in zip(bias_a, w_a, strict=True)])
        # The saturation test on plain floats; within range the clip is the identity and is skipped.
        r_g, r_a = p.gyro_range_rad_s, p.accel_range_m_s2
        saturated = any(abs(x) > r_g for x in gyro) or any(abs(x) > r_a for x in accel)
        if saturated:
            return ImuSample(
                float(t_s), np.clip(np.array(gyro), -r_g, r_g), np.clip(np.array(accel), -r_a, r_a), True
            )
        return ImuSample(float(t_s), np.array(gyro), np.array(accel), False)

    def measure_series(self, t_s: np.ndarray, omega_B: np.ndarray, f_B: np.ndarray) -> ImuSeries:
        """Readings for N consecutive samples (see :meth:`measure_series_with_biases`)."""
        series, _, _ = self.measure_series_with_biases(t_s, omega_B, f_B)
        return series

    def measure_series_with_biases(
        self, t_s: np.ndarray, omega_B: np.ndarray, f_B: np.ndarray
    ) -> tuple[ImuSeries, np.ndarray, np.ndarray]:
        """Readings for N consecutive samples plus the true biases each sample carried.

        Args:
            t_s: Sample times (s) on the IMU clock, shape (N,), strictly increasing.
            omega_B: True angular rates in B (rad/s), shape (N, 3).
            f_B: True specific forces ``R_WB^T (a_W - g_W)`` in B (m/s^2), shape (N, 3).

        Returns:
            ``(series, gyro_bias_rad_s (N, 3), accel_bias_m_s2 (N, 3))``.
        """
        t_s = np.asarray(t_s, dtype=float)
        omega_B = np.asarray(omega_B, dtype=float)
        f_B = np.asarray(f_B, dtype=float)
        n = t_s.shape[0] if t_s.ndim == 1 else -1
        if n < 0 or omega_B.shape != (n, 3) or f_B.shape != (n, 3):
            raise ValueError(
                f"measure_series expects t_s (N,), omega_B (N, 3), f_B (N, 3); got {t_s.shape}, "
                f"{omega_B.shape}, {f_B.shape}"
            )
        if n > 1 and not np.all(np.diff(t_s) > 0.0):
            k = int(np.argmin(np.diff(t_s) > 0.0))
            raise ValueError(
                f"IMU times must be strictly increasing: t[{k}]={t_s[k]}, t[{k + 1}]={t_s[k + 1]}"
            )
        if not (np.all(np.isfinite(omega_B)) and np.all(np.isfinite(f_B))):
            raise ValueError("measure_series: omega_B and f_B must be finite")
        gyro = np.empty((n, 3))
        accel = np.empty((n, 3))
        bias_g = np.empty((n, 3))
        bias_a = np.empty((n, 3))
        for start in range(0, n, _CHUNK_SAMPLES):
            stop = min(start + _CHUNK_SAMPLES, n)
            draws = self._scaled_draws(stop - start)
            # Bias used by sample k = b_0 + sum of the walk steps of samples < k (sequential order).
            walk_g = np.cumsum(np.concatenate([self._gyro_bias_rad_s[None], draws[:, 2]]), axis=0)
            walk_a = np.cumsum(np.concatenate([self._accel_bias_m_s2[None], draws[:, 3]]), axis=0)
            bias_g[start:stop] = walk_g[:-1]
            bias_a[start:stop] = walk_a[:-1]
            self._gyro_bias_rad_s = walk_g[-1].copy()
            self._accel_bias_m_s2 = walk_a[-1].copy()
            gyro[start:stop] = omega_B[start:stop] @ self._M_gyro.T + walk_g[:-1] + draws[:, 0]
            accel[start:stop] = f_B[start:stop] @ self._M_accel.T + walk_a[:-1] + draws[:, 1]
        p = self._params
        gyro = _quantize(gyro, p.gyro_quantization_rad_s)
        accel = _quantize(accel, p.accel_quantization_m_s2)
        saturated = np.any(np.abs(gyro) > p.gyro_range_rad_s, axis=1) | np.any(
            np.abs(accel) > p.accel_range_m_s2, axis=1
        )
        gyro = np.clip(gyro, -p.gyro_range_rad_s, p.gyro_range_rad_s)
        accel = np.clip(accel, -p.accel_range_m_s2, p.accel_range_m_s2)
        return ImuSeries(t_s.copy(), gyro, accel, saturated), bias_g, bias_a


def _quantize(x: np.ndarray, step: float) -> np.ndarray:
    """Round to the nearest multiple of ``step`` (no-op when ``step == 0``)."""
    if step <= 0.0:
        return x
    return np.round(x / step) * step


def _quantize_f(x: float, step: float) -> float:
    """:func:`_quantize` of one float: the same value, the sign of a zero included.

    ``np.round`` rounds half to even (``rint``), as ``round`` does; a multiple rounded to zero keeps the
    sign of ``x / step`` there (``rint(-0.3) = -0.0``), which the integer from ``round`` has lost.
    """
    if step <= 0.0:
        return x
    y = x / step
    k = round(y)
    return k * step if k else math.copysign(0.0, y) * step
