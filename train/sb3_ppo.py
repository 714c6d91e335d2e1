"""SB3's PPO as `train.ppo` runs it: the same algorithm and numbers, less per-minibatch overhead,
and the optional actor with a linear skip (`LinearSkipPolicy`).

Two settings that change no parameter (a seeded run gives the same weights bit for bit):

- Adam's ``foreach`` implementation (`OPTIMIZER_KWARGS`): one kernel per step over all tensors
  instead of a Python loop per tensor; SB3's default ``eps`` is kept.
- torch's argument checks of the action distribution are off inside `SharedPPO.learn`. Each
  rollout step and minibatch builds a Gaussian whose check costs more than its arithmetic; the
  env checks every action it receives (a NaN action raises there) instead.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch
from stable_baselines3 import PPO
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import MlpExtractor

OPTIMIZER_KWARGS: dict[str, Any] = {"eps": 1e-5, "foreach": True}
"""Adam's settings: SB3's default for PPO (``eps`` 1e-5) with the ``foreach`` implementation."""


@contextlib.contextmanager
def unchecked_distributions() -> Iterator[None]:
    """torch.distributions without argument validation, restored on exit."""
    before = torch.distributions.Distribution._validate_args
    torch.distributions.Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        torch.distributions.Distribution.set_default_validate_args(before)


class SharedPPO(PPO):
    """SB3's PPO whose `learn` builds its action distributions unchecked."""

    def learn(self, *args: Any, **kwargs: Any) -> SharedPPO:
        with unchecked_distributions():
            return super().learn(*args, **kwargs)


class LinearSkipExtractor(MlpExtractor):
    """SB3's MlpExtractor whose actor latent is [MLP(features), features]: the action layer on
    top of it is then the MLP's output plus a linear map of the features."""

    def __init__(self, feature_dim: int, *args: Any, **kwargs: Any) -> None:
        super().__init__(feature_dim, *args, **kwargs)
        self.latent_dim_pi += feature_dim

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.policy_net(features), features], dim=-1)


class LinearSkipPolicy(ActorCriticPolicy):
    """SB3's MlpPolicy whose action mean adds a linear map of the (normalised) observation to
    the MLP's output (`train.ppo --linear-skip`).

    A tanh MLP fitted to the expert saturates outside the states it was fitted on, so a UAV that
    drifts further from its reference than any demonstration gets a command of no particular
    sign. The linear part is a fitted feedback that keeps growing with the observation (up to
    VecNormalize's clip) where the MLP's part stays bounded. The value network is SB3's.
    docs/results/rl-training.md measures what it changes.
    """

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = LinearSkipExtractor(
            self.features_dim,
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            device=self.device,
        )
