"""``make_vector_env``: the vector copies step like single envs, and its workers keep to one thread."""

from __future__ import annotations

import os
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
import viotb.envs  # noqa: F401  (registers the ids)
from viotb.envs.gym.vector import make_vector_env

KWARGS = {"action_type": "position", "estimator": "ground-truth", "frontend": "sim"}


def _single_rollout(seed: int, actions: np.ndarray) -> list[np.ndarray]:
    env = gymnasium.make("viotb/Hover-v0", **KWARGS)
    out = [env.reset(seed=seed)[0]]
    out += [env.step(a)[0] for a in actions]
    env.close()
    return out


@pytest.mark.parametrize("mode", ["sync", pytest.param("async", marks=pytest.mark.slow)])  # async: spawns
def test_vector_copies_match_single_envs(mode):
    """Copy i of a vector reset with seed s is the single env reset with seed s + i, step for step."""
    rng = np.random.default_rng(1)
    actions = rng.uniform(-0.3, 0.3, size=(4, 2, 4)).astype(np.float32)
    vec = make_vector_env("viotb/Hover-v0", 2, mode, **KWARGS)
    obs = [vec.reset(seed=10)[0]]
    obs += [vec.step(a)[0] for a in actions]
    vec.close()
    for i in range(2):
        expected = _single_rollout(10 + i, actions[:, i])
        for k, (got, want) in enumerate(zip((o[i] for o in obs), expected, strict=True)):
            np.testing.assert_array_equal(got, want, err_msg=f"copy {i} step {k}")


def test_worker_thread_limits():
    """A worker process runs OpenCV and BLAS on one thread and tells llvmpipe to."""
    code = (
        "import os, cv2\n"
        "from threadpoolctl import threadpool_info\n"
        "from viotb.envs.gym.vector import limit_worker_threads\n"
        "limit_worker_threads()\n"
        "blas = max([i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'] or [1])\n"
        "print(cv2.getNumThreads(), blas, os.environ['LP_NUM_THREADS'])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["1", "1", "1"]


def test_make_vector_env_rejects_bad_arguments():
    with pytest.raises(ValueError, match="'async', 'sync'"):
        make_vector_env(mode="threads")
    with pytest.raises(ValueError, match="num_envs"):
        make_vector_env(num_envs=0)
