"""Reward and cost terms, each named, vectorised over the UAVs.

The reward comes from the NMPC's stage cost (18) evaluated on the true features:
c = sum_k q_k e_k^2 + lost + sum_k r_k u_k^2, with e = s - s* (psi wrapped) and u in SI units;
r = -c (default) or exp(-c) (for RL), minus an optional collision penalty.
"""

from __future__ import annotations

import numpy as np

from .config import RewardConfig
from .geometry import wrap_angle

FEATURE_ERROR_CAP = np.array([2.0, 2.0, 1.0, np.pi])
"""Caps on |e| so that a target at the image's edge or behind the camera gives a bounded reward."""


def feature_error(true_features: np.ndarray, references: np.ndarray) -> np.ndarray:
    """e = s - s* (n, 4), psi wrapped to (-pi, pi]."""
    e = true_features - references
    e[:, 3] = wrap_angle(e[:, 3])
    return e


def tracking_term(
    true_features: np.ndarray,
    references: np.ndarray,
    in_front: np.ndarray,
    detected: np.ndarray,
    cfg: RewardConfig,
) -> np.ndarray:
    """sum_k q_k e_k^2 (n,), capped per feature, plus ``lost_penalty`` when not detected."""
    e = np.clip(feature_error(true_features, references), -FEATURE_ERROR_CAP, FEATURE_ERROR_CAP)
    e[~in_front, :3] = FEATURE_ERROR_CAP[:3]
    # Row-wise sums, not a matrix product: the same value whatever the batch (K worlds x n).
    return (e**2 * np.asarray(cfg.q)).sum(axis=-1) + cfg.lost_penalty * ~detected


def effort_term(u: np.ndarray, cfg: RewardConfig) -> np.ndarray:
    """sum_k r_k u_k^2 (n,), the input cost of eq. (18) with u_d = 0."""
    return (u**2 * np.asarray(cfg.r)).sum(axis=-1)


def reward(stage_cost: np.ndarray, collided: np.ndarray, cfg: RewardConfig) -> np.ndarray:
    """Per-UAV reward (n,) from the stage cost: -c or exp(-c) (``cfg.shape``), minus the
    collision penalty."""
    r = -stage_cost if cfg.shape == "cost" else np.exp(-stage_cost)
    return r - cfg.collision_penalty * collided


def connected(dist: np.ndarray, alive: np.ndarray, r_c: float) -> bool:
    """Whether the alive UAVs form one connected graph with edges of length <= R_c.

    ``dist`` is the (n, n) matrix of inter-UAV distances.
    """
    return bool(connected_batch(dist[None], alive[None], r_c)[0])


def connected_batch(dist: np.ndarray, alive: np.ndarray, r_c: float) -> np.ndarray:
    """`connected` of K graphs at once: dist (K, n, n), alive (K, n) -> (K,) bool.

    The reachability of every pair by repeated squaring of the adjacency (self-loops included);
    connected when every two alive UAVs reach each other (one or none alive: connected)."""
    n = dist.shape[-1]
    pairs = alive[:, :, None] & alive[:, None, :]
    reach = ((dist <= r_c) & pairs) | np.eye(n, dtype=bool)
    hops = 1
    while hops < n - 1:
        r = reach.astype(np.float64)  # BLAS; sums of 0/1 below 2^53 are exact
        reach = (r @ r) > 0
        hops *= 2
    return (reach | ~pairs).all(axis=(1, 2))
