"""Tests of the target UKF (section II-E) and the dropout motion fit (Remark 2).

A small numpy ground-truth simulator (a UAV flying near a car that moves at constant velocity on
the ground; measurements from uavtrack_env.geometry plus Gaussian noise of 2 px, 0.1 m, 0.03 rad)
checks convergence, dropout prediction and re-convergence against stated bounds.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from uavtrack_env.config import CameraConfig
from uavtrack_env.estimation import (
    Measurement,
    MotionHistory,
    TargetEstimator,
    UKFConfig,
    fit_polynomial,
    make_filter,
    measurement_model,
    process_model,
)
from uavtrack_env.geometry import (
    cam_to_world,
    image_features,
    relative_angle,
    world_to_cam_vec,
    wrap_angle,
)

CAM = CameraConfig()
DT = 1.0 / 80.0


# ---------------------------------------------------------------- ground-truth simulator


class Sim:
    """UAV (single integrator, yaw-only) flying after a constant-velocity ground target."""

    def __init__(self, seed: int, p0=(-8.0, 1.0, 4.0), vq=(1.5, 0.5, 0.0), noise=(2.0, 0.1, 0.03)):
        self.rng = np.random.default_rng(seed)
        self.p = np.array(p0, float)
        self.yaw = 0.0
        self.r = np.array([0.0, 0.0, 0.75])
        self.V = np.array(vq, float)
        self.heading = math.atan2(self.V[1], self.V[0])
        self.noise = noise
        self.t = 0.0

    def rel_cam(self) -> np.ndarray:
        return world_to_cam_vec(self.r - self.p, self.yaw)

    def features(self) -> np.ndarray:
        return np.array(
            [*image_features(self.rel_cam()), relative_angle(self.p, self.r, self.heading)]
        )

    def measure(self) -> Measurement:
        s, rel, n = self.features(), self.rel_cam(), self.rng.standard_normal(4)
        return Measurement(
            CAM.fx * s[0] + CAM.cu + self.noise[0] * n[0],
            CAM.fy * s[1] + CAM.cv + self.noise[0] * n[1],
            rel[2] + self.noise[1] * n[2],  # d = Z, the optical-axis depth
            float(wrap_angle(s[3] + self.noise[2] * n[3])),
        )

    def command(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Global UAV velocity, camera-frame command u, global yaw rate."""
        t = self.t
        vg = self.V + np.array(
            [0.5 * math.sin(0.7 * t), 0.5 * math.cos(0.5 * t), 0.2 * math.sin(t)]
        )
        d = self.r - self.p
        yaw_rate = float(np.clip(1.5 * wrap_angle(math.atan2(d[1], d[0]) - self.yaw), -0.6, 0.6))
        u = np.array([*world_to_cam_vec(vg, self.yaw), -yaw_rate])  # global yaw rate = -omega_cy
        return vg, u, yaw_rate

    def advance(self) -> np.ndarray:
        vg, u, yaw_rate = self.command()
        self.p = self.p + vg * DT
        self.yaw += yaw_rate * DT
        self.r = self.r + self.V * DT
        self.t += DT
        return u


def run(seed: int, T: float, dropout=None, cfg: UKFConfig | None = None, **sim_kw):
    """Closed loop of simulator and estimator; returns per-step error arrays."""
    sim = Sim(seed, **sim_kw)
    est = TargetEstimator(CAM, cfg or UKFConfig(), DT)
    est.reset(sim.measure(), sim.p, sim.yaw)
    rows = []
    for _ in range(round(T / DT)):
        u = sim.advance()
        lost = dropout is not None and dropout[0] <= sim.t < dropout[1]
        e = est.step(u, sim.p, sim.yaw, None if lost else sim.measure())
        s = sim.features()
        rows.append(
            [
                sim.t,
                CAM.fx * abs(e.s[0] - s[0]),
                CAM.fy * abs(e.s[1] - s[1]),
                abs(1.0 / e.s[2] - 1.0 / s[2]),
                abs(wrap_angle(e.s[3] - s[3])),
                np.linalg.norm(e.target_position - sim.r),
                np.linalg.norm(e.target_velocity - sim.V),
                e.s[3],
                s[3],
            ]
        )
    a = np.array(rows)
    return {
        k: a[:, i]
        for i, k in enumerate(["t", "px", "py", "depth", "psi", "pos", "vel", "s4", "psi_true"])
    }, est


def _spd(P: np.ndarray) -> bool:
    return bool(np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0))


# ---------------------------------------------------------------- models


def test_measurement_model_matches_geometry():
    """h(x) of eq. (9) at the true state reproduces pixels, depth Z, psi and the UAV position."""
    sim = Sim(0)
    for _ in range(50):
        sim.advance()
    s = sim.features()
    x = np.concatenate([s, sim.r, sim.V])
    z = measurement_model(x, sim.yaw, CAM, 1e-3)
    rel = sim.rel_cam()
    expected = [CAM.fx * rel[0] / rel[2] + CAM.cu, CAM.fy * rel[1] / rel[2] + CAM.cv, rel[2], s[3]]
    np.testing.assert_allclose(z[:4], expected, atol=1e-9)
    np.testing.assert_allclose(z[4:], sim.p, atol=1e-9)
    # r_c = r_q - R_c^g r_{q/c}: the camera-frame offset rotated back gives the UAV position
    np.testing.assert_allclose(sim.r - cam_to_world(sim.yaw) @ rel, sim.p, atol=1e-9)


@pytest.mark.parametrize("h", [DT, DT / 2])
def test_process_model_one_step_error_is_second_order(h):
    """Forward-Euler (10) of (14) vs exact geometry: one-step error of x1..x3 and r_q is O(dt^2)."""

    def one_step_error(dt: float) -> float:
        sim = Sim(1)
        for _ in range(30):
            sim.advance()
        x = np.concatenate([sim.features(), sim.r, sim.V])
        vg, u, yaw_rate = sim.command()
        pred = process_model(x, dt, u, sim.yaw, np.zeros(3))
        sim.p = sim.p + vg * dt
        sim.yaw += yaw_rate * dt
        sim.r = sim.r + sim.V * dt
        true = np.concatenate([sim.features()[:3], sim.r])
        return float(np.max(np.abs(np.delete(pred, [3, 7, 8, 9])[:6] - true)))

    e1, e2 = one_step_error(h), one_step_error(h / 2)
    assert e1 < 5e-4
    assert 3.0 < e1 / e2 < 5.0  # halving dt quarters the local error: second order


def test_vectorized_sigma_points_equal_filterpys_bit_for_bit():
    from filterpy.kalman import MerweScaledSigmaPoints

    from uavtrack_env.estimation.ukf import VectorizedSigmaPoints, safe_sqrt

    rng = np.random.default_rng(5)
    A = rng.standard_normal((10, 10))
    P, x = A @ A.T + np.eye(10), rng.standard_normal(10)
    ref = MerweScaledSigmaPoints(10, 0.3, 2.0, 0.0, sqrt_method=safe_sqrt).sigma_points(x, P)
    fast = VectorizedSigmaPoints(10, 0.3, 2.0, 0.0, sqrt_method=safe_sqrt).sigma_points(x, P)
    np.testing.assert_array_equal(fast, ref)
    with pytest.raises(ValueError, match="expected size"):
        VectorizedSigmaPoints(10, 0.3, 2.0, 0.0).sigma_points(x[:9], P)


def test_vectorized_filter_equals_plain_filterpy():
    """The vectorised subclass gives filterpy's predict/update to 1e-9, also across psi = pi."""
    rng = np.random.default_rng(3)
    cfg = UKFConfig()
    plain = make_filter(CAM, cfg, DT, vectorized=False)
    fast = make_filter(CAM, cfg, DT, vectorized=True)
    A = rng.standard_normal((10, 10)) * 0.05
    P = A @ A.T + np.diag([1e-4, 1e-4, 1e-5, 0.05, 0.1, 0.1, 0.1, 0.5, 0.5, 0.05])
    x = np.array([0.05, 0.2, 0.12, 3.1, 5.0, 1.0, 0.75, 1.5, 0.5, 0.0])
    for f in (plain, fast):
        f.x, f.P = x.copy(), P.copy()
    u, yaw, acc = np.array([1.0, -0.2, 1.4, 0.1]), 0.3, np.array([0.1, -0.2, 0.0])
    for k in range(5):
        for f in (plain, fast):
            f.predict(dt=DT, u=u, yaw=yaw, accel=acc)
        np.testing.assert_allclose(fast.x, plain.x, atol=1e-9, rtol=0)
        np.testing.assert_allclose(fast.P, plain.P, atol=1e-9, rtol=0)
        z = measurement_model(plain.x, yaw, CAM, 1e-3) + rng.standard_normal(7) * 0.05
        z[3] = wrap_angle(-3.1 if k % 2 else 3.13)
        for f in (plain, fast):
            f.update(z, yaw=yaw)
        np.testing.assert_allclose(fast.x, plain.x, atol=1e-9, rtol=0)
        np.testing.assert_allclose(fast.P, plain.P, atol=1e-9, rtol=0)


# ---------------------------------------------------------------- closed-loop estimation


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_converges_and_recovers_from_dropout(seed):
    """Bounds, 2 px / 0.1 m / 0.03 rad noise:

    * converged (3 s < t <= 6 s): mean |V_q error| < 0.1 m/s, max x1/x2 error < 5 px, mean < 1.5 px,
      mean depth error < 0.05 m;
    * 2 s dropout (6 s to 8 s): target position error < 0.5 m, x1/x2 errors < 10 px;
    * re-converged 0.5 s after detections resume: x1/x2 errors < 5 px, mean velocity error < 0.1.
    """
    r, est = run(seed, 10.0, dropout=(6.0, 8.0))
    t = r["t"]
    ok = (t > 3.0) & (t <= 6.0)
    assert r["vel"][ok].mean() < 0.1
    assert max(r["px"][ok].max(), r["py"][ok].max()) < 5.0
    assert max(r["px"][ok].mean(), r["py"][ok].mean()) < 1.5
    assert r["depth"][ok].mean() < 0.05
    lost = (t >= 6.0) & (t < 8.0)
    assert r["pos"][lost].max() < 0.5
    assert max(r["px"][lost].max(), r["py"][lost].max()) < 10.0
    back = t > 8.5
    assert max(r["px"][back].max(), r["py"][back].max()) < 5.0
    assert r["vel"][back].mean() < 0.1
    assert _spd(est.ukf.P)


def test_a_box_cut_by_the_border_does_not_drag_the_estimate():
    """From 3 s on the measured v is pulled 40 px inwards, as a box cut by the image border is.
    Unflagged, the estimate follows it. Flagged ``truncated_v``, either option keeps x2 within
    5 px: ignoring v (variance x 1e6), or replacing it by the held car height's pseudo-measurement.
    u is still used."""
    configs = {
        "unflagged": UKFConfig(),
        "ignore": UKFConfig(truncated_variance_scale=1e6),
        "hold": UKFConfig(truncated_v_hold_height=True),
    }
    err = {}
    for name, cfg in configs.items():
        sim = Sim(0)
        est = TargetEstimator(CAM, cfg, DT)
        est.reset(sim.measure(), sim.p, sim.yaw)
        for _ in range(round(4.0 / DT)):
            u = sim.advance()
            m = sim.measure()
            if sim.t > 3.0:
                m = dataclasses.replace(m, v=m.v - 40.0, truncated_v=name != "unflagged")
            e = est.step(u, sim.p, sim.yaw, m)
        s = sim.features()
        err[name] = (CAM.fx * abs(e.s[0] - s[0]), CAM.fy * abs(e.s[1] - s[1]))
    assert err["unflagged"][1] > 20.0
    for name in ("ignore", "hold"):
        assert err[name][1] < 5.0 and err[name][0] < 5.0, (name, err[name])
    with pytest.raises(ValueError, match="truncated_variance_scale"):
        UKFConfig(truncated_variance_scale=0.5)


def test_psi_measurements_across_the_wrap_do_not_blow_up():
    """UAV straight behind the target: psi = pi, noisy measurements alternate sign at +-pi."""
    r, _ = run(4, 6.0, p0=(-8.0, -0.5, 4.0), vq=(1.5, 0.0, 0.0))
    late = r["t"] > 2.0
    assert r["psi"][late].mean() < 0.02
    assert r["psi"].max() < 0.15
    assert np.all(np.abs(r["psi_true"]) > 2.9)  # truth stays near the wrap ...
    assert (r["psi_true"] > 0).any() and (r["psi_true"] < 0).any()  # ... and crosses it
    assert np.all(np.abs(r["s4"]) > 2.8)  # the estimate never averages towards 0
    assert r["vel"][late].mean() < 0.1


def test_alternating_wrapped_psi_updates_stay_at_pi():
    """psi measured as pi - 0.02, -pi + 0.02 alternately: the estimate stays within 0.05 of pi."""
    sim = Sim(5, p0=(-8.0, 0.0, 4.0), vq=(0.0, 0.0, 0.0), noise=(0.0, 0.0, 0.0))
    est = TargetEstimator(CAM, UKFConfig(), DT)
    m = sim.measure()
    est.reset(m, sim.p, sim.yaw)
    for k in range(200):
        psi = math.pi - 0.02 if k % 2 else -math.pi + 0.02
        e = est.step(np.zeros(4), sim.p, sim.yaw, dataclasses.replace(m, psi=psi))
        assert abs(wrap_angle(e.s[3] - math.pi)) < 0.05
    assert e.covariance[3, 3] < 0.03**2


# ---------------------------------------------------------------- covariance guard


def test_indefinite_covariance_is_repaired():
    sim = Sim(6)
    est = TargetEstimator(CAM, UKFConfig(), DT)
    est.reset(sim.measure(), sim.p, sim.yaw)
    P = est.ukf.P.copy()
    P[3, 4] = P[4, 3] = 10.0  # makes P indefinite: Cholesky would fail in filterpy
    est.ukf.P = P
    u = sim.advance()
    e = est.step(u, sim.p, sim.yaw, sim.measure())
    assert np.all(np.isfinite(e.s))
    assert _spd(e.covariance)


def test_long_dropout_keeps_covariance_bounded_and_spd():
    """30 s without detections: no Cholesky error, P stays SPD with stds under UKFConfig.max_std."""
    sim = Sim(7)
    cfg = UKFConfig()
    est = TargetEstimator(CAM, cfg, DT)
    est.reset(sim.measure(), sim.p, sim.yaw)
    for _ in range(80):
        est.step(sim.advance(), sim.p, sim.yaw, sim.measure())
    for _ in range(round(30.0 / DT)):
        e = est.step(sim.advance(), sim.p, sim.yaw, None)
    assert not e.detected and e.steps_since_detection == round(30.0 / DT)
    assert np.all(np.isfinite(e.covariance)) and _spd(e.covariance)
    assert np.all(np.sqrt(np.diag(e.covariance)) <= np.array(cfg.max_std) * (1 + 1e-9))
    e = est.step(sim.advance(), sim.p, sim.yaw, sim.measure())  # and it can update again
    assert e.detected and np.all(np.isfinite(e.s))


def test_dropout_prediction_through_the_target_stays_finite():
    """Commanded straight at the target for 20 s without detections: the predicted target passes
    the image plane (Z -> 0, eq. 6 singular); the state and P must stay finite and P SPD."""
    sim = Sim(10)
    est = TargetEstimator(CAM, UKFConfig(), DT)
    est.reset(sim.measure(), sim.p, sim.yaw)
    u = np.array([0.0, 0.0, 3.0, 0.0])
    for _ in range(round(20.0 / DT)):
        e = est.step(u, sim.p, sim.yaw, None)
        assert np.all(np.isfinite(e.s)) and np.all(np.isfinite(e.covariance))
    assert _spd(e.covariance)


# ---------------------------------------------------------------- polynomial fit (Remark 2)


def _quadratic(t):
    p0, v0, a = np.array([1.0, -2.0, 0.75]), np.array([1.5, 0.4, 0.0]), np.array([0.3, -0.5, 0.0])
    pos = p0 + v0 * t[:, None] + 0.5 * a * t[:, None] ** 2
    vel = v0 + a * t[:, None]
    return pos, vel, a


def test_polynomial_fit_is_exact_on_a_quadratic():
    t = np.arange(0.0, 1.5, DT) + 4.0
    pos, vel, a = _quadratic(t)
    for w, v in ((0.0, None), (0.5, vel)):
        fit = fit_polynomial(t, pos, v, order=2, velocity_weight=w, t_eval=t[-1] + 0.5)
        te = np.array([t[-1] + 0.5])
        p_e, v_e, _ = _quadratic(te)
        np.testing.assert_allclose(fit.position, p_e[0], atol=1e-9)
        np.testing.assert_allclose(fit.velocity, v_e[0], atol=1e-9)
        np.testing.assert_allclose(fit.acceleration, a, atol=1e-8)


def test_polynomial_fit_with_noise_is_within_tolerance():
    """3 s at 80 Hz, 5 cm position noise: velocity within 0.05 m/s, acceleration within 0.1 m/s^2.

    (Standard errors of a quadratic least-squares fit here are about 0.01 m/s and 0.02 m/s^2.)
    """
    rng = np.random.default_rng(8)
    t = np.arange(0.0, 3.0, DT)
    pos, vel, a = _quadratic(t)
    hist = MotionHistory(window=3.0, capacity=400, order=2, velocity_weight=0.0, min_samples=10)
    for k in range(t.size):
        hist.add(t[k], pos[k] + 0.05 * rng.standard_normal(3), vel[k])
    fit = hist.fit()
    assert np.max(np.abs(fit.velocity - vel[-1])) < 0.05
    assert np.max(np.abs(fit.acceleration - a)) < 0.1


def test_motion_history_window_and_minimum():
    hist = MotionHistory(window=1.0, capacity=50, order=2, min_samples=5)
    assert hist.fit() is None
    for k in range(4):
        hist.add(float(k) * 0.1, np.zeros(3), np.zeros(3))
    assert hist.fit() is None  # fewer than min_samples
    hist.add(10.0, np.ones(3), np.zeros(3))  # the old samples fall out of the 1 s window
    assert hist.fit() is None


# ---------------------------------------------------------------- input validation


def test_bad_input_raises_value_error():
    sim = Sim(9)
    est = TargetEstimator(CAM, UKFConfig(), DT)
    with pytest.raises(ValueError, match="finite"):
        Measurement(320.0, float("nan"), 5.0, 0.0)
    with pytest.raises(ValueError, match="depth"):
        Measurement(320.0, 240.0, -1.0, 0.0)
    with pytest.raises(ValueError, match="Measurement"):
        est.reset(None, sim.p, sim.yaw)
    est.reset(sim.measure(), sim.p, sim.yaw)
    with pytest.raises(ValueError, match=r"u_applied must have shape \(4,\)"):
        est.step(np.zeros(3), sim.p, sim.yaw, None)
    with pytest.raises(ValueError, match="uav_position"):
        est.step(np.zeros(4), np.array([0.0, np.nan, 1.0]), sim.yaw, None)
    with pytest.raises(ValueError, match="uav_yaw"):
        est.step(np.zeros(4), sim.p, float("inf"), None)
    with pytest.raises(ValueError, match="meas"):
        est.step(np.zeros(4), sim.p, sim.yaw, (320.0, 240.0, 5.0, 0.0))
    with pytest.raises(ValueError):
        UKFConfig(pixel_std=0.0)
    with pytest.raises(ValueError):
        fit_polynomial(np.zeros(3), np.zeros((3, 3)), order=2)
    with pytest.raises(ValueError, match="shape"):
        fit_polynomial(np.arange(4.0), np.zeros((4, 2)))
