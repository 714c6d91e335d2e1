"""The shield's corrections as a reward penalty (`train.ppo --intervention-penalty K`).

A shielded policy that steers into the CBF rows is corrected every step and learns nothing from
it: the reward only sees the certified action's outcome. Charging K per m/s of correction,
r <- r - K ||u_certified - u_proposed|| (``info["shield"]["correction_norm"]``, camera frame),
teaches the policy to propose actions the shield passes unchanged, the usual shaping of shielded
RL (Alshiekh et al. 2018, "Safe Reinforcement Learning via Shielding"). Not in the paper.
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn


def checked_coef(coef: float) -> float:
    """``coef`` as a float; ValueError unless it is finite and >= 0."""
    if not (np.isfinite(coef) and coef >= 0):
        raise ValueError(f"the intervention penalty must be a finite number >= 0, got {coef}")
    return float(coef)


class InterventionPenalty(VecEnvWrapper):
    """Subtracts ``coef`` x the shield's correction (m/s) from each row's reward.

    Rows without a ``shield`` entry (an unshielded env, the absorbing rows of finished agents)
    keep their reward."""

    def __init__(self, venv, coef: float) -> None:
        super().__init__(venv)
        self.coef = checked_coef(coef)

    def reset(self) -> np.ndarray:
        return self.venv.reset()

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        correction = np.array(
            [float(info.get("shield", {}).get("correction_norm", 0.0)) for info in infos],
            np.float32,
        )
        return obs, (rewards - self.coef * correction).astype(np.float32), dones, infos
