"""Tests of the expert's extensions beyond the paper: the turn-rate u_d, the shield's half-spaces in
the NMPC plan, and the settle time of the dropout motion fit."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from uavtrack_env.config import DT, ControlLimits
from uavtrack_env.control import NMPC
from uavtrack_env.control.config import NMPCConfig
from uavtrack_env.estimation import Measurement, TargetEstimator, UKFConfig
from uavtrack_env.geometry import cam_to_world_vec, world_to_cam_vec
from uavtrack_env.presets import PRESETS
from uavtrack_env.safety import SafetyContext, SafetyFilter
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.qp_arrays import nearest_camera_rows

REF = np.array([0.0, 0.0, 0.1, math.pi / 2])
W_MAX = ControlLimits().scale[3]


@pytest.fixture(scope="module")
def turning() -> NMPC:
    return NMPC(REF, NMPCConfig(yaw_rate_reference="target-turn"), error_signal=False)


@pytest.mark.parametrize("seed", range(5))
def test_turn_rate_equals_the_finite_difference_heading_rate(turning: NMPC, seed: int) -> None:
    """omega_cy of u_d = -d(heading)/dt of the target (omega_z^g = -omega_cy), from camera-frame
    v and a; checked against a central difference of atan2 along v + a t."""
    rng = np.random.default_rng(seed)
    v = np.r_[rng.uniform(-2, 2, 2), 0.0]
    if np.hypot(v[0], v[1]) < 0.5:
        v[0] += 1.0
    a = np.r_[rng.uniform(-0.3, 0.3, 2), rng.uniform(-0.1, 0.1)]
    yaw = rng.uniform(-math.pi, math.pi)
    h = 1e-5
    heading = [math.atan2(*(v + a * t)[1::-1]) for t in (-h, h)]
    rate = (heading[1] - heading[0]) / (2 * h)
    expected = float(np.clip(-rate, -W_MAX, W_MAX))
    got = turning.turn_rate_reference(world_to_cam_vec(v, yaw), world_to_cam_vec(a, yaw))
    assert got == pytest.approx(expected, abs=1e-7)


def test_turn_rate_is_zero_for_the_paper_and_for_a_slow_target(turning: NMPC) -> None:
    vq, aq = np.array([1.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.5])
    assert turning.turn_rate_reference(vq, aq) != 0.0
    assert NMPC(REF, error_signal=False).turn_rate_reference(vq, aq) == 0.0
    assert turning.turn_rate_reference(0.1 * vq, aq) == 0.0  # below turn_rate_min_speed


def test_turn_rate_reference_moves_the_planned_yaw_rate_towards_it(turning: NMPC) -> None:
    """At s = s*, R_u pulls omega towards u_d's yaw rate: 'target-turn' plans a yaw rate of the
    turn's sign, the paper's u_d (omega = 0) a smaller one."""
    paper = NMPC(REF, error_signal=False)
    vq, aq = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.3])
    w_d = turning.turn_rate_reference(vq, aq)
    turning.reset()
    u_turn = turning.solve(REF, vq, aq).u
    u_paper = paper.solve(REF, vq, aq).u
    assert abs(w_d) > 0.1
    assert np.sign(u_turn[3] - u_paper[3]) == np.sign(w_d)
    assert abs(u_turn[3] - u_paper[3]) > 0.2 * abs(w_d)


@pytest.fixture(scope="module", params=["stage", "shared"])
def with_rows(request) -> NMPC:
    cfg = NMPCConfig(safety_rows=2, safety_row_stages=10, safety_row_slack=request.param)
    return NMPC(REF, cfg, error_signal=False)


S_OFF = np.array([0.3, -0.1, 0.15, REF[3] + 0.4])
VQ = np.array([0.5, 0.0, 0.3])


def test_safety_rows_hold_on_the_constrained_stages(with_rows: NMPC) -> None:
    """A half-space that cuts the free plan's first velocity binds on stages 0..K-1 only."""
    with_rows.reset()
    free = with_rows.solve(S_OFF, VQ)
    v0 = free.u[:3]
    a = v0 / np.linalg.norm(v0)
    b = 0.3 * float(np.linalg.norm(v0))
    assert a @ v0 > b + 0.1  # the row cuts the free plan
    with_rows.reset()
    res = with_rows.solve(S_OFF, VQ, safety_rows=(a[None], np.array([b])))
    assert res.success, res.status
    along = res.predicted_u[:, :3] @ a
    assert along[:10].max() <= b + 1e-6
    assert along[10:].max() > b + 0.1  # the rest of the horizon is free


@pytest.mark.parametrize("slack", ["stage", "shared"])
def test_safety_rows_sqp_matches_ipopt(slack: str) -> None:
    """The default SQP and Ipopt give the same first input with two active half-spaces."""
    cfg = NMPCConfig(safety_rows=2, safety_row_stages=10, safety_row_slack=slack)
    rows = (np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([0.2, 0.1]))
    sqp = NMPC(REF, cfg, error_signal=False)
    for _ in range(3):  # cold Ipopt start, then warm SQP
        res = sqp.solve(S_OFF, VQ, safety_rows=rows)
    assert res.solver_used == "sqpmethod" and res.success, res.status
    ref = NMPC(REF, NMPCConfig(**{**vars(cfg), "solver": "ipopt"}), error_signal=False)
    out = ref.solve(S_OFF, VQ, safety_rows=rows)
    assert out.success
    np.testing.assert_allclose(res.u, out.u, atol=1e-3)
    assert res.u[0] <= 0.2 + 1e-6 and res.u[2] <= 0.1 + 1e-6


def test_infeasible_row_slacks_are_the_exact_l1_violations(with_rows: NMPC) -> None:
    """A half-space no input within Table II meets (v_x <= -v_max - 0.5): the plan rides the
    bound on the K constrained stages, and the L1 slacks are the violations a v - b, per stage
    ('stage') or the largest over the stages ('shared')."""
    v_max = ControlLimits().scale[0]
    a, b = np.array([1.0, 0.0, 0.0]), -v_max - 0.5
    with_rows.reset()
    res = with_rows.solve(S_OFF, VQ, safety_rows=(a[None], np.array([b])))
    assert res.success, res.status
    np.testing.assert_allclose(res.predicted_u[:10, 0], -v_max, atol=1e-6)
    violation = res.predicted_u[:10, :3] @ a - b
    slack = with_rows._w[with_rows._irow[:, 0]]  # the first of the two half-spaces
    expected = violation if with_rows.cfg.safety_row_slack == "stage" else violation.max()[None]
    np.testing.assert_allclose(slack, expected, atol=1e-5)


def test_per_stage_row_slacks_shift_with_their_stages() -> None:
    """The warm start moves stage n+1's row slacks to stage n; the last stage keeps its own."""
    ctrl = NMPC(REF, NMPCConfig(safety_rows=3, safety_row_stages=4), error_signal=False)
    irow = ctrl._irow
    assert irow.shape == (4, 3)
    np.testing.assert_array_equal(ctrl._shift_w[irow], irow[[1, 2, 3, 3]])
    assert (ctrl._lbx[irow] == 0).all() and np.isinf(ctrl._ubx[irow]).all()


def test_a_half_space_keeps_its_slot_when_the_rows_come_reordered() -> None:
    """The shield lists its rows nearest-first, so their order changes from step to step; each
    keeps the slot (and so the shifted multipliers) it had. Two controllers fed the same rows,
    one of them permuted at the second step, build the same NLP and give the same plan."""
    cfg = NMPCConfig(safety_rows=4, safety_row_stages=10)
    A = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    b = np.array([0.2, 0.1, 0.5])
    ordered, shuffled = NMPC(REF, cfg, error_signal=False), NMPC(REF, cfg, error_signal=False)
    for ctrl in (ordered, shuffled):
        ctrl.solve(S_OFF, VQ, safety_rows=(A, b))
    step = S_OFF + np.array([0.01, 0.0, 0.0, 0.02])
    first = ordered.solve(step, VQ, safety_rows=(A, b))
    second = shuffled.solve(step, VQ, safety_rows=(A[[2, 0, 1]], b[[2, 0, 1]]))
    assert first.success and second.success
    assert shuffled._row_normals == ordered._row_normals
    np.testing.assert_array_equal(second.u, first.u)
    fewer = shuffled.solve(step, VQ, safety_rows=(A[[1]], b[[1]]))  # the row stays in slot 1
    assert fewer.success and shuffled._row_normals[1] == A[1].tolist()
    assert shuffled._row_normals[0] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    "rows, match",
    [
        ((np.zeros((3, 3)), np.zeros(3)), "k <= 2"),
        ((np.zeros((2, 2)), np.zeros(2)), "k <= 2"),
        ((np.full((1, 3), np.nan), np.zeros(1)), "finite"),
        ((np.zeros((1, 3)), np.array([np.inf])), "b must be finite"),
    ],
)
def test_bad_safety_rows_raise(with_rows: NMPC, rows, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        with_rows.solve(S_OFF, VQ, safety_rows=rows)


def test_safety_rows_without_slots_raise() -> None:
    with pytest.raises(ValueError, match="k <= 0"):
        NMPC(REF, error_signal=False).solve(S_OFF, VQ, safety_rows=(np.zeros((1, 3)), np.zeros(1)))


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"safety_rows": -1}, "safety_rows must be an integer >= 0"),
        ({"safety_row_stages": 0}, "safety_row_stages"),
        ({"safety_row_stages": 51}, "safety_row_stages"),
        ({"yaw_rate_reference": "heading"}, "yaw_rate_reference"),
        ({"turn_rate_min_speed": 0.0}, "turn_rate_min_speed"),
    ],
)
def test_invalid_extension_config_is_rejected(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        NMPCConfig(**kw)


def test_camera_rows_are_the_normalised_global_rows_nearest_first() -> None:
    """camera_rows(rows, yaw) = unit rows of A R(yaw), sorted by b; certify with given rows is
    certify without."""
    shield = SafetyFilter(CBFConfig())
    p = np.array([0.0, 0.0, 4.0])
    ctx = SafetyContext(
        position=p,
        yaw=0.7,
        neighbours=p + np.array([[3.0, 0.5, 0.0], [-2.5, 2.0, 0.3]]),
        obstacle_centers=p + np.array([[2.0, -2.0, 0.0], [-4.0, -1.0, 0.0]]),
        obstacle_half_extents=np.full((2, 3), 0.5),
        target_position=p + np.array([8.0, 1.0, -3.5]),
    )
    rows = shield.rows(ctx)
    A, b = shield.camera_rows(rows, ctx.yaw, 3)
    R = np.stack([cam_to_world_vec(e, ctx.yaw) for e in np.eye(3)], axis=1)  # V = R v_c
    Ac = rows.A @ R
    n = np.linalg.norm(Ac, axis=1)
    order = np.argsort(rows.b / n)[:3]
    assert len(rows.b) > 3
    np.testing.assert_allclose(A, Ac[order] / n[order, None], atol=1e-12)
    np.testing.assert_allclose(b, (rows.b / n)[order], atol=1e-12)
    u_nom = np.array([2.0, 0.0, 3.0, 0.1])
    u1, r1 = shield.certify(u_nom, ctx)
    u2, r2 = shield.certify(u_nom, ctx, rows)
    np.testing.assert_array_equal(u1, u2)
    assert r1.status == r2.status


def test_nearest_camera_rows_drop_zero_and_implied_rows_and_keep_ties_in_order() -> None:
    """The kernel against its numpy formulation: zero rows and rows the speed ball implies
    (bn >= alpha_v) are dropped, ties keep the rows' order, at most k come back."""
    yaw, alpha_v = 0.4, 2.0
    A = np.array(
        [
            [0.0, 0.0, 0.0],  # zero row
            [1.0, 0.0, 0.0],
            [0.0, 2.0, 0.0],  # the same bn as the row above: a tie
            [0.0, 0.0, -1.0],
            [3.0, 4.0, 0.0],  # bn = 15 / 5 >= alpha_v: implied by the ball
            [0.5, -0.5, 1.0],
        ]
    )
    b = np.array([-1.0, 0.5, 1.0, -0.3, 15.0, 0.2])
    R = np.stack([cam_to_world_vec(e, yaw) for e in np.eye(3)], axis=1)
    Ac = A @ R
    n = np.linalg.norm(Ac, axis=1)
    ok = n >= 1e-12
    bn_all = np.where(ok, b / np.where(ok, n, 1.0), np.inf)
    order = [j for j in np.argsort(bn_all, kind="stable") if ok[j] and bn_all[j] < alpha_v]
    assert order == [3, 5, 1, 2]  # the tie (rows 1 and 2) in row order
    for k in (1, 3, 10):
        An, bn = nearest_camera_rows(A, b, yaw, alpha_v, k)
        expect = order[:k]
        np.testing.assert_allclose(An, Ac[expect] / n[expect, None], atol=1e-14)
        np.testing.assert_allclose(bn, bn_all[expect], atol=1e-14)


def test_fit_ignores_the_settle_time() -> None:
    """No samples enter the motion fit during fit_settle_time; afterwards they do."""
    est = TargetEstimator(cfg=UKFConfig(fit_settle_time=0.5))
    p, meas = np.array([-8.0, 0.0, 4.0]), Measurement(330.0, 300.0, 8.0, 3.1)
    est.reset(meas, p, 0.0)
    for _ in range(round(0.45 / DT)):
        est.step(np.zeros(4), p, 0.0, meas)
    assert len(est.history) == 0
    for _ in range(round(0.2 / DT)):
        est.step(np.zeros(4), p, 0.0, meas)
    assert len(est.history) > 0
    with pytest.raises(ValueError, match="fit_settle_time"):
        UKFConfig(fit_settle_time=-1.0)


def _in_layout(ctl: NMPC, shared: NMPC, w: np.ndarray) -> np.ndarray:
    """A primal vector (or its bound multipliers) of ``shared``'s layout in ``ctl``'s: each
    stage's row slacks take the shared ones."""
    out = np.zeros(ctl._nw)
    for name in ("_ix", "_iu", "_isig"):
        out[getattr(ctl, name)] = w[getattr(shared, name)]
    out[ctl._irow] = w[shared._irow[0]]
    return out


@pytest.mark.parametrize("slack", ["shared", "stage"])
def test_tuned_sqp_solves_the_recorded_warm_start_that_made_qrqp_cycle(slack: str) -> None:
    """A warm start recorded in scenario C with the tuned planner's shared row slacks
    (tests/data): with qrqp's min_lam = 0 its QPs cycled and the SQP stopped
    ('Search_Direction_Becomes_Too_Small', casadi 3.8.2). With the default
    `NMPCConfig.qrqp_min_lam` the SQP converges, to Ipopt's solution; also from the same start
    in the per-stage slacks' layout."""
    case = np.load(Path(__file__).parent / "data" / "qrqp_cycling_warm_start.npz")
    cfg = PRESETS["tuned"].nmpc
    shared = NMPC(case["p"][4:8], NMPCConfig(**{**vars(cfg), "safety_row_slack": "shared"}))
    ctl = NMPC(case["p"][4:8], NMPCConfig(**{**vars(cfg), "safety_row_slack": slack}))
    args = {k: case[k] for k in ("x0", "lam_g0", "lam_x0", "p")}
    args["x0"] = _in_layout(ctl, shared, args["x0"])
    args["lam_x0"] = _in_layout(ctl, shared, args["lam_x0"])
    args.update(lbx=ctl._lbx, ubx=ctl._ubx, lbg=ctl._lbg, ubg=ctl._ubg)
    ok, sol, status, _ = ctl._call(ctl._solver, args)
    assert ok, status
    ok_ref, ref, status_ref, _ = ctl._call(ctl._cold_solver, args)
    assert ok_ref, status_ref
    u, u_ref = sol["x"][ctl._iu[0]], ref["x"][ctl._iu[0]]
    assert np.max(np.abs(u - u_ref)) < 2e-3, (u, u_ref)


def test_qrqp_min_lam_must_be_non_negative() -> None:
    with pytest.raises(ValueError, match="qrqp_min_lam"):
        NMPCConfig(qrqp_min_lam=-1.0)
