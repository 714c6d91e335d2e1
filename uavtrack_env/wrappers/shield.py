"""``CBFShield``: the expert's CBF-QP (47) as a safety shield around any policy's actions.

Every step, each agent's proposed (normalised) action goes through its `OnboardAgent` (the same
stack the expert certifies with: UKF, neighbour velocities, known map, rows, QP) with only what
that UAV knows; it never reads ``info["truth"]``. The safe action is handed to the wrapped env;
``info[agent]["shield"]`` says what happened.

Margins (`ShieldMargins`): the env counts ``d < R_s`` as a UAV-UAV collision and ``d > R_c`` as a
broken link, while the barriers keep ``h >= 0`` only up to the QP's round-off, so the stack
certifies with ``R_s + r_s_margin`` and ``R_c - r_c_margin`` and re-checks eq. (28). The car is
known only through the UKF (`uavtrack_env.onboard`).

What the certified actions guarantee, under which assumptions (feasible start, every UAV
shielded, speed and acceleration bounds, lost messages, the car's estimate), and what the shield
reports when one breaks: docs/safety.md.
"""

from __future__ import annotations

import warnings
from typing import Any

import numba
import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from uavtrack_env.config import EnvConfig
from uavtrack_env.env import UAVTrackEnv
from uavtrack_env.onboard import certify_team, observe_frame, observe_team, onboard_team
from uavtrack_env.presets import ExpertConfig, expert_config
from uavtrack_env.safety import Certificates, SafetyContext, ShieldReport

_EPISODE_KEYS = ("steps", "interventions", "fallbacks", "correction")


def warn_if_lag_unaware(env_cfg: EnvConfig, cfg: ExpertConfig) -> None:
    """Warn when a shield certifies with first-order rows a plant whose velocities lag."""
    if env_cfg.dynamics.model == "lag" and not cfg.lag_aware:
        warnings.warn(
            "the shield certifies with the paper's first-order rows (lag_aware=False) but the "
            f"env's velocities lag (dynamics.tau = {env_cfg.dynamics.tau} s): the shield is a "
            "best effort",
            stacklevel=3,
        )


@numba.njit(cache=True)
def shield_actions(u, action, changed_live, live, scale):  # pragma: no cover (compiled)
    """From the env's u (n, 4) (SI units) and the certified ``action`` (m, 4) of the UAVs
    ``live``: the proposed and certified normalised actions (n, 4) (certified clipped to
    [-1, 1], the proposed one where unchanged), which UAVs' actions changed (n,) and the u to
    step (the certified action where changed, else the env's own u)."""
    n = u.shape[0]
    proposed, certified, u_env = u / scale, np.empty((n, 4)), u.copy()
    changed = np.zeros(n, np.bool_)
    certified[:] = proposed
    for j in range(live.shape[0]):
        i = live[j]
        changed[i] = changed_live[j]
        for c in range(4):
            certified[i, c] = min(max(action[j, c] / scale[c], -1.0), 1.0)
            if changed[i]:
                u_env[i, c] = certified[i, c] * scale[c]
    return proposed, certified, changed, u_env


class CBFShield(BaseParallelWrapper):
    """PettingZoo ParallelEnv wrapper: every action passes the distributed CBF-QP (47) first.

    ``config``: an `ExpertConfig` or a preset name (default ``"tuned"``); the shield uses its
    ``ukf``, ``cbf``, ``shield``, ``margins``, ``qp_solver`` and ``lag_aware``.

    Bad actions raise the env's own errors (its validation runs first) and change nothing.
    ``info[agent]["shield"]`` holds:

    * ``proposed`` (the policy's action, clipped to [-1, 1] as the env would) and ``action``
      (the certified action the env applies), both normalised; ``correction_norm`` (SI units,
      camera frame) and ``active`` (the action was changed);
    * ``status`` ('nominal', 'optimal', 'relaxed', 'fallback'), ``active_rows`` (the binding
      rows), ``gave_up`` (hard rows a fallback violates), ``slack`` (m/s of relaxed soft rows),
      ``hard_violation``;
    * ``min_h``: the least barrier value h of each row family ('uav', 'obstacle', 'target',
      'floor', 'connect', 'occlusion'; absent families left out), ``min_hard_h``;
    * ``has_target_estimate``; and, on the agent's last step, ``episode``: steps,
      interventions, intervention_rate, fallbacks and mean_correction of the episode.

    The env's own signals stay visible: ``info["action_clipped"]`` and
    ``info["n_clipped_actions"]`` count the policy's actions outside [-1, 1], as the bare env
    would. ``last_reports`` holds the full `ShieldReport` of each agent (made when read).
    """

    def __init__(self, env: Any, config: ExpertConfig | str | None = None) -> None:
        super().__init__(env)
        raw = env.unwrapped
        if not isinstance(raw, UAVTrackEnv):
            raise TypeError(f"CBFShield wraps a UAVTrackEnv, got {type(raw).__name__}")
        self.config = cfg = expert_config(config)
        env_cfg = raw.config
        team = onboard_team(raw.possible_agents, env_cfg, cfg)[0]
        self.onboard = {agent.name: agent for agent in team}
        first = next(iter(self.onboard.values()))
        self.cbf, self.filter = first.cbf, first.filter
        warn_if_lag_unaware(env_cfg, cfg)
        self._raw = raw
        self._scale = env_cfg.limits.scale
        self._ids = {a: i for i, a in enumerate(raw.possible_agents)}
        self._everyone = list(range(len(raw.possible_agents)))
        self._certified: tuple[list[str], Certificates | None] = ([], None)
        self._clips: dict[str, int] = {}
        self._episode: dict[str, dict[str, float]] = {}

    # ------------------------------------------------------------------ API
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        obs, infos = self.env.reset(seed=seed, options=options)
        agents = self._raw.possible_agents
        for agent in self.onboard.values():
            agent.reset(self._raw.layout, agents)
        self._certified = ([], None)
        self._clips = dict.fromkeys(agents, 0)
        self._episode = {a: dict.fromkeys(_EPISODE_KEYS, 0.0) for a in agents}
        self._observe(infos)
        for info in infos.values():
            info["shield"] = {
                "active": False,
                "correction_norm": 0.0,
                "status": "reset",
                "slack": 0.0,
            }
        return obs, infos

    def step(self, actions: dict[str, Any]):
        # The env's own validation: identical errors, raised before anything changes.
        u, clipped = self._raw.validate_actions(actions)
        names = list(actions)
        live = [self._ids[a] for a in names]
        everyone = live == self._everyone  # every UAV acts, in index order: no fancy indexing
        done = certify_team([self.onboard[a] for a in names], u if everyone else u[live])
        proposed, certified, changed, u_env = shield_actions(
            u, done.action, done.changed, np.asarray(live, np.int64), self._scale
        )
        # An unchanged action is passed through as given (bit-identical behaviour).
        if self.env is self._raw:  # checked above: the env's step without checking again
            out = self._raw._step_checked(u_env, clipped & ~changed)
        else:
            out = self.env.step(
                {a: certified[i] if changed[i] else act
                 for a, act in actions.items() for i in (self._ids[a],)}
            )  # fmt: skip
        obs, rewards, terms, truncs, infos = out
        self._observe(infos)
        self._certified = (names, done)
        summaries = dict(zip(names, done.summaries(), strict=True))
        was_clipped = clipped.tolist()
        for agent, info in infos.items():
            i = self._ids[agent]
            self._clips[agent] += was_clipped[i]
            info["action_clipped"] = was_clipped[i]
            info["n_clipped_actions"] = self._clips[agent]
            info["shield"] = shield = self._telemetry(agent, summaries[agent])
            shield["proposed"], shield["action"] = proposed[i], certified[i]
            if terms[agent] or truncs[agent]:
                shield["episode"] = self._episode_summary(agent)
        return obs, rewards, terms, truncs, infos

    @property
    def last_reports(self) -> dict[str, ShieldReport]:
        """Each agent's full `ShieldReport` of the latest step (made when read)."""
        names, done = self._certified
        if done is None:
            return {}
        return {agent: done.report(j) for j, agent in enumerate(names)}

    def _telemetry(self, agent: str, shield: dict[str, Any]) -> dict[str, Any]:
        """``info[agent]["shield"]`` for one step (class docstring) but the actions, from
        `Certificates.summary`; updates the episode sums."""
        ep = self._episode[agent]
        ep["steps"] += 1
        ep["interventions"] += shield["active"]
        ep["fallbacks"] += shield["status"] == "fallback"
        ep["correction"] += shield["correction_norm"]
        shield["has_target_estimate"] = self.onboard[agent].tracker.has_estimate
        return shield

    def _episode_summary(self, agent: str) -> dict[str, float]:
        ep = self._episode[agent]
        steps = max(ep["steps"], 1.0)
        return {
            "steps": int(ep["steps"]),
            "interventions": int(ep["interventions"]),
            "intervention_rate": ep["interventions"] / steps,
            "fallbacks": int(ep["fallbacks"]),
            "mean_correction": ep["correction"] / steps,
        }

    # -------------------------------------------------------------- shield
    def certify(self, agent: str, u_nominal: np.ndarray) -> tuple[np.ndarray, ShieldReport]:
        """Certify one agent's SI camera-frame command with what that UAV knows now."""
        if agent not in self.onboard:
            raise KeyError(f"unknown agent {agent!r}; agents are {list(self.onboard)}")
        return self.onboard[agent].certify(u_nominal)

    def context(self, agent: str) -> SafetyContext:
        """The `SafetyContext` of ``agent`` from its latest info and target estimate."""
        return self.onboard[agent].context()

    def _observe(self, infos: dict[str, dict]) -> None:
        """Feed every live agent's onboard stack with its new info (`onboard.observe_arrays`:
        from the env's own arrays, what the infos hold, when no wrapper stands between)."""
        agents = [self.onboard[a] for a in infos]
        if self.env is not self._raw:
            observe_team(agents, list(infos.values()))
            return
        raw = self._raw
        uavs = [self._ids[a] for a in infos]
        state = (raw.position, raw.yaw, raw.velocity, raw.yaw_rate)
        observe_frame(
            agents, raw.last_detection, state, uavs, raw.last_received, raw.position[None],
            list(infos.values()),
        )  # fmt: skip
