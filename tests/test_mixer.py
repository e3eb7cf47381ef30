"""Tests for viotb.controllers.mixer: exact inversion within limits, documented saturation beyond."""

from __future__ import annotations

import numpy as np
import pytest
from viotb.controllers.mixer import Mixer
from viotb.controllers.vehicle import VehicleParams
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.models import load_model


@pytest.fixture(scope="module")
def vehicle() -> VehicleParams:
    return vehicle_params_from_model(load_model("quadrotor", "empty"))


@pytest.fixture(scope="module")
def mixer(vehicle: VehicleParams) -> Mixer:
    return Mixer(vehicle)


def _in_limits(f: np.ndarray, vehicle: VehicleParams) -> bool:
    return bool(np.all(f >= vehicle.min_thrust_N - 1e-12) and np.all(f <= vehicle.max_thrust_N + 1e-12))


def test_allocation_matches_hand_derived_x_configuration(mixer: Mixer, vehicle: VehicleParams) -> None:
    # Thrust along +z at (x_i, y_i): M_x = y_i f_i, M_y = -x_i f_i, M_z = k_i f_i; collective = f_i.
    x, y = vehicle.rotor_positions_B_m[:, 0], vehicle.rotor_positions_B_m[:, 1]
    expected = np.vstack([np.ones(4), y, -x, vehicle.yaw_moment_coeff_m])
    np.testing.assert_allclose(mixer.allocation, expected, atol=1e-15)


def test_hover_wrench_gives_equal_motors(mixer: Mixer, vehicle: VehicleParams) -> None:
    f = mixer.motor_thrusts(vehicle.hover_thrust_N, np.zeros(3))
    np.testing.assert_allclose(f, np.full(4, 1.2 * 9.81 / 4), atol=1e-12)


def test_inverts_exactly_within_limits(mixer: Mixer, vehicle: VehicleParams) -> None:
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(500):
        f_true = rng.uniform(vehicle.min_thrust_N + 0.05, vehicle.max_thrust_N - 0.05)
        collective, moments = mixer.wrench(f_true)
        f = mixer.motor_thrusts(collective, moments)
        np.testing.assert_allclose(f, f_true, atol=1e-12)
        collective2, moments2 = mixer.wrench(f)
        np.testing.assert_allclose(collective2, collective, atol=1e-12)
        np.testing.assert_allclose(moments2, moments, atol=1e-12)
        checked += 1
    assert checked == 500


def test_collective_clipped_to_total_motor_capacity(mixer: Mixer, vehicle: VehicleParams) -> None:
    f = mixer.motor_thrusts(100.0, np.zeros(3))
    np.testing.assert_allclose(f, vehicle.max_thrust_N, atol=1e-12)
    f = mixer.motor_thrusts(-5.0, np.zeros(3))
    np.testing.assert_allclose(f, vehicle.min_thrust_N, atol=1e-12)


def test_yaw_is_sacrificed_first(mixer: Mixer, vehicle: VehicleParams) -> None:
    collective = vehicle.hover_thrust_N
    moments = np.array([0.05, -0.03, 5.0])  # yaw far beyond the ~0.19 N m the rotors can give at hover
    f = mixer.motor_thrusts(collective, moments)
    got_collective, got_moments = mixer.wrench(f)
    assert _in_limits(f, vehicle)
    np.testing.assert_allclose(got_collective, collective, atol=1e-12)
    np.testing.assert_allclose(got_moments[:2], moments[:2], atol=1e-12)
    assert 0.0 < got_moments[2] < moments[2]
    # Yaw is scaled to the largest value that fits: one motor sits on a limit.
    assert np.min(np.minimum(f - vehicle.min_thrust_N, vehicle.max_thrust_N - f)) < 1e-12


def test_roll_pitch_scaled_keeping_direction_when_infeasible(mixer: Mixer, vehicle: VehicleParams) -> None:
    moments = np.array([3.0, 2.0, 0.1])  # needs a thrust spread far beyond 8 N
    f = mixer.motor_thrusts(vehicle.hover_thrust_N, moments)
    _, got = mixer.wrench(f)
    assert _in_limits(f, vehicle)
    assert np.linalg.norm(got[:2]) < np.linalg.norm(moments[:2])
    np.testing.assert_allclose(
        got[:2] / np.linalg.norm(got[:2]), moments[:2] / np.linalg.norm(moments[:2]), atol=1e-12
    )


def test_collective_moved_only_to_fit_roll_pitch(mixer: Mixer, vehicle: VehicleParams) -> None:
    # Roll/pitch fit within the 8 N range, but not around a near-maximal collective: collective gives way.
    moments = np.array([0.6, 0.0, 0.0])
    f = mixer.motor_thrusts(30.0, moments)
    got_collective, got_moments = mixer.wrench(f)
    assert _in_limits(f, vehicle)
    np.testing.assert_allclose(got_moments[:2], moments[:2], atol=1e-12)
    assert got_collective < 30.0


def test_random_requests_always_within_limits(mixer: Mixer, vehicle: VehicleParams) -> None:
    rng = np.random.default_rng(0)
    for _ in range(300):
        f = mixer.motor_thrusts(rng.uniform(-10.0, 50.0), rng.normal(0.0, 2.0, 3))
        assert _in_limits(f, vehicle)


def test_bad_input_raises_clear_error(mixer: Mixer) -> None:
    with pytest.raises(ValueError, match="thrusts_N"):
        mixer.wrench(np.zeros(3))
    with pytest.raises(ValueError, match="moments"):
        mixer.motor_thrusts(10.0, np.array([0.0, np.nan, 0.0]))


def test_rejects_tilted_thrust_axes(vehicle: VehicleParams) -> None:
    axes = vehicle.thrust_axes_B.copy()
    axes[0] = [0.0, np.sin(0.1), np.cos(0.1)]
    tilted = VehicleParams(
        mass_kg=vehicle.mass_kg,
        inertia_kg_m2=vehicle.inertia_kg_m2,
        rotor_positions_B_m=vehicle.rotor_positions_B_m,
        thrust_axes_B=axes,
        yaw_moment_coeff_m=vehicle.yaw_moment_coeff_m,
        min_thrust_N=vehicle.min_thrust_N,
        max_thrust_N=vehicle.max_thrust_N,
    )
    with pytest.raises(ValueError, match="thrust axis"):
        Mixer(tilted)
