"""Wrappers: ``CBFShield`` (safety shield; ``VectorCBFShield`` the same over ``vector_env``),
``SafeRLParallelEnv`` (Safety-Gymnasium's step with costs), ``SingleAgentView`` (a
gymnasium.Env for one agent), ``RecordVideo`` (episodes as MP4) and ``SharedPolicyVecEnv``
(every agent of several env copies as one row of an SB3 VecEnv).

``SharedPolicyVecEnv`` needs the ``train`` extra (SB3, torch) and is imported on first use.
"""

from __future__ import annotations

from typing import Any

from .safe_rl import SafeRLParallelEnv
from .shield import CBFShield
from .single_agent import SingleAgentView
from .vector_shield import VectorCBFShield
from .video import RecordVideo

__all__ = [
    "CBFShield",
    "RecordVideo",
    "SafeRLParallelEnv",
    "SharedPolicyVecEnv",
    "SingleAgentView",
    "VectorCBFShield",
]


def __getattr__(name: str) -> Any:
    if name == "SharedPolicyVecEnv":
        from .sb3 import SharedPolicyVecEnv

        return SharedPolicyVecEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
