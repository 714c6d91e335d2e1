"""Observation history of a shared-parameter policy (``train.ppo --frame-stack K``).

A memoryless policy sees the car in one image: where it is, not how it moves, which the expert
gets from its UKF. With K frames the policy's input is the last K observations, oldest first,
zero-filled at an episode's start: the layout of SB3's `VecFrameStack` on train.ppo's VecEnv.
`FrameHistory` builds the same input from a ParallelEnv's observation dicts, for evaluation,
demonstrations and videos.
"""

from __future__ import annotations

import numpy as np


class FrameHistory:
    """Per agent, the last ``frames`` observations concatenated oldest first (zeros before the
    episode's first), as `VecFrameStack(venv, frames)` stacks a 1-D observation."""

    def __init__(self, frames: int) -> None:
        if not isinstance(frames, int | np.integer) or frames < 1:
            raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
        self.frames = int(frames)
        self._stacks: dict[str, np.ndarray] = {}

    def reset(self) -> None:
        """Forget every agent's history (a new episode)."""
        self._stacks.clear()

    def __call__(self, obs: dict) -> dict[str, np.ndarray]:
        """Push each agent's newest observation; returns its stacked input (float32)."""
        if self.frames == 1:
            return {a: np.asarray(o, np.float32) for a, o in obs.items()}
        out = {}
        for agent, o in obs.items():
            o = np.asarray(o, np.float32)
            stack = self._stacks.get(agent)
            if stack is None:
                stack = np.zeros(self.frames * o.size, np.float32)
            stack = np.concatenate([stack[o.size :], o])
            self._stacks[agent] = stack
            out[agent] = stack
        return out
