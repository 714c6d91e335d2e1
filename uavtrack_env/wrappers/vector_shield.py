"""``VectorCBFShield``: `CBFShield` over `uavtrack_v0.vector_env`.

Every active row's action passes the onboard stack of its UAV (`OnboardAgent`: UKF, team-mates'
messages, known map, CBF-QP (47)) before the worlds step in one batch. World k behaves exactly
as ``CBFShield(parallel_env(**config))`` reset with seed s + k given the same actions (tested):
the same certified actions, observations, rewards and terminations.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uavtrack_env.onboard import certify_team, observe_frame, observe_team, onboard_team
from uavtrack_env.presets import ExpertConfig, expert_config
from uavtrack_env.safety import Certificates, ShieldReport
from uavtrack_env.vector import UAVTrackVectorEnv
from uavtrack_env.wrappers.shield import warn_if_lag_unaware


class VectorCBFShield:
    """`UAVTrackVectorEnv` wrapper: the actions of all worlds pass their UAVs' CBF-QP (47) first.

    ``config``: an `ExpertConfig` or a preset name (default ``"tuned"``), as for `CBFShield`;
    ``self.config`` is that `ExpertConfig`, the worlds' `EnvConfig` is ``self.vector.config``.
    ``reset`` and ``step`` take and return what the vector env does (bad actions raise its own
    errors and change nothing); ``infos["action_clipped"]`` flags the policy's actions outside
    [-1, 1], and ``infos["shield"]`` holds arrays (K, n): ``active`` (the action was changed),
    ``correction_norm`` (SI units, camera frame), ``fallback``, ``hard_violation`` and
    ``min_hard_h`` (inf without hard rows), and (K, n, 4) ``proposed`` and ``action`` (the
    certified action the world applies), normalised; zeros for inactive rows.
    ``last_reports[k]`` holds each agent's `ShieldReport` of the step (made when read).
    """

    def __init__(self, venv: UAVTrackVectorEnv, config: ExpertConfig | str | None = None) -> None:
        if not isinstance(venv, UAVTrackVectorEnv):
            raise TypeError(f"VectorCBFShield wraps a UAVTrackVectorEnv, got {type(venv).__name__}")
        self.vector = venv
        self.config = cfg = expert_config(config)
        env_cfg = venv.config
        warn_if_lag_unaware(env_cfg, cfg)
        names = venv.possible_agents
        self.onboard = onboard_team(names, env_cfg, cfg, venv.num_envs)
        self._certified: tuple[np.ndarray, Certificates | None] = (np.zeros((0, 2), np.int64), None)
        for name in (
            "num_envs", "possible_agents", "n_agents", "envs", "metadata",
            "single_observation_space", "single_action_space", "observation_space",
            "action_space",
        ):  # fmt: skip
            setattr(self, name, getattr(venv, name))
        self._index = {a: i for i, a in enumerate(names)}
        self._scale = venv._scale

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        obs, infos = self.vector.reset(seed=seed, options=options)
        for k in range(self.num_envs):
            self._restart(k)
        self._certified = (np.zeros((0, 2), np.int64), None)
        zeros = np.zeros((self.num_envs, self.n_agents, 4))
        infos["shield"] = self._telemetry(zeros, zeros.copy())
        return obs, infos

    def step(self, actions: Any):
        u, clipped = self.vector._checked(actions)  # the vector env's errors, nothing changed
        active = self.vector._active
        u_safe = u.copy()
        changed = np.zeros(active.shape, bool)
        live = np.argwhere(active)
        done = None
        if len(live):
            ks, ids = live[:, 0], live[:, 1]
            done = certify_team([self.onboard[k][i] for k, i in live.tolist()], u[ks, ids])
            u_safe[ks, ids], changed[ks, ids] = done.action, done.changed
        certified = np.clip(u_safe / self._scale, -1.0, 1.0)
        # An unchanged action is passed on as given: the world applies exactly what it would.
        applied = np.where(changed[..., None], certified, np.asarray(actions, np.float64))
        obs, rewards, terms, truncs, infos = self.vector.step(applied)
        infos["action_clipped"] = clipped & active
        self._certified = (live, done)
        shown = active[..., None]
        infos["shield"] = self._telemetry(u / self._scale * shown, certified * shown)
        ended = infos.get("_final_obs", np.zeros(self.num_envs, bool))
        self._observe([k for k in range(self.num_envs) if not ended[k]])
        for k in np.flatnonzero(ended):
            self._restart(k)
        return obs, rewards, terms, truncs, infos

    @property
    def last_reports(self) -> list[dict[str, ShieldReport]]:
        """Each world's `ShieldReport` by agent of the latest step (made when read)."""
        reports: list[dict[str, ShieldReport]] = [{} for _ in range(self.num_envs)]
        live, done = self._certified
        if done is not None:
            for j, (k, i) in enumerate(live.tolist()):
                reports[k][self.possible_agents[i]] = done.report(j)
        return reports

    def close(self) -> None:
        self.vector.close()

    def __enter__(self) -> VectorCBFShield:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ----------------------------------------------------------------- helpers
    def _restart(self, k: int) -> None:
        """World k has reset: its UAVs take the new map and their first observation."""
        env = self.vector.envs[k]
        for agent in self.onboard[k]:
            agent.reset(env.layout, env.possible_agents)
        self._observe([k])

    def _observe(self, worlds: list[int]) -> None:
        """The UAVs of these worlds that took part in the step take their new measurements (all
        their UKFs in one batched pass): from the batched step's arrays, or from the worlds'
        infos where those are what the vector env keeps (``full_infos``, a world's reset)."""
        venv = self.vector
        batched = [k for k in worlds if venv._world_infos[k] is None and venv._sensed is not None]
        if batched:
            take = np.zeros(venv._stepped.shape, bool)
            take[batched] = venv._stepped[batched]
            ks, ids = np.nonzero(take)
            m, position = venv._sensed, venv._state[0]
            agents = [self.onboard[k][i] for k, i in zip(ks.tolist(), ids.tolist(), strict=True)]
            uavs = ks * self.n_agents + ids
            observe_frame(agents, m.detections, venv._state, uavs, m.received, position)
        agents, infos, done = [], [], set(batched)
        for k in worlds:
            if k in done:
                continue
            for name, info in venv.sensor_infos(k).items():
                agents.append(self.onboard[k][self._index[name]])
                infos.append(info)
        if agents:
            observe_team(agents, infos)

    def _telemetry(self, proposed: np.ndarray, action: np.ndarray) -> dict[str, np.ndarray]:
        """``infos["shield"]`` (class docstring) from the step's certificates."""
        shape = (self.num_envs, self.n_agents)
        out = {
            "active": np.zeros(shape, bool),
            "correction_norm": np.zeros(shape),
            "fallback": np.zeros(shape, bool),
            "hard_violation": np.zeros(shape),
            "min_hard_h": np.full(shape, np.inf),
        }
        live, done = self._certified
        if done is not None:
            at = live[:, 0], live[:, 1]
            out["active"][at], out["correction_norm"][at] = done.changed, done.correction_norm
            out["fallback"][at], out["hard_violation"][at] = done.fallback, done.hard_violation
            out["min_hard_h"][at] = done.min_hard_h()
        out["proposed"], out["action"] = proposed, action
        return out
