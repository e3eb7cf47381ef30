"""Tests of viotb.envs.gym: Gymnasium contracts, determinism, rewards, errors (mostly ground truth)."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium
import numpy as np
import pytest
import viotb.envs  # noqa: F401  (registers the ids)
from gymnasium.utils.env_checker import check_env
from viotb.envs.gym.base import orientation_features
from viotb.envs.gym.config import ACTION_TYPES, DomainRandomization, HoverEnvConfig
from viotb.envs.gym.hover import HoverEnv
from viotb.envs.gym.rewards import cost_crash, cost_effort, cost_smoothness, reward_tracking
from viotb.vio.lie import exp_so3, rotmat_to_quat_wxyz

pytestmark = pytest.mark.filterwarnings("ignore:.*Box observation space (min|max)imum value:UserWarning")
"""Unbounded entries (position, velocity, rates) are unbounded on purpose."""

ENV_IDS = ("viotb/Hover-v0", "viotb/Waypoints-v0", "viotb/Track-v0")
FAST = {"estimator": "ground-truth"}


def _rollout(env: gymnasium.Env, actions: np.ndarray, seed: int) -> list:
    """Observations, rewards and flags of a seeded rollout (stops at termination)."""
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, reward, terminated, truncated, _ = env.step(a)
        out.append((obs, reward, terminated, truncated))
        if terminated or truncated:
            break
    return out


def test_registered_ids_and_time_limits():
    for env_id, steps in zip(ENV_IDS, (500, 1500, 1000), strict=True):
        spec = gymnasium.spec(env_id)
        assert spec.max_episode_steps == steps
        env = gymnasium.make(env_id, **FAST)
        assert env.spec.max_episode_steps == steps
        env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("action_type", ACTION_TYPES)
def test_check_env_every_id_and_action_type(env_id, action_type):
    env = gymnasium.make(env_id, action_type=action_type, **FAST)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_check_env_msckf_sim_and_dict_observations():
    env = gymnasium.make("viotb/Hover-v0", estimator="msckf", frontend="sim", obs_mode="dict", imu_window=4)
    check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    for _ in range(5):
        obs, *_ = env.step(np.zeros(4, dtype=np.float32))
    assert env.observation_space.contains(obs)
    # A gray onboard image arrives (20 Hz camera, 0.1 s elapsed); the IMU rows are the last 4 distinct
    # samples (200 Hz IMU, 5 ms low-level loop), the newest last.
    assert obs["image"].shape == (240, 320, 1) and obs["image"].max() > 0
    last = env.unwrapped.rig.last_imu
    np.testing.assert_array_equal(
        obs["imu"][-1], np.r_[last.gyro_B_rad_s, last.accel_B_m_s2].astype(np.float32)
    )
    assert len({tuple(row) for row in obs["imu"]}) == 4
    assert np.all(np.linalg.norm(obs["imu"][:, 3:], axis=1) > 5.0)  # specific force of a flying body
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_seeded_rollouts_identical_and_inside_space(env_id):
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.3, 0.3, size=(40, 4)).astype(np.float32)
    env_a = gymnasium.make(env_id, action_type="position", **FAST)
    env_b = gymnasium.make(env_id, action_type="position", **FAST)
    ra, rb = _rollout(env_a, actions, seed=7), _rollout(env_b, actions, seed=7)
    assert len(ra) == len(rb)
    np.testing.assert_array_equal(ra[0], rb[0])
    for (oa, rwa, ta, tra), (ob, rwb, tb, trb) in zip(ra[1:], rb[1:], strict=True):
        np.testing.assert_array_equal(oa, ob)
        assert rwa == rwb and ta == tb and tra == trb
        assert env_a.observation_space.contains(oa)
    other = _rollout(env_a, actions, seed=8)
    assert not np.array_equal(other[0], ra[0])
    env_a.close()
    env_b.close()


def test_msckf_rollout_deterministic():
    actions = np.zeros((15, 4), dtype=np.float32)
    kw = {"estimator": "msckf", "frontend": "sim", "action_type": "position"}
    ra = _rollout(gymnasium.make("viotb/Hover-v0", **kw), actions, seed=2)
    rb = _rollout(gymnasium.make("viotb/Hover-v0", **kw), actions, seed=2)
    for a, b in zip(ra[1:], rb[1:], strict=True):
        np.testing.assert_array_equal(a[0], b[0])


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_reward_is_sum_of_components(env_id):
    env = gymnasium.make(env_id, action_type="velocity", **FAST)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        _, reward, terminated, _, info = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        comps = info["reward_components"]
        assert {"tracking", "effort", "smoothness", "crash"} <= set(comps)
        assert reward == pytest.approx(sum(comps.values()), abs=1e-12)
        for name, value in comps.items():
            assert info[f"reward_{name}"] == value
        if terminated:
            break
    env.close()


def test_reward_terms_closed_form():
    assert reward_tracking(0.0, 2.0, 0.5) == pytest.approx(2.0, abs=1e-15)
    assert reward_tracking(0.5, 1.0, 0.5) == pytest.approx(np.exp(-1.0), abs=1e-15)
    a, n = np.array([0.5, 0.0, -0.5, 1.0]), np.array([0.0, 0.0, 0.0, 0.5])
    assert cost_effort(a, n, 0.1) == pytest.approx(-0.1 * (0.25 + 0.25 + 0.25), abs=1e-15)
    assert cost_smoothness(a, a, 3.0) == 0.0
    assert cost_crash(True, 10.0) == -10.0 and cost_crash(False, 10.0) == 0.0


def test_orientation_features_against_independent_forms():
    rng = np.random.default_rng(0)
    R = exp_so3(rng.normal(size=3))
    np.testing.assert_allclose(orientation_features(R, "rot6d"), np.r_[R[:, 0], R[:, 1]], atol=0)
    q = orientation_features(R, "quat")
    assert q[0] >= 0.0
    q_ref = rotmat_to_quat_wxyz(R)
    np.testing.assert_allclose(q, q_ref * np.sign(q_ref[0]), atol=1e-15)


def test_hover_position_hold_and_truth_only_in_info():
    env = gymnasium.make(
        "viotb/Hover-v0", action_type="position", randomization=DomainRandomization(), **FAST
    )
    obs, info = env.reset(seed=0)
    names = env.unwrapped.state_names()
    assert len(names) == obs.shape[0] == 28
    for _ in range(150):  # 3 s with the SE(3) controller on the target
        obs, reward, terminated, _, info = env.step(np.zeros(4, dtype=np.float32))
    assert not terminated
    # Observation (estimate == truth here) minus target matches the info's truth within float32 rounding.
    p_rel = obs[[names.index(f"p_rel_W_m[{i}]") for i in range(3)]]
    np.testing.assert_allclose(p_rel, info["p_true_W_m"] - info["target_W_m"], atol=1e-6)
    assert info["position_error_m"] < 0.03  # no wind: the controller settles on the point
    assert reward == pytest.approx(sum(info["reward_components"].values()), abs=1e-12)
    env.close()


def test_motor_thrust_all_off_falls_and_terminates():
    env = gymnasium.make("viotb/Hover-v0", action_type="motors", **FAST)
    env.reset(seed=0)
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(-np.ones(4, dtype=np.float32))
        if terminated:
            break
    assert terminated and not truncated
    assert info["termination_reason"] in ("crashed", "left_arena")
    assert info["reward_components"]["crash"] == -HoverEnvConfig().rewards.crash
    env.close()


def test_vector_envs_run():
    fns = [lambda: gymnasium.make("viotb/Hover-v0", action_type="position", **FAST) for _ in range(2)]
    for vec_cls in (gymnasium.vector.SyncVectorEnv, gymnasium.vector.AsyncVectorEnv):
        venv = vec_cls(fns)
        obs, _ = venv.reset(seed=0)
        assert obs.shape == (2, 28)
        for _ in range(3):
            obs, rewards, term, trunc, _ = venv.step(np.zeros((2, 4), dtype=np.float32))
        assert obs.shape == (2, 28) and rewards.shape == (2,) and np.all(np.isfinite(obs))
        venv.close()


def test_bad_actions_raise_clear_errors():
    env = gymnasium.make("viotb/Hover-v0", **FAST)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(4,\)"):
        env.unwrapped.step(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        env.unwrapped.step(np.array([0.0, np.nan, 0.0, 0.0]))
    env.close()


@pytest.mark.parametrize(
    ("kwargs", "listed"),
    [
        ({"action_type": "torque"}, "'motors', 'ctbr', 'velocity', 'position'"),
        ({"estimator": "ekf"}, "'msckf', 'window', 'imu-only', 'ground-truth'"),
        ({"frontend": "orb"}, "'klt', 'sim'"),
        ({"obs_mode": "pixels"}, "'state', 'dict'"),
        ({"imu_preset": "nope"}, "adis16448"),
        ({"no_such_option": 1}, "action_type"),
    ],
)
def test_unknown_kwargs_rejected_with_allowed_values(kwargs, listed):
    with pytest.raises(ValueError, match="allowed") as excinfo:
        gymnasium.make("viotb/Hover-v0", **kwargs)
    assert listed in str(excinfo.value)


def test_bad_periods_and_ranges_rejected():
    with pytest.raises(ValueError, match="whole multiple"):
        HoverEnv(estimator="ground-truth", ctrl_dt=0.0125)
    with pytest.raises(ValueError, match="mass_scale"):
        DomainRandomization(mass_scale=(1.2, 0.8))


def test_ctrl_dt_sets_substeps():
    env = HoverEnv(estimator="ground-truth", ctrl_dt=0.01)
    assert env.sim_dt == pytest.approx(0.001) and env.n_substeps == 10 and env.dt == 0.01
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(4))
    assert info["t_s"] == pytest.approx(0.01, abs=1e-12)
    env.close()


def test_domain_randomization_draws_from_reset_seed():
    dr = DomainRandomization(mass_scale=(0.8, 1.2), imu_noise_scale=(0.5, 2.0), wind_gust_sigma_N=(0.5, 1.0))
    env = HoverEnv(estimator="imu-only", randomization=dr)
    masses = []
    for seed in (0, 0, 1):
        env.reset(seed=seed)
        m = env.unwrapped.rig.sim.model
        masses.append(float(m.body_mass[m.body("quadrotor").id]))
    assert masses[0] == masses[1] != masses[2]
    assert all(0.8 * 1.2 <= x <= 1.2 * 1.2 for x in masses)
    env.close()


def test_render_rgb_array_chase_and_onboard():
    env = gymnasium.make(
        "viotb/Hover-v0", render_mode="rgb_array", render_width=160, render_height=120, **FAST
    )
    env.reset(seed=0)
    img = env.render()
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8 and img.std() > 1.0
    onboard = env.unwrapped.render_camera("onboard")
    assert onboard.shape == (120, 160, 3) and not np.array_equal(onboard, img)
    with pytest.raises(ValueError, match="allowed"):
        env.unwrapped.render_camera("top")
    env.close()


def test_waypoints_reached_in_order_with_position_action():
    env = gymnasium.make(
        "viotb/Waypoints-v0", action_type="position", n_waypoints=2, position_range_m=0.0, **FAST
    )
    env.reset(seed=0)
    bonuses, info = 0.0, {}
    for _ in range(400):
        _, _, terminated, _, info = env.step(np.zeros(4, dtype=np.float32))
        bonuses += info["reward_components"]["waypoint"]
        if terminated:
            break
    assert info["termination_reason"] == "success"
    assert bonuses == pytest.approx(2 * HoverEnvConfig().rewards.waypoint)
    env.close()


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ({"ctrl_dt": "0.02"}, "ctrl_dt"),
        ({"start_p_W_m": (0.0, 0.0)}, "start_p_W_m"),
        ({"start_position_sigma_m": -1.0}, "start_position_sigma_m"),
        ({"camera_width": -5}, "camera_width"),
        ({"position_range_m": float("nan")}, "position_range_m"),
        ({"render_width": 0}, "render_width"),
        ({"max_speed_m_s": -1.0}, "max_speed_m_s"),
        ({"max_target_distance_m": -1.0}, "max_target_distance_m"),
        ({"arena_margin_m": 100.0}, "arena_margin_m"),
    ],
)
def test_constructor_arguments_are_validated_naming_the_field(override, field):
    with pytest.raises(ValueError, match=rf"HoverEnvConfig\.{field}"):
        gymnasium.make("viotb/Hover-v0", **override)


def test_step_after_terminated_without_reset_raises():
    env = gymnasium.make("viotb/Hover-v0", estimator="ground-truth", action_type="motors")
    env.reset(seed=0)
    terminated = False
    for _ in range(500):  # motors off: the drone falls and crashes
        _, _, terminated, _, info = env.step(np.full(4, -1.0, dtype=np.float32))
        if terminated:
            break
    assert terminated and info["termination_reason"] in ("crashed", "left_arena", "too_far")
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros(4, dtype=np.float32))
    env.reset(seed=1)
    env.step(np.zeros(4, dtype=np.float32))
    env.close()
