"""`train.sb3_ppo.LinearSkipPolicy`: the actor's mean is its MLP's output plus a linear map of the
observation; `train.ppo --linear-skip` builds it and it loads back."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import torch
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv

from baselines.compare import load_policy
from tests.test_train_bc import _Box
from train.ppo import make_args, model_and_env
from train.sb3_ppo import LinearSkipPolicy, SharedPPO


def _mean(model, x: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model.policy.get_distribution(torch.as_tensor(x)).distribution.mean.numpy()


def test_the_mean_is_the_mlp_output_plus_a_linear_map_of_the_observation():
    model = PPO(LinearSkipPolicy, DummyVecEnv([_Box]), seed=0, device="cpu")
    policy = model.policy
    net = policy.action_net
    hidden = policy.mlp_extractor.policy_net[-2].out_features
    assert net.in_features == hidden + 5
    assert policy.mlp_extractor.latent_dim_vf == hidden  # the critic is SB3's
    rng = np.random.default_rng(0)
    A, B, b = rng.normal(size=(2, hidden)), rng.normal(size=(2, 5)), rng.normal(size=2)
    with torch.no_grad():
        net.weight.copy_(torch.as_tensor(np.hstack([A, B]), dtype=torch.float32))
        net.bias.copy_(torch.as_tensor(b, dtype=torch.float32))
    x = rng.uniform(-3, 3, (64, 5)).astype(np.float32)
    with torch.no_grad():
        mlp = policy.mlp_extractor.policy_net(torch.as_tensor(x)).numpy()
    np.testing.assert_allclose(_mean(model, x), mlp @ A.T + x @ B.T + b, rtol=1e-5, atol=1e-5)
    # far out, the MLP's part stays bounded while the linear part grows with the input
    far = 100.0 * x
    with torch.no_grad():
        mlp_far = policy.mlp_extractor.policy_net(torch.as_tensor(far)).numpy()
    assert np.abs(mlp_far).max() <= 1.0
    np.testing.assert_allclose(_mean(model, far), mlp_far @ A.T + far @ B.T + b, rtol=1e-4)


def test_train_ppo_builds_the_skip_actor_on_request_and_it_loads_back(tmp_path):
    model, vec = model_and_env(make_args(out=tmp_path, shield=False, n_envs=1, n_steps=16))
    vec.close()
    assert type(model.policy) is not LinearSkipPolicy
    args = make_args(out=tmp_path, shield=False, n_envs=1, n_steps=16, linear_skip=True)
    model, vec = model_and_env(args)
    assert isinstance(model, SharedPPO) and isinstance(model.policy, LinearSkipPolicy)
    obs = vec.reset()
    model.save(tmp_path / "skip.zip")
    vec.close()
    loaded = load_policy(tmp_path / "skip.zip", None, 1).model
    assert isinstance(loaded.policy, LinearSkipPolicy)
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0]
    )
