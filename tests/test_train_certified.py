"""PPO learning from the shield's certified actions (`train.callbacks.CertifiedActions`)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import torch
from stable_baselines3.common.callbacks import BaseCallback

from train import ppo
from train.callbacks import CertifiedActions
from train.sb3_ppo import SharedPPO
from uavtrack_env.wrappers.sb3 import VectorSharedPolicyVecEnv


class _Certified(BaseCallback):
    """Keeps each step's certified actions and the proposals PPO sampled."""

    def __init__(self) -> None:
        super().__init__()
        self.certified: list[np.ndarray] = []
        self.proposed: list[np.ndarray] = []

    def _on_step(self) -> bool:
        self.certified.append(np.array([i["shield"]["action"] for i in self.locals["infos"]]))
        self.proposed.append(self.locals["clipped_actions"].copy())
        return True


def test_the_rollout_buffer_holds_the_certified_actions_and_their_log_probabilities():
    vec = VectorSharedPolicyVecEnv(2, shield="tuned", scenario="random", max_cycles=50)
    model = SharedPPO(
        "MlpPolicy", vec, n_steps=16, batch_size=32, n_epochs=1, learning_rate=0.0, seed=3,
        device="cpu", policy_kwargs={"log_std_init": 0.0},
    )  # fmt: skip
    seen = _Certified()
    model.learn(total_timesteps=16 * vec.num_envs, callback=[seen, CertifiedActions()])
    # after the update SB3's buffer is flattened row-major: row 0's steps, then row 1's, ...
    certified = np.stack(seen.certified).swapaxes(0, 1).reshape(-1, 4)
    proposed = np.stack(seen.proposed).swapaxes(0, 1).reshape(-1, 4)
    stored = model.rollout_buffer.actions
    np.testing.assert_allclose(stored, certified, atol=1e-6)
    # wide random proposals: the shield changed some of them, so the test could fail
    assert (np.abs(proposed - certified).max(axis=-1) > 1e-3).any()
    with torch.no_grad():  # learning rate 0: the policy that acted is the one stored
        buf = model.rollout_buffer.observations
        obs = torch.as_tensor(buf.reshape(-1, buf.shape[-1]))
        logp = model.policy.get_distribution(obs).log_prob(torch.as_tensor(stored))
    np.testing.assert_allclose(
        model.rollout_buffer.log_probs.reshape(-1), logp.numpy(), rtol=1e-5, atol=1e-5
    )


def test_learn_certified_needs_the_shield(tmp_path):
    with pytest.raises(ValueError, match="--learn-certified needs"):
        ppo.main(["--no-shield", "--learn-certified", "--out", str(tmp_path / "x")])
