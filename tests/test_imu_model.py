"""Tests of the synthetic IMU (envs/imu_model.py)."""

from __future__ import annotations

import dataclasses
import math

import allantools
import numpy as np
import pytest
from viotb.envs.sim.imu_model import ImuModel, ImuModelParams, imu_preset, imu_preset_names
from viotb.vio.types import GRAVITY_M_S2, ImuNoise


def _static(n: int, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(n) / rate_hz
    f = np.tile([0.0, 0.0, GRAVITY_M_S2], (n, 1))
    return t, np.zeros((n, 3)), f


def test_ideal_static_level_reads_gravity_up():
    model = ImuModel(imu_preset("ideal"), np.random.default_rng(0))
    series = model.measure_series(*_static(200, 200.0))
    np.testing.assert_array_equal(series.gyro_B_rad_s, 0.0)
    np.testing.assert_allclose(series.accel_B_m_s2, np.tile([0.0, 0.0, 9.81], (200, 1)), atol=0.0)
    assert not series.saturated.any()
    sample = model.measure(1.0, np.zeros(3), np.array([0.0, 0.0, GRAVITY_M_S2]))
    np.testing.assert_array_equal(sample.accel_B_m_s2, [0.0, 0.0, 9.81])


def test_presets_values_and_unknown_name():
    adis = imu_preset("adis16448")
    assert adis.rate_hz == 200.0
    assert adis.noise == ImuNoise(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3)
    np.testing.assert_allclose(adis.gyro_range_rad_s, np.deg2rad(1000.0), rtol=1e-12)
    np.testing.assert_allclose(adis.accel_range_m_s2, 18.0 * 9.80665, rtol=1e-12)
    mems = imu_preset("bmi088")
    np.testing.assert_allclose(mems.gyro_range_rad_s, np.deg2rad(2000.0), rtol=1e-12)
    assert mems.noise.gyro_noise_density_rad_s_sqrthz > adis.noise.gyro_noise_density_rad_s_sqrthz
    ideal = imu_preset("ideal")
    assert math.isinf(ideal.gyro_range_rad_s) and math.isinf(ideal.accel_range_m_s2)
    assert set(imu_preset_names()) >= {"adis16448", "bmi088", "ideal"}
    with pytest.raises(ValueError, match="adis16448.*bmi088.*ideal"):
        imu_preset("nope")


def test_bad_params_and_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="rate_hz"):
        ImuModelParams(rate_hz=0.0)
    with pytest.raises(ValueError, match="gyro_scale_sigma"):
        ImuModelParams(gyro_scale_sigma=-1.0)
    model = ImuModel(imu_preset("ideal"), np.random.default_rng(0))
    with pytest.raises(ValueError, match="omega_B"):
        model.measure_series(np.zeros(3), np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="strictly increasing"):
        model.measure_series(np.array([0.0, 0.0]), np.zeros((2, 3)), np.zeros((2, 3)))


def test_allan_deviation_recovers_noise_densities():
    """2 h static log: white density from the -1/2 line at tau=1 s, random walk from the +1/2 line.

    Densities are chosen so the two regimes separate within 2 h (crossover tau_c = sqrt(3) N / K of
    ~3 s and ~1 s); the Allan variance is averaged over the three i.i.d. axes of each sensor (IEEE 952-1997,
    Annex C: K = sigma(tau) sqrt(3 / tau) on the +1/2 slope). Over 12 seeds the K error had std 3 %.
    """
    rate_hz = 200.0
    noise = ImuNoise(1.7e-4, 1.0e-4, 2.0e-3, 3.0e-3)
    params = ImuModelParams(rate_hz=rate_hz, noise=noise)
    duration_s = 2.0 * 3600.0
    n = int(duration_s * rate_hz)
    series = ImuModel(params, np.random.default_rng(0)).measure_series(
        np.arange(n) / rate_hz, np.zeros((n, 3)), np.zeros((n, 3))
    )
    for y, n_true, k_true in (
        (series.gyro_B_rad_s, noise.gyro_noise_density_rad_s_sqrthz, noise.gyro_random_walk_rad_s2_sqrthz),
        (series.accel_B_m_s2, noise.accel_noise_density_m_s2_sqrthz, noise.accel_random_walk_m_s3_sqrthz),
    ):
        tau_c = math.sqrt(3.0) * n_true / k_true
        taus_white = np.logspace(np.log10(0.02), np.log10(0.1), 5)
        taus_walk = np.logspace(np.log10(10.0 * tau_c), np.log10(duration_s / 100.0), 8)
        avar_white = np.zeros(5)
        avar_walk = np.zeros(8)
        avar_1s = 0.0
        for axis in range(3):
            tw, adev_w, _, _ = allantools.oadev(y[:, axis], rate=rate_hz, data_type="freq", taus=taus_white)
            tk, adev_k, _, _ = allantools.oadev(y[:, axis], rate=rate_hz, data_type="freq", taus=taus_walk)
            _, adev_1, _, _ = allantools.oadev(y[:, axis], rate=rate_hz, data_type="freq", taus=[1.0])
            avar_white += adev_w**2 / 3.0
            avar_walk += adev_k**2 / 3.0
            avar_1s += float(adev_1[0]) ** 2 / 3.0
        # -1/2 slope line evaluated at tau = 1 s.
        n_hat = float(np.exp(np.mean(np.log(np.sqrt(avar_white * tw)))))
        # +1/2 slope line: K = ADEV * sqrt(3 / tau).
        k_hat = float(np.exp(np.mean(np.log(np.sqrt(avar_walk * 3.0 / tk)))))
        np.testing.assert_allclose(n_hat, n_true, rtol=0.10)
        np.testing.assert_allclose(k_hat, k_true, rtol=0.10)
        # Closed form of the ADEV at tau = 1 s with both terms: sigma^2 = N^2 / tau + K^2 tau / 3.
        np.testing.assert_allclose(math.sqrt(avar_1s), math.sqrt(n_true**2 + k_true**2 / 3.0), rtol=0.10)


def test_saturation_clips_and_flags_exactly_the_clipped_samples():
    params = dataclasses.replace(imu_preset("ideal"), gyro_range_rad_s=2.0, accel_range_m_s2=20.0)
    model = ImuModel(params, np.random.default_rng(0))
    n = 400
    t = np.arange(n) / 200.0
    omega = np.zeros((n, 3))
    omega[:, 2] = np.linspace(-4.0, 4.0, n)
    f = np.tile([0.0, 0.0, GRAVITY_M_S2], (n, 1))
    f[100:110, 0] = 25.0
    series = model.measure_series(t, omega, f)
    assert np.abs(series.gyro_B_rad_s).max() == 2.0
    assert np.abs(series.accel_B_m_s2).max() == 20.0
    expected = (np.abs(omega[:, 2]) > 2.0) | (np.abs(f[:, 0]) > 20.0)
    np.testing.assert_array_equal(series.saturated, expected)
    np.testing.assert_array_equal(series.gyro_B_rad_s, np.clip(omega, -2.0, 2.0))
    np.testing.assert_array_equal(series.accel_B_m_s2, np.clip(f, -20.0, 20.0))


def test_same_seed_identical_and_sequential_equals_vectorized():
    params = imu_preset("bmi088")
    rng = np.random.default_rng(0)
    n = 500
    t = np.arange(n) / params.rate_hz
    omega = rng.normal(size=(n, 3))
    f = rng.normal(size=(n, 3)) + [0.0, 0.0, 9.81]
    a = ImuModel(params, np.random.default_rng(7)).measure_series(t, omega, f)
    b = ImuModel(params, np.random.default_rng(7)).measure_series(t, omega, f)
    c = ImuModel(params, np.random.default_rng(8)).measure_series(t, omega, f)
    np.testing.assert_array_equal(a.gyro_B_rad_s, b.gyro_B_rad_s)
    np.testing.assert_array_equal(a.accel_B_m_s2, b.accel_B_m_s2)
    assert not np.array_equal(a.gyro_B_rad_s, c.gyro_B_rad_s)
    seq = ImuModel(params, np.random.default_rng(7))
    samples = [seq.measure(t[i], omega[i], f[i]) for i in range(n)]
    np.testing.assert_array_equal(np.array([s.gyro_B_rad_s for s in samples]), a.gyro_B_rad_s)
    np.testing.assert_array_equal(np.array([s.accel_B_m_s2 for s in samples]), a.accel_B_m_s2)


def test_quantization_step_respected():
    params = imu_preset("adis16448")
    model = ImuModel(params, np.random.default_rng(0))
    series = model.measure_series(*_static(1000, params.rate_hz))
    for values, step in (
        (series.gyro_B_rad_s, params.gyro_quantization_rad_s),
        (series.accel_B_m_s2, params.accel_quantization_m_s2),
    ):
        levels = values / step
        np.testing.assert_allclose(levels, np.round(levels), atol=1e-6)
        assert len(np.unique(values[:, 0])) > 3


def test_bias_model_and_error_matrices():
    """Biases follow the turn-on + walk model; scale/misalignment multiply the truth."""
    noise = ImuNoise(0.0, 1.0e-3, 0.0, 2.0e-3)
    params = ImuModelParams(
        rate_hz=100.0,
        noise=noise,
        gyro_turn_on_bias_sigma_rad_s=0.01,
        accel_turn_on_bias_sigma_m_s2=0.1,
        gyro_scale_sigma=0.01,
        misalignment_sigma_rad=0.001,
    )
    model = ImuModel(params, np.random.default_rng(0))
    b0_g, b0_a = model.gyro_bias_rad_s, model.accel_bias_m_s2
    M_g = model.gyro_matrix
    assert np.abs(b0_g).max() > 0.0 and np.abs(np.diag(M_g) - 1.0).max() > 0.0
    n = 20000
    rng = np.random.default_rng(1)
    omega = rng.normal(size=(n, 3))
    series, bias_g, bias_a = model.measure_series_with_biases(np.arange(n) / 100.0, omega, np.zeros((n, 3)))
    np.testing.assert_array_equal(bias_g[0], b0_g)
    np.testing.assert_array_equal(bias_a[0], b0_a)
    # No white noise: reading = M omega + bias exactly (up to float rounding).
    np.testing.assert_allclose(series.gyro_B_rad_s, omega @ M_g.T + bias_g, atol=1e-14)
    # Walk steps have sigma = density * sqrt(dt).
    steps = np.diff(bias_a, axis=0)
    np.testing.assert_allclose(steps.std(), 2.0e-3 * math.sqrt(0.01), rtol=0.02)
    # The model's current bias is the one after the last step.
    assert not np.array_equal(model.accel_bias_m_s2, bias_a[-1])


def test_single_sample_fast_path_bit_identical_with_saturation_and_biases():
    # measure() is a separate single-sample code path: it must match the vectorized series exactly, including
    # the saturation flags, the clipped values and the bias each sample carried.
    params = dataclasses.replace(imu_preset("adis16448"), gyro_range_rad_s=1.5, accel_range_m_s2=12.0)
    rng = np.random.default_rng(0)
    n = 300
    t = np.arange(n) / params.rate_hz
    omega = rng.normal(scale=1.0, size=(n, 3))
    f = rng.normal(scale=2.0, size=(n, 3)) + [0.0, 0.0, 9.81]
    batch = ImuModel(params, np.random.default_rng(3))
    series, bias_g, bias_a = batch.measure_series_with_biases(t, omega, f)
    assert 0 < int(series.saturated.sum()) < n  # both branches exercised
    seq = ImuModel(params, np.random.default_rng(3))
    for i in range(n):
        np.testing.assert_array_equal(seq.gyro_bias_rad_s, bias_g[i])
        np.testing.assert_array_equal(seq.accel_bias_m_s2, bias_a[i])
        s = seq.measure(t[i], omega[i], f[i])
        assert s.t_s == t[i] and s.saturated == bool(series.saturated[i])
        np.testing.assert_array_equal(s.gyro_B_rad_s, series.gyro_B_rad_s[i])
        np.testing.assert_array_equal(s.accel_B_m_s2, series.accel_B_m_s2[i])


def test_single_sample_rejects_bad_input():
    model = ImuModel(imu_preset("adis16448"), np.random.default_rng(0))
    with pytest.raises(ValueError, match="omega_B_true"):
        model.measure(0.0, np.zeros(2), np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        model.measure(0.0, np.array([0.0, np.nan, 0.0]), np.zeros(3))


def test_block_drawn_normals_equal_per_sample_draws_across_mixed_calls(monkeypatch):
    """Blocks drawn ahead give the per-call draws' output, over block boundaries and mixed calls.

    Single samples are served from blocks, a series takes the rest of a block: the output must equal one
    ``standard_normal((n, 4, 3))`` per call (the form before the blocks).
    """
    params = imu_preset("adis16448")
    rng = np.random.default_rng(1)
    n = 700
    t = np.arange(n) / params.rate_hz
    omega = rng.normal(scale=0.5, size=(n, 3))
    f = rng.normal(scale=1.0, size=(n, 3)) + [0.0, 0.0, 9.81]
    plan = [("one", 200), ("series", 40), ("one", 100), ("series", 1), ("series", 90), ("one", 269)]
    assert sum(k for _, k in plan) == n

    def run(model):
        out, i = [], 0
        for kind, k in plan:
            if kind == "one":
                out += [np.concatenate([s.gyro_B_rad_s, s.accel_B_m_s2]) for s in
                        (model.measure(t[j], omega[j], f[j]) for j in range(i, i + k))]  # fmt: skip
            else:
                s = model.measure_series(t[i : i + k], omega[i : i + k], f[i : i + k])
                out += list(np.hstack([s.gyro_B_rad_s, s.accel_B_m_s2]))
            i += k
        return np.array(out), model.gyro_bias_rad_s

    blocks = run(ImuModel(params, np.random.default_rng(5)))
    with monkeypatch.context() as m:
        m.setattr(
            ImuModel,
            "_scaled_draws",
            lambda self, k: self._rng.standard_normal((k, 4, 3)) * self._sigmas[None, :, None],
        )
        per_call = run(ImuModel(params, np.random.default_rng(5)))
    np.testing.assert_array_equal(blocks[0], per_call[0])
    np.testing.assert_array_equal(blocks[1], per_call[1])
