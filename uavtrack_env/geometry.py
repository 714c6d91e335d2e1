"""Frames, rotations, pinhole projection and the feature vector s = [x1, x2, x3, psi].

Conventions (docs/conventions.md):

* Global frame: x forward along the road, y left, z up, ground at z = 0.
* Camera frame (paper, Fig. 2): optical axis Z forward along the UAV heading, X right, Y down.
  The UAV only yaws; with yaw ``phi`` the camera-to-global rotation has columns
  right = (sin phi, -cos phi, 0), down = (0, 0, -1), forward = (cos phi, sin phi, 0).
* omega_cy turns the camera about its Y (down) axis, so the global yaw rate is -omega_cy.
* psi follows eq. (4): the angle of the target-to-UAV vector minus the target's heading,
  wrapped to (-pi, pi]. It grows when the UAV orbits counter-clockwise, which is the sign of
  eq. (12)/(15). Under eq. (4) UAV2 of scenario A starts behind the target at psi = pi, so its
  reference is pi (the paper prints 0; see docs/conventions.md).

Functions accept a trailing batch dimension where noted and are plain numpy; the feature
dynamics `feature_rates` also work with CasADi symbols.
"""

from __future__ import annotations

import math

import numpy as np

_SCALARS = (float, int, np.floating, np.integer)


def wrap_angle(a):
    """Wrap angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)


def wrap_scalar(a: float) -> float:
    """`wrap_angle` of one real number (the same value, without numpy's dispatch)."""
    return math.pi - (math.pi - a) % (2.0 * math.pi)


def cam_to_world(yaw) -> np.ndarray:
    """Rotation (R)_c^g from the camera frame to the global frame, shape (..., 3, 3)."""
    yaw = np.asarray(yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(yaw), np.ones_like(yaw)
    cols = [np.stack([s, -c, z], -1), np.stack([z, z, -o], -1), np.stack([c, s, z], -1)]
    return np.stack(cols, -1)


def _one_vector(v, yaw) -> bool:
    """A real scalar yaw and one float64 3-vector (the rotations' fast path)."""
    return (
        isinstance(yaw, _SCALARS)
        and isinstance(v, np.ndarray)
        and v.shape == (3,)
        and v.dtype == np.float64
    )


def world_to_cam_vec(v_world: np.ndarray, yaw) -> np.ndarray:
    """Express global vectors (..., 3) in the camera frame of a UAV with this yaw."""
    if _one_vector(v_world, yaw):  # no broadcasting machinery
        c, s = math.cos(yaw), math.sin(yaw)
        x, y, z = v_world.tolist()
        return np.array((s * x - c * y, -z, c * x + s * y))
    v_world, yaw = np.asarray(v_world, dtype=float), np.asarray(yaw, dtype=float)[..., None]
    c, s = np.cos(yaw), np.sin(yaw)
    x, y, z = v_world[..., 0:1], v_world[..., 1:2], v_world[..., 2:3]
    return np.concatenate([s * x - c * y, -z, c * x + s * y], -1)


def cam_to_world_vec(v_cam: np.ndarray, yaw) -> np.ndarray:
    """Express camera-frame vectors (..., 3) in the global frame."""
    if _one_vector(v_cam, yaw):  # no broadcasting machinery
        c, s = math.cos(yaw), math.sin(yaw)
        X, Y, Z = v_cam.tolist()
        return np.array((s * X + c * Z, -c * X + s * Z, -Y))
    v_cam, yaw = np.asarray(v_cam, dtype=float), np.asarray(yaw, dtype=float)[..., None]
    c, s = np.cos(yaw), np.sin(yaw)
    X, Y, Z = v_cam[..., 0:1], v_cam[..., 1:2], v_cam[..., 2:3]
    return np.concatenate([s * X + c * Z, -c * X + s * Z, -Y], -1)


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame points (..., 3) to pixels (..., 2), eq. (8)."""
    z = points_cam[..., 2:3]
    return np.concatenate(
        [
            K[0, 0] * points_cam[..., 0:1] / z + K[0, 2],
            K[1, 1] * points_cam[..., 1:2] / z + K[1, 2],
        ],
        -1,
    )


def image_features(r_qc_cam: np.ndarray) -> np.ndarray:
    """[x1, x2, x3] = [X/Z, Y/Z, 1/Z] of eq. (6) for camera-frame relative positions (..., 3)."""
    z = r_qc_cam[..., 2:3]
    return np.concatenate([r_qc_cam[..., 0:1] / z, r_qc_cam[..., 1:2] / z, 1.0 / z], -1)


def relative_angle(p_uav: np.ndarray, p_target: np.ndarray, target_heading) -> np.ndarray:
    """psi of eq. (4): angle of the target-to-UAV vector minus the target heading, in (-pi, pi]."""
    d = np.asarray(p_uav, dtype=float) - np.asarray(p_target, dtype=float)
    return wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - target_heading)


def feature_rates(s, u, vq_cam):
    """Feature dynamics s_dot of eq. (15) for s = [x1, x2, x3, psi], u = [v_cx, v_cy, v_cz, w_cy].

    ``vq_cam`` is the target velocity expressed in the camera frame. Rows 1-3 are exact for a point
    target and a yaw-only camera; row 4 is the paper's approximation (12) under Assumption 2.
    Works on numpy arrays (1-D) and on CasADi SX/MX vectors; returns a list of four expressions.
    """
    x1, x2, x3 = s[0], s[1], s[2]
    dvx, dvy, dvz = u[0] - vq_cam[0], u[1] - vq_cam[1], u[2] - vq_cam[2]
    w = u[3]
    return [
        -x3 * dvx + x1 * x3 * dvz - (1 + x1 * x1) * w,
        -x3 * dvy + x2 * x3 * dvz - w * x1 * x2,
        x3 * x3 * dvz - w * x1 * x3,
        dvx * x3 / (1 + x1 * x1 + x2 * x2) ** 0.5,
    ]


def occlusion_angle(p_uav: np.ndarray, p_obstacle: np.ndarray, n: np.ndarray) -> np.ndarray:
    """theta of eq. (38): angle between p_o - p and the UAV-to-target vector n (radians)."""
    d = np.asarray(p_obstacle, dtype=float) - np.asarray(p_uav, dtype=float)
    cos = np.sum(d * n, -1) / (np.linalg.norm(d, axis=-1) * np.linalg.norm(n, axis=-1))
    return np.arccos(np.clip(cos, -1.0, 1.0))


def point_box_distance(points: np.ndarray, centers: np.ndarray, half_extents: np.ndarray):
    """Euclidean distance from points (P, 3) to axis-aligned boxes (M, 3): returns (P, M).

    Zero for a point inside a box.
    """
    d = np.abs(points[:, None, :] - centers[None, :, :]) - half_extents[None, :, :]
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1)


def segment_hits_boxes(
    a: np.ndarray, b: np.ndarray, centers: np.ndarray, half_extents: np.ndarray
) -> np.ndarray:
    """Which axis-aligned boxes (M, 3) the segment a -> b crosses (slab test): bool (M,)."""
    if len(centers) == 0:
        return np.zeros(0, bool)
    d = np.asarray(b, float) - np.asarray(a, float)
    lo, hi = centers - half_extents - a, centers + half_extents - a
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = lo * inv, hi * inv
    parallel = np.abs(d) < 1e-12
    inside = (lo <= 0.0) & (hi >= 0.0)
    tmin = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    tmax = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = np.max(tmin, axis=1), np.min(tmax, axis=1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)
