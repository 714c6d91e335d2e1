"""Tests of the NMPC of section III (eqs. 15-19) against an independent fine RK4 simulation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uavtrack_env.config import DT, ControlLimits
from uavtrack_env.control import NMPC
from uavtrack_env.control.config import NMPCConfig
from uavtrack_env.geometry import feature_rates

U_MAX = ControlLimits().scale
REF = np.array([0.0, 0.0, 0.1, math.pi / 2])  # 10 m away, centred, beside the target


def _f(s: np.ndarray, u: np.ndarray, vq: np.ndarray) -> np.ndarray:
    return np.array(feature_rates(s, u, vq), dtype=float)


def _rk4(s: np.ndarray, u: np.ndarray, vq: np.ndarray, dt: float = DT, sub: int = 4) -> np.ndarray:
    """Eq. (15) integrated with `sub` RK4 substeps (the 'plant' of the closed-loop tests)."""
    h = dt / sub
    for _ in range(sub):
        k1 = _f(s, u, vq)
        k2 = _f(s + h / 2 * k1, u, vq)
        k3 = _f(s + h / 2 * k2, u, vq)
        k4 = _f(s + h * k3, u, vq)
        s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


@pytest.fixture(scope="module")
def sqp() -> NMPC:
    return NMPC(REF)


@pytest.fixture(scope="module")
def ipopt() -> NMPC:
    return NMPC(REF, NMPCConfig(solver="ipopt"), error_signal=False)


@pytest.mark.slow
@pytest.mark.parametrize(
    "s0",
    [
        [0.3, -0.2, 0.2, 1.0],
        [-0.5, 0.3, 0.09, 2.5],
        [0.6, 0.4, 0.5, math.pi / 2 + 0.3],
    ],
)
def test_closed_loop_converges_to_reference(sqp: NMPC, s0: list[float]) -> None:
    """14 s of closed loop on eq. (15) with a target moving at constant vq reach s*.

    Table III's weights make the loop slow (psi and x2 time constants of ~4 s).
    """
    sqp.reset()
    vq = np.array([0.5, 0.0, 1.0])
    s = np.array(s0)
    for _ in range(1120):
        res = sqp.solve(s, vq)
        assert res.success, res.status
        assert np.all(np.abs(res.u) <= U_MAX + 1e-9)
        s = _rk4(s, res.u, vq)
    err = s - REF
    assert abs(err[0]) < 0.02 and abs(err[1]) < 0.03, err
    assert abs(err[2]) < 0.005, err
    assert abs(err[3]) < 0.1, err
    # at steady state the UAV moves with the target (u -> u_d = [vq, 0])
    assert np.allclose(res.u[:3], vq, atol=0.15) and abs(res.u[3]) < 0.03


def test_default_solver_matches_ipopt(ipopt: NMPC) -> None:
    """Warm-started SQP (from another state's plan) and cold Ipopt agree on u_k to 1e-3.

    States within 3.3-12.5 m (x3 in [0.08, 0.3]); closer (x3 ~ 0.6) with a large psi error
    the Gauss-Newton SQP can exceed 20 iterations and is rescued by Ipopt.
    """
    rng = np.random.default_rng(1)
    ctrl = NMPC(REF, error_signal=False)
    for _ in range(6):
        s = np.array([rng.uniform(-0.7, 0.7), rng.uniform(-0.5, 0.5), rng.uniform(0.08, 0.3), 0.0])
        s[3] = REF[3] + rng.uniform(-1.0, 1.0)
        vq = rng.uniform(-2.0, 2.0, 3)
        ctrl.reset()
        for _ in range(3):  # cold Ipopt, then SQP: leaves an SQP plan to warm-start from
            ctrl.solve(s + np.array([0.05, -0.05, 0.01, 0.1]), vq)
        res = ctrl.solve(s, vq)
        assert res.solver_used == "sqpmethod" and res.success, res.status
        ipopt.reset()
        ref = ipopt.solve(s, vq)
        assert ref.solver_used == "ipopt" and ref.success
        np.testing.assert_allclose(res.u, ref.u, atol=1e-3)


def test_psi_wrap_gives_same_input() -> None:
    """psi* + 2 pi - d, psi* - d and psi on the far side of +-pi give the same input."""
    ctrl = NMPC(np.array([0.0, 0.0, 0.1, math.pi]), error_signal=False)
    vq = np.array([0.3, 0.0, 0.5])
    base = np.array([0.1, 0.05, 0.12, math.pi - 0.2])
    u_ref = ctrl.solve(base, vq).u
    for psi in (math.pi - 0.2 + 2 * math.pi, math.pi - 0.2 - 4 * math.pi):
        ctrl.reset()
        np.testing.assert_allclose(ctrl.solve([*base[:3], psi], vq).u, u_ref, atol=1e-8)
    # across the +-pi cut: pi + 0.2 measured as -pi + 0.2 is a small error of +0.2
    ctrl.reset()
    u_plus = ctrl.solve([*base[:3], math.pi + 0.2], vq).u
    ctrl.reset()
    np.testing.assert_allclose(ctrl.solve([*base[:3], -math.pi + 0.2], vq).u, u_plus, atol=1e-8)
    # the two sides of the reference push in opposite lateral directions (small angle error)
    assert np.sign(u_plus[0] - vq[0]) == -np.sign(u_ref[0] - vq[0])


def test_wrap_jump_in_closed_loop_keeps_input_continuous() -> None:
    """A measurement crossing +-pi between steps does not make the input jump."""
    ctrl = NMPC(np.array([0.0, 0.0, 0.1, math.pi]))
    vq = np.zeros(3)
    u1 = ctrl.solve([0.0, 0.0, 0.1, math.pi - 0.005], vq).u
    u2 = ctrl.solve([0.0, 0.0, 0.1, -math.pi + 0.005], vq)
    assert u2.success and u2.solver_used == "sqpmethod"
    assert np.max(np.abs(u2.u - u1)) < 0.2


@pytest.mark.parametrize(
    "s",
    [[1.2, 0.0, 0.1, 1.5], [0.0, -0.9, 0.1, 1.5], [0.2, 0.1, 1.6, 1.5], [0.0, 0.0, 0.03, 1.5]],
)
def test_states_outside_table_i_still_solve(sqp: NMPC, s: list[float]) -> None:
    """Soft Table I bounds: x1 = 1.2, x2 = -0.9, x3 = 1.6 or 0.03 still give a solution."""
    sqp.reset()
    vq = np.array([0.5, 0.0, 0.0])
    for _ in range(3):  # the cold (Ipopt) and warm (SQP) paths
        res = sqp.solve(s, vq)
        assert res.success, res.status
        assert np.all(np.abs(res.u) <= U_MAX + 1e-9)
    # the plan heads back into Table I: the predicted violation shrinks over the horizon
    lo, hi = np.array([-0.84, -0.63, 0.07]), np.array([0.84, 0.63, 1.0])
    viol = np.maximum(lo - res.predicted_s[:, :3], res.predicted_s[:, :3] - hi).max(axis=1)
    assert viol[-1] < viol[0]


def test_bounds_inside_are_respected_by_plan(sqp: NMPC) -> None:
    """A state near the image edge with the target pushing outward stays inside x1 <= 0.84."""
    sqp.reset()
    s = np.array([0.8, 0.0, 0.1, REF[3]])
    vq = np.array([3.0, 0.0, 0.0])  # target runs to the right, x1 would grow
    res = sqp.solve(s, vq)
    assert res.success
    assert res.predicted_s[1:, 0].max() <= 0.84 + 1e-4


def test_error_signal_is_one_step_model_mismatch() -> None:
    """eps_k of (16) equals s_k minus the one-step RK4 prediction from (s_k-1, u_k-1)."""
    ctrl = NMPC(REF)
    vq_told, vq_true = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.5])
    s = np.array([0.1, 0.0, 0.12, 1.4])
    r0 = ctrl.solve(s, vq_told)
    assert np.all(r0.eps == 0)
    s1 = _rk4(s, r0.u, vq_true, sub=8)
    r1 = ctrl.solve(s1, vq_told)
    expected = s1 - _rk4(s, r0.u, vq_told, sub=1)  # the model F_m: one RK4 step of dt
    np.testing.assert_allclose(r1.eps, expected, atol=1e-10)
    assert np.abs(r1.eps).max() > 1e-4  # the mismatch is visible
    off = NMPC(REF, error_signal=False)
    off.solve(s, vq_told)
    assert np.all(off.solve(s1, vq_told).eps == 0)


@pytest.mark.parametrize("integrator", ["rk4", "euler"])
def test_float_prediction_equals_the_nlp_model(integrator: str) -> None:
    """predict_one_step (a compiled kernel) equals the CasADi F_m inside the NLP."""
    ctrl = NMPC(REF, integrator=integrator)
    rng = np.random.default_rng(3)
    for _ in range(20):
        s = np.array([*rng.uniform(-0.6, 0.6, 2), rng.uniform(0.05, 0.5), rng.uniform(-3, 3)])
        u, vq = rng.uniform(-2, 2, 4), rng.uniform(-3, 3, 3)
        nlp_model = np.asarray(ctrl._F(s, u, vq)).ravel()
        np.testing.assert_allclose(ctrl.predict_one_step(s, u, vq), nlp_model, rtol=0, atol=1e-13)
        assert np.abs(nlp_model - s).max() > 1e-4  # the step moves the state


def test_error_signal_wraps_psi_and_caps_each_entry() -> None:
    """eps of (16): psi's difference across +-pi wraps to the short way round; every entry is
    clipped to +-`NMPCConfig.eps_max`."""
    from uavtrack_env.control.nmpc import _capped_error

    cap = np.array(NMPCConfig().eps_max)
    eps = _capped_error(np.array([0.5, -0.5, 0.01, 3.1]), np.array([0.0, 0.0, 0.0, -3.1]), cap)
    np.testing.assert_allclose(eps, [cap[0], -cap[1], 0.01, 6.2 - 2 * math.pi], atol=1e-15)
    eps = _capped_error(np.zeros(4), np.array([0.0, 0.0, -0.2, 2.0]), cap)
    np.testing.assert_allclose(eps, [0.0, 0.0, cap[2], -cap[3]], atol=0)


def test_error_signal_uses_applied_input() -> None:
    """With u_applied (e.g. after the CBF shield) the prediction uses that input."""
    ctrl = NMPC(REF)
    vq = np.array([0.2, 0.0, 0.0])
    s = np.array([0.1, 0.0, 0.12, 1.4])
    ctrl.solve(s, vq)
    u_shield = np.array([1.0, 0.5, -0.5, 0.1])
    s1 = _rk4(s, u_shield, vq, sub=8)
    r1 = ctrl.solve(s1, vq, u_applied=u_shield)
    assert np.abs(r1.eps).max() < 1e-8  # the model is right once it knows the input


def test_fallback_shifted_plan_after_real_failure() -> None:
    """One SQP iteration cannot converge after a big jump: the shifted plan's next input."""
    ctrl = NMPC(REF, NMPCConfig(max_iter=1), error_signal=False, rescue_with_ipopt=False)
    vq = np.array([0.5, 0.0, 0.0])
    first = ctrl.solve([0.0, 0.0, 0.1, REF[3]], vq)
    assert first.success and first.solver_used == "ipopt"
    res = ctrl.solve([0.7, 0.5, 0.6, REF[3] - 2.0], vq)
    assert not res.success
    assert res.status == "fallback-shifted" and res.solver_status == "Maximum_Iterations_Exceeded"
    assert res.iterations == 1
    np.testing.assert_allclose(res.u, first.predicted_u[1])


def test_a_converged_warm_solve_skips_the_statistics() -> None:
    """The per-step solver raises on failure, so a converged solve reads no stats():
    iterations -1, and `last_stats` has the count."""
    ctrl = NMPC(REF, error_signal=False)
    vq = np.array([0.5, 0.0, 0.0])
    ctrl.solve([0.1, 0.05, 0.2, REF[3]], vq)
    res = ctrl.solve([0.11, 0.05, 0.2, REF[3]], vq)
    assert res.success and res.status == "Solve_Succeeded" and res.iterations == -1
    stats = ctrl.last_stats()
    assert stats["success"] and 1 <= stats["iter_count"] <= NMPCConfig().max_iter


def test_ipopt_rescues_a_failed_sqp() -> None:
    """With the rescue on, the same iteration-limited SQP failure is solved by Ipopt."""
    ctrl = NMPC(REF, NMPCConfig(max_iter=1), error_signal=False)
    vq = np.array([0.5, 0.0, 0.0])
    ctrl.solve([0.0, 0.0, 0.1, REF[3]], vq)
    res = ctrl.solve([0.7, 0.5, 0.6, REF[3] - 2.0], vq)
    assert res.success and res.solver_used == "sqpmethod+ipopt"


def test_fallback_hover_when_solver_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    """No plan and a raising solver: hover with the target, u = clip([vq, 0])."""

    class Broken:
        def call(self, args):
            raise RuntimeError("boom")

        def stats(self):
            return {}

    ctrl = NMPC(REF)
    monkeypatch.setattr(ctrl, "_cold_solver", Broken())
    monkeypatch.setattr(ctrl, "_solver", Broken())
    res = ctrl.solve([0.1, 0.0, 0.1, 1.0], np.array([12.0, -0.5, 1.0]))
    assert not res.success and res.status == "fallback-hover"
    np.testing.assert_allclose(res.u, [10.0, -0.5, 1.0, 0.0])


def test_fallback_shifted_when_solver_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    ctrl = NMPC(REF, rescue_with_ipopt=False)
    vq = np.array([0.5, 0.0, 0.0])
    first = ctrl.solve([0.2, 0.1, 0.1, 1.0], vq)

    def boom(args):
        raise RuntimeError("boom")

    broken = {"call": staticmethod(boom), "stats": lambda self: {}}
    monkeypatch.setattr(ctrl, "_solver", type("B", (), broken)())
    for k in (1, 2):
        res = ctrl.solve([0.2, 0.1, 0.1, 1.0], vq)
        assert res.status == "fallback-shifted" and not res.success
        np.testing.assert_allclose(res.u, first.predicted_u[k])


@pytest.mark.parametrize(
    ("s", "vq", "aq", "match"),
    [
        ([0.0, 0.0, np.nan, 1.0], np.zeros(3), None, "s must be finite"),
        ([0.0, 0.0, 0.1], np.zeros(3), None, r"s must have shape \(4,\)"),
        ([0.0, 0.0, -0.1, 1.0], np.zeros(3), None, "x3"),
        ([0.0, 0.0, 0.1, 1.0], np.zeros(4), None, r"vq_cam must have shape \(3,\)"),
        ([0.0, 0.0, 0.1, 1.0], np.zeros(3), [np.inf, 0, 0], "aq_cam must be finite"),
    ],
)
def test_bad_input_raises(sqp: NMPC, s, vq, aq, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        sqp.solve(np.asarray(s, dtype=float), vq, aq)


def test_bad_construction_raises() -> None:
    with pytest.raises(ValueError, match="reference"):
        NMPC(np.array([0.0, 0.0, 0.1]))
    with pytest.raises(ValueError, match="integrator"):
        NMPCConfig(integrator="euler2")  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        NMPC(REF, not_an_option=1)


def test_rti_and_acceleration_feedforward() -> None:
    """RTI tracks too; with a target acceleration, u_d ramps over the horizon as in (19)."""
    ctrl = NMPC(REF, NMPCConfig(solver="rti"), error_signal=False)
    aq = np.array([0.0, 0.0, 2.0])
    s = REF.copy()
    vq = np.zeros(3)
    res = ctrl.solve(s, vq, aq)
    # the target accelerates away: the plan accelerates along Z at about the same rate
    dvz = np.diff(res.predicted_u[5:40, 2]) / DT
    assert np.all(np.abs(dvz - 2.0) < 0.5), dvz


def test_instances_share_one_build_without_crosstalk() -> None:
    """Same settings share the built solver; interleaved closed loops equal separate ones."""
    ref2 = np.array([0.0, 0.188, 1 / 7, -math.pi / 2])
    a, b = NMPC(REF), NMPC(ref2)
    assert a._nlpsol is b._nlpsol and a._cold_nlpsol is b._cold_nlpsol
    assert NMPC(REF, error_signal=False)._nlpsol is not a._nlpsol  # other options, other build
    vq = np.array([0.4, 0.0, 0.1])

    def loop(ctrls):
        s = {id(c): np.array([0.2, -0.1, 0.12, c.reference[3] + 0.3]) for c in ctrls}
        out = {id(c): [] for c in ctrls}
        for _ in range(15):
            for c in ctrls:
                u = c.solve(s[id(c)], vq).u
                out[id(c)].append(u)
                s[id(c)] = s[id(c)] + DT * np.asarray(feature_rates(s[id(c)], u, vq))
        return out

    together = loop([a, b])
    a.reset()
    b.reset()
    alone = {**loop([a]), **loop([b])}
    for key in together:
        np.testing.assert_array_equal(np.array(together[key]), np.array(alone[key]))


REF_A = np.array([0.0, 0.188, 1 / 7, math.pi / 2])  # scenario A's reference for UAV1


def test_lqr_terminal_weight_solves_riccati_of_the_model() -> None:
    """W_s = P with P = Q + A'PA - A'PB (R + B'PB)^-1 B'PA, A and B by finite differences."""
    ctrl = NMPC(REF_A, NMPCConfig(terminal_weight="lqr"))
    P = ctrl.w_terminal
    np.testing.assert_allclose(P, P.T)
    assert np.linalg.eigvalsh(P).min() > 0
    zero_u, still = np.zeros(4), np.zeros(3)
    h = 1e-6
    A = np.column_stack(
        [
            (ctrl.predict_one_step(REF_A + h * e, zero_u, still)
             - ctrl.predict_one_step(REF_A - h * e, zero_u, still)) / (2 * h)
            for e in np.eye(4)
        ]
    )  # fmt: skip
    B = np.column_stack(
        [
            (ctrl.predict_one_step(REF_A, h * e, still)
             - ctrl.predict_one_step(REF_A, -h * e, still)) / (2 * h)
            for e in np.eye(4)
        ]
    )  # fmt: skip
    Q, R = np.diag(NMPCConfig().q_s), np.diag(NMPCConfig().r_u)
    riccati = Q + A.T @ P @ A - A.T @ P @ B @ np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    np.testing.assert_allclose(riccati, P, rtol=1e-5, atol=1e-5 * np.abs(P).max())
    # the default keeps the paper's reading: W_s = diag(w_s)
    np.testing.assert_array_equal(NMPC(REF_A).w_terminal, np.diag(NMPCConfig().w_s))


def test_lqr_terminal_weight_converges_faster() -> None:
    """On its own model, 1 s after an offset the LQR terminal weight leaves < 0.8x the error."""
    errors = {}
    for weight in ("w_s", "lqr"):
        ctrl = NMPC(REF_A, NMPCConfig(terminal_weight=weight))
        s, vq = REF_A + np.array([0.3, 0.1, 0.0, 0.3]), np.zeros(3)
        for _ in range(80):
            res = ctrl.solve(s, vq)
            assert res.success, res.status
            s = _rk4(s, res.u, vq)
        errors[weight] = np.linalg.norm((s - REF_A)[[0, 1, 3]])
    assert errors["lqr"] < 0.8 * errors["w_s"], errors


def test_invalid_terminal_weight_is_rejected() -> None:
    with pytest.raises(ValueError, match="terminal_weight must be 'w_s' or 'lqr'"):
        NMPCConfig(terminal_weight="riccati")
    with pytest.raises(ValueError, match="needs every r_u > 0"):
        NMPCConfig(terminal_weight="lqr", r_u=(0.02, 0.03, 0.0, 0.3))
    with pytest.raises(ValueError, match="ipopt_tol"):
        NMPCConfig(ipopt_tol=0.0)
