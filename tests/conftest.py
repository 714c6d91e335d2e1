"""Shared test fixtures and constants."""

from __future__ import annotations

import os

import numpy as np
import pytest

from uavtrack_env import uavtrack_v0

# The default NMPC compiles its solver once per settings (`NMPCConfig.jit` None); the suite's many
# settings run interpreted instead (equal to 1e-9, tests/test_nmpc_jit.py).
os.environ.setdefault("UAVTRACK_JIT", "0")

METRICS_UAV_KEYS = frozenset(
    {
        "rms_u_px",
        "rms_v_px",
        "rms_depth_m",
        "collision_ok",
        "connectivity_ok",
        "occlusion_ok",
        "min_uav_dist_m",
        "max_uav_dist_m",
        "min_obstacle_clearance_m",
        "min_occlusion_angle_deg",
        "detected_fraction",
    }
)
"""Per-UAV keys that metrics.json must hold (issue 3's schema)."""


def car_inside(p, center, half, clearance, yaw=0.0) -> float:
    """Reference for the car box barrier's inside (`barrier_rows.box_sdist`, grounded):
    ``-e_xy (t + clearance)``, e_xy the depth inside the nearest side, t under the top; 0
    outside."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(p, float) - center
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
    if not (np.abs(local) < half).all():
        return 0.0
    side = np.min(np.asarray(half)[:2] - np.abs(local[:2]))
    return float(-side * (half[2] - local[2] + clearance))


def car_h(p, center, half, clearance, yaw=0.0) -> float:
    """Reference for the car's frustum barrier (`barrier_rows.target_row`): horizontal distance
    to the (yawed) footprint plus height over the top minus sqrt(2) clearance; inside the box
    plus `car_inside` per clearance."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(p, float) - center
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    out = np.maximum(np.abs(local) - np.asarray(half)[:2], 0.0)
    frustum = np.linalg.norm(out) + d[2] - half[2] - np.sqrt(2.0) * clearance
    return float(frustum + car_inside(p, center, half, clearance, yaw) / clearance)


def growing_car_case(rng: np.random.Generator):
    """A stale car's box (centre q on the ground, yaw, half sizes, per-axis face speeds) and a
    UAV position p beside, above, at a corner of or inside it, never under its centre (the
    grounded box's bottom is never the way out): (q, heading, half, growth, p)."""
    q, heading = np.array([0.0, 0.0, 0.75]), rng.uniform(-np.pi, np.pi)
    half = rng.uniform(1.0, 4.0, 3)
    growth = np.array([rng.uniform(0.2, 2.0), rng.uniform(0.2, 2.0), rng.choice([0.0, 0.5])])
    c, s = np.cos(heading), np.sin(heading)
    local = rng.uniform(-1.8, 1.8, 3) * half
    local[2] = abs(local[2]) + 0.1
    p = q + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1], local[2]])
    return q, heading, half, growth, p


def step_both(a, b, actions: np.ndarray) -> tuple[list[dict], list[dict]]:
    """Step two SB3 VecEnvs with the same actions; assert equal observations, rewards and dones
    and return both info lists."""
    o1, r1, d1, i1 = a.step(actions)
    o2, r2, d2, i2 = b.step(actions)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(d1, d2)
    return i1, i2


@pytest.fixture
def make_env():
    made = []

    def factory(**kwargs):
        kwargs.setdefault("scenario", "A")
        env = uavtrack_v0.parallel_env(**kwargs)
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()
