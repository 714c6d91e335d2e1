"""`SafetyFilter`'s QP layers in one compiled call, daqp called from inside (`daqp_native`).

The same layers, in the same order, with the same arrays as `SafetyFilter._solve_layers` on
`daqp.solve` (the module docstring of `uavtrack_env.safety.shield`): the hard QP, the
relaxations, the fallbacks by row priority, then brake; each QP with the speed ball's tangent
cuts. tests/test_qp_layers.py checks the two give the same answers bit for bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from uavtrack_env.safety.cbf import CONNECT, OCCLUSION, TARGET, UAV
from uavtrack_env.safety.daqp_native import quadprog
from uavtrack_env.safety.qp_arrays import (
    meets,
    nominal_holds,
    outcome,
    qp_problem,
    triage,
    with_cut,
)

LAYER_STATUS = ("optimal", "relaxed", "fallback", "brake")
"""`solve_layers`'s status codes."""


@numba.njit(cache=True)
def occlusion_factors(kind, h, A, theta_star, most, length):  # pragma: no cover (compiled)
    """`SafetyFilter.slack_factors`: each row's factor on its slack weight, 1 but for the occlusion
    rows: their urgency (1 at h = 0 to ``most`` at h = -theta*) times their leverage
    ``length |A_j|`` clipped to [1e-3, 1] (``length`` <= 0: none)."""
    out = np.ones(kind.shape[0])
    for j in range(kind.shape[0]):
        if kind[j] != OCCLUSION:
            continue
        depth = min(max(-h[j] / theta_star, 0.0), 1.0)
        out[j] = 1.0 + (most - 1.0) * depth
        if length > 0.0:
            a0, a1, a2 = abs(A[j, 0]), abs(A[j, 1]), abs(A[j, 2])
            # one component reaching 1 / length caps the factor: no square to overflow
            if length * max(a0, a1, a2) < 1.0:
                grad = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
                out[j] *= min(max(length * grad, 1e-3), 1.0)  # > 0: the row stays soft
    return out


@numba.njit(cache=True)
def occlusion_weight_cap(v_hat, An, bn, scale):  # pragma: no cover (compiled)
    """The cap on an occlusion row's slack weight in the relaxed QPs:
    ``scale max(D, 0.1)``, D the nominal ``v_hat``'s largest violation of the unit rows
    ``An v <= bn`` (m/s); ``scale`` <= 0: no cap (`ShieldOptions.occlusion_price`)."""
    if scale <= 0.0:
        return np.inf
    most = 0.1
    for j in range(bn.shape[0]):
        e = An[j, 0] * v_hat[0] + An[j, 1] * v_hat[1] + An[j, 2] * v_hat[2] - bn[j]
        most = max(most, e)
    return scale * most


@numba.njit(cache=True)
def _solve(v_hat, An, bn, weights, lb3, ub3, params, settings):  # pragma: no cover (compiled)
    """`SafetyFilter._solve`: (found, v, QP calls)."""
    alpha_v, slack_reg, verify_tol, norm_cuts = params[2], params[3], params[4], int(params[5])
    H, f, G, bounds, sense = qp_problem(v_hat, An, bn, weights, lb3, ub3, slack_reg)
    bu, bl = bounds[0], bounds[1]
    calls = 0
    v = np.zeros(3)
    speed = 0.0
    have = False
    for it in range(norm_cuts + 1):
        x, flag = quadprog(H, f, G, bu, bl, sense, settings)
        calls += 1
        if flag < 1 or not meets(x, G, bu, bl, verify_tol):
            if not have:
                return False, v, calls
            return True, v * (alpha_v / speed), calls
        v = x[:3]
        have = True
        speed = math.sqrt(np.dot(v, v))  # BLAS, as numpy's v @ v
        if speed <= alpha_v * (1.0 + 1e-9):
            return True, v, calls
        if it == norm_cuts:
            return True, v * (alpha_v / speed), calls
        G, cut_bounds, sense = with_cut(G, bu, bl, sense, v, speed, alpha_v)
        bu, bl = cut_bounds[0], cut_bounds[1]
    return False, v, calls


@numba.njit(cache=True)
def solve_layers(
    v_hat, An, bn, kinds, slack_factors, lb3, ub3, params, settings
):  # pragma: no cover
    """The layers of `SafetyFilter._layers` until one gives an answer: (v0, v1, v2, status
    (index into `LAYER_STATUS`), QP calls). ``slack_factors``: each row's factor on its occlusion
    slack weight (`SafetyFilter.slack_factors`); ``params``: soft_penalty, hard_penalty, alpha_v,
    slack_regularization, verify_tol, norm_cuts, and at `P_OCCLUSION_PRICE` the scale of the
    cap on the occlusion rows' weights (`occlusion_weight_cap`); ``settings``:
    `daqp_native.settings`."""
    soft, hard = params[0], params[1]
    cap = occlusion_weight_cap(v_hat, An, bn, params[P_OCCLUSION_PRICE])
    m = kinds.shape[0]
    occlusion = np.zeros(m, np.bool_)
    connect = np.zeros(m, np.bool_)
    target = np.zeros(m, np.bool_)
    uav = np.zeros(m, np.bool_)
    for j in range(m):
        k = kinds[j]
        occlusion[j], connect[j], target[j], uav[j] = (
            k == OCCLUSION, k == CONNECT, k == TARGET, k == UAV
        )  # fmt: skip
    calls = 0
    found, v, n = _solve(v_hat, An, bn, np.zeros(m), lb3, ub3, params, settings)
    calls += n
    if found:
        return v[0], v[1], v[2], 0, calls
    if occlusion.any():
        weights = np.where(occlusion, np.minimum(soft * slack_factors, cap), 0.0)
        found, v, n = _solve(v_hat, An, bn, weights, lb3, ub3, params, settings)
        calls += n
        if found:
            return v[0], v[1], v[2], 1, calls
    base = np.where(
        connect, soft, np.where(occlusion, np.minimum(1e-2 * soft * slack_factors, cap), 0.0)
    )
    if connect.any():
        found, v, n = _solve(v_hat, An, bn, base, lb3, ub3, params, settings)
        calls += n
        if found:
            return v[0], v[1], v[2], 1, calls
    if target.any():
        base = np.where(target, hard * 1e-2, base)
        found, v, n = _solve(v_hat, An, bn, base, lb3, ub3, params, settings)
        calls += n
        if found:
            return v[0], v[1], v[2], 2, calls
    if uav.any():
        base = np.where(uav, hard, base)
        found, v, n = _solve(v_hat, An, bn, base, lb3, ub3, params, settings)
        calls += n
        if found:
            return v[0], v[1], v[2], 2, calls
    found, v, n = _solve(
        v_hat, An, bn, np.where(base > 0.0, base, hard * 1e2), lb3, ub3, params, settings
    )
    calls += n
    if found:
        return v[0], v[1], v[2], 2, calls
    return 0.0, 0.0, 0.0, 3, calls


P_ALPHA_V = 2
"""`solve_layers`' params[2]: the speed ball's radius alpha_v."""
P_V_MAX, P_W_MAX, P_TOL, P_ACCEL_STEP, P_ACTIVE_TOL, P_PRUNE, P_BOUNDS = range(6, 13)
"""`certify_changed`'s params after `solve_layers`' six: Table II's v_max and the yaw-rate
bound, the fast path's tolerance, the lag plant's step box, the active-row tolerance, prune,
`qp_arrays.triage`'s bounds code."""
P_OCCLUSION_PRICE = 13
"""`solve_layers`' scale of the cap on the occlusion rows' weights (`occlusion_weight_cap`)."""
OUT_HEAD = 15
"""`certify_changed`'s output: u_safe (4), status code (`LAYER_STATUS`; closed-form answers are
'optimal'), solver code (0 closed-form, 1 the QP, 2 brake), QP calls, soft slack, hard
violation, speed ball active, box active, correction norm, then the counts of the active, the
violated soft and the violated hard rows; after these ``OUT_HEAD`` values, the active rows'
indices, the violated soft rows' indices and their violations, the violated hard rows' indices
(indices into the `CBFRows`)."""


@numba.njit(cache=True)
def certify_changed(
    u, yaw, velocity, has_velocity, A, b, kind, slack_factors, lb3, ub3, params, settings
):  # pragma: no cover (compiled)
    """`SafetyFilter.certify` of a nominal ``u`` that `qp_arrays.nominal_holds` rejected, up to
    its report's names: `qp_arrays.triage`, `solve_layers`, `qp_arrays.outcome` in one call,
    packed in one array (`OUT_HEAD`)."""
    stage, v, w, An, bn, ints, bounds = triage(
        u, yaw, velocity, has_velocity, A, b, kind, params[P_ALPHA_V], params[P_V_MAX],
        params[P_W_MAX], params[P_TOL], params[P_ACCEL_STEP], lb3, ub3, params[P_PRUNE] > 0.0,
        int(params[P_BOUNDS]),
    )  # fmt: skip
    kinds, kept = ints[0], ints[1]
    status, solver, calls = 0, 0, 0
    u_safe = np.empty(4)
    u_safe[0], u_safe[1], u_safe[2], u_safe[3] = v[0], v[1], v[2], w
    if stage == 2:
        v0, v1, v2, status, calls = solve_layers(
            v, An, bn, kinds, slack_factors[kept], bounds[0], bounds[1], params, settings
        )
        solver = 1
        if status == 3:
            status, solver = 2, 2
        u_safe[0], u_safe[1], u_safe[2] = v0, v1, v2
    if not math.isfinite(u_safe[0] + u_safe[1] + u_safe[2] + w):  # defensive: never NaN
        u_safe[0], u_safe[1], u_safe[2] = 0.0, 0.0, 0.0
        status, solver = 2, 2
    active, over_soft, over_hard, viol, slack, hard, speed, box, norm = outcome(
        An, bn, kinds, CONNECT, params[P_ACTIVE_TOL], u, u_safe, params[P_ALPHA_V],
        params[P_V_MAX],
    )  # fmt: skip
    na, ns, nh = active.shape[0], over_soft.shape[0], over_hard.shape[0]
    out = np.empty(OUT_HEAD + na + 2 * ns + nh)
    out[0], out[1], out[2], out[3] = u_safe[0], u_safe[1], u_safe[2], u_safe[3]
    out[4], out[5], out[6], out[7], out[8] = status, solver, calls, slack, hard
    out[9], out[10], out[11] = speed, box, norm
    out[12], out[13], out[14] = na, ns, nh
    j = OUT_HEAD
    for i in range(na):
        out[j] = kept[active[i]]
        j += 1
    for i in range(ns):
        out[j] = kept[over_soft[i]]
        out[j + ns] = viol[over_soft[i]]
        j += 1
    j += ns
    for i in range(nh):
        out[j] = kept[over_hard[i]]
        j += 1
    return out


@numba.njit(cache=True)
def certify_many(
    u, yaw, velocity, A, b, kind, slack_factors, begin, end, lb3, ub3, params, settings
):  # pragma: no cover (compiled)
    """`qp_arrays.nominal_holds`, then `certify_changed` where it fails, for m UAVs at once:
    UAV j's command ``u[j]``, yaw, actual velocity and rows
    ``A/b/kind/slack_factors[begin[j]:end[j]]``.
    Returns (changed (m,), outputs (m, width)): row j is `certify_changed`'s packed output, or
    ``u[j]`` alone where the nominal holds."""
    m = u.shape[0]
    width = OUT_HEAD
    for j in range(m):
        width = max(width, OUT_HEAD + 4 * (end[j] - begin[j]))
    changed = np.zeros(m, np.bool_)
    outs = np.zeros((m, width))
    alpha_v, v_max, w_max = params[P_ALPHA_V], params[P_V_MAX], params[P_W_MAX]
    tol, accel_step = params[P_TOL], params[P_ACCEL_STEP]
    for j in range(m):
        a, e = begin[j], end[j]
        if nominal_holds(
            u[j], yaw[j], velocity[j], True, A[a:e], b[a:e], alpha_v, v_max, w_max, tol,
            accel_step, lb3, ub3,
        ):  # fmt: skip
            outs[j, :4] = u[j]
            continue
        out = certify_changed(
            u[j], yaw[j], velocity[j], True, A[a:e], b[a:e], kind[a:e], slack_factors[a:e],
            lb3, ub3, params, settings,
        )  # fmt: skip
        outs[j, : out.shape[0]] = out
        changed[j] = True
    return changed, outs
