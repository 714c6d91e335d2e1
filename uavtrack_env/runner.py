"""One episode of any policy on a (possibly shielded) env -> recorder and metrics.

The single episode runner of `baselines.evaluate`, `baselines.compare`, `train.*` evaluations and
the closed-loop tests. A policy is ``policy(obs, infos) -> {agent: action}``; if it has
``reset(layout)`` (like `ExpertPolicy`) it is called with the new layout after the env's reset.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tqdm import tqdm

from .config import DT
from .kernels import kernels_cached, onboard_kernels, shield_kernels
from .metrics import EpisodeRecorder

VIOLATIONS = ("collision", "disconnection", "occlusion")
Policy = Callable[[dict, dict], dict]


@dataclass
class EpisodeResult:
    """What `run_episode` measured: the recorder (for figures) and the metrics dict."""

    recorder: EpisodeRecorder
    metrics: dict[str, Any]


def _kernels_used(env: Any) -> list[Any]:
    """The numba kernels an episode on ``env`` compiles: the onboard stack's, and a shield's
    if a `CBFShield` is among ``env``'s wrappers."""
    from .wrappers import CBFShield

    layer = env
    while layer is not None and not isinstance(layer, CBFShield):
        layer = getattr(layer, "env", None)
    return onboard_kernels() + (shield_kernels() if layer is not None else [])


def run_episode(
    env: Any,
    policy: Policy,
    *,
    seed: int,
    steps: int,
    theta_star: float = math.radians(30.0),
    label: str = "",
    progress: bool = False,
    on_step: Callable[[dict[str, dict]], None] | None = None,
) -> EpisodeResult:
    """Reset ``env`` with ``seed`` and run ``policy`` for at most ``steps`` steps. A policy with
    ``reset(layout)`` is reset to the episode's layout; one with ``compile_kernels()`` (the
    expert) builds its one-off kernels before the loop, so that no build stalls the episode.

    ``metrics`` holds: scenario, init, seed, duration_s, ``uavs`` (`EpisodeRecorder.summary`),
    ``timing_ms`` (medians per UAV-step: env, policy, and the policy's own stages if it keeps
    ``timings``), initial_conditions, ``violation_steps`` (agent-steps with each violation),
    ``violations_per_1000_steps``, ``agent_steps``, ``real_time_factor`` (simulated over wall
    time after the first step; NaN for a one-step episode), ``startup_s`` (the wall time up to
    the end of the first step: one-off compiles, the cold solve) and
    ``shield_intervention_rate`` (fraction of agent-steps whose action a shield or the
    expert's CBF-QP changed; None without either).
    ``theta_star`` (rad) is the occlusion angle the recorder compares theta of eq. (38) with;
    ``on_step(infos)`` is called after every step.
    """
    obs, infos = env.reset(seed=seed)
    raw = env.unwrapped
    if callable(getattr(policy, "reset", None)):
        policy.reset(raw.layout)
    rec = EpisodeRecorder(raw.possible_agents, DT, theta_star, raw.layout.obstacle_centers)
    rec.record(infos)
    tally = _Tally()
    slacks = getattr(policy, "slacks", None)
    if progress and not kernels_cached(_kernels_used(env)):
        print(
            "compiling the onboard stack's numba kernels for this machine (once, about a "
            "minute; cached for later runs) ...",
            file=sys.stderr,
            flush=True,
        )
    start = time.perf_counter()
    if callable(getattr(policy, "compile_kernels", None)):
        policy.compile_kernels()  # one-off builds before the loop, not in mid-episode
    after_first = None  # wall clock after the first step, which holds the one-off builds
    bar = tqdm(range(steps), desc=label, disable=not progress, leave=False)
    for k in bar:
        if not env.agents:
            break
        if k == 1:
            after_first = time.perf_counter()
        elif k and k % 80 == 0:  # once per simulated second
            rt = (k - 1) * DT / (time.perf_counter() - after_first)
            bar.set_postfix_str(f"x{rt:.2f} real time")
        t0 = time.perf_counter()
        actions = policy(obs, infos)
        t1 = time.perf_counter()
        obs, _, _, _, infos = env.step(actions)
        tally.env_time.append(time.perf_counter() - t1)
        tally.policy_time.append(t1 - t0)
        rec.record(infos, slacks() if slacks else None)
        if on_step is not None:
            on_step(infos)
        tally.add(infos, _shield_flags(infos, policy))
    end = time.perf_counter()
    after_first = end if after_first is None else after_first
    wall = end - after_first
    n = raw.config.n_uavs
    timing = {"env": _median_ms(tally.env_time) / n, "policy": _median_ms(tally.policy_time) / n}
    for stage, times in getattr(policy, "timings", {}).items():
        timing[stage] = _median_ms(times)
    metrics = {
        "scenario": raw.config.scenario,
        "init": raw.config.init,
        "seed": seed,
        "duration_s": (rec.steps - 1) * DT,
        "uavs": rec.summary(),
        "timing_ms": timing,
        "real_time_factor": (rec.steps - 2) * DT / wall if rec.steps > 2 and wall > 0 else math.nan,
        "startup_s": after_first - start,
        "initial_conditions": {
            a: [*map(float, raw.layout.uav_positions[i][:2]), float(raw.layout.uav_yaws[i])]
            for i, a in enumerate(raw.possible_agents)
        },
        **tally.summary(),
    }
    return EpisodeResult(rec, metrics)


@dataclass
class _Tally:
    """Violation agent-steps, interventions and step times of one episode."""

    agent_steps: int = 0
    active: int = 0
    certified: int = 0
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(VIOLATIONS, 0))
    env_time: list[float] = field(default_factory=list)
    policy_time: list[float] = field(default_factory=list)

    def add(self, infos: dict[str, dict], flags: dict[str, bool] | None) -> None:
        for info in infos.values():
            self.agent_steps += 1
            for k in VIOLATIONS:
                self.counts[k] += bool(info["violations"][k])
        if flags is not None:
            self.certified += len(flags)
            self.active += sum(flags.values())

    def summary(self) -> dict[str, Any]:
        steps = self.agent_steps
        return {
            "violations_per_1000_steps": {
                k: 1000.0 * v / steps if steps else math.nan for k, v in self.counts.items()
            },
            "violation_steps": self.counts,
            "agent_steps": steps,
            "shield_intervention_rate": self.active / self.certified if self.certified else None,
        }


def _median_ms(times: list[float]) -> float:
    return 1e3 * float(np.median(times)) if times else math.nan


def _shield_flags(infos: dict, policy: Any) -> dict[str, bool] | None:
    """Whether the shield (wrapper) or the expert's own CBF-QP changed each agent's action."""
    flags = {a: bool(i["shield"]["active"]) for a, i in infos.items() if "shield" in i}
    if flags:
        return flags
    planners = getattr(policy, "planners", None)
    if isinstance(planners, dict) and getattr(policy, "use_cbf", False):
        return {
            a: bool(st.last_report is not None and st.last_report.active)
            for a, st in planners.items()
            if a in infos
        }
    return None
