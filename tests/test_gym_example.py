"""The stable-baselines3 hover example runs end to end (a few hundred steps) and reports both estimators."""

from __future__ import annotations

import json
import os

import gymnasium
import numpy as np
import pytest
from data_paths import load_repo_script

os.environ.setdefault("MUJOCO_GL", "egl")


def _load_example():
    return load_repo_script("examples/train_hover_sb3.py")


def test_kinematic_observation_drops_health_entries():
    example = _load_example()
    env = example.make_env("msckf", "sim", "position", episode_steps=5)
    obs, _ = env.reset(seed=0)
    names = env.unwrapped.state_names()
    assert obs.shape == (len(names) - 7,)  # 3 + 3 covariance entries and the feature count
    assert env.observation_space.contains(obs)
    full_env = gymnasium.make("viotb/Hover-v0", estimator="msckf", frontend="sim", action_type="position")
    full, _ = full_env.reset(seed=0)
    kept = [i for i, n in enumerate(names) if not n.startswith(example.HEALTH_PREFIXES)]
    np.testing.assert_array_equal(obs, full[kept])
    env.close()
    full_env.close()


def test_train_and_evaluate_few_hundred_steps(capsys):
    pytest.importorskip(
        "stable_baselines3", reason="the 'rl' extra (stable-baselines3, torch) is not installed"
    )
    example = _load_example()
    result = example.main(
        ["--timesteps", "256", "--episode-steps", "40", "--eval-episodes", "1", "--no-subproc"]
    )
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed == result
    for name in ("ground_truth", "msckf_sim", "zero_action_ground_truth", "zero_action_msckf_sim"):
        r = result[name]
        assert r["episodes"] == 1 and 1 <= r["steps"] <= 40
        assert np.isfinite(r["mean_return"]) and r["hover_rms_m"] >= 0.0
        assert r["crash_rate"] == r["failed_episodes"] / r["episodes"]
    assert result["ground_truth"]["estimate_rms_m"] == 0.0  # truth passed through
    assert result["msckf_sim"]["estimate_rms_m"] > 0.0
    assert result["gap"]["mean_return"] == pytest.approx(
        result["ground_truth"]["mean_return"] - result["msckf_sim"]["mean_return"], abs=1e-12
    )
    assert gymnasium.spec("viotb/Hover-v0") is not None


def test_zero_action_baseline_is_the_velocity_hold():
    # The zero-action baseline is "hold zero velocity where you are": with wind it drifts, so it must not be
    # a hover controller in disguise (which a policy could never beat). Same seed, truth observations.
    example = _load_example()
    env = example.make_env("ground-truth", "sim", "velocity", episode_steps=50)
    result = example.evaluate(lambda obs: np.zeros(4, dtype=np.float32), env, episodes=1, seed=3)
    assert result["steps"] == 50 and result["failed_episodes"] == 0
    obs, _ = env.reset(seed=3)
    p0 = obs[:3].copy()  # estimated position minus target at the start (truth here)
    for _ in range(50):
        obs, *_ = env.step(np.zeros(4, dtype=np.float32))
    # It does not steer back: the offset from the target is not reduced below half of the initial one.
    assert np.linalg.norm(obs[:3]) > 0.5 * np.linalg.norm(p0)
    env.close()


@pytest.mark.slow
def test_default_budget_policy_beats_zero_action_on_truth():
    pytest.importorskip(
        "stable_baselines3", reason="the 'rl' extra (stable-baselines3, torch) is not installed"
    )
    example = _load_example()
    result = example.main([])  # the default training budget and evaluation
    trained, zero = result["ground_truth"], result["zero_action_ground_truth"]
    assert trained["crash_rate"] == 0.0
    assert trained["mean_return"] > zero["mean_return"]
    assert trained["hover_rms_m"] < 0.7 * zero["hover_rms_m"]
