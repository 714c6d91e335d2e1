"""Shared-parameter PPO on a PettingZoo ParallelEnv: every agent of several env copies is one row
of a Stable-Baselines3 ``VecEnv``.

Rows are ordered copy-major: row ``k * n_agents + j`` is agent ``possible_agents[j]`` of copy k.
SB3's conventions hold row by row: ``reset()`` returns the observations only; ``step_wait()``
returns ``(obs, rewards, dones, infos)`` with ``dones = terminated or truncated``,
``infos[i]["TimeLimit.truncated"] = truncated and not terminated`` and
``infos[i]["terminal_observation"]`` on every done row. When every agent of a copy is done, the
copy is reset at once and its rows return the reset observations (auto-reset).

**Agent death inside a copy** (``terminate_on_collision="agent"``, or any per-agent end): the
agent's row reports ``done=True`` once, with its terminal observation, and then sits in an *inert
absorbing state* until its copy resets: observation ``absorbing_obs`` (zeros clipped into the
observation space; a real observation never has sin yaw = cos yaw = 0, so it is distinguishable),
reward 0, the row's action ignored, ``info["absorbing"] = True``. When the copy resets, the
absorbing chain ends with ``done=True`` (terminated, not truncated, terminal observation
``absorbing_obs``, flagged ``absorbing``). Why this is right for PPO's GAE: SB3 computes
``delta_t = r_t + gamma V(s_{t+1}) (1 - done_t) - V(s_t)``. The real episode ends at the death
with done=True (no bootstrap into the absorbing state), and the absorbing chain ends with a
terminal done (no bootstrap into the next real episode), so every real transition's advantage is
exactly what it would be without the padding, and the absorbing state's true value is 0. What
remains: absorbing samples are in the batch (advantage -> 0 as V learns V(absorbing) = 0; they
still count in the advantage normalisation and the entropy term). Use :class:`AgentVecMonitor`
instead of SB3's ``VecMonitor`` so that the absorbing chains are not counted as episodes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecMonitor
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvStepReturn

if TYPE_CHECKING:
    from uavtrack_env.presets import ExpertConfig

__all__ = ["AgentVecMonitor", "SharedPolicyVecEnv", "VectorSharedPolicyVecEnv"]


def _absorbing_obs(space: gymnasium.spaces.Box) -> np.ndarray:
    """The observation of a finished agent's row: zeros clipped into the space."""
    return np.clip(np.zeros(space.shape, space.dtype), space.low, space.high).astype(space.dtype)


def _one_per_row(actions: np.ndarray, rows: int) -> np.ndarray:
    """``actions`` as an array with one row per VecEnv row; ValueError otherwise."""
    act = np.asarray(actions)
    if act.shape[:1] != (rows,):
        raise ValueError(
            f"actions must have one row per agent: shape ({rows}, ...), got {act.shape}"
        )
    return act


class SharedPolicyVecEnv(VecEnv):
    """An SB3 VecEnv over ``n_copies`` copies of a PettingZoo ParallelEnv, one row per agent.

    ``env_fn()`` builds one copy (e.g. ``lambda: CBFShield(parallel_env(scenario="random"))``);
    every agent must share one observation and one action space (shared parameters). See the
    module docstring for the reset and agent-death conventions.
    """

    def __init__(self, env_fn: Callable[[], Any], n_copies: int = 1) -> None:
        if not callable(env_fn):
            raise ValueError(f"env_fn must be a callable returning a ParallelEnv, got {env_fn!r}")
        if not isinstance(n_copies, int) or n_copies < 1:
            raise ValueError(f"n_copies must be an int >= 1, got {n_copies!r}")
        self.envs = [env_fn() for _ in range(n_copies)]
        first = self.envs[0]
        self.possible_agents: list[str] = list(first.possible_agents)
        if not self.possible_agents:
            raise ValueError("the env has no possible_agents")
        for env in self.envs[1:]:
            if list(env.possible_agents) != self.possible_agents:
                raise ValueError("every copy must have the same possible_agents")
        obs_space = first.observation_space(self.possible_agents[0])
        act_space = first.action_space(self.possible_agents[0])
        for a in self.possible_agents[1:]:
            if first.observation_space(a) != obs_space or first.action_space(a) != act_space:
                raise ValueError(
                    f"agent {a!r} has different spaces from {self.possible_agents[0]!r}; "
                    "a shared policy needs identical observation and action spaces"
                )
        if not isinstance(obs_space, gymnasium.spaces.Box):
            raise ValueError(f"observation space must be a Box, got {obs_space}")
        self.n_copies = n_copies
        self.n_agents = len(self.possible_agents)
        self.absorbing_obs = _absorbing_obs(obs_space)
        super().__init__(n_copies * self.n_agents, obs_space, act_space)
        self._copy_seeds: list[int | None] = [None] * n_copies
        self._live = np.zeros((n_copies, self.n_agents), bool)
        self._actions: np.ndarray | None = None
        self._obs = np.zeros((self.num_envs, *obs_space.shape), obs_space.dtype)

    # ------------------------------------------------------------ rows and copies
    def _row(self, k: int, j: int) -> int:
        return k * self.n_agents + j

    def _copies(self, indices: VecEnvIndices) -> list[int]:
        """Distinct copies behind the given rows, in row order."""
        rows = self._rows(indices)
        return list(dict.fromkeys(i // self.n_agents for i in rows))

    def _rows(self, indices: VecEnvIndices) -> list[int]:
        rows = list(self._get_indices(indices))
        bad = [i for i in rows if not 0 <= int(i) < self.num_envs]
        if bad:
            raise ValueError(f"row indices {bad} out of range [0, {self.num_envs})")
        return [int(i) for i in rows]

    # ------------------------------------------------------------------ reset
    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Seeds for the next reset: copy k gets ``seed + k``; returns the per-copy list."""
        if seed is None:
            # as SB3: from the global numpy RNG, which SB3's set_random_seed seeds
            seed = int(np.random.randint(0, 2**32 - 1, dtype=np.uint32))  # noqa: NPY002
        self._copy_seeds = [int(seed) + k for k in range(self.n_copies)]
        return list(self._copy_seeds)

    def _reset_copy(self, k: int) -> None:
        opts = self._options[self._row(k, 0)] or None
        obs, infos = self.envs[k].reset(seed=self._copy_seeds[k], options=opts)
        self._copy_seeds[k] = None
        for j, agent in enumerate(self.possible_agents):
            row = self._row(k, j)
            live = agent in obs
            self._live[k, j] = live
            self._obs[row] = obs[agent] if live else self.absorbing_obs
            info = dict(infos.get(agent, {}))
            if not live:
                info["absorbing"] = True
            self.reset_infos[row] = info

    def reset(self) -> np.ndarray:
        for k in range(self.n_copies):
            self._reset_copy(k)
        self._reset_seeds()
        self._reset_options()
        return self._obs.copy()

    # ------------------------------------------------------------------- step
    def step_async(self, actions: np.ndarray) -> None:
        self._actions = _one_per_row(actions, self.num_envs)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async(actions)")
        actions, self._actions = self._actions, None
        rewards = np.zeros(self.num_envs, np.float32)
        dones = np.zeros(self.num_envs, bool)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for k, env in enumerate(self.envs):
            was_live = self._live[k].copy()
            act = {
                a: actions[self._row(k, j)]
                for j, a in enumerate(self.possible_agents)
                if was_live[j]
            }
            obs, rew, term, trunc, info = env.step(act)
            for j, agent in enumerate(self.possible_agents):
                row = self._row(k, j)
                if not was_live[j]:
                    self._obs[row] = self.absorbing_obs
                    infos[row] = {"absorbing": True}
                    continue
                terminated, truncated = bool(term.get(agent, False)), bool(trunc.get(agent, False))
                if agent not in env.agents and not (terminated or truncated):
                    raise RuntimeError(
                        f"agent {agent!r} left env.agents without a termination or truncation "
                        "flag; a ParallelEnv must report why an agent ended"
                    )
                infos[row] = dict(info.get(agent, {}))
                rewards[row] = rew.get(agent, 0.0)
                if terminated or truncated:
                    dones[row] = True
                    infos[row]["terminal_observation"] = np.asarray(obs[agent])
                    infos[row]["TimeLimit.truncated"] = truncated and not terminated
                    self._live[k, j] = False
                    self._obs[row] = self.absorbing_obs
                else:
                    self._obs[row] = obs[agent]
            if not env.agents:
                for j in range(self.n_agents):
                    row = self._row(k, j)
                    if not was_live[j]:  # end of an absorbing chain: terminal, value 0
                        dones[row] = True
                        infos[row]["terminal_observation"] = self.absorbing_obs.copy()
                        infos[row]["TimeLimit.truncated"] = False
                self._reset_copy(k)
        return self._obs.copy(), rewards, dones, infos

    # ----------------------------------------------------------------- extras
    def close(self) -> None:
        for env in self.envs:
            env.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The attribute of the copy behind each row (one entry per row)."""
        return [getattr(self.envs[i // self.n_agents], attr_name) for i in self._rows(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set on every copy behind the rows (once per copy)."""
        for k in self._copies(indices):
            setattr(self.envs[k], attr_name, value)

    def env_method(
        self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs
    ) -> list[Any]:
        """Call the method once per copy behind the rows; the result is repeated for each row."""
        rows = self._rows(indices)
        results = {
            k: getattr(self.envs[k], method_name)(*method_args, **method_kwargs)
            for k in self._copies(rows)
        }
        return [results[i // self.n_agents] for i in rows]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        """Whether the copy behind each row has ``wrapper_class`` in its ``.env`` chain."""
        out = []
        for i in self._rows(indices):
            env, found = self.envs[i // self.n_agents], False
            while env is not None and not found:
                found = isinstance(env, wrapper_class)
                env = getattr(env, "env", None)
            out.append(found)
        return out

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One frame per copy (not per row)."""
        return [env.render() for env in self.envs]


class VectorSharedPolicyVecEnv(VecEnv):
    """An SB3 VecEnv over `uavtrack_v0.vector_env`: the K worlds' n agents are the K n rows, in
    the same order and with the same conventions as `SharedPolicyVecEnv` (module docstring), but
    every step is one batched step of all worlds (`uavtrack_env.core`).

    Each row's info holds the vector env's array infos of that row (``cost``, ``costs``,
    ``reward_tracking``, ``reward_effort``, ``action_clipped``) and ``violations`` (the costs as
    flags); not the ParallelEnv's nested per-agent dicts. ``**config`` as for ``vector_env``.
    ``shield``: an `ExpertConfig` or preset name to pass every action through
    `VectorCBFShield` (rows then also hold ``shield``: ``active``, ``correction_norm`` and
    ``action``, the certified action the world applies, normalised).
    """

    def __init__(
        self, num_worlds: int, shield: ExpertConfig | str | None = None, **config: Any
    ) -> None:
        from uavtrack_env.vector import UAVTrackVectorEnv

        self.vector = UAVTrackVectorEnv(num_worlds, **config)
        if shield is not None:
            from uavtrack_env.wrappers.vector_shield import VectorCBFShield

            self.vector = VectorCBFShield(self.vector, shield)
        v = self.vector
        self.n_worlds, self.n_agents = v.num_envs, v.n_agents
        obs_space = v.single_observation_space
        self.absorbing_obs = _absorbing_obs(obs_space)
        super().__init__(self.n_worlds * self.n_agents, obs_space, v.single_action_space)
        self._seed: int | None = None
        self._live = np.zeros((self.n_worlds, self.n_agents), bool)
        self._actions: np.ndarray | None = None

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """The next reset seeds world k with ``seed + k``; returns the per-world list."""
        if seed is None:
            seed = int(np.random.randint(0, 2**32 - 1, dtype=np.uint32))  # noqa: NPY002
        self._seed = int(seed)
        return [self._seed + k for k in range(self.n_worlds)]

    def reset(self) -> np.ndarray:
        obs, _ = self.vector.reset(seed=self._seed)
        self._seed = None
        self._live[:] = True
        self.reset_infos = [{} for _ in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs.reshape(self.num_envs, -1)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = _one_per_row(actions, self.num_envs)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async(actions)")
        shape = (self.n_worlds, self.n_agents)
        actions, self._actions = self._actions.reshape(*shape, -1), None
        obs, rew, term, trunc, info = self.vector.step(actions)
        was_live = self._live
        done = term | trunc
        ended = info.get("_final_obs", np.zeros(self.n_worlds, bool))
        last = np.where(ended[:, None, None], info.get("final_obs", obs), obs)
        rows = np.zeros((*shape, obs.shape[-1]), obs.dtype)
        rows[:] = np.where(was_live[..., None] & ~done[..., None], obs, self.absorbing_obs)
        rows[ended] = obs[ended]  # the worlds that reset: their first observations
        dones = (done & was_live) | (ended[:, None] & ~was_live)
        infos: list[dict[str, Any]] = []
        # Python lists: indexing them per row costs a fraction of indexing the arrays.
        costs = [(name, values.tolist()) for name, values in info["costs"].items()]
        cost, tracking, effort, clipped = (
            info[key].tolist()
            for key in ("cost", "reward_tracking", "reward_effort", "action_clipped")
        )
        shield = info.get("shield")
        if shield is not None:
            active, correction = shield["active"].tolist(), shield["correction_norm"].tolist()
            certified = shield["action"]
        live, ends, dead = was_live.tolist(), ended.tolist(), done.tolist()
        time_limit = (trunc & ~term).tolist()
        for k in range(self.n_worlds):
            for j in range(self.n_agents):
                if not live[k][j]:
                    row = {"absorbing": True}
                    if ends[k]:  # end of an absorbing chain: terminal, value 0
                        row["terminal_observation"] = self.absorbing_obs.copy()
                        row["TimeLimit.truncated"] = False
                    infos.append(row)
                    continue
                c = {name: float(values[k][j]) for name, values in costs}
                row = {
                    "cost": float(cost[k][j]),
                    "costs": c,
                    "violations": {name: value > 0.0 for name, value in c.items()},
                    "reward_tracking": float(tracking[k][j]),
                    "reward_effort": float(effort[k][j]),
                    "action_clipped": bool(clipped[k][j]),
                }
                if shield is not None:
                    row["shield"] = {
                        "active": bool(active[k][j]),
                        "correction_norm": float(correction[k][j]),
                        "action": certified[k, j],
                    }
                if dead[k][j]:
                    row["terminal_observation"] = last[k, j].copy()
                    row["TimeLimit.truncated"] = bool(time_limit[k][j])
                infos.append(row)
        self._live = (was_live & ~done) | ended[:, None]
        rewards = np.where(was_live, rew, 0.0).astype(np.float32).reshape(-1)
        return rows.reshape(self.num_envs, -1), rewards, dones.reshape(-1), infos

    def close(self) -> None:
        self.vector.close()

    def _worlds(self, indices: VecEnvIndices) -> list[int]:
        rows = [int(i) for i in self._get_indices(indices)]
        bad = [i for i in rows if not 0 <= i < self.num_envs]
        if bad:
            raise ValueError(f"row indices {bad} out of range [0, {self.num_envs})")
        return [i // self.n_agents for i in rows]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The attribute of the world's ParallelEnv behind each row."""
        return [getattr(self.vector.envs[k], attr_name) for k in self._worlds(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise NotImplementedError("the worlds of a vector env share one configuration")

    def env_method(
        self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs
    ) -> list[Any]:
        raise NotImplementedError("step the worlds through the VecEnv, not their methods")

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(self._worlds(indices))

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None] * self.n_worlds


class AgentVecMonitor(VecMonitor):
    """SB3's VecMonitor that does not count the absorbing chains of dead agents as episodes and
    adds each episode's summed ``info["cost"]`` as ``info["episode"]["c"]``."""

    def reset(self) -> np.ndarray:
        self.episode_costs = np.zeros(self.num_envs)
        return super().reset()

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = super().step_wait()
        self.episode_costs += [float(info.get("cost", 0.0)) for info in infos]
        for i in np.flatnonzero(dones):
            if "episode" in infos[i]:
                infos[i]["episode"]["c"] = float(self.episode_costs[i])
            self.episode_costs[i] = 0.0
        for i in _flagged(dones, infos):
            infos[i].pop("episode", None)
            self.episode_count -= 1
        return obs, rewards, dones, infos


def _flagged(dones: np.ndarray, infos: list[dict]) -> Iterable[int]:
    return (i for i, d in enumerate(dones) if d and infos[i].get("absorbing", False))
