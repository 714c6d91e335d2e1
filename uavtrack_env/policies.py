"""Simple reference policies on the env's observations: hover, uniform random, visual servo.

Each is a callable ``policy(agent, obs) -> action in [-1, 1]^4``; none is safe by itself.
"""

from __future__ import annotations

import numpy as np

from .config import ControlLimits


class HoverPolicy:
    """Zero velocity command."""

    def __call__(self, agent: str, obs: np.ndarray) -> np.ndarray:
        return np.zeros(4, np.float32)


class RandomPolicy:
    """Uniform random actions from its own seeded generator."""

    def __init__(self, seed: int = 0, scale: float = 1.0) -> None:
        self.rng = np.random.default_rng(seed)
        self.scale = scale

    def __call__(self, agent: str, obs: np.ndarray) -> np.ndarray:
        return (self.scale * self.rng.uniform(-1.0, 1.0, 4)).astype(np.float32)


class VisualServoPolicy:
    """Proportional image-based servo that inverts the dominant terms of eq. (15).

    With e = s - s*: v_cx = -k_psi e_psi / x3 (row 4), omega_cy cancels x1's drift and adds
    k1 e1 (row 1), v_cy = k2 e2 / x3 (row 2), v_cz = -k3 e3 / x3^2 (row 3); hover when not detected.
    No target-velocity feed-forward and no safety: a baseline, not the paper's controller.
    """

    def __init__(
        self,
        gains: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 0.5),
        limits: ControlLimits | None = None,
    ) -> None:
        self.k = gains
        self.scale = (limits or ControlLimits()).scale

    def __call__(self, agent: str, obs: np.ndarray) -> np.ndarray:
        x1, x2, x3, sp, cp, detected = obs[:6]
        if detected < 0.5 or x3 <= 0:
            return np.zeros(4, np.float32)
        r1, r2, r3, srp, crp = obs[14:19]
        e_psi = np.arctan2(sp * crp - cp * srp, cp * crp + sp * srp)
        k1, k2, k3, kp = self.k
        v_cx = -kp * e_psi / x3
        w = (k1 * (x1 - r1) - x3 * v_cx) / (1.0 + x1 * x1)
        v_cy = k2 * (x2 - r2) / x3
        v_cz = -k3 * (x3 - r3) / (x3 * x3)
        u = np.array([v_cx, v_cy, v_cz, w])
        return np.clip(u / self.scale, -1.0, 1.0).astype(np.float32)
