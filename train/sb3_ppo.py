"""SB3's PPO as `train.ppo` runs it: the same algorithm and numbers, less per-minibatch overhead.

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
