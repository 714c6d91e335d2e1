"""Rendering: an overview of the scene beside each UAV's camera image (TinyRenderer, headless).

Works from the env's public seams only: a :class:`~uavtrack_env.sensors.UAVSnapshot`
(``env.snapshot()``), the episode's ``Layout``, the ``EnvConfig`` and the ``World``'s public
methods; it never imports the env.
"""

from __future__ import annotations

import math

import numpy as np

from .config import EnvConfig
from .geometry import cam_to_world_vec
from .scenarios import Layout
from .sensors import UAVSnapshot
from .target import CAR_HALF_EXTENTS
from .world import UAV_COLOURS, World

OVERVIEW = 480
"""Side of the square overview image (px)."""
CAM_W, CAM_H = 192, 144
"""Size of each UAV's camera thumbnail (px); the full camera is 640 x 480."""
_UP = np.array([0.0, 0.0, 1.0])


def _draw_box(img: np.ndarray, u0: float, v0: float, u1: float, v1: float, rgb) -> None:
    h, w = img.shape[:2]
    a, b = int(np.clip(u0, 0, w - 1)), int(np.clip(u1, 0, w - 1))
    c, d = int(np.clip(v0, 0, h - 1)), int(np.clip(v1, 0, h - 1))
    img[c : d + 1, [a, b]] = rgb
    img[[c, d], a : b + 1] = rgb


def camera_view(
    world: World,
    config: EnvConfig,
    layout: Layout,
    snap: UAVSnapshot,
    i: int,
    width: int = CAM_W,
    height: int = CAM_H,
) -> np.ndarray:
    """UAV i's camera image scaled to (height, width), reference pixel and detection drawn."""
    cam = config.camera
    fov = math.degrees(2.0 * math.atan(cam.height / 2.0 / cam.fy))
    forward = cam_to_world_vec(np.array([0.0, 0.0, 1.0]), snap.yaws[i])
    eye = snap.positions[i] + forward * (config.uav_radius + 0.05)
    img = world.camera_image(eye, eye + forward, _UP, fov, width, height)
    sx, sy = width / cam.width, height / cam.height
    ref = layout.references[i]
    ru, rv = (cam.fx * ref[0] + cam.cu) * sx, (cam.fy * ref[1] + cam.cv) * sy
    _draw_box(img, ru - 3, rv - 3, ru + 3, rv + 3, (255, 255, 0))
    det = snap.detection
    if det is not None and det.detected[i]:
        du, dv = det.u[i] * sx, det.v[i] * sy
        _draw_box(img, du - 5, dv - 5, du + 5, dv + 5, (0, 255, 0))
    colour = np.array(UAV_COLOURS[i % len(UAV_COLOURS)][:3]) * 255
    img[:4] = colour.astype(np.uint8)
    if not snap.alive[i]:
        img //= 3
    return img


def overview(world: World, snap: UAVSnapshot, size: int = OVERVIEW) -> np.ndarray:
    """A perspective view from behind and above the target, framing the UAVs."""
    tgt = snap.target_center
    spread = np.max(np.linalg.norm(snap.positions[snap.alive] - tgt, axis=1), initial=8.0)
    back = np.array([-math.cos(snap.target_heading), -math.sin(snap.target_heading), 0.0])
    eye = tgt + back * (1.2 * spread + 6.0) + np.array([0.0, 0.0, 1.5 * spread + 8.0])
    return world.camera_image(eye, tgt, _UP, 60.0, size, size)


def rgb_frame(world: World, config: EnvConfig, layout: Layout, snap: UAVSnapshot) -> np.ndarray:
    """Overview on the left, the UAVs' camera images in columns on the right: (H, W, 3) uint8."""
    ov = overview(world, snap)
    n = config.n_uavs
    rows = max(1, OVERVIEW // CAM_H)
    cols = -(-n // rows)
    panel = np.full((OVERVIEW, cols * CAM_W, 3), 30, np.uint8)
    for i in range(n):
        r, c = i % rows, i // rows
        view = camera_view(world, config, layout, snap, i)
        panel[r * CAM_H : (r + 1) * CAM_H, c * CAM_W : (c + 1) * CAM_W] = view
    return np.concatenate([ov, panel], axis=1)


def follow_target(world: World, snap: UAVSnapshot) -> None:
    """Point the GUI's camera at the target (render_mode='human')."""
    world.point_gui_camera(
        snap.target_center - [0.0, 0.0, CAR_HALF_EXTENTS[2]],
        distance=25.0,
        yaw_deg=math.degrees(snap.target_heading) - 90.0,
        pitch_deg=-45.0,
    )
