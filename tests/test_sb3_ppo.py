"""`train.sb3_ppo.SharedPPO`: the same weights as SB3's PPO bit for bit, distribution checks off
only inside `learn`."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from train.ppo import make_args, model_and_env
from train.sb3_ppo import OPTIMIZER_KWARGS, SharedPPO
from uavtrack_env.wrappers.sb3 import AgentVecMonitor, VectorSharedPolicyVecEnv

SMALL = {"n_steps": 32, "batch_size": 48, "n_epochs": 2, "seed": 0, "device": "cpu"}


def _trained(cls: type, **policy_kwargs) -> list[np.ndarray]:
    vec = AgentVecMonitor(VectorSharedPolicyVecEnv(2, scenario="random", max_cycles=40))
    vec.seed(3)
    model = cls("MlpPolicy", vec, policy_kwargs=policy_kwargs or None, **SMALL)
    model.learn(total_timesteps=384)
    vec.close()
    return [p.detach().numpy().copy() for p in model.policy.parameters()]


def test_shared_ppo_trains_the_weights_of_sb3s_ppo_bit_for_bit():
    plain = _trained(PPO)
    shared = _trained(SharedPPO, optimizer_kwargs=OPTIMIZER_KWARGS)
    assert all(np.array_equal(a, b) for a, b in zip(plain, shared, strict=True))
    torch.manual_seed(0)
    vec = VectorSharedPolicyVecEnv(2, scenario="random")
    untrained = PPO("MlpPolicy", vec, **SMALL)
    vec.close()
    before = [p.detach().numpy() for p in untrained.policy.parameters()]
    assert not all(np.array_equal(a, b) for a, b in zip(before, shared, strict=True))


class _Seen(BaseCallback):
    """Records whether distributions are validated during rollouts; optionally raises."""

    def __init__(self, fail: bool = False) -> None:
        super().__init__()
        self.seen: list[bool] = []
        self.fail = fail

    def _on_step(self) -> bool:
        self.seen.append(torch.distributions.Distribution._validate_args)
        if self.fail:
            raise KeyboardInterrupt
        return True


@pytest.mark.parametrize("fail", [False, True])
def test_learn_checks_distributions_again_on_return_or_error(fail):
    vec = AgentVecMonitor(VectorSharedPolicyVecEnv(1, scenario="random", max_cycles=20))
    model = SharedPPO("MlpPolicy", vec, **SMALL)
    seen = _Seen(fail)
    before = torch.distributions.Distribution._validate_args
    if fail:
        with pytest.raises(KeyboardInterrupt):
            model.learn(total_timesteps=96, callback=seen)
    else:
        model.learn(total_timesteps=96, callback=seen)
    vec.close()
    assert seen.seen and not any(seen.seen)
    assert torch.distributions.Distribution._validate_args is before


def test_train_ppo_builds_shared_ppo_with_foreach_adam(tmp_path):
    model, vec = model_and_env(make_args(out=tmp_path, shield=False, n_envs=1, n_steps=16))
    vec.close()
    assert isinstance(model, SharedPPO)
    assert model.policy.optimizer.defaults["foreach"] is True
    assert model.policy.optimizer.defaults["eps"] == 1e-5
