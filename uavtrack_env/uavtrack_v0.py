"""PettingZoo-style versioned entry points: ``parallel_env``, ``env`` (AEC), ``raw_env`` and
``vector_env`` (K worlds as arrays)."""

from __future__ import annotations

from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec_wrapper
from pettingzoo.utils.wrappers import OrderEnforcingWrapper

from .env import UAVTrackEnv
from .vector import UAVTrackVectorEnv


def raw_env(**kwargs: Any) -> UAVTrackEnv:
    """The unwrapped ParallelEnv (the env is parallel-native)."""
    return UAVTrackEnv(**kwargs)


def parallel_env(**kwargs: Any) -> UAVTrackEnv:
    """The ParallelEnv; keyword arguments are the fields of ``EnvConfig`` (e.g. max_cycles)."""
    return UAVTrackEnv(**kwargs)


class _AECEnv(parallel_to_aec_wrapper):
    """PettingZoo's parallel-to-AEC conversion that checks each agent's action when that agent
    steps, not when the last one completes the joint action (a bad action changes nothing)."""

    def step(self, action: Any) -> None:
        agent = self.agent_selection
        if action is not None and not (self.terminations[agent] or self.truncations[agent]):
            UAVTrackEnv.check_action(agent, action)
        super().step(action)


def env(**kwargs: Any):
    """The AEC version, as PettingZoo's ``parallel_to_aec`` builds it (order enforced)."""
    return OrderEnforcingWrapper(_AECEnv(UAVTrackEnv(**kwargs)))


def vector_env(num_envs: int, full_infos: bool = False, **kwargs: Any) -> UAVTrackVectorEnv:
    """K = ``num_envs`` worlds of the same ``EnvConfig`` stepped as arrays (K, n, ...), world k
    seeded s + k, autoreset (`uavtrack_env.vector`)."""
    return UAVTrackVectorEnv(num_envs, full_infos=full_infos, **kwargs)
