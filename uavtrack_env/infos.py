"""The per-agent info dicts of a step, built for the whole team at once.

Every number is read from the step's arrays once (``tolist`` for scalars, one copy per array whose
rows the agents get), so an agent's dict costs its dict literals and little else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .config import CameraConfig
from .core import Measurements, Score
from .sensors import Detections
from .target import TargetMotion

NOTHING_NEAR = 1.0e4
"""``info["truth"]["nearest_uav_distance"]`` with no other live UAV and
``"nearest_obstacle_clearance"`` without obstacles (m): finite, so every info value is."""

State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(position (n, 3), yaw (n,), velocity (n, 3), yaw rate (n,))."""


@dataclass(frozen=True)
class PixelFrame:
    """What turns features into pixels for one episode: the camera and the references' pixels."""

    focal: np.ndarray
    """(2,) [fx, fy]."""
    principal: np.ndarray
    """(2,) [cu, cv]."""
    image_size: np.ndarray
    """(2,) [width, height]: pixel errors are capped at it."""
    reference_px: np.ndarray
    """(n, 2) each UAV's reference [x1*, x2*] in pixels."""

    @classmethod
    def of(cls, camera: CameraConfig, references: np.ndarray) -> PixelFrame:
        focal = np.array([camera.fx, camera.fy])
        principal = np.array([camera.cu, camera.cv])
        return cls(
            focal,
            principal,
            np.array([camera.width, camera.height], float),
            references[:, :2] * focal + principal,
        )


@numba.njit(cache=True)
def _truth_numbers(
    box_center,
    features,
    reference_px,
    focal,
    principal,
    size,
    theta,
    candidates,
    near_uav,
    near_obstacle,
):  # pragma: no cover (compiled)
    """Per UAV: the box centre's error to the reference (px, capped at the image size: a car
    behind the camera projects arbitrarily far), the car centre's error (px), the least
    occlusion angle over N_oi (pi without candidates) and the nearest distances to a UAV and
    to an obstacle with `NOTHING_NEAR` for nothing (not finite)."""
    n, M = theta.shape
    pixel_error, center_error, least = np.empty((n, 2)), np.empty((n, 2)), np.empty(n)
    uav = np.where(np.isfinite(near_uav), near_uav, NOTHING_NEAR)
    obstacle = np.where(np.isfinite(near_obstacle), near_obstacle, NOTHING_NEAR)
    for i in range(n):
        for c in range(2):
            e = box_center[i, c] - reference_px[i, c]
            pixel_error[i, c] = e if e != e else min(max(e, -size[c]), size[c])  # NaN stays
            center_error[i, c] = features[i, c] * focal[c] + principal[c] - reference_px[i, c]
        least[i] = math.pi
        for m in range(M):
            t = theta[i, m]
            if candidates[i, m] and (t < least[i] or t != t):  # NaN stays, as in np.min
                least[i] = t
    return pixel_error, center_error, least, uav, obstacle


def sensor_infos(
    rows: list[int],
    names: list[str],
    det: Detections,
    received: np.ndarray,
    state: State,
) -> list[dict[str, dict]]:
    """What the sensors and radio of each UAV i in ``rows`` report, the part of its info an
    onboard stack reads: ``measurement`` (the detector's report; u, v, depth, psi None when not
    detected), ``own`` (position, yaw, velocity, yaw_rate from ``state``) and ``neighbours``
    (name -> position of each team-mate heard, ``received[i]``)."""
    position, yaw, velocity, yaw_rate = state
    detected, visible = det.detected.tolist(), det.visible_fraction.tolist()
    u, v, depth, psi = det.u.tolist(), det.v.tolist(), det.depth.tolist(), det.psi.tolist()
    cut, heard = det.truncated.tolist(), received.tolist()
    yaws, rates = yaw.tolist(), yaw_rate.tolist()
    velocities = velocity.copy()
    out = []
    for i in rows:
        ok = detected[i]
        team = position.copy()  # this UAV's own row and its team-mates' rows
        out.append(
            {
                "measurement": {
                    "detected": ok,
                    "u": u[i] if ok else None,
                    "v": v[i] if ok else None,
                    "depth": depth[i] if ok else None,
                    "psi": psi[i] if ok else None,
                    "visible_fraction": visible[i],
                    "truncated_u": ok and cut[i][0],
                    "truncated_v": ok and cut[i][1],
                },
                "own": {
                    "position": team[i],
                    "yaw": yaws[i],
                    "velocity": velocities[i],
                    "yaw_rate": rates[i],
                },
                "neighbours": {names[j]: team[j] for j, got in enumerate(heard[i]) if got},
            }
        )
    return out


def agent_infos(
    rows: list[int],
    names: list[str],
    m: Measurements,
    score: Score,
    u: np.ndarray,
    clipped: np.ndarray,
    clip_count: np.ndarray,
    references: np.ndarray,
    pixels: PixelFrame,
    target: TargetMotion,
    state: State,
) -> list[dict]:
    """The info dict of each UAV i in ``rows``: cost, violations, reward terms, the sensors'
    report (`sensor_infos`), the reference and the ground truth (the env's docstring)."""
    det = m.detections
    s, theta = det.true_features, m.occlusion_angles
    pixel_error, center_error, least_theta, near_uav, near_obstacle = _truth_numbers(
        det.box_center, s, pixels.reference_px, pixels.focal, pixels.principal,
        pixels.image_size, theta, m.occlusion_candidates, m.nearest_uav, m.nearest_obstacle,
    )  # fmt: skip
    features, thetas = s.copy(), theta.copy()
    candidates, refs, applied = m.occlusion_candidates.copy(), references.copy(), u.copy()
    x3, x3_ref = s[:, 2].tolist(), references[:, 2].tolist()
    in_front, blocked = det.in_front.tolist(), det.blocked_fraction.tolist()
    nearest_uav, nearest_obstacle = near_uav.tolist(), near_obstacle.tolist()
    target_clearance, least = m.target_clearance.tolist(), least_theta.tolist()
    collided, occluded = score.collided.tolist(), score.occluded.tolist()
    too_close, tracking, effort = (
        score.uav_too_close.tolist(), score.tracking.tolist(), score.effort.tolist()
    )  # fmt: skip
    hits = m.contacts
    ground, obstacle, car = (hits[k].tolist() for k in ("ground", "obstacle", "target"))
    cut, n_clipped = clipped.tolist(), clip_count.tolist()
    disconnected = score.disconnected
    motion = target.kinematics()
    sensed = sensor_infos(rows, names, det, m.received, state)
    out = []
    for i, sense in zip(rows, sensed, strict=True):
        collision, occlusion = collided[i], occluded[i]
        costs = {
            "collision": float(collision),
            "disconnection": float(disconnected),
            "occlusion": float(occlusion),
        }
        position, velocity, acceleration = motion.copy()
        info = {
            "cost": costs["collision"] + costs["disconnection"] + costs["occlusion"],
            "costs": costs,
            "violations": {
                "collision": collision,
                "disconnection": disconnected,
                "occlusion": occlusion,
            },
            "collision_with": {
                "uav": too_close[i],
                "ground": ground[i],
                "obstacle": obstacle[i],
                "target": car[i],
            },
            "reward_tracking": -tracking[i],
            "reward_effort": -effort[i],
            "action_clipped": cut[i],
            "n_clipped_actions": n_clipped[i],
            **sense,
            "reference": refs[i],
            "truth": {
                "features": features[i],
                "pixel_error": pixel_error[i],
                "center_pixel_error": center_error[i],
                "depth_error": 1.0 / x3[i] - 1.0 / x3_ref[i] if in_front[i] else None,
                "target_position": position,
                "target_velocity": velocity,
                "target_acceleration": acceleration,
                "nearest_uav_distance": nearest_uav[i],
                "nearest_obstacle_clearance": nearest_obstacle[i],
                "target_clearance": target_clearance[i],
                "occlusion_angles": thetas[i],
                "occlusion_candidates": candidates[i],
                "min_occlusion_angle": least[i],
                "blocked_fraction": blocked[i],
            },
        }
        sense["own"]["applied_u"] = applied[i]
        out.append(info)
    return out
