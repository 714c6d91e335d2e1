"""The paper's expert: per UAV, UKF (II-E) -> NMPC (18)-(19) -> distributed CBF-QP (47).

It sees only what a real UAV has: the detector's report, its own GPS/IMU state, the positions its
neighbours sent, the known obstacle map and its reference. It never reads ``info["truth"]``.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field, replace

import numpy as np

from .config import DT, CBFConfig, NMPCConfig
from .control import NMPC, NMPCOptions, NMPCResult
from .control.viewpoint import ViewpointConfig, ViewpointPlanner
from .estimation import UKFConfig
from .geometry import world_to_cam_vec
from .onboard import NeighbourVelocities, OnboardTracker, safety_context
from .safety import SafetyFilter, ShieldReport
from .safety.margins import ShieldMargins, shield_cbf

EXPERT_UKF = UKFConfig(truncated_v_hold_height=True)
"""The expert's filter: a box cut by the top or bottom border gives v from the held car height."""

TUNED_NMPC = NMPCConfig(
    terminal_weight="lqr", yaw_rate_reference="target-turn", safety_rows=4, safety_row_stages=10
)
"""The 'tuned' planner (not the paper's; ``--planner tuned``): LQR terminal weight, the target's
turn rate in u_d, and the shield's 4 nearest-active CBF rows on the plan's first 10 stages."""
TUNED_UKF = replace(EXPERT_UKF, fit_settle_time=2.0)
"""The 'tuned' planner's filter: the turn rate comes from the fitted acceleration, so the first
2 s of estimates, while V_q converges from 0, are left out of the fit."""
PLANNERS: dict[str, tuple[NMPCConfig, UKFConfig]] = {
    "paper": (NMPCConfig(), EXPERT_UKF),
    "tuned": (TUNED_NMPC, TUNED_UKF),
}
"""(NMPC, UKF) settings by planner name: 'paper' is eqs. (18)-(19) exactly (the default of
`ExpertPolicy`), 'tuned' the default of ``baselines.evaluate`` (docs/conventions.md)."""


@dataclass
class AgentState:
    """One UAV's onboard pipeline and its last outputs."""

    tracker: OnboardTracker
    nmpc: NMPC
    viewpoint: ViewpointPlanner
    last_nmpc: NMPCResult | None = None
    last_report: ShieldReport | None = None
    last_u: np.ndarray = field(default_factory=lambda: np.zeros(4))
    neighbour_velocities: NeighbourVelocities = field(default_factory=NeighbourVelocities)
    """Differences the neighbours' messages into velocities (second-order rows only)."""


class ExpertPolicy:
    """UKF -> NMPC -> CBF-QP for every agent; ``policy(obs, infos) -> {agent: action}``.

    Actions are the env's normalised [-1, 1]^4. ``timings[stage]`` holds per-agent-step wall
    times (s) of 'ukf', 'nmpc' (with the viewpoint layer) and 'qp'. ``use_cbf=False`` skips the
    QP (the ``--no-cbf`` ablation); ``viewpoint`` configures the x2* layer that looks over tall
    boxes (not in the paper; `uavtrack_env.control.viewpoint`). ``nmpc`` and ``ukf`` default to
    the paper's planner; ``PLANNERS["tuned"]`` gives baselines.evaluate's default.
    With the env's 'lag' dynamics the shield certifies with second-order rows
    (`ShieldOptions.lag_tau`, the neighbours' velocities differenced from their messages), as
    `CBFShield` does; ``lag_aware=False`` keeps the paper's first-order rows.
    """

    def __init__(
        self,
        agents: list[str],
        references: dict[str, np.ndarray],
        obstacle_centers: np.ndarray,
        obstacle_half_extents: np.ndarray,
        env_config,
        nmpc: NMPCConfig | None = None,
        nmpc_options: NMPCOptions | None = None,
        ukf: UKFConfig | None = None,
        cbf: CBFConfig | None = None,
        use_cbf: bool = True,
        viewpoint: ViewpointConfig | None = None,
        qp_solver: str | None = None,
        lag_aware: bool = True,
        **shield_options,
    ) -> None:
        self.config = env_config
        self.scale = env_config.limits.scale
        self.use_cbf = use_cbf
        self.obstacle_centers = np.asarray(obstacle_centers, float).reshape(-1, 3)
        self.obstacle_half_extents = np.asarray(obstacle_half_extents, float).reshape(-1, 3)
        if qp_solver is not None:
            shield_options["solver"] = qp_solver
        if lag_aware and env_config.dynamics.model == "lag":
            shield_options["lag_tau"] = env_config.dynamics.tau
        # Certify with the RL shield's margins (R_s + 5 cm, R_c - 5 cm): the env counts d < R_s.
        cbf = shield_cbf(cbf or env_config.cbf, ShieldMargins())
        self.shield = SafetyFilter(cbf, env_config.limits, **shield_options)
        self.lag_aware = self.shield.options.lag_tau > 0.0
        nmpc_cfg = nmpc or NMPCConfig()
        self.agents: dict[str, AgentState] = {
            a: AgentState(
                tracker=OnboardTracker(env_config.camera, ukf or EXPERT_UKF),
                nmpc=NMPC(
                    references[a], nmpc_cfg, env_config.limits, env_config.features, nmpc_options
                ),
                viewpoint=ViewpointPlanner(
                    references[a][1],
                    self.obstacle_centers,
                    self.obstacle_half_extents,
                    viewpoint or ViewpointConfig(),
                    DT,
                ),
            )
            for a in agents
        }
        self.timings: dict[str, list[float]] = defaultdict(list)

    @classmethod
    def from_env(cls, env, **kwargs) -> ExpertPolicy:
        """Build for a reset env: its agents, references and known obstacle map."""
        if env.layout is None:
            raise RuntimeError("ExpertPolicy.from_env needs an env that has been reset")
        refs = {a: env.layout.references[i] for i, a in enumerate(env.possible_agents)}
        return cls(
            env.possible_agents,
            refs,
            env.layout.obstacle_centers,
            env.layout.obstacle_half_extents,
            env.config,
            **kwargs,
        )

    def reset(self) -> None:
        """Forget all estimates and warm starts (call after env.reset)."""
        for st in self.agents.values():
            st.tracker.reset()
            st.last_nmpc, st.last_report = None, None
            st.last_u = np.zeros(4)
            st.neighbour_velocities.reset()
            st.nmpc.reset()
            st.viewpoint.reset()
            st.nmpc.reference[1] = st.viewpoint.x2
        self.timings.clear()

    def __call__(self, obs: dict, infos: dict[str, dict]) -> dict[str, np.ndarray]:
        return {agent: self.act(agent, infos[agent]) for agent in obs}

    def act(self, agent: str, info: dict) -> np.ndarray:
        """One UAV's action from its own info (measurement, own state, messages)."""
        st = self.agents[agent]
        t0 = time.perf_counter()
        est = st.tracker.update(info)
        if est is None:
            return np.zeros(4, np.float32)  # nothing seen yet: hover
        yaw = info["own"]["yaw"]
        t1 = time.perf_counter()
        plan_rows = rows = None
        if self.use_cbf:  # the CBF rows (47): the QP's, and with safety_rows also the plan's
            nb_v = st.neighbour_velocities(info["neighbours"]) if self.lag_aware else None
            ctx = safety_context(info, est, self.obstacle_centers, self.obstacle_half_extents, nb_v)
            rows = self.shield.rows(ctx)
            if st.nmpc.cfg.safety_rows:
                plan_rows = self.shield.camera_rows(rows, yaw, st.nmpc.cfg.safety_rows)
        t2 = time.perf_counter()
        own = info["own"]["position"]
        st.nmpc.reference[1] = st.viewpoint.update(
            est.target_position, est.target_velocity, own, est.s[1], 1.0 / est.s[2]
        )
        aq_cam = world_to_cam_vec(est.target_acceleration, yaw)
        st.last_nmpc = res = st.nmpc.solve(
            est.s, est.vq_cam, aq_cam, u_applied=st.last_u, safety_rows=plan_rows
        )
        u = res.u
        t3 = time.perf_counter()
        if self.use_cbf:
            u, st.last_report = self.shield.certify(u, ctx, rows)
        t4 = time.perf_counter()
        self.timings["ukf"].append(t1 - t0)
        self.timings["nmpc"].append(t3 - t2)
        self.timings["qp"].append(t2 - t1 + t4 - t3)
        st.last_u = np.asarray(u, float)
        return np.clip(st.last_u / self.scale, -1.0, 1.0).astype(np.float32)

    def slacks(self) -> dict[str, float]:
        """The QP slack of each agent's last step (0 without a report)."""
        return {
            a: (st.last_report.slack if st.last_report is not None else 0.0)
            for a, st in self.agents.items()
        }
