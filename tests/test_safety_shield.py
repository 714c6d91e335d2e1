"""The CBF-QP (47): closed forms, slack exactness, fallbacks and closed-loop forward invariance."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from scipy.optimize import linprog, minimize

from uavtrack_env.config import DT
from uavtrack_env.geometry import cam_to_world_vec, segment_hits_boxes, world_to_cam_vec
from uavtrack_env.safety import SOLVERS, SafetyContext, SafetyFilter, build_rows
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.shield import pairs_answered

BACKENDS = list(SOLVERS)


def ctx_with(**kw):
    base = {"position": [0.0, 0.0, 5.0], "yaw": 0.4}
    return SafetyContext(**{**base, **kw})


def global_v(u, yaw):
    return cam_to_world_vec(np.asarray(u[:3], float), yaw)


def cam_u(V, yaw, w=0.0):
    return np.r_[world_to_cam_vec(np.asarray(V, float), yaw), w]


@pytest.mark.parametrize("solver", BACKENDS)
def test_safe_nominal_is_returned_unchanged(solver):
    f = SafetyFilter(solver=solver)
    ctx = ctx_with(neighbours=[[6, 0, 5]], obstacle_centers=[[0, 8, 5]],
                   obstacle_half_extents=[[1, 1, 1]], target_position=[15, 0, 0.75])  # fmt: skip
    u = np.array([1.0, -0.5, 2.0, 0.3])
    out, rep = f.certify(u, ctx)
    assert np.array_equal(out, u)
    assert rep.status == "nominal" and not rep.active and rep.slack == 0.0
    assert rep.correction_norm == 0.0 and rep.solver_calls == 0


@pytest.mark.parametrize("solver", BACKENDS)
@pytest.mark.parametrize("case", ["uav", "obstacle", "moving-target", "floor"])
def test_one_active_row_gives_the_halfspace_projection(solver, case):
    """With one violated row a^T V <= b, the answer is V_hat - (a^T V_hat - b)/|a|^2 a."""
    yaw = 0.4
    cbf = CBFConfig().resolve()
    if case == "uav":  # neighbour 3 m ahead along x: row 6 V_x <= gamma_s (9 - 4) / 2
        ctx = ctx_with(yaw=yaw, neighbours=[[3.0, 0.0, 5.0]])
        a, b = np.array([6.0, 0.0, 0.0]), 0.5 * cbf.gamma_s * 5.0
        V_hat = np.array([5.0, 1.0, 0.5])
    elif case == "obstacle":  # box face 2 m ahead along y: h = 4 - c^2, grad = (0, -4, 0)
        ctx = ctx_with(yaw=yaw, obstacle_centers=[[0.0, 3.0, 5.0]],
                       obstacle_half_extents=[[1.0, 1.0, 1.0]])  # fmt: skip
        a, b = np.array([0.0, 4.0, 0.0]), cbf.gamma_obstacle * (4.0 - cbf.obstacle_clearance**2)
        V_hat = np.array([1.0, 6.0, -1.0])
    elif case == "moving-target":  # car 3 m ahead (rear face 0.7 m away) driving towards us
        ctx = ctx_with(yaw=yaw, position=[0.0, 0.0, 0.75], target_position=[3.0, 0.0, 0.75],
                       target_velocity=[-1.0, 0.0, 0.0], target_heading=0.0)  # fmt: skip
        gap = 3.0 - 2.3
        g = np.array([-2 * gap, 0.0, 0.0])  # grad h w.r.t. p
        a = -g
        b = cbf.gamma_obstacle * (gap**2 - cbf.obstacle_clearance**2) - g @ np.array([-1.0, 0, 0])
        V_hat = np.array([3.0, 0.5, 1.0])
    else:  # floor: -V_z <= gamma_z (z - z_min)
        ctx = ctx_with(yaw=yaw, position=[0.0, 0.0, 1.0])
        a, b = np.array([0.0, 0.0, -1.0]), cbf.gamma_z * (1.0 - cbf.z_min)
        V_hat = np.array([2.0, -1.0, -4.0])
    assert a @ V_hat > b  # the nominal violates the row
    expected = V_hat - (a @ V_hat - b) / (a @ a) * a
    out, rep = SafetyFilter(cbf=cbf, solver=solver, occlusion=False).certify(
        cam_u(V_hat, yaw, 0.2), ctx
    )
    assert rep.status == "optimal" and rep.active
    assert np.allclose(global_v(out, yaw), expected, atol=1e-6)
    assert out[3] == 0.2
    assert rep.correction_norm == pytest.approx(np.linalg.norm(expected - V_hat), abs=1e-6)
    name = {"uav": "uav:0", "obstacle": "obstacle:0", "moving-target": "target", "floor": "floor"}
    assert name[case] in rep.active_rows


def test_speed_and_yaw_rate_bounds_are_projected_in_closed_form():
    f = SafetyFilter()
    u = np.array([9.0, -8.0, 9.0, 2.0])  # inside Table II per axis, but ||v|| = 15 > alpha_v
    out, rep = f.certify(u, ctx_with())
    assert np.allclose(out[:3], u[:3] * 10.0 / np.linalg.norm(u[:3]))
    assert (
        out[3] == 0.6 and rep.status == "optimal" and {"speed", "yaw_rate"} <= set(rep.active_rows)
    )


def reference_qp(V_hat, A, b, alpha, v_max, yaw):
    """Independent SLSQP solution of min ||V - V_hat||^2 s.t. A V <= b, ||V|| <= alpha, Table II."""
    cons = [
        {"type": "ineq", "fun": lambda V: b - A @ V, "jac": lambda V: -A},
        {"type": "ineq", "fun": lambda V: alpha**2 - V @ V, "jac": lambda V: -2 * V},
    ]
    M = world_to_cam_vec(np.eye(3), yaw).T  # v_c = M V
    box = np.vstack([M, -M])
    cons.append({"type": "ineq", "fun": lambda V: v_max - box @ V, "jac": lambda V: -box})
    best = None
    for x0 in (np.zeros(3), V_hat * 0.1):
        r = minimize(
            lambda V: (V - V_hat) @ (V - V_hat),
            x0,
            jac=lambda V: 2 * (V - V_hat),
            constraints=cons,
            method="SLSQP",
            options={"ftol": 1e-12, "maxiter": 500},
        )
        ok = all((c["fun"](r.x) >= -1e-8).all() for c in cons)  # SLSQP may stop with "positive
        if ok and (best is None or r.fun < best.fun):  # directional derivative" at the optimum
            best = r
    return best.x


@pytest.mark.parametrize("solver", BACKENDS)
def test_norm_bound_with_active_rows_matches_a_reference_solver(solver):
    rng = np.random.default_rng(3)
    f = SafetyFilter(solver=solver, occlusion=False)
    checked = 0
    for _ in range(15):
        yaw = rng.uniform(-np.pi, np.pi)
        nb = rng.normal(size=(2, 3))
        nb = 3.0 * nb / np.linalg.norm(nb, axis=1, keepdims=True) + [0, 0, 5]
        ctx = ctx_with(yaw=yaw, neighbours=nb)
        V_hat = rng.uniform(-10, 10, 3)
        out, rep = f.certify(cam_u(V_hat, yaw), ctx)
        rows = build_rows(ctx, f.cbf, connectivity_margin=f.connectivity_margin)
        ref = reference_qp(V_hat, rows.A, rows.b, f.alpha_v, f.v_max, yaw)
        V = global_v(out, yaw)
        assert V @ V <= f.alpha_v**2 * (1 + 1e-9)
        assert (rows.A @ V - rows.b <= 1e-6 * np.linalg.norm(rows.A, axis=1)).all()
        assert np.linalg.norm(V - V_hat) <= np.linalg.norm(ref - V_hat) + 1e-4
        assert np.allclose(V, ref, atol=1e-3)
        checked += rep.active
    assert checked >= 10


def hard_feasible(rows, alpha):
    """LP feasibility of all rows inside the cube inscribed in ||V|| <= alpha (independent)."""
    k = alpha / np.sqrt(3.0)
    res = linprog(np.zeros(3), A_ub=rows.A, b_ub=rows.b, bounds=[(-k, k)] * 3, method="highs")
    return res.status == 0


def test_slack_is_exactly_zero_whenever_the_hard_problem_is_feasible():
    rng = np.random.default_rng(11)
    f = SafetyFilter()
    feasible_seen = 0
    for _ in range(150):
        p = np.array([0, 0, 3.0]) + rng.uniform(-1, 1, 3)
        ctx = SafetyContext(
            position=p,
            yaw=rng.uniform(-np.pi, np.pi),
            neighbours=p + rng.uniform(-15, 15, (3, 3)),
            obstacle_centers=p + np.c_[rng.uniform(-6, 6, (6, 2)), rng.uniform(-1, 1, 6)],
            obstacle_half_extents=rng.uniform(0.2, 0.8, (6, 3)),
            target_position=p + [12, 0, -2],
        )
        rows = build_rows(ctx, f.cbf, connectivity_margin=f.connectivity_margin)
        if (rows.h[rows.hard] < 0).any() or not hard_feasible(rows, f.alpha_v):
            continue
        feasible_seen += 1
        _, rep = f.certify(np.r_[rng.uniform(-10, 10, 3), 0.0], ctx)
        assert rep.status in ("nominal", "optimal")
        assert rep.slack == 0.0 and rep.slack_per_row == {}
    assert feasible_seen >= 50


@pytest.mark.parametrize("solver", BACKENDS)
def test_conflict_relaxes_the_soft_row_only(solver):
    """Connectivity needs V_x >= ~0.07 towards a far neighbour; a near one forbids V_x > 1.5e-4."""
    f = SafetyFilter(solver=solver)
    yaw = 0.0
    far, near = 19.99, 2.0001
    ctx = ctx_with(yaw=yaw, neighbours=[[far, 0, 5], [near, 0, 5]])
    out, rep = f.certify(cam_u([0.0, 3.0, 0.0], yaw), ctx)
    cbf = f.cbf
    vx_max = 0.5 * cbf.gamma_s * (near**2 - cbf.r_s**2) / (2 * near)  # hard collision row (25)
    b_conn = 0.5 * cbf.gamma_c * (cbf.r_c**2 - far**2) - f.connectivity_margin
    vx_min = -b_conn / (2 * far)  # soft connectivity row (34): -2 far V_x <= b_conn
    assert vx_min > vx_max  # the two rows conflict
    V = global_v(out, yaw)
    assert rep.status == "relaxed"
    assert V[0] == pytest.approx(vx_max, abs=1e-7)  # hard row kept, soft one minimally violated
    assert rep.slack == pytest.approx(vx_min - vx_max, rel=1e-5)
    assert list(rep.slack_per_row) == ["connect:0"]
    assert V[1] == pytest.approx(3.0, abs=1e-6)  # the unconstrained direction is untouched


@pytest.mark.parametrize("solver", BACKENDS)
def test_unsafe_state_and_solver_failure_fall_back_without_raising(monkeypatch, solver):
    f = SafetyFilter(solver=solver)
    # Squeezed between two neighbours 1 m away on both sides: the hard rows contradict.
    ctx = ctx_with(neighbours=[[1.0, 0, 5], [-1.0, 0, 5]])
    out, rep = f.certify(np.array([3.0, 0.0, 0.0, 0.1]), ctx)
    assert rep.status == "fallback" and np.isfinite(out).all() and rep.min_hard_h < 0
    assert rep.hard_violation > 0

    def boom(*args, **kwargs):
        raise RuntimeError("solver crashed")

    monkeypatch.setattr("daqp.solve", boom)
    monkeypatch.setattr("qpsolvers.solve_qp", boom)
    native = f._native
    f._native = None  # the Python layers: a solver that raises
    out, rep = f.certify(np.array([3.0, 0.0, 0.0, 0.1]), ctx)
    assert rep.status == "fallback" and rep.solver == "brake"
    assert np.array_equal(out, [0.0, 0.0, 0.0, 0.1])  # brake, keep the yaw rate
    if native is not None:  # the compiled layers: daqp fails every QP (no iterations allowed)
        params, settings = native
        settings = settings.copy()
        settings.view(np.int32)[11] = 0  # DAQPSettings.iter_limit
        f._native = (params, settings)
        out, rep = f.certify(np.array([3.0, 0.0, 0.0, 0.1]), ctx)
        assert rep.status == "fallback" and rep.solver == "brake" and rep.solver_calls == 3
        assert np.array_equal(out, [0.0, 0.0, 0.0, 0.1])


@pytest.mark.parametrize("solver", BACKENDS)
@pytest.mark.parametrize("rival", ["target", "uav"])
def test_fallback_never_trades_the_floor_for_an_estimate_or_a_teammate(solver, rival):
    """0.1 m above the floor row's level, a (diverged) car estimate or a team-mate right above
    demands a dive: the fallback keeps the floor row (V_z >= -gamma_z (z - z_min)), gives the
    rival up and says so. The car's box row given up, the certificate is made again with its
    frustum (`SafetyFilter.climb_over_car`), which the floor row leaves a way out of: up."""
    f = SafetyFilter(solver=solver)
    above = {"target": {"target_position": [0.0, 0.0, 1.4], "target_heading": 0.0},
             "uav": {"neighbours": [[0.0, 0.0, 1.5]]}}[rival]  # fmt: skip
    ctx = ctx_with(position=[0.0, 0.0, 0.6], **above)
    out, rep = f.certify(cam_u([1.0, 0.0, -8.0], ctx.yaw), ctx)  # a dive, as the rival asks
    V = global_v(out, ctx.yaw)
    floor_rate = f.cbf.gamma_z * (0.6 - f.cbf.z_min)
    assert np.isfinite(out).all()
    assert V[2] >= -floor_rate - 1e-7  # the floor row holds
    if rival == "target":
        assert rep.status == "optimal" and not rep.gave_up and V[2] > 0.0, rep
        return
    assert rep.status == "fallback"
    assert rep.gave_up and all(name.split(":")[0] == rival for name in rep.gave_up), rep.gave_up
    assert "floor" not in rep.gave_up


@pytest.mark.parametrize("solver", BACKENDS)
def test_fallback_keeps_the_teammates_rows_over_the_cars(solver):
    """A team-mate 2.2 m above and a car estimate around the UAV, 9 m inside its nearest side
    (no command leaves it fast enough): the car's row is given up first, the pair row (25)
    holds."""
    f = SafetyFilter(solver=solver)
    ctx = ctx_with(
        position=[0.0, 0.0, 5.0],
        neighbours=[[0.0, 0.0, 7.2]],
        target_position=[-1.0, 0.0, 5.0],
        target_half_extents=[10.0, 10.0, 0.75],
        target_heading=0.0,
    )
    out, rep = f.certify(cam_u([0.0, 0.0, 0.0], ctx.yaw), ctx)
    V = global_v(out, ctx.yaw)
    h_pair = 2.2**2 - f.cbf.r_s**2
    assert rep.status == "fallback"
    assert 2 * 2.2 * V[2] <= 0.5 * f.cbf.gamma_s * h_pair + 1e-7  # row (25) holds
    assert rep.gave_up == ["target"]


@pytest.mark.parametrize(
    "u", [np.array([np.nan, 0, 0, 0]), np.zeros(3), np.zeros((4, 1)), [0, 0, np.inf, 0]]
)
def test_bad_action_raises_value_error(u):
    with pytest.raises(ValueError):
        SafetyFilter().certify(u, ctx_with())


def test_bad_construction_raises():
    with pytest.raises(ValueError):
        SafetyFilter().certify(np.zeros(4), {"position": [0, 0, 1]})
    with pytest.raises(ValueError):
        SafetyFilter(solver="osqp")
    with pytest.raises(ValueError):
        SafetyFilter(obstacle_model="sphere")
    with pytest.raises(TypeError):
        SafetyFilter(not_an_option=1)


@pytest.mark.parametrize(
    ("own_id", "match"), [(1.5, "own_id must be an int"), (True, "own_id must be an int"),
                          (4, "also in neighbour_ids")],
)  # fmt: skip
def test_bad_own_id_raises(own_id, match):
    with pytest.raises(ValueError, match=match):
        ctx_with(neighbours=[[6, 0, 5]], neighbour_ids=(4,), own_id=own_id)


def test_report_logs_barrier_values_by_name():
    ctx = ctx_with(neighbours=[[6, 0, 5]], neighbour_ids=(4,), obstacle_centers=[[0, 8, 5]],
                   obstacle_half_extents=[[1, 1, 1]], target_position=[15, 0, 0.75])  # fmt: skip
    _, rep = SafetyFilter().certify(np.zeros(4), ctx)
    assert rep.h["uav:4"] == pytest.approx(36 - 4)
    assert rep.h["floor"] == pytest.approx(5 - 0.5)
    assert rep.h["obstacle:0"] == pytest.approx(7**2 - 0.75**2)


# ----------------------------------------------------------------------------- closed loop
# Boxes inside and outside the ring of radius 7 on which the UAVs start (clear of it).
OBST_C = np.array([[3.0, 0.0, 1.5], [-2.5, 2.5, 2.0], [0.0, -10.5, 1.0], [-10.0, -4.0, 3.0]])
OBST_H = np.array([[1.0, 1.0, 1.5], [0.8, 0.8, 2.0], [1.5, 0.6, 1.0], [0.7, 0.7, 3.0]])
TARGET = np.array([10.0, 10.0, 0.75])


def box_clearance(p, c, h):
    return np.linalg.norm(np.maximum(np.abs(p - c) - h, 0.0))


def run_closed_loop(n, policy, seed, steps=2000, obstacle_model="box"):
    """Single integrators at 80 Hz, each UAV certifying with its own (distributed) context."""
    rng = np.random.default_rng(seed)
    cbf = CBFConfig().resolve()
    f = SafetyFilter(cbf=cbf, obstacle_model=obstacle_model)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3
    p = np.c_[7.0 * np.cos(ang), 7.0 * np.sin(ang), rng.uniform(2.0, 4.0, n)]
    yaw = rng.uniform(-np.pi, np.pi, n)
    worst = {"uav": np.inf, "obstacle": np.inf, "connect": np.inf, "floor": np.inf}
    assert (
        min(box_clearance(pi, c, h) for pi in p for c, h in zip(OBST_C, OBST_H, strict=True)) > 2.0
    )
    for k in range(steps):
        V = np.zeros((n, 3))
        w = np.zeros(n)
        for i in range(n):
            others = np.delete(np.arange(n), i)
            dist = np.linalg.norm(p[others] - p[i], axis=1)
            nb = others[dist <= cbf.r_c]
            ctx = SafetyContext(
                position=p[i], yaw=yaw[i], neighbours=p[nb], neighbour_ids=tuple(nb),
                obstacle_centers=OBST_C, obstacle_half_extents=OBST_H, target_position=TARGET,
            )  # fmt: skip
            u_nom = policy(i, k, p, yaw, rng)
            u, rep = f.certify(u_nom, ctx)
            assert rep.status != "fallback", (k, i, rep)
            V[i] = cam_to_world_vec(u[:3], yaw[i])
            w[i] = -u[3]
        p = p + DT * V
        yaw = yaw + DT * w
        d2 = np.sum((p[:, None] - p[None]) ** 2, -1)[np.triu_indices(n, 1)]
        worst["uav"] = min(worst["uav"], (d2 - cbf.r_s**2).min())
        worst["connect"] = min(worst["connect"], (cbf.r_c**2 - d2).min())
        worst["floor"] = min(worst["floor"], (p[:, 2] - cbf.z_min).min())
        if obstacle_model == "box":
            cl = min(
                box_clearance(pi, c, h) for pi in p for c, h in zip(OBST_C, OBST_H, strict=True)
            )
            worst["obstacle"] = min(worst["obstacle"], cl**2 - cbf.obstacle_clearance**2)
        else:
            dd = np.sum((p[:, None] - OBST_C[None]) ** 2, -1)
            worst["obstacle"] = min(worst["obstacle"], (dd - cbf.r_s**2).min())
    return worst


def toward(p_from, p_to, yaw, w=0.0):
    d = p_to - p_from
    return np.r_[world_to_cam_vec(10.0 * d / max(np.linalg.norm(d), 1e-9), yaw), w]


POLICIES = {
    "random": lambda i, k, p, yaw, rng: np.r_[rng.uniform(-10, 10, 3), rng.uniform(-0.6, 0.6)],
    "seek-uav": lambda i, k, p, yaw, rng: toward(p[i], p[(i + 1) % len(p)], yaw[i], 0.3),
    "seek-obstacle": lambda i, k, p, yaw, rng: toward(p[i], OBST_C[i % len(OBST_C)], yaw[i]),
    "seek-ground": lambda i, k, p, yaw, rng: toward(p[i], p[i] * [0.5, 0.5, 0.0], yaw[i]),
    "flee": lambda i, k, p, yaw, rng: toward(p.mean(0), p[i] + [0, 0, 1e-3], yaw[i]),
}


@pytest.mark.parametrize(
    ("policy", "n", "model"),
    [
        pytest.param("random", 4, "box", marks=pytest.mark.slow),
        ("seek-uav", 3, "box"),
        pytest.param("seek-uav", 6, "box", marks=pytest.mark.slow),
        pytest.param("seek-obstacle", 4, "box", marks=pytest.mark.slow),
        pytest.param("seek-obstacle", 4, "point", marks=pytest.mark.slow),
        pytest.param("seek-ground", 5, "box", marks=pytest.mark.slow),
        pytest.param("flee", 4, "box", marks=pytest.mark.slow),
    ],
)
def test_closed_loop_forward_invariance(policy, n, model):
    worst = run_closed_loop(n, POLICIES[policy], seed=n, obstacle_model=model)
    for name, h in worst.items():
        assert h >= -1e-9, (name, h)


def test_least_barrier_per_family_is_the_minimum_over_its_rows():
    from uavtrack_env.safety import ShieldReport
    from uavtrack_env.safety.cbf import KIND_NAMES, CBFRows

    rng = np.random.default_rng(4)
    for size in (1, 5, 40):
        kind = rng.integers(0, 6, size)  # families in any order, repeated
        h = rng.normal(size=size)
        rows = CBFRows(np.zeros((size, 3)), h, h, h, h, h, kind, np.arange(size))
        got = ShieldReport("optimal", False, 0.0, 0.0, [], rows=rows).min_h_by_family
        want = {KIND_NAMES[k]: float(h[kind == k].min()) for k in sorted(set(kind.tolist()))}
        assert got == want and list(got) == list(want)


def test_connectivity_is_kept_where_it_conflicts_only_with_occlusion():
    """A connectivity row (v_x <= 0) and an occlusion row (v_x >= 1) cannot both hold: the shield
    relaxes the occlusion row and keeps the link, whatever the nominal pulls towards."""
    from uavtrack_env.safety.cbf import CONNECT, OCCLUSION

    qp = SafetyFilter()
    An = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    bn = np.array([0.0, -1.0])
    kinds = np.array([CONNECT, OCCLUSION])
    box = np.full(3, qp.v_max)
    v, status, _, _ = qp._solve_layers(np.array([2.0, 0.5, 0.0]), An, bn, kinds, -box, box)
    assert status == "relaxed"
    assert v[0] <= 1e-6  # the link holds; the occlusion row took the slack
    np.testing.assert_allclose(v[1:], [0.5, 0.0], atol=1e-6)


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("urgency", [10.0, 1.0])
def test_the_occlusion_row_nearest_to_an_occlusion_is_kept_first(native, urgency):
    """Two occlusion rows that no command meets together: one whose sight line is about to touch
    its occluder (h just above -theta*), one far from it (h > 0). The nominal pulls towards the
    second. With urgency the first is kept and the second takes the slack; with equal weights
    (``occlusion_urgency=1``) the L1 slack is the same either way and the nominal wins."""
    from uavtrack_env.safety.cbf import OCCLUSION, CBFRows

    f = SafetyFilter(occlusion_urgency=urgency)
    if not native:
        f._native = None
    theta_star = f.cbf.theta_star
    two = np.ones(2)
    rows = CBFRows(
        A=np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]), b=np.array([-0.5, -0.5]),
        h=np.array([-theta_star + 0.02, 0.8]), gamma=0.1 * two, drift=0.0 * two,
        margin=0.0 * two, kind=np.full(2, OCCLUSION), index=np.array([6, 4]),
    )  # fmt: skip
    out, rep = f.certify_pose(cam_u([1.0, 0.3, 0.0], 0.0), 0.0, None, rows)
    assert rep.status == "relaxed"
    urgent_kept = urgency > 1
    slacked = "occlusion:4" if urgent_kept else "occlusion:6"
    assert list(rep.slack_per_row) == [slacked]
    assert rep.slack_per_row[slacked] == pytest.approx(1.0, abs=1e-6)
    V = global_v(out, 0.0)
    np.testing.assert_allclose(V, [-0.5 if urgent_kept else 0.5, 0.3, 0.0], atol=1e-6)


def test_urgency_grows_from_one_at_the_cone_to_its_bound_at_the_occluder():
    from uavtrack_env.safety.cbf import CONNECT, OCCLUSION

    f = SafetyFilter(occlusion_urgency=10.0)
    t = f.cbf.theta_star
    h = np.array([0.3, 0.0, -0.5 * t, -t, -2.0 * t, -t])
    kind = np.array([OCCLUSION] * 5 + [CONNECT])
    unit = np.tile([0.0, 0.6, 0.8], (6, 1))
    np.testing.assert_allclose(f.slack_factors(kind, h, unit), [1.0, 1.0, 5.5, 10.0, 10.0, 1.0])
    with pytest.raises(ValueError, match="occlusion_urgency"):
        SafetyFilter(occlusion_urgency=0.5)


@pytest.mark.parametrize("length", [1.0, 2.0, None])
def test_an_occlusion_rows_weight_scales_with_how_fast_a_velocity_turns_its_angle(length):
    """The leverage factor is L |grad h| clipped to [1e-3, 1], on occlusion rows only, without
    overflow for a gradient beyond float range squared (the UAV at its occluder)."""
    from uavtrack_env.safety.cbf import CONNECT, OCCLUSION

    f = SafetyFilter(occlusion_urgency=10.0, occlusion_leverage=length)
    t = f.cbf.theta_star
    grad = np.array([0.03, 0.3, 0.7, 4.0, 0.0, 1e200, 0.03])
    A = grad[:, None] * np.array([0.6, 0.0, -0.8])
    h = np.array([-t, -t, 0.0, 0.0, -t, 0.0, -t])
    kind = np.array([OCCLUSION] * 6 + [CONNECT])
    urgency = np.array([10.0, 10.0, 1.0, 1.0, 10.0, 1.0, 1.0])
    leverage = np.ones(7) if length is None else np.clip(length * grad, 1e-3, 1.0)
    leverage[-1] = 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = f.slack_factors(kind, h, A)
    np.testing.assert_allclose(got, urgency * leverage)
    assert (got > 0).all()  # a zero gradient keeps the row soft


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("length", [1.0, None])
def test_an_occlusion_row_no_velocity_can_keep_does_not_take_the_command(native, length):
    """Two occlusion rows equally near their occluders that no command meets together. The
    first's angle barely moves with the UAV (|grad h| = 0.03: occluder near the car, both far)
    and the car's motion drives it in faster than any velocity can answer (v_x <= -20 m/s). The
    second's occluder is near (|grad h| = 0.5, v_x >= -0.5). The nominal pulls towards the first.
    Priced by leverage, the second is kept and the first takes the slack it must take anyway;
    priced in m/s (``occlusion_leverage=None``) the hopeless row takes the command."""
    from uavtrack_env.safety.cbf import OCCLUSION, CBFRows

    f = SafetyFilter(occlusion_leverage=length)
    if not native:
        f._native = None
    two = np.ones(2)
    rows = CBFRows(
        A=np.array([[0.03, 0.0, 0.0], [-0.5, 0.0, 0.0]]), b=np.array([-0.6, 0.25]),
        h=np.full(2, -f.cbf.theta_star + 0.05), gamma=0.1 * two, drift=0.0 * two,
        margin=0.0 * two, kind=np.full(2, OCCLUSION), index=np.array([8, 17]),
    )  # fmt: skip
    out, rep = f.certify_pose(cam_u([-1.5, 0.3, 0.0], 0.0), 0.0, None, rows)
    assert rep.status == "relaxed"
    V = global_v(out, 0.0)
    if length is not None:
        assert list(rep.slack_per_row) == ["occlusion:8"]
        np.testing.assert_allclose(V, [-0.5, 0.3, 0.0], atol=1e-6)
    else:
        assert set(rep.slack_per_row) == {"occlusion:8", "occlusion:17"}
        np.testing.assert_allclose(V, [-1.5, 0.3, 0.0], atol=1e-4)  # slack_regularization


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("price", [None, 10.0])
def test_a_slacked_occlusion_row_moves_the_directions_it_barely_touches_by_its_price(native, price):
    """An occlusion row that asks for v_x >= 0.5 against an obstacle's row v_x <= 0, with a
    0.002 component on v_z: no command keeps it, so it takes slack. The nominal descends at
    1 m/s. With the L1 price at soft_penalty (1000 m/s per m/s of slack) the row's pull on
    v_z, 1000 x 0.002, turns the descent into a climb; priced in proportion to the nominal's
    violation (``occlusion_price``, D = 1.5 m/s here) it moves v_z by at most c D 0.002. Either
    way the row still beats the nominal in its main direction (v_x from -1 to 0)."""
    from uavtrack_env.safety.cbf import OBSTACLE, OCCLUSION, CBFRows

    f = SafetyFilter(occlusion_price=price)
    if not native:
        f._native = None
    two = np.ones(2)
    a = np.array([-1.0, 0.0, -0.002])
    rows = CBFRows(
        A=np.array([[1.0, 0.0, 0.0], a]), b=np.array([0.0, -0.5]), h=np.array([1.0, 0.0]),
        gamma=0.1 * two, drift=0.0 * two, margin=0.0 * two,
        kind=np.array([OBSTACLE, OCCLUSION]), index=np.array([3, 9]),
    )  # fmt: skip
    nominal = np.array([-1.0, 0.0, -1.0])
    out, rep = f.certify_pose(cam_u(nominal, 0.0), 0.0, None, rows)
    assert rep.status == "relaxed" and list(rep.slack_per_row) == ["occlusion:9"]
    V = global_v(out, 0.0)
    assert V[0] == pytest.approx(0.0, abs=1e-6)
    assert V[1] == pytest.approx(0.0, abs=1e-6)
    lift = V[2] - nominal[2]
    if price is None:
        assert lift == pytest.approx(1e3 * 0.002 / np.linalg.norm(a), rel=1e-3)
    else:
        D = (a @ nominal + 0.5) / np.linalg.norm(a)
        assert 0.0 < lift <= price * D * 0.002 + 1e-9
    with pytest.raises(ValueError, match="occlusion_price"):
        SafetyFilter(occlusion_price=0.0)


def squeezed(**kw):
    """A UAV 1.9 m from a team-mate on each side along x (inside R_s = 2 m): each pair row
    asks it to move away from its team-mate, so no command keeps both."""
    return ctx_with(neighbours=[[1.9, 0, 5], [-1.9, 0, 5]], **kw)


def pair_excess(f, ctx, out):
    """How far (m/s on unit rows) ``out`` breaks each pair row, by team-mate slot."""
    rows = f.rows(ctx)
    V = global_v(out, ctx.yaw)
    uav = rows.kind == 0
    excess = (rows.A[uav] @ V - rows.b[uav]) / np.linalg.norm(rows.A[uav], axis=1)
    return dict(zip(rows.index[uav].tolist(), excess.tolist(), strict=True))


@pytest.mark.parametrize("solver", BACKENDS)
@pytest.mark.parametrize("ids", [(2, 0), (0, 2)])
def test_squeezed_fallback_keeps_the_pair_row_it_answers_for(solver, ids):
    """Between two team-mates, ids 0 and 2, with no velocities: UAV 1 answers for its pair
    with id 2 (the lower id answers), so it keeps that row whole and gives up the other.
    Unranked (no own id), the fallback splits the violation over both rows."""
    f = SafetyFilter(solver=solver)
    u = np.zeros(4)
    out, rep = f.certify(u, squeezed(neighbour_ids=ids, own_id=1))
    excess = pair_excess(f, squeezed(), out)
    kept, lost = ids.index(2), ids.index(0)
    assert rep.status == "fallback" and rep.gave_up == ["uav:0"], rep.gave_up
    assert excess[kept] <= 1e-6 < excess[lost]
    out, rep = f.certify(u, squeezed(neighbour_ids=ids))
    assert sorted(rep.gave_up) == ["uav:0", "uav:2"]
    assert min(pair_excess(f, squeezed(), out).values()) > 1e-6


@pytest.mark.parametrize("solver", BACKENDS)
def test_the_uav_closing_the_gap_answers_for_the_pair(solver):
    """With velocities the one closing the gap faster answers, whatever the ids: UAV 1 flying
    at the team-mate id 0 (which holds still) keeps that row; the team-mate id 2 flying at
    UAV 1 answers for theirs, so UAV 1 gives that one up."""
    f = SafetyFilter(solver=solver)
    moving = {
        "velocity": [-1.0, 0.0, 0.0],
        "neighbour_velocities": [[-2.5, 0.0, 0.0], [0.0, 0.0, 0.0]],
        "neighbour_ids": (2, 0),
        "own_id": 1,
    }
    out, rep = f.certify(np.zeros(4), squeezed(**moving))
    excess = pair_excess(f, squeezed(), out)
    assert rep.status == "fallback" and rep.gave_up == ["uav:2"], rep.gave_up
    assert excess[1] <= 1e-6 < excess[0]


def test_pairs_answered_split_each_pair_between_its_two_uavs():
    """Each of three UAVs at random places and velocities computes which of its pairs it
    answers for; every pair is answered for by exactly one of its two UAVs, with velocities
    (the faster closer) and without (the lower id), and ties fall to the lower id."""
    rng = np.random.default_rng(7)
    for trial in range(50):
        p = rng.normal(size=(3, 3)) * 3
        v = rng.normal(size=(3, 3))
        if trial % 5 == 0:
            v[:] = 0.0  # every pair a tie
        for with_v in (True, False):
            answers = {}
            for i in range(3):
                others = [j for j in range(3) if j != i]
                kw = {"velocity": v[i], "neighbour_velocities": v[others]} if with_v else {}
                ctx = SafetyContext(
                    position=p[i], yaw=0.0, neighbours=p[others],
                    neighbour_ids=tuple(others), own_id=i, **kw,
                )  # fmt: skip
                got = pairs_answered(ctx, np.arange(2))
                answers.update({(i, j): bool(a) for j, a in zip(others, got, strict=True)})
            for i in range(3):
                for j in range(i + 1, 3):
                    assert answers[i, j] != answers[j, i]
                    if not with_v or trial % 5 == 0:
                        assert answers[i, j]  # the lower id
    ctx = SafetyContext(position=np.zeros(3), yaw=0.0, neighbours=[[1.0, 0, 0]])
    assert pairs_answered(ctx, np.arange(1)) is None  # no ids: no ranking


@pytest.mark.parametrize("radius", [0.25, 0.0])
def test_a_team_mate_crossing_the_sight_line_is_kept_out_of_the_cone(radius):
    """A UAV hovering 15 m from a parked car; a team-mate 3 m away crosses its sight line at
    1 m/s. With team-mate occlusion rows (radius 0.25 m) the UAV moves so that the team-mate's
    least angle to the sight line stays at theta* or above (the row's h >= 0 in closed loop);
    with the paper's rows (obstacles only) it hovers and the team-mate crosses the line."""
    cbf = CBFConfig(occlusion_point="edges", team_mate_radius=radius).resolve()
    f = SafetyFilter(cbf=cbf)
    p, q = np.array([0.0, 0.0, 3.0]), np.array([15.0, 0.0, 0.75])
    sight = (q - p) / np.linalg.norm(q - p)
    side = np.array([0.0, 1.0, 0.0])
    mate, mate_v = p + 3.0 * (np.cos(0.9) * sight + np.sin(0.9) * side), -side
    least = np.inf
    for _ in range(int(4.0 / DT)):
        ctx = SafetyContext(
            position=p, yaw=0.0, neighbours=[mate], neighbour_velocities=[mate_v],
            neighbour_ids=(1,), own_id=0, target_position=q, target_heading=0.0,
        )  # fmt: skip
        u, rep = f.certify(np.zeros(4), ctx)
        assert rep.status != "fallback", rep
        p = p + DT * global_v(u, 0.0)
        mate = mate + DT * mate_v
        exact = SafetyContext(position=p, yaw=0.0, neighbours=[mate], target_position=q)
        rows = build_rows(exact, dataclasses.replace(cbf, team_mate_radius=0.25))
        least = min(least, rows.h[(rows.kind == 5) & (rows.index < 0)].min(initial=np.inf))
    if radius > 0:  # first-order rows without a discrete-time margin: Euler at 80 Hz
        assert least >= -5e-3  # lets h dip O(dt^2) per step (5e-3 rad = 0.3 deg)
    else:
        assert least < -0.2  # it crossed the cone: the rows are what keeps it out


@pytest.mark.parametrize("depth", [0.0, 0.3, 0.6])
def test_a_sight_line_through_an_obstacle_is_steered_out(depth):
    """A UAV hovering 15 m from a parked car sees it through a box (the sight line ``depth``
    of the box's half width from its middle). With the tuned 'edges' rows, certifying a zero
    command moves the UAV until its sight line passes beside the box, without a fallback."""
    cbf = CBFConfig(occlusion_point="edges").resolve()
    f = SafetyFilter(cbf=cbf)
    p, q = np.array([0.0, 0.0, 3.0]), np.array([15.0, 0.0, 0.75])
    half = np.array([0.6, 0.6, 1.5])
    center = p + 0.45 * (q - p) + [0.0, depth * half[1], 0.0]
    center[2] = half[2]  # standing on the ground

    def through(p):
        return segment_hits_boxes(p, q, center[None], half[None])[0]

    assert through(p)
    steps = 0
    while through(p) and steps < int(6.0 / DT):
        ctx = SafetyContext(
            position=p, yaw=0.0, target_position=q, target_heading=0.0,
            obstacle_centers=center[None], obstacle_half_extents=half[None],
        )  # fmt: skip
        u, rep = f.certify(np.zeros(4), ctx)
        assert rep.status != "fallback", rep
        p = p + DT * global_v(u, 0.0)
        steps += 1
    assert not through(p), f"still behind the box after {steps * DT:.1f} s"


def pinned_low(rng):
    """A UAV 0.6-0.9 m up whose sight line to a parked car 8-14 m away goes through a box
    near the car, 0.05-0.2 m inside its side edge and 0.25-0.6 m under its top, so that the
    box's outline is nearest to the line at the side; a wall 10 mm outside the UAV's clearance
    on that side. (p, q, centres, half sizes, the side: +-1.)"""
    clearance = CBFConfig().obstacle_clearance
    length, z0, side = rng.uniform(8, 14), rng.uniform(0.6, 0.9), rng.choice([-1.0, 1.0])
    p, q = np.array([0.0, 0.0, z0]), np.array([length, 0.0, 0.75])
    x = length - rng.uniform(1.5, 4.0)
    top = z0 + x / length * (q[2] - z0) + rng.uniform(0.25, 0.6)
    width, edge = rng.uniform(1.0, 2.5), side * rng.uniform(0.05, 0.2)
    centers = [[x, edge - side * width / 2, top / 2], [0.0, side * (clearance + 1.01), 3.0]]
    half = [[rng.uniform(0.3, 0.8), width / 2, top / 2], [3.0, 1.0, 3.0]]
    return p, q, np.array(centers), np.array(half), side


@pytest.mark.parametrize("climb", [True, False])
@pytest.mark.parametrize("seed", range(6))
def test_a_uav_pinned_low_climbs_over_the_box_that_hides_the_car(seed, climb):
    """Closed loop, 5 s, tuned 'edges' rows, a command into the wall and down: the sideways way
    out of the occlusion is blocked by the wall, and the occlusion row's least-angle outline
    point is on the box's vertical edge, whose gradient is level. Made again with the way out
    over the box's top (`SafetyFilter.climb_over_occluders`), the certificate climbs: the line
    clears the box and stays clear for the last second, with every obstacle's clearance and
    the floor kept and no fallback. Without it the car stays hidden."""
    p, q, centers, half, side = pinned_low(np.random.default_rng(900 + seed))
    cbf = CBFConfig(occlusion_model="moving-target", occlusion_point="edges").resolve()
    f = SafetyFilter(cbf=cbf, climb_over_occluders=climb)
    nominal = cam_u([0.0, side, -0.3], 0.0)
    assert segment_hits_boxes(p, q, centers, half).any()
    hidden = []
    for _ in range(int(5.0 / DT)):
        ctx = SafetyContext(
            position=p, yaw=0.0, target_position=q, target_heading=0.0,
            obstacle_centers=centers, obstacle_half_extents=half,
        )  # fmt: skip
        u, rep = f.certify(nominal, ctx)
        assert rep.status != "fallback", rep
        p = p + DT * global_v(u, 0.0)
        for c, h in zip(centers, half, strict=True):
            assert box_clearance(p, c, h) >= cbf.obstacle_clearance - 1e-6
        assert p[2] >= cbf.z_min - 1e-6
        hidden.append(segment_hits_boxes(p, q, centers, half).any())
    last_second = hidden[-int(1.0 / DT) :]
    assert not any(last_second) if climb else all(last_second)


@pytest.mark.parametrize(("room", "taller"), [(0.5, 0.0), (0.2, 2.0)])
@pytest.mark.parametrize("seed", range(2))
def test_the_climb_is_not_taken_where_the_line_leaves_sooner_sideways(seed, room, taller):
    """The pinned case of `pinned_low` with the wall ``room`` m further out or the box
    ``taller`` m taller: the row's own relaxed certificate still moves the line sideways out of
    the box, sooner than climbing would (first order), and is kept unchanged."""
    p, q, centers, half, side = pinned_low(np.random.default_rng(900 + seed))
    centers[1, 1] += side * room
    centers[0, 2] += taller
    half[0, 2] += taller
    cbf = CBFConfig(occlusion_model="moving-target", occlusion_point="edges").resolve()
    ctx = SafetyContext(
        position=p, yaw=0.0, target_position=q, target_heading=0.0,
        obstacle_centers=centers, obstacle_half_extents=half,
    )  # fmt: skip
    nominal = cam_u([0.0, side, -0.3], 0.0)
    plain, report = SafetyFilter(cbf=cbf).certify(nominal, ctx)
    assert report.status == "relaxed"
    climbing, _ = SafetyFilter(cbf=cbf, climb_over_occluders=True).certify(nominal, ctx)
    np.testing.assert_array_equal(climbing, plain)


def test_exit_time_is_the_longest_angle_over_its_rate():
    """`shield._exit_time`: rows through boxes at h = -theta* - angle with rates
    -A V + drift; the longest angle / rate, inf if a rate is not positive."""
    from uavtrack_env.safety.cbf import OCCLUSION, CBFRows
    from uavtrack_env.safety.shield import _exit_time

    ts, yaw = 0.5, 0.3
    three = np.ones(3)
    rows = CBFRows(
        A=np.array([[0.0, 0.0, -0.2], [-0.1, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        b=0.0 * three, h=-ts - np.array([0.3, 0.1, 0.2]), gamma=0.1 * three,
        drift=np.array([0.0, 0.05, 0.0]), margin=0.0 * three, kind=np.full(3, OCCLUSION),
        index=np.arange(3),
    )  # fmt: skip
    u = cam_u([1.0, 0.0, 0.5], yaw)  # rates 0.1 and 0.15 rad/s
    through = np.array([True, True, False])
    assert _exit_time(rows, through, u, yaw, ts) == pytest.approx(max(0.3 / 0.1, 0.1 / 0.15))
    assert _exit_time(rows, np.ones(3, bool), u, yaw, ts) == np.inf  # the third: rate 0


def test_the_team_certificate_climbs_over_the_occluder_as_each_uav_alone():
    """`onboard.certify_team`'s settling (`onboard._settle`) makes the relaxed certificates of
    pinned UAVs again over the top, as `SafetyFilter.certify` does for one: the same action and
    status for every UAV of a batch of the pinned cases and one UAV in free air."""
    from types import SimpleNamespace

    from uavtrack_env.onboard import _settle

    cbf = CBFConfig(occlusion_model="moving-target", occlusion_point="edges").resolve()
    f = SafetyFilter(cbf=cbf, climb_over_occluders=True)
    contexts, u = [], []
    for seed in range(4):
        p, q, centers, half, side = pinned_low(np.random.default_rng(900 + seed))
        contexts.append(SafetyContext(
            position=p, yaw=0.0, target_position=q, target_heading=0.0,
            obstacle_centers=centers, obstacle_half_extents=half,
        ))  # fmt: skip
        u.append(cam_u([0.0, side, -0.3], 0.0))
    contexts.append(ctx_with(target_position=[12.0, 0.0, 0.75]))
    u.append(cam_u([1.0, 0.0, 0.0], 0.4))
    u = np.array(u)
    agents = [SimpleNamespace(filter=f, context=lambda c=c: c) for c in contexts]
    raw = f.certify_many(
        u, np.array([c.yaw for c in contexts]), np.zeros((len(u), 3)),
        [f.rows(c) for c in contexts], [None] * len(u),
    )  # fmt: skip
    assert raw.relaxed[:4].all()
    team = _settle(agents, u, raw)
    for j, ctx in enumerate(contexts):
        alone, report = f.certify(u[j], ctx)
        np.testing.assert_array_equal(team.action[j], alone)
        assert team.report(j).status == report.status
    assert [team.report(j).status for j in range(4)] == ["optimal"] * 4  # over the top
