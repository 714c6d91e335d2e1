"""The paper's expert: per UAV, UKF (II-E) -> NMPC (18)-(19) -> distributed CBF-QP (47).

Each UAV is an `OnboardAgent` (what it knows, its CBF-QP) plus a planner (NMPC and the viewpoint
layer). It sees only what a real UAV has: the detector's report, its own GPS/IMU state, the
positions its neighbours sent, the known obstacle map and its reference; never ``info["truth"]``.
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .config import DT, EnvConfig
from .control import NMPC, NMPCResult
from .control.viewpoint import ViewpointPlanner
from .geometry import world_to_cam_vec
from .kernels import compile_filter_kernels
from .onboard import observe_team, onboard_team
from .presets import ExpertConfig, expert_config
from .safety import ShieldReport
from .scenarios import Layout


@dataclass
class PlannerState:
    """One UAV's planner (NMPC and viewpoint layer) and its last outputs."""

    reference: np.ndarray
    """The layout's s* the NMPC was built for (the NMPC's own x2* follows the viewpoint)."""
    nmpc: NMPC
    viewpoint: ViewpointPlanner
    last_nmpc: NMPCResult | None = None
    last_report: ShieldReport | None = None
    last_u: np.ndarray = field(default_factory=lambda: np.zeros(4))


class ExpertPolicy:
    """UKF -> NMPC -> CBF-QP for every agent; ``policy(obs, infos) -> {agent: action}``.

    ``config``: an `ExpertConfig` or a preset name (`uavtrack_env.presets.PRESETS`; default
    ``"tuned"``). Call `reset` with the env's layout after every env reset (`from_env` does the
    first). Actions are the env's normalised [-1, 1]^4. ``timings[stage]`` holds per-agent-step
    wall times (s) of 'ukf', 'nmpc' (with the viewpoint layer) and 'qp' (rows and QP).

    ``threads``: UAVs planned at once, as each UAV plans on its own computer in the paper's
    distributed scheme: their NMPC solves run in parallel (CasADi releases the GIL), the Python
    parts in turn. None: one per UAV, at most the CPUs this process may use (`default_threads`);
    1: one after the other. The actions do not depend on it; with more than one thread the stage
    timings include waiting for the other UAVs' Python work.
    """

    def __init__(
        self,
        agents: list[str],
        env_config: EnvConfig,
        config: ExpertConfig | str | None = None,
        threads: int | None = None,
    ) -> None:
        if threads is None:
            threads = default_threads(len(agents))
        elif isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be an integer >= 1 or None, got {threads!r}")
        self.threads = threads
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0
        self.config = cfg = expert_config(config)
        self.env_config = env_config
        self.scale = env_config.limits.scale
        self.agent_names = list(agents)
        team = onboard_team(self.agent_names, env_config, cfg)[0]
        self.onboard = {agent.name: agent for agent in team}
        self.planners: dict[str, PlannerState] = {}
        self.layout: Layout | None = None
        self.timings: dict[str, list[float]] = defaultdict(list)
        self._ukf_time = 0.0

    @property
    def use_cbf(self) -> bool:
        return self.config.use_cbf

    @classmethod
    def from_env(
        cls, env, config: ExpertConfig | str | None = None, threads: int | None = None
    ) -> ExpertPolicy:
        """Build for a reset env: its agents, world and layout."""
        layout = getattr(env, "layout", None)
        if layout is None:
            raise RuntimeError("ExpertPolicy.from_env needs an env that has been reset")
        expert = cls(env.possible_agents, env.config, config, threads)
        expert.reset(layout)
        return expert

    def reset(self, layout: Layout) -> None:
        """A new episode on ``layout``: new map and references for every stateful part; forgets
        all estimates and warm starts."""
        cfg = self.config
        self.layout = layout
        for i, a in enumerate(self.agent_names):
            self.onboard[a].reset(layout, self.agent_names)
            ref = np.asarray(layout.references[i], float)
            viewpoint = ViewpointPlanner(
                ref[1], layout.obstacle_centers, layout.obstacle_half_extents, cfg.viewpoint, DT
            )
            st = self.planners.get(a)
            if st is None or not np.array_equal(st.reference, ref):
                limits = self.env_config.limits
                nmpc = NMPC(ref, cfg.nmpc, limits, cfg.feature_bounds)
                self.planners[a] = PlannerState(ref, nmpc, viewpoint)
            else:
                st.viewpoint = viewpoint
                st.last_nmpc, st.last_report, st.last_u = None, None, np.zeros(4)
                st.nmpc.reset()
            self.planners[a].nmpc.reference[1] = viewpoint.x2
        self.timings.clear()

    def __call__(self, obs: dict, infos: dict[str, dict]) -> dict[str, np.ndarray]:
        if self.layout is None:
            raise RuntimeError("ExpertPolicy called before reset(layout)")
        t0 = time.perf_counter()
        observe_team([self.onboard[a] for a in obs], [infos[a] for a in obs])
        self._ukf_time = (time.perf_counter() - t0) / max(len(obs), 1)
        agents = list(obs)
        if self.threads == 1 or len(agents) == 1:
            plans = [self._plan(agent, infos[agent]) for agent in agents]
        else:
            if self._pool is None or self._pool_pid != os.getpid():  # none yet, or forked
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="uavtrack-plan")
                self._pool_pid = os.getpid()
            plans = list(self._pool.map(lambda agent: self._plan(agent, infos[agent]), agents))
        return {agent: self._record(plan) for agent, plan in zip(agents, plans, strict=True)}

    def compile_kernels(self) -> None:
        """Compile the CBF-QP's correction and plan-row kernels (`kernels.compile_filter_kernels`,
        with the CBF) and the NMPC's one-step prediction (first used at the second step) now
        rather than in the episode."""
        if self.use_cbf:
            compile_filter_kernels(self.onboard[self.agent_names[0]].filter)
        st = next(iter(self.planners.values()), None)  # the planners exist after reset()
        if st is not None:
            st.nmpc.predict_one_step(st.nmpc.reference, np.zeros(4), np.zeros(3))

    def close(self) -> None:
        """Stop the planning threads (a later call starts them again)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def act(self, agent: str, info: dict) -> np.ndarray:
        """One UAV's action from its own info (measurement, own state, messages)."""
        if self.layout is None:
            raise RuntimeError("ExpertPolicy.act before reset(layout)")
        t0 = time.perf_counter()
        self.onboard[agent].observe(info)
        self._ukf_time = time.perf_counter() - t0
        return self._record(self._plan(agent, info))

    def _record(self, plan: tuple[np.ndarray, tuple[float, float] | None]) -> np.ndarray:
        """Keep a plan's stage times (in the caller's thread, in the agents' order); its action."""
        action, times = plan
        if times is not None:
            self.timings["ukf"].append(self._ukf_time)
            self.timings["nmpc"].append(times[0])
            self.timings["qp"].append(times[1])
        return action

    def _plan(self, agent: str, info: dict) -> tuple[np.ndarray, tuple[float, float] | None]:
        """The agent's action from its observed stack (viewpoint, NMPC, CBF-QP) and the times
        (s) of its 'nmpc' and 'qp' stages (None when it hovers: nothing seen yet)."""
        onboard, st = self.onboard[agent], self.planners[agent]
        est = onboard.estimate
        if est is None:
            return np.zeros(4, np.float32), None  # nothing seen yet: hover
        yaw = info["own"]["yaw"]
        t1 = time.perf_counter()
        use_cbf = self.config.use_cbf
        plan_rows = None
        if use_cbf and st.nmpc.cfg.safety_rows:  # the plan respects the QP's nearest rows
            plan_rows = onboard.filter.camera_rows(onboard.rows(), yaw, st.nmpc.cfg.safety_rows)
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
        if use_cbf:
            u, st.last_report = onboard.certify(u)
        t4 = time.perf_counter()
        st.last_u = np.asarray(u, float)
        action = np.clip(st.last_u / self.scale, -1.0, 1.0).astype(np.float32)
        return action, (t3 - t2, t2 - t1 + t4 - t3)

    def applied(self, actions: dict[str, np.ndarray]) -> None:
        """The normalised actions the env applied when they were not this expert's (a learner
        acting while the expert labels, DAgger: `train.bc.collect`): each NMPC's error signal
        (16) then starts from the applied input."""
        for agent, action in actions.items():
            u = np.clip(np.asarray(action, float), -1.0, 1.0) * self.scale
            self.planners[agent].last_u = u

    def slacks(self) -> dict[str, float]:
        """The QP slack of each agent's last step (0 without a report)."""
        return {
            a: (st.last_report.slack if st.last_report is not None else 0.0)
            for a, st in self.planners.items()
        }


def usable_cpus() -> int:
    """The CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def default_threads(n_agents: int) -> int:
    """Planning threads for a team of ``n_agents``: one per UAV, at most `usable_cpus`."""
    return max(1, min(n_agents, usable_cpus()))
