"""SB3 callbacks of `train.ppo`: the learning curve (console and TensorBoard), the exact step
budget and the progress bar.

Rates are per agent-step of one rollout (a violation rate of 0.002 is 2 violating agent-steps
per 1,000); episode returns and costs are per agent (one VecEnv row).
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

VIOLATIONS = ("collision", "disconnection", "occlusion")
COUNTS = ("agent_steps", *VIOLATIONS, "shield_active")


class StopAtTimesteps(BaseCallback):
    """Ends ``learn`` once ``num_timesteps`` reaches its ``total_timesteps``, inside a rollout.

    SB3 finishes the rollout it is in, which rounds the budget up to a multiple of
    ``n_steps * num_envs``; this stops at the first vector step at or beyond the budget (so
    the count overshoots by less than ``num_envs``). The steps of the unfinished rollout are
    sampled but not trained on."""

    def _on_training_start(self) -> None:
        self.target = int(self.locals["total_timesteps"])

    def _on_step(self) -> bool:
        rollout_done = self.locals["n_steps"] + 1 >= self.locals["n_rollout_steps"]
        return rollout_done or self.num_timesteps < self.target


class TrainingLog(BaseCallback):
    """Per rollout: mean episode return and cost per agent, violation and shield-intervention
    rates, agent-steps/s to TensorBoard (``rollout/ep_cost_mean``, ``safety/*_rate``,
    ``time/agent_steps_per_s``); a console line every ``every`` agent-steps, whose return and
    cost are the means over the last ``recent`` finished agent-episodes (SB3's
    ``ep_rew_mean`` convention: a number on every line, not only after rollouts in which
    episodes ended). ``totals`` counts the agent-steps of every violation over the whole call
    (for args.json). With ``events``, every violating agent-step is appended to that JSON-lines
    file: the agent-steps counter, the row, its world and UAV (row = world x UAVs + UAV) and
    the violations' names, so that a training violation can be found and replayed."""

    def __init__(
        self,
        every: int = 10_000,
        echo: Callable[[str], None] | None = print,
        recent: int = 100,
        events: Path | None = None,
    ) -> None:
        super().__init__()
        self.every, self.echo, self.events = every, echo, events
        self.recent: deque[tuple[float, float]] = deque(maxlen=recent)
        self.totals = dict.fromkeys(COUNTS, 0)
        self.extra: dict[str, Callable[[], float]] = {}
        """Further numbers for the log, read at each rollout's end (e.g. the multiplier)."""
        self._last_echo = 0

    def _on_training_start(self) -> None:
        self._last_echo = self.num_timesteps
        self._uavs = int(getattr(self.training_env, "n_agents", 1))
        self._on_rollout_start()

    def _on_rollout_start(self) -> None:
        self.counts = dict.fromkeys(COUNTS, 0)
        self.returns: list[float] = []
        self.costs: list[float] = []
        self.t0, self.steps0 = time.perf_counter(), self.num_timesteps

    def _on_step(self) -> bool:
        events: list[str] = []
        for row, info in enumerate(self.locals["infos"]):
            episode = info.get("episode")
            if episode is not None:
                self.returns.append(float(episode["r"]))
                self.costs.append(float(episode.get("c", np.nan)))
                self.recent.append((self.returns[-1], self.costs[-1]))
            v = info.get("violations")
            if v is None:  # absorbing row of a finished agent
                continue
            self.counts["agent_steps"] += 1
            names = [k for k in VIOLATIONS if v[k]]
            for k in names:
                self.counts[k] += 1
            if names and self.events is not None:
                events.append(self._event(row, names))
            self.counts["shield_active"] += bool(info.get("shield", {}).get("active", False))
        if events:  # one write per vector step that had violations
            with self.events.open("a") as f:
                f.writelines(events)
        return True

    def _event(self, row: int, names: list[str]) -> str:
        """One line of ``events``."""
        world, uav = divmod(row, self._uavs)
        line = {"agent_steps": self.num_timesteps, "row": row, "world": world, "uav": uav}
        return json.dumps({**line, "violations": names}) + "\n"

    def _on_rollout_end(self) -> None:
        row = self.row()
        for k in COUNTS:
            self.totals[k] += self.counts[k]
        for key, value in row.items():
            console_only = key == "agent_steps" or key.startswith("recent_")
            if not console_only and np.isfinite(value):
                self.logger.record(_TB_NAMES.get(key, key), value)
        if self.echo is not None and self.num_timesteps - self._last_echo >= self.every:
            self._last_echo = self.num_timesteps
            self.echo(format_row(row))
        self._on_rollout_start()

    def _on_training_end(self) -> None:
        if self.counts["agent_steps"]:  # a rollout that StopAtTimesteps cut short
            for k in COUNTS:
                self.totals[k] += self.counts[k]
        if self.echo is not None and self.num_timesteps != self._last_echo:
            self.echo(format_row(self.row()))

    def row(self) -> dict[str, float]:
        """This rollout's numbers (NaN where no episode ended) and the means over the last
        finished episodes (``recent_*``; NaN before the first)."""
        steps = max(self.counts["agent_steps"], 1)
        seconds = max(time.perf_counter() - self.t0, 1e-9)
        recent = np.array(self.recent, float).reshape(-1, 2)
        row = {
            "agent_steps": float(self.num_timesteps),
            "ep_return": float(np.mean(self.returns)) if self.returns else np.nan,
            "ep_cost": _nanmean(np.array(self.costs, float)),
            "recent_episodes": float(len(recent)),
            "recent_return": float(recent[:, 0].mean()) if len(recent) else np.nan,
            "recent_cost": _nanmean(recent[:, 1]),
            **{f"{k}_rate": self.counts[k] / steps for k in VIOLATIONS},
            "shield_rate": self.counts["shield_active"] / steps,
            "agent_steps_per_s": (self.num_timesteps - self.steps0) / seconds,
        }
        row.update({k: float(f()) for k, f in self.extra.items()})
        return row


_TB_NAMES = {
    "ep_return": "rollout/ep_agent_return_mean",
    "ep_cost": "rollout/ep_cost_mean",
    "collision_rate": "safety/collision_rate",
    "disconnection_rate": "safety/disconnection_rate",
    "occlusion_rate": "safety/occlusion_rate",
    "shield_rate": "safety/shield_intervention_rate",
    "agent_steps_per_s": "time/agent_steps_per_s",
    "lambda": "lagrangian/lambda",
}


def _nanmean(x: np.ndarray) -> float:
    """Mean of the finite entries; NaN if there are none."""
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else np.nan


def format_row(row: dict[str, float]) -> str:
    """One console line of the learning curve: return and cost over the last finished
    episodes ('-' before the first), the rates of the last rollout."""

    def num(x: float, spec: str) -> str:
        return format(x, spec) if np.isfinite(x) else "-"

    rates = " ".join(f"{k[:4]} {1000 * row[f'{k}_rate']:.2f}" for k in VIOLATIONS)
    text = (
        f"{row['agent_steps']:>10,.0f} steps | return {num(row['recent_return'], '.2f')} "
        f"| cost {num(row['recent_cost'], '.2f')} (last {row['recent_episodes']:.0f} "
        f"episodes) | violations/1k steps: {rates} "
        f"| shield {100 * row['shield_rate']:.0f} %"
    )
    if "lambda" in row:
        text += f" | lambda {row['lambda']:.3f}"
    return text + f" | {row['agent_steps_per_s']:,.0f} steps/s"


def progress_callback(enabled: bool) -> tuple[BaseCallback | None, bool]:
    """SB3's rich progress bar if rich is installed, else a tqdm callback (None if disabled);
    the flag says whether to pass ``progress_bar=True`` to ``learn``."""
    if not enabled:
        return None, False
    try:
        import rich  # noqa: F401

        return None, True
    except ImportError:
        pass
    from tqdm import tqdm

    class TqdmCallback(BaseCallback):
        def _on_training_start(self) -> None:
            total = self.locals["total_timesteps"]
            self.bar = tqdm(total=total, initial=self.model.num_timesteps, unit="step")

        def _on_step(self) -> bool:
            self.bar.update(self.model.num_timesteps - self.bar.n)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return TqdmCallback(), False


class VideoEvery(BaseCallback):
    """Every ``every`` agent-steps, a video of the current deterministic policy
    (`train.video.record_policy`) as ``folder/step-<agent-steps>-episode-0.mp4``."""

    def __init__(self, every: int, record: Callable[[BaseCallback, str], object]) -> None:
        super().__init__()
        self.every, self.record = every, record

    def _on_training_start(self) -> None:
        self.next = (self.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next:
            self.next += self.every
            self.record(self, f"step-{self.num_timesteps}")
        return True


class CertifiedActions(BaseCallback):
    """Stores the shield's certified actions in PPO's rollout buffer in place of the proposed
    ones, with their log-probabilities under the acting policy (`train.ppo --learn-certified`).

    The world executes the certified action, so the advantage belongs to it; trained on the
    proposed one, PPO credits every proposal the shield maps to the same certified action alike
    and learns little where the shield acts. SB3 calls callbacks after each vector step and
    before it stores the step, so the stored arrays are changed in place. Rows without a
    ``shield`` entry (absorbing rows) keep their action. Not in the paper."""

    def _on_step(self) -> bool:
        import torch

        infos, actions = self.locals["infos"], self.locals["actions"]
        rows = [i for i, info in enumerate(infos) if "action" in info.get("shield", {})]
        if not rows:
            return True
        for i in rows:
            actions[i] = infos[i]["shield"]["action"]
        policy = self.model.policy
        with torch.no_grad():
            dist = policy.get_distribution(self.locals["obs_tensor"][rows])
            taken = torch.as_tensor(actions[rows], device=policy.device)
            self.locals["log_probs"][rows] = dist.log_prob(taken)
        return True
