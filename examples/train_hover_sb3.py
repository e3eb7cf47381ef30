"""Train a hover policy on ground-truth observations, then fly it on the MSCKF's estimate: the sim-to-VIO gap.

Needs the ``rl`` extra (``pip install -e .[rl]``: stable-baselines3 and torch). Usage::

    python examples/train_hover_sb3.py --timesteps 50000

1. Train PPO (stable-baselines3) on ``viotb/Hover-v0`` with ``estimator="ground-truth"`` (fast: the
   observation is the truth).
2. Evaluate the same policy, deterministically and with the same seeds, on ground-truth observations and on
   ``estimator="msckf", frontend="sim"`` observations (VIO on simulated features).
3. Print one JSON object: mean return and true hover RMS error (m) of both, and their differences.

The policy sees only the kinematic part of the observation (:class:`KinematicObservation` drops the
estimator-health entries: the ground-truth estimator reports zero covariance and no features, so a policy
trained on it would meet out-of-range inputs under the MSCKF for a reason unrelated to estimation error).
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium
import numpy as np
import viotb.envs  # noqa: F401  (registers the ids)

HEALTH_PREFIXES = ("var_p_m2", "var_v_m2_s2", "tracked_features")
"""State entries describing the estimator's health (dropped by :class:`KinematicObservation`)."""


class KinematicObservation(gymnasium.ObservationWrapper):
    """Keep the kinematic entries of the flat state observation (pose, velocity, rate, target).

    Args:
        env: A ``viotb`` env with ``obs_mode="state"``.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        """Select the entries whose names do not start with :data:`HEALTH_PREFIXES`."""
        super().__init__(env)
        names = env.unwrapped.state_names()
        self._keep = np.array([i for i, n in enumerate(names) if not n.startswith(HEALTH_PREFIXES)])
        box = env.observation_space
        self.observation_space = gymnasium.spaces.Box(
            box.low[self._keep], box.high[self._keep], dtype=np.float32
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        """The kept entries."""
        return observation[self._keep]


def make_env(estimator: str, frontend: str, action_type: str, episode_steps: int) -> gymnasium.Env:
    """``viotb/Hover-v0`` with the given estimator and the kinematic observation."""
    env = gymnasium.make(
        "viotb/Hover-v0",
        estimator=estimator,
        frontend=frontend,
        action_type=action_type,
        max_episode_steps=episode_steps,
    )
    return KinematicObservation(env)


def evaluate(model, env: gymnasium.Env, episodes: int, seed: int) -> dict:
    """Deterministic rollouts: mean return, true hover RMS (m), estimate RMS error (m), failures."""
    returns, sq_err, sq_est, failures, steps = [], [], [], 0, 0
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            sq_err.append(info["position_error_m"] ** 2)
            sq_est.append(info["estimate_error_m"] ** 2)
            steps += 1
            done = terminated or truncated
        failures += int(info["termination_reason"] not in ("", "success"))
        returns.append(total)
    return {
        "mean_return": float(np.mean(returns)),
        "hover_rms_m": float(np.sqrt(np.mean(sq_err))),
        "estimate_rms_m": float(np.sqrt(np.mean(sq_est))),
        "failed_episodes": failures,
        "episodes": episodes,
        "steps": steps,
    }


def main(argv: list[str] | None = None) -> dict:
    """Train, evaluate on both observation sources, print the JSON summary (last line) and return it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=50_000, help="PPO training steps")
    parser.add_argument("--action-type", default="velocity", help="motors, ctbr, velocity or position")
    parser.add_argument("--episode-steps", type=int, default=250, help="steps per episode (0.02 s each)")
    parser.add_argument("--eval-episodes", type=int, default=3, help="evaluation episodes per estimator")
    parser.add_argument("--seed", type=int, default=0, help="training and evaluation seed")
    parser.add_argument(
        "--log-std-init",
        type=float,
        default=-1.0,
        help="initial log std of the Gaussian policy (SB3 default 0 explores so wildly with setpoint "
        "actions that most early episodes leave the arena)",
    )
    parser.add_argument("--save", default=None, help="optional path to save the trained policy (.zip)")
    args = parser.parse_args(argv)
    if args.timesteps < 1 or args.episode_steps < 1 or args.eval_episodes < 1:
        parser.error("--timesteps, --episode-steps and --eval-episodes must be >= 1")
    try:
        from stable_baselines3 import PPO
    except ImportError as exc:
        raise SystemExit(f"this example needs the 'rl' extra (pip install -e .[rl]): {exc}") from None

    train_env = make_env("ground-truth", "sim", args.action_type, args.episode_steps)
    n_steps = int(min(2048, max(64, args.timesteps)))
    model = PPO(
        "MlpPolicy",
        train_env,
        n_steps=n_steps,
        batch_size=min(64, n_steps),
        seed=args.seed,
        policy_kwargs={"log_std_init": args.log_std_init},
        device="cpu",
        verbose=0,
    )
    model.learn(total_timesteps=args.timesteps)
    if args.save:
        model.save(args.save)
    train_env.close()

    results = {"timesteps": args.timesteps, "action_type": args.action_type}
    for name, (estimator, frontend) in {
        "ground_truth": ("ground-truth", "sim"),
        "msckf_sim": ("msckf", "sim"),
    }.items():
        env = make_env(estimator, frontend, args.action_type, args.episode_steps)
        results[name] = evaluate(model, env, args.eval_episodes, seed=1000 + args.seed)
        env.close()
    results["gap"] = {
        "mean_return": results["ground_truth"]["mean_return"] - results["msckf_sim"]["mean_return"],
        "hover_rms_m": results["msckf_sim"]["hover_rms_m"] - results["ground_truth"]["hover_rms_m"],
    }
    print(json.dumps(results))
    return results


if __name__ == "__main__":
    main()
