"""Tests of vio/preintegration.py: lesson numbers, constant twist, finite differences, Monte Carlo, gtsam."""

import numpy as np
import pytest
from viotb.vio.lie import exp_so3, left_jacobian_so3, log_so3, right_jacobian_so3, skew
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.types import ImuNoise, gravity_W

DT_S = 0.005  # 200 Hz


def _random_motion(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw (accel, gyro) sequences, shape (n, 3) each, with rotation and acceleration excitation."""
    accel = np.array([1.0, 0.5, 9.81]) + rng.normal(0.0, 1.0, size=(n, 3))
    gyro = np.array([0.3, -0.5, 0.8]) + rng.normal(0.0, 0.5, size=(n, 3))
    return accel, gyro


def _integrate(accel, gyro, bg, ba, noise=None, dt_s=DT_S) -> ImuPreintegration:
    pim = ImuPreintegration(bg, ba, noise if noise is not None else ImuNoise())
    for a, w in zip(accel, gyro, strict=True):
        pim.integrate(a, w, dt_s)
    return pim


def test_lesson_1d_worked_example():
    """Lesson ch. 5: 3 samples a_raw = 2.00, b = 0.10, dt = 0.1 -> dv = 0.57, d dv/db = -0.3, 0.555."""
    pim = ImuPreintegration(np.zeros(3), np.array([0.10, 0.0, 0.0]))
    for _ in range(3):
        pim.integrate(np.array([2.00, 0.0, 0.0]), np.zeros(3), 0.1)
    assert pim.delta_v[0] == pytest.approx(0.57, abs=1e-12)
    # dp = sum of dv_k dt + 1/2 a dt^2 = 1.9 * 0.3^2 / 2 = 0.0855.
    assert pim.delta_p[0] == pytest.approx(0.0855, abs=1e-12)
    assert pim.d_v_d_ba[0, 0] == pytest.approx(-0.3, abs=1e-12)
    assert pim.d_p_d_ba[0, 0] == pytest.approx(-0.045, abs=1e-12)
    _, dv_corr, _ = pim.corrected(np.zeros(3), np.array([0.15, 0.0, 0.0]))
    assert dv_corr[0] == pytest.approx(0.555, abs=1e-12)
    reint = ImuPreintegration(np.zeros(3), np.array([0.15, 0.0, 0.0]))
    for _ in range(3):
        reint.integrate(np.array([2.00, 0.0, 0.0]), np.zeros(3), 0.1)
    assert reint.delta_v[0] == pytest.approx(dv_corr[0], abs=1e-12)
    assert pim.dt_s == pytest.approx(0.3, abs=1e-15)


def _constant_twist_closed_form(w: np.ndarray, a: np.ndarray, t: float):
    """Exact increments for constant body rate w and body specific force a over time t.

    dR = Exp(w t); dv = int_0^t Exp(w s) a ds = t Jl(w t) a;
    dp = int_0^t (t - s) Exp(w s) a ds
       = [t^2/2 I + (t/th - sin(th t)/th^2) K + (t^2/2 - (1-cos th t)/th^2) K^2] a,
    with th = |w| and K = skew(w / th).
    """
    th = np.linalg.norm(w)
    K = skew(w / th)
    dR = exp_so3(w * t)
    dv = t * left_jacobian_so3(w * t) @ a
    P = (
        0.5 * t * t * np.eye(3)
        + (t / th - np.sin(th * t) / th**2) * K
        + (0.5 * t * t - (1.0 - np.cos(th * t)) / th**2) * K @ K
    )
    return dR, dv, P @ a


def test_constant_twist_closed_form_and_first_order_convergence():
    w = np.array([0.4, -0.7, 1.1])  # rad/s
    a = np.array([0.8, 0.3, 9.5])  # m/s^2
    t = 1.0
    dR_ref, dv_ref, dp_ref = _constant_twist_closed_form(w, a, t)
    errors = []
    for n in (250, 500):
        pim = _integrate(np.tile(a, (n, 1)), np.tile(w, (n, 1)), np.zeros(3), np.zeros(3), dt_s=t / n)
        np.testing.assert_allclose(log_so3(pim.delta_R.T @ dR_ref), np.zeros(3), atol=1e-12)
        errors.append((np.linalg.norm(pim.delta_v - dv_ref), np.linalg.norm(pim.delta_p - dp_ref)))
    # Forward-Euler (zero-order hold on dR) error: |w| dt |a| t / 2 ~ 0.027 m/s at dt = 4 ms.
    assert errors[1][0] < 0.02 and errors[1][1] < 0.01
    # First-order scheme: halving dt halves the error (ratio 2 within 5 %).
    assert errors[0][0] / errors[1][0] == pytest.approx(2.0, rel=0.05)
    assert errors[0][1] / errors[1][1] == pytest.approx(2.0, rel=0.05)


def test_predict_matches_constant_twist_world_motion():
    """predict() (eq. 33) maps the body-frame increments to world states with gravity."""
    rng = np.random.default_rng(0)
    accel, gyro = _random_motion(rng, 100)
    bg = np.array([0.01, -0.02, 0.03])
    ba = np.array([0.1, -0.05, 0.2])
    pim = _integrate(accel, gyro, bg, ba)
    R_i = exp_so3(np.array([0.1, -0.2, 0.3]))
    p_i = np.array([1.0, 2.0, 3.0])
    v_i = np.array([0.5, -0.1, 0.2])
    # Independent world-frame Euler integration of the same samples.
    R, p, v = R_i.copy(), p_i.copy(), v_i.copy()
    g = gravity_W()
    for acc, gy in zip(accel, gyro, strict=True):
        a_W = R @ (acc - ba) + g
        p = p + v * DT_S + 0.5 * a_W * DT_S**2
        v = v + a_W * DT_S
        R = R @ exp_so3((gy - bg) * DT_S)
    R_j, p_j, v_j = pim.predict(R_i, p_i, v_i, g)
    np.testing.assert_allclose(R_j, R, atol=1e-12)
    np.testing.assert_allclose(v_j, v, atol=1e-12)
    np.testing.assert_allclose(p_j, p, atol=1e-12)


def test_bias_jacobians_match_central_finite_differences_of_reintegration():
    rng = np.random.default_rng(0)
    accel, gyro = _random_motion(rng, 200)
    bg = np.array([0.01, -0.02, 0.03])
    ba = np.array([0.1, -0.05, 0.2])
    pim = _integrate(accel, gyro, bg, ba)
    eps = 1e-6
    fd = {name: np.zeros((3, 3)) for name in ("R_bg", "v_bg", "p_bg", "v_ba", "p_ba")}
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        plus, minus = _integrate(accel, gyro, bg + e, ba), _integrate(accel, gyro, bg - e, ba)
        rot_plus = log_so3(pim.delta_R.T @ plus.delta_R)
        rot_minus = log_so3(pim.delta_R.T @ minus.delta_R)
        fd["R_bg"][:, k] = (rot_plus - rot_minus) / (2 * eps)
        fd["v_bg"][:, k] = (plus.delta_v - minus.delta_v) / (2 * eps)
        fd["p_bg"][:, k] = (plus.delta_p - minus.delta_p) / (2 * eps)
        plus, minus = _integrate(accel, gyro, bg, ba + e), _integrate(accel, gyro, bg, ba - e)
        fd["v_ba"][:, k] = (plus.delta_v - minus.delta_v) / (2 * eps)
        fd["p_ba"][:, k] = (plus.delta_p - minus.delta_p) / (2 * eps)
    np.testing.assert_allclose(pim.d_R_d_bg, fd["R_bg"], atol=1e-7)
    np.testing.assert_allclose(pim.d_v_d_bg, fd["v_bg"], atol=1e-7)
    np.testing.assert_allclose(pim.d_p_d_bg, fd["p_bg"], atol=1e-7)
    np.testing.assert_allclose(pim.d_v_d_ba, fd["v_ba"], atol=1e-7)
    np.testing.assert_allclose(pim.d_p_d_ba, fd["p_ba"], atol=1e-7)


def test_corrected_is_first_order_accurate():
    """Error of the eq. 44 correction vs re-integration shrinks quadratically with the bias change."""
    rng = np.random.default_rng(0)
    accel, gyro = _random_motion(rng, 200)
    bg, ba = np.zeros(3), np.zeros(3)
    pim = _integrate(accel, gyro, bg, ba)
    direction_g, direction_a = np.array([0.3, -0.2, 0.5]), np.array([0.2, 0.1, -0.3])
    errs = []
    for scale in (1e-2, 5e-3):
        reint = _integrate(accel, gyro, bg + scale * direction_g, ba + scale * direction_a)
        dR, dv, dp = pim.corrected(bg + scale * direction_g, ba + scale * direction_a)
        errs.append(
            np.linalg.norm(log_so3(dR.T @ reint.delta_R))
            + np.linalg.norm(dv - reint.delta_v)
            + np.linalg.norm(dp - reint.delta_p)
        )
    assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.1)


def test_covariance_symmetric_psd_and_single_step_closed_form():
    pim = ImuPreintegration(np.zeros(3), np.zeros(3), ImuNoise())
    pim.integrate(np.array([0.0, 0.0, 9.81]), np.zeros(3), DT_S)
    noise = ImuNoise()
    var_g = noise.gyro_noise_density_rad_s_sqrthz**2 / DT_S
    var_a = noise.accel_noise_density_m_s2_sqrthz**2 / DT_S
    # First step from zero covariance: dtheta = Jr dt n_g, dv = dt n_a, dp = dt^2/2 n_a.
    expected = np.zeros((9, 9))
    expected[0:3, 0:3] = var_g * DT_S**2 * np.eye(3)
    expected[3:6, 3:6] = var_a * DT_S**2 * np.eye(3)
    expected[6:9, 6:9] = var_a * DT_S**4 / 4 * np.eye(3)
    expected[3:6, 6:9] = expected[6:9, 3:6] = var_a * DT_S**3 / 2 * np.eye(3)
    np.testing.assert_allclose(pim.cov, expected, rtol=1e-12, atol=1e-30)

    rng = np.random.default_rng(0)
    accel, gyro = _random_motion(rng, 200)
    cov = _integrate(accel, gyro, np.zeros(3), np.zeros(3)).cov
    np.testing.assert_allclose(cov, cov.T, atol=1e-20)
    assert np.linalg.eigvalsh(cov).min() > 0.0


def _monte_carlo_cov(n_runs: int, n_steps: int, rng: np.random.Generator):
    """Sample covariance of the increment errors [dtheta, dv, dp] under Kalibr white noise."""
    noise = ImuNoise(gyro_noise_density_rad_s_sqrthz=5e-3, accel_noise_density_m_s2_sqrthz=5e-2)
    accel, gyro = _random_motion(np.random.default_rng(1), n_steps)
    nominal = _integrate(accel, gyro, np.zeros(3), np.zeros(3), noise)
    sigma_g = noise.gyro_noise_density_rad_s_sqrthz / np.sqrt(DT_S)
    sigma_a = noise.accel_noise_density_m_s2_sqrthz / np.sqrt(DT_S)
    errors = np.zeros((n_runs, 9))
    for r in range(n_runs):
        noisy = _integrate(
            accel + sigma_a * rng.normal(size=accel.shape),
            gyro + sigma_g * rng.normal(size=gyro.shape),
            np.zeros(3),
            np.zeros(3),
            noise,
        )
        # Forster's error convention: dR_meas = dR_true Exp(dtheta).
        errors[r, 0:3] = log_so3(nominal.delta_R.T @ noisy.delta_R)
        errors[r, 3:6] = noisy.delta_v - nominal.delta_v
        errors[r, 6:9] = noisy.delta_p - nominal.delta_p
    return nominal.cov, np.cov(errors.T)


def _check_cov_against_samples(cov_pred: np.ndarray, cov_mc: np.ndarray, n_runs: int) -> None:
    # Whitened sample covariance should be I: each diagonal entry has std sqrt(2 / n_runs).
    L = np.linalg.cholesky(cov_pred)
    white = np.linalg.solve(L, np.linalg.solve(L, cov_mc).T)
    tol = 5.0 * np.sqrt(2.0 / n_runs)
    np.testing.assert_allclose(np.diag(white), np.ones(9), atol=tol)
    off = white - np.diag(np.diag(white))
    assert np.abs(off).max() < 5.0 * np.sqrt(1.0 / n_runs)


def test_covariance_matches_monte_carlo_short():
    n_runs = 150
    cov_pred, cov_mc = _monte_carlo_cov(n_runs, 40, np.random.default_rng(0))
    _check_cov_against_samples(cov_pred, cov_mc, n_runs)


@pytest.mark.slow
def test_covariance_matches_monte_carlo_long():
    n_runs = 2000
    cov_pred, cov_mc = _monte_carlo_cov(n_runs, 200, np.random.default_rng(0))
    _check_cov_against_samples(cov_pred, cov_mc, n_runs)


def test_bad_input_raises_clear_errors():
    pim = ImuPreintegration(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="dt_s"):
        pim.integrate(np.zeros(3), np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="accel_B_m_s2"):
        pim.integrate(np.zeros(2), np.zeros(3), DT_S)
    with pytest.raises(ValueError, match="gyro_B_rad_s"):
        pim.integrate(np.zeros(3), np.array([np.nan, 0.0, 0.0]), DT_S)
    with pytest.raises(ValueError, match="gyro_bias_rad_s"):
        ImuPreintegration(np.zeros(4), np.zeros(3))


def test_matches_gtsam_preintegrated_imu_measurements():
    """Deltas, covariance and bias Jacobians vs gtsam (tangent-space preintegration, gtsam >= 4.2).

    gtsam integrates in the tangent space of the total rotation, a discretization that differs from ours
    at O(|w| dt) per step, and expresses rotation covariance in log coordinates (dtheta = Jr dtheta_log).
    """
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(0)
    accel, gyro = _random_motion(rng, 200)
    bg = np.array([0.01, -0.02, 0.03])
    ba = np.array([0.1, -0.05, 0.2])
    noise = ImuNoise()
    params = gtsam.PreintegrationParams.MakeSharedU(0.0)  # zero gravity: predict() returns the raw deltas
    params.setGyroscopeCovariance(noise.gyro_noise_density_rad_s_sqrthz**2 * np.eye(3))
    params.setAccelerometerCovariance(noise.accel_noise_density_m_s2_sqrthz**2 * np.eye(3))
    params.setIntegrationCovariance(np.zeros((3, 3)))
    gpim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias(ba, bg))
    for a, w in zip(accel, gyro, strict=True):
        gpim.integrateMeasurement(a, w, DT_S)
    ours = _integrate(accel, gyro, bg, ba, noise)

    assert np.linalg.norm(log_so3(gpim.deltaRij().matrix().T @ ours.delta_R)) < 2e-4
    np.testing.assert_allclose(gpim.deltaVij(), ours.delta_v, atol=5e-4)
    np.testing.assert_allclose(gpim.deltaPij(), ours.delta_p, atol=2e-4)

    perm = [0, 1, 2, 6, 7, 8, 3, 4, 5]  # gtsam order [rot, pos, vel] -> ours [rot, vel, pos]
    cov_g = gpim.preintMeasCov()[np.ix_(perm, perm)]
    M = np.eye(9)
    M[0:3, 0:3] = right_jacobian_so3(log_so3(gpim.deltaRij().matrix()))
    cov_g = M @ cov_g @ M.T
    np.testing.assert_allclose(cov_g, ours.cov, atol=1e-3 * np.abs(ours.cov).max())

    def predict(bias_g, bias_a):
        nav = gpim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(bias_a, bias_g))
        return nav.attitude().matrix(), nav.velocity(), nav.position()

    eps = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        (Rp, vp, pp), (Rm, vm, pm) = predict(bg + e, ba), predict(bg - e, ba)
        np.testing.assert_allclose(log_so3(Rm.T @ Rp) / (2 * eps), ours.d_R_d_bg[:, k], atol=1e-3)
        np.testing.assert_allclose((vp - vm) / (2 * eps), ours.d_v_d_bg[:, k], atol=1e-3)
        np.testing.assert_allclose((pp - pm) / (2 * eps), ours.d_p_d_bg[:, k], atol=1e-3)
        (_, vp, pp), (_, vm, pm) = predict(bg, ba + e), predict(bg, ba - e)
        np.testing.assert_allclose((vp - vm) / (2 * eps), ours.d_v_d_ba[:, k], atol=1e-4)
        np.testing.assert_allclose((pp - pm) / (2 * eps), ours.d_p_d_ba[:, k], atol=1e-4)
