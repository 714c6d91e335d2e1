"""``CBFShield``: the expert's CBF-QP (47) as a safety shield around any policy's actions.

Every step, each agent's proposed (normalised) action goes through its `OnboardAgent` (the same
stack the expert certifies with: UKF, neighbour velocities, known map, rows, QP) with only what
that UAV knows; it never reads ``info["truth"]``. The safe action is handed to the wrapped env;
``info[agent]["shield"]`` says what happened.

Margins (`ShieldMargins`): the env counts ``d < R_s`` as a UAV-UAV collision and ``d > R_c`` as a
broken link, while the barriers keep ``h >= 0`` only up to the QP's round-off, so the stack
certifies with ``R_s + r_s_margin`` and ``R_c - r_c_margin`` and re-checks eq. (28). The car is
known only through the UKF (`uavtrack_env.onboard`).

Guarantees hold for the paper's single-integrator dynamics (eq. 3, ``dynamics.model =
'integrator'``), with every agent shielded and messages not dropped. Under the 'lag' model with
``lag_aware`` the shield certifies with second-order rows, which assume the commanded change of
velocity is reachable (``|u - v| / tau <= a_max`` is not clipped). Before a UAV has ever detected
the car it has no estimate, so no car row (documented limitation).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from uavtrack_env.env import UAVTrackEnv
from uavtrack_env.onboard import OnboardAgent
from uavtrack_env.presets import ExpertConfig, expert_config
from uavtrack_env.safety import SafetyContext, ShieldReport


class CBFShield(BaseParallelWrapper):
    """PettingZoo ParallelEnv wrapper: every action passes the distributed CBF-QP (47) first.

    ``config``: an `ExpertConfig` or a preset name (default ``"tuned"``); the shield uses its
    ``ukf``, ``cbf``, ``shield``, ``margins``, ``qp_solver`` and ``lag_aware``.

    Bad actions raise the env's own errors (its validation runs first) and change nothing.
    ``info[agent]["shield"]`` holds ``active``, ``correction_norm`` (SI units, camera frame),
    ``status``, ``slack`` (m/s of relaxed soft rows), ``active_rows``, ``hard_violation``,
    ``min_hard_h``, ``action`` (the normalised action sent to the env) and
    ``has_target_estimate``. ``last_reports`` keeps the full `ShieldReport` of each agent.
    """

    def __init__(self, env: Any, config: ExpertConfig | str | None = None) -> None:
        super().__init__(env)
        raw = env.unwrapped
        if not isinstance(raw, UAVTrackEnv):
            raise TypeError(f"CBFShield wraps a UAVTrackEnv, got {type(raw).__name__}")
        self.config = cfg = expert_config(config)
        env_cfg = raw.config
        self.onboard = {
            a: OnboardAgent(a, i, env_cfg, cfg) for i, a in enumerate(raw.possible_agents)
        }
        first = next(iter(self.onboard.values()))
        self.cbf, self.filter = first.cbf, first.filter
        if env_cfg.dynamics.model == "lag" and not cfg.lag_aware:
            warnings.warn(
                "CBFShield certifies with the paper's first-order rows (lag_aware=False) but the "
                f"env's velocities lag (dynamics.tau = {env_cfg.dynamics.tau} s): the shield is a "
                "best effort",
                stacklevel=2,
            )
        if env_cfg.comms.drop_prob > 0:
            warnings.warn(
                "CBFShield's guarantees assume every message within R_c arrives (comms.drop_prob "
                f"= {env_cfg.comms.drop_prob}): the distributed rows (23)-(34) need both UAVs' "
                "halves",
                stacklevel=2,
            )
        self._raw = raw
        self._scale = env_cfg.limits.scale
        self._ids = {a: i for i, a in enumerate(raw.possible_agents)}
        self.last_reports: dict[str, ShieldReport] = {}

    # ------------------------------------------------------------------ API
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        obs, infos = self.env.reset(seed=seed, options=options)
        agents = self._raw.possible_agents
        for agent in self.onboard.values():
            agent.reset(self._raw.layout, agents)
        self.last_reports = {}
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
        u, _ = self._raw.validate_actions(actions)
        safe, reports = {}, {}
        for agent, action in actions.items():
            u_safe, report = self.certify(agent, u[self._ids[agent]])
            reports[agent] = report
            # An unchanged action is passed through as given (bit-identical behaviour).
            safe[agent] = np.clip(u_safe / self._scale, -1.0, 1.0) if report.active else action
        obs, rewards, terms, truncs, infos = self.env.step(safe)
        self._observe(infos)
        self.last_reports = reports
        for agent, info in infos.items():
            rep = reports[agent]
            info["shield"] = {
                "active": rep.active,
                "correction_norm": rep.correction_norm,
                "status": rep.status,
                "slack": rep.slack,
                "active_rows": list(rep.active_rows),
                "hard_violation": rep.hard_violation,
                "min_hard_h": rep.min_hard_h,
                "action": np.asarray(safe[agent], np.float64).copy(),
                "has_target_estimate": self.onboard[agent].estimate is not None,
            }
        return obs, rewards, terms, truncs, infos

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
        """Feed every live agent's onboard stack with its new info."""
        for agent, info in infos.items():
            self.onboard[agent].observe(info)
