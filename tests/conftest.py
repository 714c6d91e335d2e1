"""Shared test fixtures and constants."""

from __future__ import annotations

import pytest

from uavtrack_env import uavtrack_v0

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
