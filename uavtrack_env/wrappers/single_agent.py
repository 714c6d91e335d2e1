"""``SingleAgentView``: one agent of the ParallelEnv as a ``gymnasium.Env``, the others scripted.

So that Gymnasium's and SB3's checkers and single-agent tools (SB3's PPO, wrappers, evaluation
helpers) apply to one UAV while its team-mates follow a fixed policy: the paper's expert (UKF ->
NMPC -> CBF-QP, the default), hovering, or any callable.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np

from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.presets import ExpertConfig

OthersPolicy = Callable[[dict[str, np.ndarray], dict[str, dict]], dict[str, Any]]
"""``(obs of the other live agents, infos of all live agents) -> {other agent: action}``."""


_HOVER = np.zeros(4, np.float32)


class SingleAgentView(gymnasium.Env):
    """A gymnasium.Env for ``agent`` of a uavtrack ParallelEnv (raw or `CBFShield`-wrapped).

    * Spaces: exactly the wrapped env's ``observation_space(agent)`` and ``action_space(agent)``.
    * ``others``: ``"expert"`` (`ExpertPolicy.from_env` with ``expert_config``, handed the new
      layout at every reset), ``"hover"`` (zero actions) or a callable
      ``(obs_dict, infos) -> {agent: action}`` that receives the other live agents'
      observations and all live agents' infos; a ``reset()`` method, if any, is called after
      each env reset.
    * ``reset(seed, options) -> (obs, info)`` and ``step(action) -> (obs, reward, terminated,
      truncated, info)`` are the chosen agent's. The episode ends when that agent is done
      (terminated/truncated as the env says); team-mates that finish earlier are simply dropped
      by the env while the agent keeps going. Stepping after the end raises RuntimeError.
    * ``render()`` forwards to the wrapped env; ``close()`` closes it.
    """

    def __init__(
        self,
        env: Any,
        agent: str = "uav_0",
        others: str | OthersPolicy = "expert",
        expert_config: ExpertConfig | str | None = None,
    ) -> None:
        if agent not in env.possible_agents:
            raise ValueError(f"unknown agent {agent!r}; agents are {env.possible_agents}")
        if isinstance(others, str):
            if others not in ("expert", "hover"):
                raise ValueError(f"others must be 'expert', 'hover' or a callable, got {others!r}")
        elif not callable(others):
            raise ValueError(f"others must be 'expert', 'hover' or a callable, got {others!r}")
        if expert_config is not None and others != "expert":
            raise TypeError(f"expert_config given with others={others!r}")
        self.env = env
        self.agent = agent
        self.others = others
        self.expert_config = expert_config
        self.observation_space = env.observation_space(agent)
        self.action_space = env.action_space(agent)
        self.metadata = dict(env.metadata)
        self.render_mode = env.render_mode
        self.expert: ExpertPolicy | None = None
        self._obs: dict[str, np.ndarray] = {}
        self._infos: dict[str, dict] = {}
        self._done = True

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._obs, self._infos = self.env.reset(seed=seed, options=options)
        if self.others == "expert":
            self._reset_expert()
        elif callable(getattr(self.others, "reset", None)):
            self.others.reset()
        self._done = False
        return self._obs[self.agent], self._infos[self.agent]

    def _reset_expert(self) -> None:
        """Build the expert once; every reset hands it the new layout."""
        raw = self.env.unwrapped
        if self.expert is None:
            self.expert = ExpertPolicy.from_env(raw, self.expert_config)
        else:
            self.expert.reset(raw.layout)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._done:
            if self.env.unwrapped.np_random is None:
                raise RuntimeError("step() called before reset(); call env.reset(seed=...) first")
            raise RuntimeError("the episode is over for this agent; call reset() first")
        live = self.env.agents
        others = {a: o for a, o in self._obs.items() if a != self.agent and a in live}
        # The env's validation of this agent's action first, so a bad action changes nothing
        # (not even the team-mates' estimators).
        self.env.unwrapped.validate_actions({**{a: _HOVER for a in others}, self.agent: action})
        actions = dict(self._others_actions(others)) if others else {}
        actions[self.agent] = action
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        self._obs, self._infos = obs, infos
        a = self.agent
        terminated, truncated = bool(terms[a]), bool(truncs[a])
        self._done = terminated or truncated or a not in self.env.agents
        return obs[a], float(rewards[a]), terminated, truncated, infos[a]

    def _others_actions(self, others: dict[str, np.ndarray]) -> dict[str, Any]:
        if self.others == "hover":
            return {a: _HOVER.copy() for a in others}
        if self.others == "expert":
            return self.expert(others, self._infos)
        return self.others(others, self._infos)

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()
