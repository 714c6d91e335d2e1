"""PettingZoo-style versioned entry points: ``parallel_env``, ``env`` (AEC) and ``raw_env``."""

from __future__ import annotations

from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec

from .env import UAVTrackEnv


def raw_env(**kwargs: Any) -> UAVTrackEnv:
    """The unwrapped ParallelEnv (the env is parallel-native)."""
    return UAVTrackEnv(**kwargs)


def parallel_env(**kwargs: Any) -> UAVTrackEnv:
    """The ParallelEnv; keyword arguments are the fields of ``EnvConfig`` (e.g. max_cycles)."""
    return UAVTrackEnv(**kwargs)


def env(**kwargs: Any):
    """The AEC version, through PettingZoo's ``parallel_to_aec``."""
    return parallel_to_aec(UAVTrackEnv(**kwargs))
