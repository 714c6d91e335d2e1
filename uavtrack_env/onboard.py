"""What one UAV knows, read from its own ``info``: target estimate and the shield's context.

Shared by the expert and the RL shield so that both see exactly a real UAV's information: the
detector's report, its own GPS/IMU state, its neighbours' messages and the known obstacle map,
never ``info["truth"]``.
"""

from __future__ import annotations

import numpy as np

from .config import DT, CameraConfig
from .estimation import Estimate, Measurement, TargetEstimator, UKFConfig
from .geometry import world_to_cam_vec
from .safety import SafetyContext


class OnboardTracker:
    """One UAV's UKF, fed step by step from its info; ``estimate`` is None until a detection."""

    def __init__(self, camera: CameraConfig, cfg: UKFConfig | None = None) -> None:
        self.estimator = TargetEstimator(camera, cfg or UKFConfig())
        self.estimate: Estimate | None = None

    def reset(self) -> None:
        self.estimate = None

    def update(self, info: dict) -> Estimate | None:
        """Advance the filter with this step's info (measurement and own motion)."""
        own, m = info["own"], info["measurement"]
        pos, yaw = own["position"], own["yaw"]
        meas = None
        if m["detected"]:
            meas = Measurement(
                m["u"], m["v"], m["depth"], m["psi"], m["truncated_u"], m["truncated_v"]
            )
        if self.estimate is None:
            if meas is not None:
                self.estimate = self.estimator.reset(meas, pos, yaw)
            return self.estimate
        # The UAV's own velocity (IMU/odometry) in the camera frame, as applied over the step.
        u_meas = np.concatenate([world_to_cam_vec(own["velocity"], yaw), [-own["yaw_rate"]]])
        self.estimate = self.estimator.step(u_meas, pos, yaw, meas)
        return self.estimate


class NeighbourVelocities:
    """Neighbours' global velocities, differenced from their consecutive position messages.

    A UAV hears only positions (section III); second-order CBF rows (`ShieldOptions.lag_tau`)
    also need the neighbours' velocities. Call once per step with that step's messages; a
    neighbour not heard at the previous step counts as still (exact at a reset, where all start
    at rest). With the env's forward-Euler step the difference is the velocity exactly.
    """

    def __init__(self, dt: float = DT) -> None:
        self.dt = dt
        self._last: dict[str, np.ndarray] = {}

    def reset(self) -> None:
        self._last = {}

    def __call__(self, messages: dict) -> np.ndarray:
        """(k, 3) velocities of the k neighbours in ``messages`` (name -> position), in order."""
        out = np.zeros((len(messages), 3))
        for k, (name, pos) in enumerate(messages.items()):
            before = self._last.get(name)
            if before is not None:
                out[k] = (np.asarray(pos) - before) / self.dt
        self._last = {name: np.array(pos, float) for name, pos in messages.items()}
        return out


def safety_context(
    info: dict,
    estimate: Estimate | None,
    obstacle_centers: np.ndarray,
    obstacle_half_extents: np.ndarray,
    neighbour_velocities: np.ndarray | None = None,
) -> SafetyContext:
    """The CBF-QP's view for one UAV: own pose and velocity, received positions (and, for
    second-order rows, the neighbours' velocities), obstacles, target estimate."""
    own = info["own"]
    nb = info["neighbours"]
    return SafetyContext(
        position=own["position"],
        yaw=own["yaw"],
        velocity=own["velocity"],
        neighbours=np.array(list(nb.values()), float).reshape(-1, 3),
        neighbour_velocities=neighbour_velocities,
        obstacle_centers=obstacle_centers,
        obstacle_half_extents=obstacle_half_extents,
        target_position=None if estimate is None else estimate.target_position,
        target_velocity=None if estimate is None else estimate.target_velocity,
    )
