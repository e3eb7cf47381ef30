"""Vector envs of the viotb tasks with one compute thread per worker (``make_vector_env``).

A single env may use every core: Mesa's llvmpipe renders with one thread per CPU (``LP_NUM_THREADS``) and
OpenCV's KLT runs its ``parallel_for_`` over all cores. K workers on K cores then each ask for K threads and
the machine thrashes. The workers built here limit OpenCV, llvmpipe and BLAS to one thread before the env
(and its GL context) exists, so each worker keeps to its own core (the usual rule for vectorized RL
workers, cf. Stable-Baselines3's ``SubprocVecEnv`` guidance and ``torch.set_num_threads(1)``).
"""

from __future__ import annotations

import os
from functools import partial

import gymnasium

VECTOR_MODES = ("async", "sync")
"""``async``: ``gymnasium.vector.AsyncVectorEnv`` (one spawned worker process per copy); ``sync``: a
``SyncVectorEnv`` in this process."""


def limit_worker_threads() -> None:
    """One thread for OpenCV, Mesa llvmpipe and BLAS in this process (a vector-env worker).

    llvmpipe reads ``LP_NUM_THREADS`` when the GL context is created, so call this before the first env;
    an explicit user setting of ``LP_NUM_THREADS`` wins.
    """
    os.environ.setdefault("LP_NUM_THREADS", "1")
    import cv2
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    threadpool_limits(1)


def _make_worker_env(env_id: str, kwargs: dict) -> gymnasium.Env:
    """A worker's env: threads limited first (module level, so a spawned worker can unpickle it)."""
    limit_worker_threads()
    import viotb.envs  # noqa: F401  (registers the ids in a fresh interpreter)

    return gymnasium.make(env_id, **kwargs)


def make_vector_env(
    env_id: str = "viotb/Hover-v0", num_envs: int = 2, mode: str = "async", **kwargs
) -> gymnasium.vector.VectorEnv:
    """``num_envs`` copies of ``env_id`` (``kwargs`` as for ``gymnasium.make``) in a vector env.

    ``async`` workers are spawned (a fresh interpreter: no GL context or thread pool inherited from this
    process) and each limits its threads (:func:`limit_worker_threads`); ``sync`` copies run in this process
    and leave its threads alone. Pass ``info="flat"`` for training: the vector env merges every ``info`` key
    of every copy at every step, and the flat form keeps only the scalars (:mod:`viotb.envs.gym.info`).

    Raises:
        ValueError: Unknown ``mode`` or ``num_envs < 1``.
    """
    if mode not in VECTOR_MODES:
        raise ValueError(f"unknown vector mode {mode!r}; allowed: {', '.join(map(repr, VECTOR_MODES))}")
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    if mode == "sync":
        return gymnasium.vector.SyncVectorEnv([partial(gymnasium.make, env_id, **kwargs)] * num_envs)
    fns = [partial(_make_worker_env, env_id, kwargs) for _ in range(num_envs)]
    return gymnasium.vector.AsyncVectorEnv(fns, context="spawn")
