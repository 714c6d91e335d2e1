"""The arrays of the CBF-QP (47) in camera coordinates, compiled with numba.

`SafetyFilter` solves a QP of 3 velocity variables and a few rows per UAV at 80 Hz; building its
arrays, checking a solver's answer and measuring the rows at the answer are a handful of tiny
array operations each, so they run as compiled loops (`cache=True`: compiled once per machine).
The QP itself is solved by daqp or ProxSuite (`SafetyFilter.solver`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

INF = 1e30
"""Stands for an infinite bound in the solvers' arrays."""


@numba.njit(cache=True, inline="always")
def _camera_row(A, j, c, s):  # pragma: no cover (compiled)
    """Row j of A R (R = `cam_to_world(yaw)`, c = cos yaw, s = sin yaw) and its norm."""
    a0 = s * A[j, 0] - c * A[j, 1]
    a1 = -A[j, 2]
    a2 = c * A[j, 0] + s * A[j, 1]
    return a0, a1, a2, math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)


@numba.njit(cache=True)
def camera_rows(A, b, kind, yaw, alpha_v, prune):  # pragma: no cover (compiled)
    """Rows ``A V^g <= b`` as unit rows on the camera-frame velocity (A R v_c, R =
    `cam_to_world(yaw)`): (An, bn, kinds, kept indices). Zero rows that hold are dropped, and with
    ``prune`` those the speed ball ``||v|| <= alpha_v`` implies (``bn >= alpha_v``)."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = A.shape[0]
    An = np.empty((m, 3))
    bn = np.empty(m)
    kept = np.empty(m, np.int64)
    k = 0
    for j in range(m):
        a0, a1, a2, norm = _camera_row(A, j, c, s)
        zero = norm < 1e-12
        scale = 1.0 if zero else norm
        bj = b[j] / scale
        if zero and bj >= 0.0:
            continue
        if prune and bj >= alpha_v * (1.0 + 1e-9):
            continue
        An[k, 0], An[k, 1], An[k, 2] = a0 / scale, a1 / scale, a2 / scale
        bn[k] = bj
        kept[k] = j
        k += 1
    return An[:k], bn[:k], kind[kept[:k]], kept[:k]


@numba.njit(cache=True)
def nearest_camera_rows(A, b, yaw, alpha_v, k):  # pragma: no cover (compiled)
    """Up to ``k`` rows ``A V^g <= b`` as unit rows on the camera-frame velocity (as in
    `camera_rows`), those closest to active first (smallest bn, ties in row order); zero rows
    and the rows the speed ball implies (``bn >= alpha_v``) are dropped: (An, bn)."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = A.shape[0]
    An = np.empty((m, 3))
    bn = np.empty(m)
    n = 0
    for j in range(m):
        a0, a1, a2, norm = _camera_row(A, j, c, s)
        if norm < 1e-12:
            continue
        An[n, 0], An[n, 1], An[n, 2] = a0 / norm, a1 / norm, a2 / norm
        bn[n] = b[j] / norm
        n += 1
    order = np.argsort(bn[:n], kind="mergesort")[:k]  # stable
    kept = 0
    for i in range(order.shape[0]):
        if bn[order[i]] < alpha_v:
            order[kept] = order[i]
            kept += 1
    order = order[:kept]
    return An[order], bn[order]


@numba.njit(cache=True)
def qp_problem(v_hat, An, bn, weights, lb3, ub3, slack_reg):  # pragma: no cover (compiled)
    """``min 1/2 ||v - v_hat||^2 + sum w_j s_j`` s.t. ``An v - s <= bn``, box, s >= 0, one slack
    per row with a weight > 0, over x = [v, s], in daqp's form: (H, f, G, [bu, bl], sense) with
    the bounds stacked, variables then rows (``bl <= [x; G x] <= bu``, rows unbounded below)."""
    m = bn.shape[0]
    ns = 0
    for j in range(m):
        ns += weights[j] > 0.0
    nv = 3 + ns
    H = np.zeros((nv, nv))
    f = np.empty(nv)
    G = np.zeros((m, nv))
    bounds = np.empty((2, nv + m))
    bu, bl = bounds[0], bounds[1]
    for i in range(3):
        H[i, i] = 1.0
        f[i] = -v_hat[i]
        bl[i], bu[i] = lb3[i], ub3[i]
    col = 3
    for j in range(m):
        G[j, 0], G[j, 1], G[j, 2] = An[j, 0], An[j, 1], An[j, 2]
        if weights[j] > 0.0:
            H[col, col] = slack_reg
            f[col] = weights[j]
            G[j, col] = -1.0
            bl[col], bu[col] = 0.0, INF
            col += 1
        bu[nv + j], bl[nv + j] = bn[j], -INF
    return H, f, G, bounds, np.zeros(nv + m, np.int32)


@numba.njit(cache=True)
def with_cut(G, bu, bl, sense, v, speed, alpha_v):  # pragma: no cover (compiled)
    """The problem of `qp_problem` plus the speed ball's tangent cut ``(v / speed)^T x <= alpha_v``
    (a row on the velocity part of x): (G, [bu, bl], sense)."""
    m, nv = G.shape
    G2 = np.zeros((m + 1, nv))
    G2[:m] = G
    G2[m, :3] = v / speed
    k = bu.shape[0]
    bounds = np.empty((2, k + 1))
    bounds[0, :k], bounds[1, :k] = bu, bl
    bounds[0, k], bounds[1, k] = alpha_v, -INF
    return G2, bounds, np.zeros(sense.shape[0] + 1, np.int32)


@numba.njit(cache=True)
def rows_hold(A, b, v, tol):  # pragma: no cover (compiled)
    """Every row ``A v <= b`` holds within ``tol`` (A (m, 3))."""
    for j in range(b.shape[0]):
        if A[j, 0] * v[0] + A[j, 1] * v[1] + A[j, 2] * v[2] - b[j] > tol:
            return False
    return True


@numba.njit(cache=True)
def meets(x, G, bu, bl, tol):  # pragma: no cover (compiled)
    """A solver's answer to a `qp_problem` is finite and meets ``G x <= h`` (h the rows' upper
    bounds) within ``tol (1 + |h|)`` and the variable bounds within ``tol``."""
    nv = x.shape[0]
    for i in range(nv):
        if not math.isfinite(x[i]) or x[i] < bl[i] - tol or x[i] > bu[i] + tol:
            return False
    for j in range(G.shape[0]):
        h = bu[nv + j]
        if G[j] @ x - h > tol * (1.0 + abs(h)):
            return False
    return True


@numba.njit(cache=True)
def family_lows(kind, h, n_kinds, hard_below):  # pragma: no cover (compiled)
    """The least h of each row family (``kind`` in [0, n_kinds); NaN: no such row), then the
    least h of the families below ``hard_below`` (inf without such rows), in one array."""
    out = np.full(n_kinds + 1, np.nan)
    out[n_kinds] = np.inf
    for j in range(h.shape[0]):
        k = kind[j]
        if not h[j] >= out[k]:  # NaN (absent) or a new least value
            out[k] = h[j]
        if k < hard_below and h[j] < out[n_kinds]:
            out[n_kinds] = h[j]
    return out


@numba.njit(cache=True)
def row_violations(An, bn, v, soft, active_tol):  # pragma: no cover (compiled)
    """The rows at the velocity v: (active rows, violated soft rows, violated hard rows, their
    violations (m/s, per row), total soft violation, total hard violation)."""
    viol = An @ v - bn
    active = np.flatnonzero(np.abs(viol) <= active_tol)
    over = viol > active_tol
    over_soft = np.flatnonzero(over & soft)
    over_hard = np.flatnonzero(over & ~soft)
    return active, over_soft, over_hard, viol, viol[over_soft].sum(), viol[over_hard].sum()


@numba.njit(cache=True)
def outcome(An, bn, kinds, soft_from, active_tol, u, u_safe, alpha_v, v_max):  # pragma: no cover
    """What a changed action does (`SafetyFilter`'s report): `row_violations` at its velocity
    with the rows of kind >= ``soft_from`` soft, whether the speed ball and the box are active,
    and ``||u_safe - u||``."""
    v = u_safe[:3]
    soft = kinds >= soft_from
    active, over_soft, over_hard, viol, slack, hard = row_violations(An, bn, v, soft, active_tol)
    speed = np.dot(v, v) >= alpha_v**2 * (1.0 - 1e-9)  # BLAS, as numpy's v @ v
    box = max(abs(v[0]), abs(v[1]), abs(v[2])) >= v_max * (1.0 - 1e-9)
    d = u_safe - u
    return active, over_soft, over_hard, viol, slack, hard, speed, box, math.sqrt(np.dot(d, d))


@numba.njit(cache=True)
def _bounds(
    u, yaw, velocity, has_velocity, A, b, v_max, w_max, tol, accel_step, lb3, ub3, alpha_v
):  # pragma: no cover (compiled)
    """`triage`'s bounds and its nominal check: (w, lb, ub, has_box, in_bounds, V), V the
    nominal velocity in the global frame."""
    vx, vy, vz, wn = u[0], u[1], u[2], u[3]
    w = min(max(wn, -w_max), w_max)
    c, s = math.cos(yaw), math.sin(yaw)
    lb, ub = lb3.copy(), ub3.copy()
    has_box = False
    if accel_step > 0.0 and has_velocity and b.shape[0] > 0 and not rows_hold(A, b, velocity, tol):
        x, y, z = velocity[0], velocity[1], velocity[2]
        vc = (s * x - c * y, -z, c * x + s * y)  # world_to_cam_vec
        for i in range(3):
            lb[i] = max(vc[i] - accel_step, lb3[i])
            ub[i] = min(vc[i] + accel_step, ub3[i])
        has_box = True
    in_bounds = vx * vx + vy * vy + vz * vz <= alpha_v**2
    for i in range(3):
        if has_box:
            in_bounds &= lb[i] <= u[i] <= ub[i]
        else:
            in_bounds &= abs(u[i]) <= v_max
    V = np.array((s * vx + c * vz, -c * vx + s * vz, -vy))  # cam_to_world_vec
    return w, lb, ub, has_box, in_bounds, V


@numba.njit(cache=True)
def nominal_holds(
    u, yaw, velocity, has_velocity, A, b, alpha_v, v_max, w_max, tol, accel_step, lb3, ub3
):  # pragma: no cover (compiled)
    """`triage`'s stage 0 alone: the nominal ``u`` meets every bound and row (a bool, which
    returns to Python far cheaper than `triage`'s arrays)."""
    w, _lb, _ub, _box, in_bounds, V = _bounds(
        u, yaw, velocity, has_velocity, A, b, v_max, w_max, tol, accel_step, lb3, ub3, alpha_v
    )
    return in_bounds and w == u[3] and rows_hold(A, b, V, tol)


@numba.njit(cache=True)
def triage(
    u,
    yaw,
    velocity,
    has_velocity,
    A,
    b,
    kind,
    alpha_v,
    v_max,
    w_max,
    tol,
    accel_step,
    lb3,
    ub3,
    prune,
    bounds_kind,
):  # pragma: no cover (compiled)
    """The CBF-QP (47) up to its QP for a nominal ``u`` that `nominal_holds` rejected
    (`SafetyFilter.certify`): (stage, v, w, An, bn, [kinds, kept] (2, m), [lb, ub] (2, 3)).

    The bounds on the camera-frame velocity are Table II's box ``lb3``, ``ub3`` and the speed ball
    ``alpha_v``, intersected, while a row asks for braking (``A V > b`` at the actual global
    velocity), with the box ``accel_step`` around that velocity. Stage 1: ``v``, ``u``'s velocity
    or its closed-form projection onto the bounds (``bounds_kind`` 0: the ball lies inside the
    box, 1: the box inside the ball, 2: neither), meets every row; 2: a QP is needed, with the
    camera-frame rows (`camera_rows`) and the bounds lb, ub. ``w``: the yaw rate clipped to
    ``w_max``.
    """
    w, lb, ub, has_box, in_bounds, _V = _bounds(
        u, yaw, velocity, has_velocity, A, b, v_max, w_max, tol, accel_step, lb3, ub3, alpha_v
    )
    vx, vy, vz = u[0], u[1], u[2]
    v = np.array((vx, vy, vz))
    bounds = np.empty((2, 3))
    bounds[0], bounds[1] = lb, ub
    An, bn, kinds, kept = camera_rows(A, b, kind, yaw, alpha_v, prune)
    ints = _stacked(kinds, kept)
    closed = in_bounds
    if not in_bounds:  # the closed-form projection onto the bounds, where there is one
        if has_box:  # exact when the box's projection lies inside the ball
            for i in range(3):
                v[i] = min(max(v[i], lb[i]), ub[i])
            closed = np.dot(v, v) <= alpha_v**2  # BLAS, as numpy's v @ v
        elif bounds_kind == 0:
            norm = math.sqrt(np.dot(v, v))
            if norm > alpha_v:
                v = v * (alpha_v / norm)
            closed = True
        elif bounds_kind == 1:
            for i in range(3):
                v[i] = min(max(v[i], -v_max), v_max)
            closed = True
    if closed and rows_hold(An, bn, v, tol):
        return 1, v, w, An, bn, ints, bounds
    return 2, np.array((vx, vy, vz)), w, An, bn, ints, bounds


@numba.njit(cache=True)
def _stacked(a, b):  # pragma: no cover (compiled)
    """Two int arrays of one length as rows of one (2, m) array (one array to return, not two)."""
    out = np.empty((2, a.shape[0]), np.int64)
    out[0], out[1] = a, b
    return out
