"""PPO-Lagrangian for `train.ppo --lagrangian`: the constrained problem
max_pi J_r(pi) s.t. J_c(pi) <= d as the saddle point of L = J_r - lambda (J_c - d).

J_c is the expected episode cost per agent (the sum of ``info["cost"]``, one per violation and
agent-step) and d the cost limit. PPO maximises the penalised reward (r - lambda c) / (1 +
lambda) with one critic (the 1 / (1 + lambda) keeps its scale as lambda grows); after each
rollout lambda takes a projected gradient-ascent step on the episodes that ended in it:
lambda <- max(0, lambda + lr (mean J_c - d)). The PPO-Lagrangian of Ray et al. (2019,
"Benchmarking Safe Exploration in Deep RL") estimates the advantage of c with a second critic;
here one critic learns the penalised reward, the multiplier's update is the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from uavtrack_env.validation import Fields


@dataclass(frozen=True)
class LagrangianConfig:
    """The multiplier's settings (not in the paper: the safe-RL baseline)."""

    cost_limit: float = 25.0
    """d: the episode cost per agent the policy may spend (violating agent-steps); 25 is
    Safety-Gymnasium's budget. On 1200-step episodes a limit of 1 drives lambda past 300, where
    the penalty outweighs the reward (docs/results/rl-training.md)."""
    lambda_lr: float = 0.05
    """Step size of lambda's gradient ascent per rollout."""
    lambda_init: float = 0.0
    """lambda before the first update."""

    def __post_init__(self) -> None:
        f = Fields(self)
        f.number("cost_limit", lo=0)
        f.number("lambda_lr", lo=0, lo_open=True)
        f.number("lambda_init", lo=0)


class LagrangianReward(VecEnvWrapper):
    """Replaces each row's reward r by (r - lambda c) / (1 + lambda), c = ``info["cost"]``.

    Rows without a cost (the absorbing rows of finished agents) keep their reward. ``update``
    moves lambda from the costs of finished episodes."""

    def __init__(self, venv, config: LagrangianConfig) -> None:
        super().__init__(venv)
        self.config = config
        self.lam = float(config.lambda_init)

    def reset(self) -> np.ndarray:
        return self.venv.reset()

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        cost = np.array([float(info.get("cost", 0.0)) for info in infos], np.float32)
        rewards = (rewards - self.lam * cost) / (1.0 + self.lam)
        return obs, rewards.astype(np.float32), dones, infos

    def update(self, episode_costs: list[float]) -> float:
        """One ascent step on the mean of ``episode_costs``; no step without episodes."""
        if episode_costs:
            gap = float(np.mean(episode_costs)) - self.config.cost_limit
            self.lam = max(0.0, self.lam + self.config.lambda_lr * gap)
        return self.lam


class MultiplierUpdate(BaseCallback):
    """After each rollout, `LagrangianReward.update` on the episode costs (``episode["c"]`` of
    `AgentVecMonitor`) of the episodes that ended in it."""

    def __init__(self, penalty: LagrangianReward) -> None:
        super().__init__()
        self.penalty = penalty
        self.costs: list[float] = []

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            episode = info.get("episode")
            if episode is not None and "c" in episode:
                self.costs.append(float(episode["c"]))
        return True

    def _on_rollout_end(self) -> None:
        self.penalty.update(self.costs)
        self.costs = []
