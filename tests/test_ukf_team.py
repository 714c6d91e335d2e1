"""`step_team` (the team's UKFs in one batched pass) against filterpy, one UAV at a time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uavtrack_env.config import DT, CameraConfig
from uavtrack_env.estimation import Measurement, TargetEstimator, UKFConfig
from uavtrack_env.estimation.team import sigma_points, step_team
from uavtrack_env.geometry import relative_angle, world_to_cam_vec

CAM = CameraConfig()


def _scene(rng: np.random.Generator, k: int, steps: int):
    """Inputs of ``steps`` estimator steps for UAV ``k``: a car on a curve seen from a moving,
    yawing UAV, with noise, truncated boxes and two dropouts."""
    r0, v0 = np.array([0.0, 0.0, 0.75]), np.array([1.5, 0.3 * k - 0.4, 0.0])
    p0 = np.array([-8.0 + k, 2.0 * k - 3.0, 3.0 + 0.5 * k])
    w = rng.uniform(-0.3, 0.3, 3) * [1, 1, 0] + v0
    wobble = rng.uniform(0.05, 0.2)
    lost = [(rng.integers(20, 80), rng.integers(5, 40)), (rng.integers(120, 200), 60)]

    def pose(t):  # the UAV looks at the car, give or take a wobble
        r = r0 + v0 * t + np.array([0.0, 0.5 * np.sin(0.4 * t), 0.0])
        p = p0 + w * t
        return r, p, np.arctan2(*(r - p)[1::-1]) + wobble * np.sin(1.3 * t + k)

    out = []
    for i in range(steps + 1):
        t = i * DT
        r, p, yaw = pose(t)
        omega = (pose(t)[2] - pose(t - DT)[2]) / DT  # the yaw rate applied over the last step
        heading = np.arctan2(v0[1] + 0.2 * np.cos(0.4 * t), v0[0])
        X, Y, Z = world_to_cam_vec(r - p, yaw)
        meas = Measurement(
            CAM.fx * X / Z + CAM.cu + rng.normal(0, 2.0),
            CAM.fy * Y / Z + CAM.cv + rng.normal(0, 2.0),
            Z + rng.normal(0, 0.1),
            float(relative_angle(p, r, heading)) + rng.normal(0, 0.03),
            truncated_u=bool(rng.random() < 0.1),
            truncated_v=bool(rng.random() < 0.1),
        )
        if any(a <= i < a + n for a, n in lost):
            meas = None
        u = np.concatenate([world_to_cam_vec(w, yaw), [-omega]])
        out.append((u, p, yaw, meas))
    return out


def _estimators(cfg: UKFConfig, scenes) -> list[TargetEstimator]:
    ests = [TargetEstimator(CAM, cfg, DT) for _ in scenes]
    for est, scene in zip(ests, scenes, strict=True):
        _u, p, yaw, meas = scene[0]
        est.reset(meas, p, yaw)
    return ests


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("held", [False, True])
def test_team_step_equals_filterpy_one_uav_at_a_time(seed, held):
    """Four UAVs, 300 steps with truncations and dropouts: states, covariances and estimates of
    the batched pass equal plain filterpy's per-UAV filters to 1e-8."""
    rng = np.random.default_rng(seed)
    scenes = [_scene(rng, k, 300) for k in range(4)]
    cfg = UKFConfig(truncated_variance_scale=4.0, truncated_v_hold_height=held)
    team = _estimators(cfg, scenes)
    alone = _estimators(dataclasses.replace(cfg, vectorized=False), scenes)
    for i in range(1, 301):
        inputs = [scene[i] for scene in scenes]
        batched = step_team(team, inputs)
        reference = [est.step(*inp) for est, inp in zip(alone, inputs, strict=True)]
        for b, r in zip(batched, reference, strict=True):
            assert b.detected == r.detected
            assert b.steps_since_detection == r.steps_since_detection
            np.testing.assert_allclose(b.s, r.s, atol=1e-8, rtol=0)
            np.testing.assert_allclose(b.target_position, r.target_position, atol=1e-8, rtol=0)
            np.testing.assert_allclose(b.target_velocity, r.target_velocity, atol=1e-8, rtol=0)
            np.testing.assert_allclose(b.covariance, r.covariance, atol=1e-8, rtol=0)
            np.testing.assert_allclose(
                b.target_acceleration, r.target_acceleration, atol=1e-8, rtol=0
            )
    lost = sum(s[i][3] is None for s in scenes for i in range(301))
    assert 0 < lost < 4 * 301 / 2  # detections and dropouts both ran


def test_team_step_takes_an_indefinite_covariance_like_filterpy():
    """One UAV's P is indefinite: the batched sigma points fall back to the eigen square root
    for it, as filterpy's sqrt hook does, and the step still equals filterpy's."""
    rng = np.random.default_rng(4)
    scenes = [_scene(rng, k, 2) for k in range(3)]
    cfg = UKFConfig()
    team = _estimators(cfg, scenes)
    alone = _estimators(dataclasses.replace(cfg, vectorized=False), scenes)
    for est in (team[1], alone[1]):
        est.ukf.P[4, 5] = est.ukf.P[5, 4] = 10.0  # |rho| >> 1: indefinite
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(team[1].ukf.P)
    batched = step_team(team, [s[1] for s in scenes])
    reference = [est.step(*s[1]) for est, s in zip(alone, scenes, strict=True)]
    for b, r in zip(batched, reference, strict=True):
        np.testing.assert_allclose(b.covariance, r.covariance, atol=1e-8, rtol=0)
        assert np.all(np.linalg.eigvalsh(b.covariance) > 0)


def test_repair_covariance_of_a_stack_equals_one_at_a_time():
    from uavtrack_env.estimation.ukf import repair_covariance

    rng = np.random.default_rng(6)
    A = rng.standard_normal((4, 10, 10))
    P = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(10)
    P[1, 2, 3] = P[1, 3, 2] = 40.0  # indefinite
    P[2] *= 1e4  # stds above the cap
    max_std = np.full(10, 10.0)
    stacked, repaired, capped = repair_covariance(P, max_std)
    assert repaired.tolist() == [False, True, False, False]
    assert capped[2]
    for k in range(4):
        one, rep, cap = repair_covariance(P[k : k + 1], max_std)
        np.testing.assert_array_equal(stacked[k], one[0])
        assert (rep[0], cap[0]) == (repaired[k], capped[k])
        assert np.all(np.linalg.eigvalsh(stacked[k]) > 0)
        assert np.all(np.sqrt(np.diag(stacked[k])) <= 10.0 * (1 + 1e-12))


def test_sigma_points_equal_filterpys():
    from filterpy.kalman import MerweScaledSigmaPoints

    from uavtrack_env.estimation.ukf import safe_sqrt

    rng = np.random.default_rng(2)
    A = rng.standard_normal((3, 10, 10))
    P = A @ np.swapaxes(A, 1, 2) + np.eye(10)
    x = rng.standard_normal((3, 10))
    ref = MerweScaledSigmaPoints(10, 0.5, 2.0, 0.0, sqrt_method=safe_sqrt)
    lam = 0.5**2 * 10 - 10
    batched = sigma_points(x, P, lam)
    for k in range(3):
        np.testing.assert_allclose(batched[k], ref.sigma_points(x[k], P[k]), atol=1e-12, rtol=0)


def test_team_step_rejects_mixed_configs_and_mismatched_inputs():
    rng = np.random.default_rng(0)
    scenes = [_scene(rng, k, 1) for k in range(2)]
    ests = _estimators(UKFConfig(), scenes[:1]) + _estimators(UKFConfig(pixel_std=3.0), scenes[1:])
    with pytest.raises(ValueError, match="one camera, UKFConfig and dt"):
        step_team(ests, [s[1] for s in scenes])
    with pytest.raises(ValueError, match="2 estimators but 1 inputs"):
        step_team(ests, [scenes[0][1]])
    assert step_team([], []) == []
