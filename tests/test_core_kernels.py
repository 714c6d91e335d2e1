"""The step's numba kernels equal their numpy formulation bit for bit (`core_kernels`)."""

from __future__ import annotations

import numpy as np
import pytest

from uavtrack_env import core_kernels
from uavtrack_env.config import DT, DynamicsConfig
from uavtrack_env.dynamics import integrate
from uavtrack_env.infos import NOTHING_NEAR, _truth_numbers


def _state(rng: np.random.Generator, K: int, n: int):
    position = rng.uniform(-50, 50, (K, n, 3))
    yaw = rng.uniform(-np.pi, np.pi, (K, n))
    yaw[0, 0] = np.pi  # on the wrap's edge
    velocity = rng.uniform(-12, 12, (K, n, 3))
    yaw_rate = rng.uniform(-1, 1, (K, n))
    alive = rng.random((K, n)) < 0.8
    u = rng.uniform(-10, 10, (K, n, 4))
    return position, yaw, velocity, yaw_rate, alive, u


@pytest.mark.parametrize("model", ["integrator", "lag"])
@pytest.mark.parametrize("seed", range(4))
def test_integrate_equals_the_numpy_dynamics(model, seed):
    """Including finished UAVs (zero command), yaw at +-pi and accelerations beyond a_max."""
    rng = np.random.default_rng(seed)
    cfg = DynamicsConfig(model=model, tau=0.25, a_max=6.0, yaw_tau=0.1)
    position, yaw, velocity, yaw_rate, alive, u = _state(rng, 5, 7)
    applied = np.where(alive[..., None], u, 0.0)
    want = integrate(position, yaw, velocity, yaw_rate, applied, cfg, DT)
    got = core_kernels.integrate(
        position, yaw, velocity, yaw_rate, alive, u, model == "lag", cfg.tau, cfg.a_max,
        min(1.0, DT / cfg.yaw_tau), DT,
    )  # fmt: skip
    for g, w in zip(got[:4], want, strict=True):
        np.testing.assert_array_equal(g, w)
    np.testing.assert_array_equal(got[4], applied)


@pytest.mark.parametrize("drop_prob", [0.0, 0.3, 1.0])
def test_received_equals_the_numpy_mask(drop_prob):
    rng = np.random.default_rng(1)
    K, n, r_c = 4, 6, 20.0
    dist = rng.uniform(0, 40, (K, n, n))
    dist[:, :, 2] = r_c  # exactly at the range: heard
    alive = rng.random((K, n)) < 0.8
    draws = rng.random((K, n, n))
    want = (dist <= r_c) & ~(draws < drop_prob) & alive[:, :, None] & alive[:, None, :]
    want[:, np.arange(n), np.arange(n)] = False
    got = core_kernels.received(dist, alive, draws, drop_prob, r_c)
    np.testing.assert_array_equal(got, want)
    assert got.any() or drop_prob == 1.0


def test_truth_numbers_equal_the_numpy_formulation():
    """Capped box errors, the car centre's pixel error, the least angle over N_oi (pi with no
    candidate; NaN propagates as in numpy) and nearest distances, NOTHING_NEAR where not
    finite."""
    rng = np.random.default_rng(2)
    n, M = 5, 4
    box = rng.uniform(-3000, 3000, (n, 2))
    box[1, 0] = np.nan
    features = rng.uniform(-1, 1, (n, 4))
    ref_px = rng.uniform(0, 600, (n, 2))
    focal, principal = np.array([500.0, 510.0]), np.array([320.0, 240.0])
    size = np.array([640.0, 480.0])
    theta = rng.uniform(0, np.pi, (n, M))
    candidates = rng.random((n, M)) < 0.5
    candidates[0] = False
    candidates[2, :2] = True
    theta[2, 1] = np.nan
    nearest = rng.uniform(0, 30, (2, n))
    nearest[0, 3] = nearest[1, 0] = np.inf
    nearest[1, 2] = np.nan
    pixel, center, least, *near = _truth_numbers(
        box, features, ref_px, focal, principal, size, theta, candidates, nearest[0], nearest[1]
    )
    finite = np.stack(near)
    np.testing.assert_array_equal(pixel, np.clip(box - ref_px, -size, size))
    np.testing.assert_array_equal(center, features[:, :2] * focal + principal - ref_px)
    want = np.where(candidates, theta, np.pi).min(axis=1, initial=np.pi)
    np.testing.assert_array_equal(least, want)
    assert least[0] == np.pi and np.isnan(least[2]) and np.isnan(pixel[1, 0])
    np.testing.assert_array_equal(finite, np.where(np.isfinite(nearest), nearest, NOTHING_NEAR))
    assert finite[0, 3] == NOTHING_NEAR and finite[0, 0] == nearest[0, 0]


def test_scaled_actions_equal_numpy_clip_and_scale():
    rng = np.random.default_rng(3)
    a = rng.uniform(-2, 2, (50, 4))
    a[0] = [1.0, -1.0, 0.0, -0.0]  # on the bounds: not clipped
    scale = np.array([10.0, 10.0, 10.0, 0.6])
    u, clipped = core_kernels.scaled_actions(a, scale)
    np.testing.assert_array_equal(u, np.clip(a, -1.0, 1.0) * scale)
    np.testing.assert_array_equal(clipped, np.any(np.abs(a) > 1.0, axis=1))
    assert not clipped[0] and clipped.any()
