"""UAV motion: the paper's single integrator (eq. 3) or a first-order velocity lag.

Commands are camera-frame u = [v_cx, v_cy, v_cz, omega_cy]; the state is global position, yaw,
global velocity and yaw rate, for all UAVs at once (arrays with a leading UAV axis).
"""

from __future__ import annotations

import numpy as np

from .config import DynamicsConfig
from .geometry import cam_to_world_vec, wrap_angle


def commanded_rates(u: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global velocity (n, 3) and yaw rate (n,) that command u (n, 4) asks for, eq. (3)."""
    return cam_to_world_vec(u[..., :3], yaw), -u[..., 3]


def integrate(
    position: np.ndarray,
    yaw: np.ndarray,
    velocity: np.ndarray,
    yaw_rate: np.ndarray,
    u: np.ndarray,
    cfg: DynamicsConfig,
    dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One control period: returns new (position, yaw, velocity, yaw_rate).

    'integrator': the velocity is the command (eq. 3), rotated with the yaw at the period's start;
    forward Euler, as the paper discretises (10). 'lag': v_dot = (v_cmd - v) / tau with
    ||v_dot|| <= a_max, and the yaw rate follows its command with time constant yaw_tau.
    """
    v_cmd, w_cmd = commanded_rates(u, yaw)
    if cfg.model == "integrator":
        velocity, yaw_rate = v_cmd, w_cmd
    else:
        accel = (v_cmd - velocity) / cfg.tau
        norm = np.linalg.norm(accel, axis=-1, keepdims=True)
        accel *= np.minimum(1.0, cfg.a_max / np.maximum(norm, 1e-12))
        velocity = velocity + accel * dt
        yaw_rate = yaw_rate + (w_cmd - yaw_rate) * min(1.0, dt / cfg.yaw_tau)
    return position + velocity * dt, wrap_angle(yaw + yaw_rate * dt), velocity, yaw_rate
