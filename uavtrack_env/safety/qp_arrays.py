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
        a0 = s * A[j, 0] - c * A[j, 1]
        a1 = -A[j, 2]
        a2 = c * A[j, 0] + s * A[j, 1]
        norm = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
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
def qp_arrays(v_hat, An, bn, weights, lb3, ub3, slack_reg):  # pragma: no cover (compiled)
    """``min 1/2 ||v - v_hat||^2 + sum w_j s_j`` s.t. ``An v - s <= bn``, box, s >= 0, one slack
    per row with a weight > 0: (H, f, G, h, lb, ub) over x = [v, s]."""
    m = bn.shape[0]
    ns = 0
    for j in range(m):
        ns += weights[j] > 0.0
    nv = 3 + ns
    H = np.zeros((nv, nv))
    f = np.empty(nv)
    G = np.zeros((m, nv))
    lb = np.empty(nv)
    ub = np.empty(nv)
    for i in range(3):
        H[i, i] = 1.0
        f[i] = -v_hat[i]
        lb[i], ub[i] = lb3[i], ub3[i]
    col = 3
    for j in range(m):
        G[j, 0], G[j, 1], G[j, 2] = An[j, 0], An[j, 1], An[j, 2]
        if weights[j] > 0.0:
            H[col, col] = slack_reg
            f[col] = weights[j]
            G[j, col] = -1.0
            lb[col], ub[col] = 0.0, INF
            col += 1
    return H, f, G, bn.copy(), lb, ub


@numba.njit(cache=True)
def daqp_bounds(lb, ub, h):  # pragma: no cover (compiled)
    """daqp's stacked bounds: variables then rows (``bl <= [x; G x] <= bu``), and their sense."""
    nv, m = lb.shape[0], h.shape[0]
    bu = np.empty(nv + m)
    bl = np.empty(nv + m)
    bu[:nv], bl[:nv] = ub, lb
    bu[nv:], bl[nv:] = h, -INF
    return bu, bl, np.zeros(nv + m, np.int32)


@numba.njit(cache=True)
def rows_hold(A, b, v, tol):  # pragma: no cover (compiled)
    """Every row ``A v <= b`` holds within ``tol`` (A (m, 3))."""
    for j in range(b.shape[0]):
        if A[j, 0] * v[0] + A[j, 1] * v[1] + A[j, 2] * v[2] - b[j] > tol:
            return False
    return True


@numba.njit(cache=True)
def meets(x, G, h, lb, ub, tol):  # pragma: no cover (compiled)
    """A solver's answer is finite and meets ``G x <= h`` within ``tol (1 + |h|)`` and the
    bounds within ``tol``."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]) or x[i] < lb[i] - tol or x[i] > ub[i] + tol:
            return False
    for j in range(h.shape[0]):
        if G[j] @ x - h[j] > tol * (1.0 + abs(h[j])):
            return False
    return True


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
