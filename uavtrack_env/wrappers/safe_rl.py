"""``SafeRLParallelEnv``: the env with Safety-Gymnasium's multi-agent step signature.

Safe-RL code written for Safety-Gymnasium's multi-agent tasks expects ``step`` to return the
per-agent cost beside the reward: ``(obs, rewards, costs, terminations, truncations, infos)``.
This wrapper returns ``info[agent]["cost"]`` there (the sum of the per-constraint costs
``info[agent]["costs"]``: collision, disconnection, occlusion) and, on each agent's last step of
an episode, ``info[agent]["episode_costs"]``: the episode's summed cost per constraint and in
all, its length and its cost rate (cost per step).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uavtrack_env.env import UAVTrackEnv

COST_KEYS = ("collision", "disconnection", "occlusion")


class SafeRLParallelEnv:
    """A PettingZoo ParallelEnv (or a wrapper of one, e.g. `CBFShield`) whose ``step`` also
    returns each agent's cost: ``(obs, rewards, costs, terminations, truncations, infos)``.

    Everything else (spaces, ``agents``, ``state``, ``render``, ``close``, attributes) is the
    wrapped env's.
    """

    def __init__(self, env: Any) -> None:
        if not isinstance(getattr(env, "unwrapped", None), UAVTrackEnv):
            raise TypeError(f"SafeRLParallelEnv wraps a UAVTrackEnv, got {type(env).__name__}")
        self.env = env
        self._totals: dict[str, dict[str, float]] = {}

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        obs, infos = self.env.reset(seed=seed, options=options)
        self._totals = {a: dict.fromkeys((*COST_KEYS, "cost", "steps"), 0.0) for a in infos}
        return obs, infos

    def step(self, actions: dict[str, Any]):
        """``(obs, rewards, costs, terminations, truncations, infos)``."""
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        costs = {}
        for agent, info in infos.items():
            costs[agent] = float(info["cost"])
            total = self._totals[agent]
            for key in COST_KEYS:
                total[key] += info["costs"][key]
            total["cost"] += costs[agent]
            total["steps"] += 1
            if terms[agent] or truncs[agent]:
                info["episode_costs"] = {
                    **{k: total[k] for k in (*COST_KEYS, "cost")},
                    "steps": int(total["steps"]),
                    "cost_rate": total["cost"] / total["steps"],
                }
        return obs, rewards, costs, terms, truncs, infos
