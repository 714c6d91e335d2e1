"""EpisodeRecorder's per-UAV summary against hand-computed values on synthetic infos."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uavtrack_env.metrics import EpisodeRecorder


def _info(position, pixel_error, blocked, detected=True, theta=(0.7, 0.2), in_noi=(True, False)):
    return {
        "truth": {
            "pixel_error": np.array(pixel_error, float),
            "depth_error": 0.5,
            "target_position": np.zeros(3),
            "nearest_uav_distance": 5.0,
            "nearest_obstacle_clearance": 1.5,
            "occlusion_angles": np.array(theta),
            "occlusion_candidates": np.array(in_noi),
            "blocked_fraction": blocked,
        },
        "measurement": {"detected": detected, "u": 320.0, "v": 240.0},
        "own": {"position": np.array(position, float)},
        "violations": {"collision": False, "disconnection": False, "occlusion": blocked > 0.5},
    }


def test_summary_counts_partial_occlusion_and_half_hidden_car_separately():
    rec = EpisodeRecorder(["a", "b"], dt=0.0125, theta_star=math.radians(30))
    blocked = {"a": [0.0, 1 / 12, 0.0], "b": [0.0, 7 / 12, 0.0]}
    for k in range(3):
        rec.record(
            {
                "a": _info([0, 0, 2], [3.0 * k, 4.0], blocked["a"][k]),
                "b": _info([6, 0, 2], [0.0, 0.0], blocked["b"][k], detected=k != 1),
            }
        )
    s = rec.summary()
    assert s["a"]["rms_u_px"] == pytest.approx(math.sqrt((0 + 9 + 36) / 3))
    assert s["a"]["rms_v_px"] == pytest.approx(4.0)
    assert s["a"]["occlusion_ok"] is False  # one of 12 rays blocked: partial occlusion
    assert s["a"]["detection_kept_ok"] is True  # the env's violation: more than half hidden
    assert s["a"]["max_blocked_fraction"] == pytest.approx(1 / 12)
    assert s["b"]["occlusion_ok"] is False and s["b"]["detection_kept_ok"] is False
    assert s["b"]["detected_fraction"] == pytest.approx(2 / 3)
    assert s["a"]["min_uav_dist_m"] == pytest.approx(6.0)
    assert s["a"]["min_occlusion_angle_deg"] == pytest.approx(math.degrees(0.7))
    assert s["a"]["theta_ok"] is True  # 40 deg >= theta*; the 0.2 rad obstacle is not in N_oi


def test_summary_is_occlusion_free_when_no_ray_is_ever_blocked():
    rec = EpisodeRecorder(["a"], dt=0.0125, theta_star=math.radians(30))
    for _ in range(3):
        rec.record({"a": _info([0, 0, 2], [1.0, 1.0], 0.0, theta=(0.3,), in_noi=(True,))})
    s = rec.summary()["a"]
    assert s["occlusion_ok"] is True and s["detection_kept_ok"] is True
    assert s["max_blocked_fraction"] == 0.0
    assert s["theta_ok"] is False  # 17 deg < theta* = 30 deg
