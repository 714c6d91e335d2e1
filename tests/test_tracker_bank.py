"""`TrackerBank` (a team's target estimators in one compiled call) against filterpy's
`TargetEstimator`, one UAV at a time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uavtrack_env.config import DT, CameraConfig
from uavtrack_env.estimation import Measurement, TargetEstimator, UKFConfig
from uavtrack_env.estimation.bank import INPUT_COLUMNS, TrackerBank
from uavtrack_env.estimation.team import sigma_points
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
        out.append(((u, p, yaw, meas), _row(p, yaw, w, omega, meas)))
    return out


def _row(p, yaw, velocity, yaw_rate, meas) -> list[float]:
    """A bank input row (`INPUT_COLUMNS`): own state, then the detection (or none)."""
    state = [*p, yaw, *velocity, yaw_rate]
    if meas is None:
        return [*state, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    seen = [meas.u, meas.v, meas.depth, meas.psi, meas.truncated_u, meas.truncated_v]
    return [*state, 1.0, *map(float, seen)]


def _bank(cfg: UKFConfig, scenes, steps=(0,)) -> TrackerBank:
    """A bank of the scenes' UAVs after their steps ``steps`` (the first one initialises)."""
    bank = TrackerBank(len(scenes), CAM, cfg, DT)
    for i in steps:
        bank.step(range(len(scenes)), np.array([s[i][1] for s in scenes]))
    return bank


def _estimators(cfg: UKFConfig, scenes) -> list[TargetEstimator]:
    ests = [TargetEstimator(CAM, cfg, DT) for _ in scenes]
    for est, scene in zip(ests, scenes, strict=True):
        _u, p, yaw, meas = scene[0][0]
        est.reset(meas, p, yaw)
    return ests


def _assert_same(b, r, atol=1e-8) -> None:
    assert b.detected == r.detected
    assert b.steps_since_detection == r.steps_since_detection
    for name in ("s", "target_position", "target_velocity", "target_acceleration", "vq_cam",
                 "covariance"):  # fmt: skip
        np.testing.assert_allclose(getattr(b, name), getattr(r, name), atol=atol, rtol=0)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
@pytest.mark.parametrize("held", [False, True])
def test_bank_equals_filterpy_one_uav_at_a_time(seed, held):
    """Four UAVs, 300 steps with truncations and dropouts: the bank's estimates equal plain
    filterpy's per-UAV estimators to 1e-8 (first detection, predictions, updates, the dropout
    fit of Remark 2, the held height)."""
    rng = np.random.default_rng(seed)
    scenes = [_scene(rng, k, 300) for k in range(4)]
    cfg = UKFConfig(truncated_variance_scale=4.0, truncated_v_hold_height=held)
    bank = _bank(cfg, scenes)
    alone = _estimators(dataclasses.replace(cfg, vectorized=False), scenes)
    for i in range(1, 301):
        bank.step(range(4), np.array([s[i][1] for s in scenes]))
        reference = [est.step(*s[i][0]) for est, s in zip(alone, scenes, strict=True)]
        for b, r in zip(bank.estimates, reference, strict=True):
            _assert_same(b, r)
    lost = sum(s[i][0][3] is None for s in scenes for i in range(301))
    assert 0 < lost < 4 * 301 / 2  # detections and dropouts both ran
    fitted = [np.abs(e.target_acceleration).max() for e in bank.estimates]
    assert max(fitted) > 0  # the motion fit ran


def test_bank_steps_a_subset_and_forgets_a_slot():
    """Slots step only when asked (the others keep their estimate), a slot waits for a first
    detection, and a forgotten slot starts over like a new estimator."""
    rng = np.random.default_rng(3)
    scenes = [_scene(rng, k, 40) for k in range(3)]
    cfg = UKFConfig()
    bank = TrackerBank(3, CAM, cfg, DT)
    lost = [*scenes[2][0][1][:8], 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    bank.step([0, 2], np.array([scenes[0][0][1], lost]))
    assert bank.estimates[1] is None and bank.estimates[2] is None  # no detection yet
    alone = _estimators(dataclasses.replace(cfg, vectorized=False), scenes)
    kept = bank.estimates[0]
    for i in range(1, 21):
        bank.step([1], np.array([scenes[1][i - 1][1]]) if i > 1 else np.array([scenes[1][0][1]]))
    assert bank.estimates[0] is kept
    bank.forget(0)
    assert bank.estimates[0] is None
    bank.step([0], np.array([scenes[0][0][1]]))
    _assert_same(bank.estimates[0], alone[0]._estimate(scenes[0][0][0][2], True), atol=0)
    for i in range(1, 30):
        bank.step([0], np.array([scenes[0][i][1]]))
        _assert_same(bank.estimates[0], alone[0].step(*scenes[0][i][0]))


def test_bank_takes_an_indefinite_covariance_like_filterpy():
    """One UAV's P is indefinite: the sigma points fall back to the eigen square root for it,
    as filterpy's sqrt hook does, and the step still equals filterpy's."""
    rng = np.random.default_rng(4)
    scenes = [_scene(rng, k, 2) for k in range(3)]
    cfg = UKFConfig()
    bank = _bank(cfg, scenes)
    alone = _estimators(dataclasses.replace(cfg, vectorized=False), scenes)
    bank._P[1, 4, 5] = bank._P[1, 5, 4] = 10.0  # |rho| >> 1: indefinite
    alone[1].ukf.P[4, 5] = alone[1].ukf.P[5, 4] = 10.0
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(bank._P[1])
    bank.step(range(3), np.array([s[1][1] for s in scenes]))
    reference = [est.step(*s[1][0]) for est, s in zip(alone, scenes, strict=True)]
    for b, r in zip(bank.estimates, reference, strict=True):
        np.testing.assert_allclose(b.covariance, r.covariance, atol=1e-8, rtol=0)
        assert np.all(np.linalg.eigvalsh(b.covariance) > 0)
    assert bank.n_covariance_repairs.tolist() == [e.n_covariance_repairs for e in alone]


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


def test_bank_rejects_plain_filterpy_configs_and_malformed_rows():
    with pytest.raises(ValueError, match="vectorized must be True"):
        TrackerBank(2, CAM, UKFConfig(vectorized=False))
    bank = TrackerBank(2, CAM, UKFConfig())
    row = np.zeros(len(INPUT_COLUMNS))
    with pytest.raises(ValueError, match=r"shape \(2, 15\)"):
        bank.step([0, 1], np.array([row]))
    with pytest.raises(ValueError, match="float64"):
        bank.step([0], np.zeros((1, 15), np.float32))
    assert list(bank.estimates) == [None, None]
