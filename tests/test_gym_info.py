"""``info="flat"`` (envs/gym/info.py): the scalar entries of the full info, the same values, nothing else."""

import numpy as np
import pytest
from viotb.envs.gym.hover import HoverEnv


def _infos(info_mode: str, n_steps: int = 30) -> list[dict]:
    env = HoverEnv(estimator="ground-truth", frontend="sim", action_type="position", info=info_mode)
    rng = np.random.default_rng(4)
    out = [env.reset(seed=2)[1]]
    for _ in range(n_steps):
        out.append(env.step(rng.uniform(-0.2, 0.2, 4).astype(np.float32))[4])
    env.close()
    return out


def test_flat_info_is_the_full_infos_scalars():
    full, flat = _infos("full"), _infos("flat")
    assert "reward_tracking" in flat[-1] and "termination_reason" in flat[-1]
    for f, s in zip(full, flat, strict=True):
        scalar_keys = [k for k, v in f.items() if isinstance(v, float | int | str)]
        assert list(s) == scalar_keys  # same keys, same order, only scalars
        dropped = {"p_true_W_m", "v_true_W_m_s", "R_true_WB", "target_W_m", "conditions", "reward_components"}
        assert set(f) - set(s) == dropped
        for k in scalar_keys:
            assert s[k] == f[k] or (np.isnan(s[k]) and np.isnan(f[k])), k
        assert all(type(v) in (float, int, str) for v in s.values())


def test_unknown_info_mode_names_the_field():
    with pytest.raises(ValueError, match=r"HoverEnvConfig\.info: unknown value 'lean'.*'full', 'flat'"):
        HoverEnv(info="lean")
