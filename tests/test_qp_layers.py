"""The shield's QP layers in one compiled call (daqp's C entry point, `qp_layers`) against the
same layers through `daqp.solve` one QP at a time: the same answers and reports, bit for bit."""

from __future__ import annotations

from collections import Counter

import daqp
import numpy as np
import pytest

from uavtrack_env.safety import SafetyContext, SafetyFilter, daqp_native


def test_daqp_entry_point_is_available_here():
    assert daqp_native.AVAILABLE, "daqp_quadprog from compiled code failed its self-check"


def test_quadprog_equals_daqp_solve_on_feasible_and_infeasible_qps():
    rng = np.random.default_rng(3)
    settings = daqp_native.settings(1e-10)
    flags = Counter()
    for _ in range(300):
        nv, m = 3 + int(rng.integers(0, 4)), int(rng.integers(1, 9))
        H = np.eye(nv)
        H[3:, 3:] *= 1e-6
        f, G = rng.normal(size=nv) * 3, rng.normal(size=(m, nv))
        bu = np.concatenate([np.full(nv, 2.0), rng.normal(size=m) - 1.0])
        bl = np.concatenate([np.full(nv, -2.0), np.full(m, -1e30)])
        x1, _, flag1, _ = daqp.solve(H, f, G, bu, bl, np.zeros(nv + m, np.int32), primal_tol=1e-10)
        x2, flag2 = daqp_native.quadprog(H, f, G, bu, bl, np.zeros(nv + m, np.int32), settings)
        assert flag2 == flag1
        if flag1 >= 1:
            assert np.array_equal(x2, x1)
        flags[flag1 >= 1] += 1
    assert flags[True] > 50 and flags[False] > 20  # both kinds of problem were exercised


def _random_context(rng: np.random.Generator, lag: bool) -> SafetyContext:
    """A UAV among close (sometimes too close) team-mates, boxes, the car and the floor."""
    p = np.array([0.0, 0.0, rng.uniform(0.5, 4.0)])
    k = int(rng.integers(0, 4))
    neighbours = p + rng.uniform(-3.0, 3.0, (k, 3)) * [1, 1, 0.5]
    m = int(rng.integers(0, 3))
    centers = p + rng.uniform(-4.0, 4.0, (m, 3)) * [1, 1, 0.3]
    kw = {}
    if lag:
        kw = {
            "velocity": rng.uniform(-3.0, 3.0, 3),
            "neighbour_velocities": rng.uniform(-2.0, 2.0, (k, 3)),
        }
    return SafetyContext(
        position=p,
        yaw=rng.uniform(-np.pi, np.pi),
        neighbours=neighbours.reshape(-1, 3),
        neighbour_radius=rng.uniform(0.0, 0.5, k),
        obstacle_centers=centers.reshape(-1, 3),
        obstacle_half_extents=rng.uniform(0.5, 2.0, (m, 3)),
        target_position=np.array([rng.uniform(-6, 6), rng.uniform(-6, 6), 0.75]),
        target_velocity=rng.uniform(-1.0, 1.0, 3) * [1, 1, 0],
        neighbour_ids=tuple(range(1, k + 1)),
        **kw,
    )


FIELDS = ("status", "active", "correction_norm", "slack", "active_rows", "solver", "solver_calls",
          "hard_violation", "gave_up", "slack_per_row")  # fmt: skip
"""The `ShieldReport` fields compared."""


@pytest.mark.parametrize("price", [None, 10.0])
@pytest.mark.parametrize("lag", [False, True])
def test_compiled_layers_equal_the_python_layers(lag, price):
    opts = {"lag_tau": 0.15, "accel_bound": 6.0} if lag else {}
    opts["occlusion_price"] = price
    native, python = SafetyFilter(**opts), SafetyFilter(**opts)
    python._native = None
    assert native._native is not None
    rng = np.random.default_rng(11 + lag)
    statuses = Counter()
    for _ in range(400):
        ctx = _random_context(rng, lag)
        u = rng.uniform(-6.0, 6.0, 4)
        rows = native.rows(ctx)
        u1, r1 = native.certify(u, ctx, rows)
        u2, r2 = python.certify(u, ctx, rows)
        assert np.array_equal(u1, u2)
        for field in FIELDS:
            assert getattr(r1, field) == getattr(r2, field), field
        statuses[r1.status] += 1
    # the random states reach every layer, the fallbacks included
    assert {"nominal", "optimal", "relaxed", "fallback"} <= set(statuses), statuses
