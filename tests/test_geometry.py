"""Frames, projection (eq. 8), features (eqs. 4, 6) and their dynamics (eq. 15) on known cases."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from uavtrack_env import uavtrack_v0
from uavtrack_env.config import CameraConfig, DetectorConfig, DynamicsConfig
from uavtrack_env.dynamics import integrate
from uavtrack_env.geometry import (
    cam_to_world,
    cam_to_world_vec,
    feature_rates,
    image_features,
    point_box_distance,
    project,
    relative_angle,
    segment_hits_boxes,
    world_to_cam_vec,
    wrap_angle,
)

F, CU, CV = 381.36, 320.0, 240.0
K = CameraConfig().K


def _hand_features(p_uav, yaw, q, heading) -> np.ndarray:
    """s = [X/Z, Y/Z, 1/Z, psi] written out from the conventions (X right, Y down, Z forward)."""
    d = np.asarray(q, float) - np.asarray(p_uav, float)
    X = d[0] * math.sin(yaw) - d[1] * math.cos(yaw)
    Y = -d[2]
    Z = d[0] * math.cos(yaw) + d[1] * math.sin(yaw)
    psi = math.atan2(p_uav[1] - q[1], p_uav[0] - q[0]) - heading
    psi = math.atan2(math.sin(psi), math.cos(psi))
    return np.array([X / Z, Y / Z, 1.0 / Z, psi])


# --------------------------------------------------------------------- projection, K
def test_intrinsics_are_the_papers():
    np.testing.assert_array_equal(K, [[F, 0, CU], [0, F, CV], [0, 0, 1]])


def test_project_known_point():
    """7 m ahead, 1 m right, 1.32 m down: u = 320 + 381.36/7, v = 240 + 381.36*1.32/7."""
    uv = project(np.array([1.0, 1.32, 7.0]), K)
    np.testing.assert_allclose(uv, [CU + F / 7.0, CV + F * 1.32 / 7.0], rtol=0, atol=1e-12)
    # The optical axis projects on the principal point, batches work.
    uv = project(np.array([[0.0, 0.0, 3.0], [-2.0, 0.0, 4.0]]), K)
    np.testing.assert_allclose(uv, [[CU, CV], [CU - F / 2.0, CV]], atol=1e-12)


@pytest.mark.parametrize("yaw", [0.0, 0.7, -1.9, math.pi])
def test_project_world_point_through_uav_frame(yaw):
    """The same point placed in the world in front of a yawed UAV lands on the same pixel."""
    p = np.array([1.5, -2.0, 3.0])
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    q = p + 7.0 * forward + 1.0 * right + 1.32 * down
    rel = world_to_cam_vec(q - p, yaw)
    np.testing.assert_allclose(rel, [1.0, 1.32, 7.0], atol=1e-12)
    np.testing.assert_allclose(
        project(rel, K), [CU + F / 7.0, CV + F * 1.32 / 7.0], rtol=0, atol=1e-9
    )
    np.testing.assert_allclose(image_features(rel), [1 / 7.0, 1.32 / 7.0, 1 / 7.0], atol=1e-12)


@pytest.mark.parametrize("yaw", [0.0, 0.3, 1.57, -2.5, 3.0])
def test_cam_to_world_is_a_rotation_with_z_along_heading(yaw):
    R = cam_to_world(yaw)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R @ [0, 0, 1], [math.cos(yaw), math.sin(yaw), 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1], atol=1e-12)  # Y down
    np.testing.assert_allclose(R @ [1, 0, 0], [math.sin(yaw), -math.cos(yaw), 0], atol=1e-12)
    v = np.array([0.3, -1.2, 2.5])
    np.testing.assert_allclose(cam_to_world_vec(v, yaw), R @ v, atol=1e-12)
    np.testing.assert_allclose(world_to_cam_vec(R @ v, yaw), v, atol=1e-12)


def test_cam_to_world_batched():
    yaws = np.array([0.1, -0.4, 2.0])
    R = cam_to_world(yaws)
    assert R.shape == (3, 3, 3)
    for k, y in enumerate(yaws):
        np.testing.assert_allclose(R[k], cam_to_world(y), atol=1e-15)


# ------------------------------------------------------------------------- psi, eq. (4)
def test_relative_angle_table_vi_scenario_a():
    starts = np.array([[0.0, 6.0, 0.85], [-6.0, 0.0, 0.85], [0.0, -6.0, 0.85]])
    psi = relative_angle(starts, np.zeros(3), 0.0)
    np.testing.assert_allclose(psi, [math.pi / 2, math.pi, -math.pi / 2], atol=1e-12)


def test_relative_angle_target_heading_shifts_psi():
    uav = np.array([0.0, 6.0, 0.85])
    for h in (0.3, -0.8, 2.0):
        expected = wrap_angle(math.pi / 2 - h)
        assert relative_angle(uav, np.zeros(3), h) == pytest.approx(expected, abs=1e-12)
    # A UAV in front of a target heading along +y sees psi = 0; behind it, pi.
    assert relative_angle(np.array([2.0, 9.0, 1.0]), np.array([2.0, 1.0, 0.0]), math.pi / 2) == (
        pytest.approx(0.0, abs=1e-12)
    )
    assert relative_angle(np.array([2.0, -9.0, 1.0]), np.array([2.0, 1.0, 0.0]), math.pi / 2) == (
        pytest.approx(math.pi, abs=1e-12)
    )


def test_env_truth_features_match_hand_computation():
    env = uavtrack_v0.parallel_env(scenario="A", detector=DetectorConfig.noiseless())
    try:
        _, infos = env.reset(seed=0)
        rng = np.random.default_rng(0)
        for step in range(120):
            if step % 30 == 0:
                for agent in env.agents:
                    i = env.possible_agents.index(agent)
                    hand = _hand_features(
                        env.position[i], env.yaw[i], env.target.center(), env.target.heading
                    )
                    np.testing.assert_allclose(
                        infos[agent]["truth"]["features"], hand, rtol=1e-9, atol=1e-12
                    )
            acts = {a: 0.1 * rng.uniform(-1, 1, 4) for a in env.agents}
            _, _, _, _, infos = env.step(acts)
        # At reset the Table VI starts give the references' psi exactly (target at origin).
        _, infos = env.reset(seed=0)
        psi = [infos[a]["truth"]["features"][3] for a in env.agents]
        np.testing.assert_allclose(psi, [math.pi / 2, math.pi, -math.pi / 2], atol=2e-3)
    finally:
        env.close()


# ------------------------------------------------------------------ dynamics, eq. (15)
def _features_after(h, p0, yaw0, u, q0, vq, heading):
    """Features after time h of the env's integrator (eq. 3) and a straight-moving target."""
    pos, yaw, _, _ = integrate(
        p0[None], np.array([yaw0]), np.zeros((1, 3)), np.zeros(1), u[None], DynamicsConfig(), h
    )
    return _hand_features(pos[0], yaw[0], q0 + vq * h, heading)


def _finite_difference(p0, yaw0, u, q0, vq, heading, h=1e-5):
    """Central difference of s along the motion; the forward-Euler step is exact in h's first
    order and symmetric, so the error is O(h^2) ~ 1e-10 relative."""
    plus = _features_after(h, p0, yaw0, u, q0, vq, heading)
    minus = _features_after(-h, p0, yaw0, u, q0, vq, heading)
    d = plus - minus
    d[3] = wrap_angle(d[3])
    return d / (2 * h)


CASES = [
    # (UAV position, yaw, u = [v_cx, v_cy, v_cz, omega_cy], target velocity (global))
    (np.array([-6.0, 0.5, 2.0]), 0.1, np.array([0.8, -0.3, 1.2, 0.25]), np.array([0.5, 0, 0])),
    (np.array([1.0, 6.0, 0.85]), -1.3, np.array([-2.0, 0.4, 0.7, -0.4]), np.array([0.3, -0.2, 0])),
    (np.array([3.0, -5.0, 4.0]), 2.0, np.array([0.0, 0.0, 0.0, 0.6]), np.array([0.0, 0.0, 0.0])),
    (np.array([-4.0, -4.0, 1.5]), 0.9, np.array([5.0, 1.0, -3.0, 0.0]), np.array([-0.4, 0.4, 0])),
]


@pytest.mark.parametrize(("p0", "yaw0", "u", "vq"), CASES)
def test_feature_rates_rows_1_to_3_exact_for_point_target(p0, yaw0, u, vq):
    """Rows x1..x3 of eq. (15) are exact kinematics: |error| <= 1e-6 relative (FD is ~1e-10)."""
    q0 = np.array([0.0, 0.0, 0.75])
    s = _hand_features(p0, yaw0, q0, 0.0)
    assert s[2] > 0  # the target is in front
    vq_cam = world_to_cam_vec(vq, yaw0)
    model = np.array(feature_rates(s, u, vq_cam), float)
    fd = _finite_difference(p0, yaw0, u, q0, vq, 0.0)
    np.testing.assert_allclose(model[:3], fd[:3], rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("x2_height", [0.0, 1.316])
def test_feature_rate_psi_when_camera_looks_at_target(x2_height):
    """Row 4 of eq. (15) is the paper's approximation (12). With the target on the optical axis
    horizontally (x1 = 0) the exact rate is dvx * x3 (X is then tangential, Z the horizontal range),
    so the paper's row equals exact / sqrt(1 + x2^2): exact for x2 = 0, and 1.7 % low at the
    reference height x2 = 0.188. Tolerance: 1e-6 on that closed form, and 2 % against the FD."""
    q0 = np.array([0.0, 0.0, 0.75])
    p0 = np.array([0.0, 7.0, 0.75 + x2_height])  # 7 m left of the car, looking at it (-y)
    yaw0 = -math.pi / 2
    u = np.array([1.5, 0.2, -0.4, 0.3])
    vq = np.array([0.5, 0.0, 0.0])
    s = _hand_features(p0, yaw0, q0, 0.0)
    assert s[0] == pytest.approx(0.0, abs=1e-12)
    assert s[1] == pytest.approx(x2_height / 7.0, abs=1e-12)
    model = np.array(feature_rates(s, u, world_to_cam_vec(vq, yaw0)), float)
    fd = _finite_difference(p0, yaw0, u, q0, vq, 0.0)
    np.testing.assert_allclose(model[:3], fd[:3], rtol=1e-6, atol=1e-8)
    assert model[3] * math.sqrt(1 + s[1] ** 2) == pytest.approx(fd[3], rel=1e-6)
    assert model[3] == pytest.approx(fd[3], rel=0.02)


def test_feature_rates_casadi_matches_numpy():
    s, u, vq = (
        np.array([0.1, 0.2, 0.15, 1.0]),
        np.array([1.0, -0.5, 0.3, 0.2]),
        np.array([0.2, 0, 0.4]),
    )
    S, U, V = ca.SX.sym("s", 4), ca.SX.sym("u", 4), ca.SX.sym("v", 3)
    f = ca.Function("f", [S, U, V], [ca.vertcat(*feature_rates(S, U, V))])
    np.testing.assert_allclose(
        np.array(f(s, u, vq)).ravel(), np.array(feature_rates(s, u, vq), float), rtol=1e-12
    )


# ------------------------------------------------------------------------- boxes, angles
BOXES_C = np.array([[0.0, 0.0, 0.5], [10.0, 0.0, 1.0]])
BOXES_H = np.array([[0.5, 0.5, 0.5], [1.0, 2.0, 1.0]])


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        ([-3, 0, 0.5], [3, 0, 0.5], [True, False]),  # straight through box 0
        ([-3, 0, 0.5], [-0.6, 0, 0.5], [False, False]),  # stops short of box 0
        ([-3, 0, 0.5], [-0.5, 0, 0.5], [True, False]),  # ends on its face
        ([0.6, 0, 0.5], [3, 0, 0.5], [False, False]),  # starts past it, moving away
        ([-3, 0.6, 0.5], [3, 0.6, 0.5], [False, False]),  # parallel, just outside
        ([-3, 0.4, 0.5], [3, 0.4, 0.5], [True, False]),  # parallel, just inside
        ([0.1, 0.1, 0.5], [0.2, 0.1, 0.6], [True, False]),  # entirely inside
        ([-3, 0, 0.5], [20, 0, 0.5], [True, True]),  # through both
        ([5, -5, 1], [15, 5, 1], [False, True]),  # diagonal through box 1
        ([-1, -1, 2.0], [1, 1, 2.0], [False, False]),  # above box 0
        ([-1, -1, 0.0], [1, 1, 2.0], [True, False]),  # diagonal through box 0 in 3-D
    ],
)
def test_segment_hits_boxes(a, b, expected):
    hit = segment_hits_boxes(np.array(a, float), np.array(b, float), BOXES_C, BOXES_H)
    assert hit.tolist() == expected


def test_segment_hits_no_boxes():
    hit = segment_hits_boxes(np.zeros(3), np.ones(3), np.zeros((0, 3)), np.zeros((0, 3)))
    assert hit.shape == (0,)


def test_point_box_distance_hand_cases():
    pts = np.array(
        [
            [0.0, 0.0, 0.5],  # centre of box 0
            [0.4, -0.4, 0.9],  # inside box 0
            [2.0, 0.0, 0.5],  # 1.5 m in front of box 0's +x face
            [1.5, 1.5, 0.5],  # 1 m beyond an edge in x and y
            [1.5, 1.5, 2.0],  # beyond a corner: (1, 1, 1)
            [10.0, 0.0, 5.0],  # 3 m above box 1
        ]
    )
    d = point_box_distance(pts, BOXES_C, BOXES_H)
    assert d.shape == (6, 2)
    np.testing.assert_allclose(
        d[:, 0], [0.0, 0.0, 1.5, math.sqrt(2.0), math.sqrt(3.0), math.hypot(9.5, 4.0)], atol=1e-12
    )
    np.testing.assert_allclose(d[5, 1], 3.0, atol=1e-12)
    np.testing.assert_allclose(d[2, 1], 7.0, atol=1e-12)


@pytest.mark.parametrize(
    ("a", "expected"),
    [
        (0.0, 0.0),
        (math.pi, math.pi),
        (-math.pi, math.pi),
        (3 * math.pi, math.pi),
        (2 * math.pi, 0.0),
        (-math.pi / 2, -math.pi / 2),
        (1.5 * math.pi, -math.pi / 2),
        (-1.5 * math.pi, math.pi / 2),
        (100.0, 100.0 - 32 * math.pi),
        (-7.0, -7.0 + 2 * math.pi),
    ],
)
def test_wrap_angle_known_values(a, expected):
    assert float(wrap_angle(a)) == pytest.approx(expected, abs=1e-12)


def test_wrap_angle_range_and_equivalence():
    a = np.linspace(-50, 50, 10001)
    w = wrap_angle(a)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
