"""Second-order CBF right-hand sides for a velocity lag (not in the paper), compiled with numba.

`cbf.RowBuilder` calls `second_order_b` for every row stack when the plant's velocity lags its
command (``lag_tau > 0``); the derivation is in `cbf.RowBuilder._second_order`'s docstring.
Row-wise dot products are summed in ``einsum``'s order and the matrix-vector products numpy
does through BLAS come from the caller, so the rows equal a numpy formulation to the bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np

OCCLUSION = 5
"""`cbf.OCCLUSION`: occlusion rows stay first order."""


@numba.njit(cache=True)
def _dot3(a0, a1, a2, b0, b1, b2):  # pragma: no cover (compiled)
    """a . b of 3-vectors summed as numpy's ``einsum`` sums them: (x0 + x2) + x1."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@numba.njit(cache=True)
def _rowdot(a, b):  # pragma: no cover (compiled)
    """Row-wise dot products of two (m, 3) arrays (``einsum("ij,ij->i")``)."""
    out = np.empty(a.shape[0])
    for r in range(a.shape[0]):
        out[r] = _dot3(a[r, 0], a[r, 1], a[r, 2], b[r, 0], b[r, 1], b[r, 2])
    return out


@numba.njit(cache=True)
def second_order_b(
    A,
    h,
    b,
    margin,
    kind,
    index,
    sizes,
    v,
    nb_v,
    grad_v,
    target_dv,
    target_curvature,
    target_frustum,
    has_rho,
    rho,
    has_sigma,
    sigma,
    tau,
    gamma_s,
    gamma_c,
    gamma_obstacle,
    gamma_z,
    clearance,
    clearance2,
    standoff,
    standoff2,
    box_model,
    r_s,
    r_c,
    alpha_v,
    brake_decel,
):  # pragma: no cover (compiled)
    """Right-hand sides b of the rows ``A V <= b`` as second-order CBFs for ``v-dot = (u - v) /
    tau`` (`cbf.RowBuilder._second_order`), with braking-distance rows where
    ``brake_decel`` > 0. The caller passes what numpy computes through BLAS: ``grad_v`` =
    (-A) @ v, and the car row's relative velocity (`cbf.car_relative_velocity`) and curvature
    (``target_frustum``: the row is the frustum of `barrier_rows.target_row`); ``clearance2``,
    ``standoff2``: the squares as Python computes them."""
    n = h.shape[0]
    ends = np.cumsum(sizes)
    starts = ends - sizes
    dv = np.empty((n, 3))
    for r in range(n):
        dv[r] = v
    curv = np.zeros(n)
    gamma1 = np.zeros(n)
    share = np.ones(n)
    for f, g1, sign in ((0, gamma_s, 2.0), (4, gamma_c, -2.0)):  # uav: H = 2I, connect: -2I
        for r in range(starts[f], ends[f]):
            dv[r] = v - nb_v[index[r]]
            curv[r] = sign * _dot3(dv[r, 0], dv[r, 1], dv[r, 2], dv[r, 0], dv[r, 1], dv[r, 2])
            gamma1[r] = g1
    grad = -A
    o0, o1 = starts[1], ends[1]
    if o1 > o0:
        if box_model:  # H = 2 diag(axes outside the slab) outside, -2 n n' inside the box
            mask = (grad[o0:o1] != 0.0).astype(np.float64)
            outer = np.dot(mask, v * v)
            for r in range(o0, o1):
                curv[r] = (2.0 if h[r] + clearance2 >= 0.0 else -2.0) * outer[r - o0]
        else:
            vv = np.dot(v, v)
            for r in range(o0, o1):
                curv[r] = 2.0 * vv
        for r in range(o0, o1):
            gamma1[r] = gamma_obstacle
    if sizes[2]:
        r = starts[2]
        dv[r] = target_dv
        curv[r] = target_curvature
        gamma1[r] = gamma_obstacle
    for r in range(starts[3], ends[3]):
        gamma1[r] = gamma_z  # H = 0
    hdot = _rowdot(grad, dv)
    need = tau * curv + (tau * gamma1 + 1.0) * hdot + gamma1 * h
    second = -grad_v
    speed = math.sqrt(np.dot(v, v))
    for f, g1, collision in ((0, gamma_s, True), (4, gamma_c, False)):
        lo, hi = starts[f], ends[f]
        if has_rho and hi > lo:
            # Neighbours known within a ball, d = d_hat + e, ||e|| <= rho, v_j = v_hat + f,
            # ||f|| <= sigma (their h is already the ball's worst case): each term is bounded
            # over the balls, -grad h . v by 2 rho ||v||, the curvature +-2 ||dv||^2 by its
            # value at ||dv|| -+ sigma, grad h . dv by 2 (rho ||dv|| + ||d|| sigma + rho sigma)
            # and A u (||u|| <= alpha_v) by 2 rho alpha_v; the UAV takes its share.
            rh = rho[index[lo:hi]]
            sg = sigma[index[lo:hi]] if has_sigma else np.zeros(hi - lo)
            dvn = np.sqrt(_rowdot(dv[lo:hi], dv[lo:hi]))
            if collision:  # H = 2I: the curvature is at least 2 (||dv|| - sigma)_+^2
                low = np.maximum(dvn - sg, 0.0)
                curv_drop = 2.0 * (dvn * dvn - low * low)
            else:  # H = -2I: at least -2 (||dv|| + sigma)^2
                high = dvn + sg
                curv_drop = 2.0 * (high * high - dvn * dvn)
            dn = 0.5 * np.sqrt(_rowdot(A[lo:hi], A[lo:hi]))
            hdot_drop = 2.0 * (rh * dvn + dn * sg + rh * sg)
            own = 2.0 * rh * (speed + alpha_v)
            second[lo:hi] -= own
            need[lo:hi] -= tau * curv_drop + (tau * g1 + 1.0) * hdot_drop
        for r in range(lo, hi):  # a pair that must brake: each UAV brakes for it on its own
            share[r] = 1.0 if need[r] < 0.0 else 0.5
    second += share * need
    if brake_decel > 0.0:
        second = np.minimum(
            second,
            _braking(
                A,
                h,
                dv,
                gamma1,
                index,
                starts,
                ends,
                v,
                target_frustum,
                has_rho,
                rho,
                has_sigma,
                sigma,
                tau,
                brake_decel,
                clearance,
                clearance2,
                standoff,
                standoff2,
                r_s,
                r_c,
            ),
        )
    out = b.copy()
    for r in range(n):
        if kind[r] < OCCLUSION:
            out[r] = second[r] - margin[r]
    return out


@numba.njit(cache=True)
def _braking(
    A,
    h,
    dv,
    gamma1,
    index,
    starts,
    ends,
    v,
    target_frustum,
    has_rho,
    rho,
    has_sigma,
    sigma,
    tau,
    a,
    clearance,
    clearance2,
    standoff,
    standoff2,
    r_s,
    r_c,
):  # pragma: no cover (compiled)
    """Right-hand sides of braking-distance rows on the same A as the collision, car, floor and
    connectivity rows (not in the paper): each keeps ``s - w^2 / (2 a) >= 0``.

    s is the distance left before the row's limit (to the clearance of an obstacle or of the
    car's box, h / ||grad h|| for its frustum, the floor, R_s from a team-mate, or R_c), w > 0
    the speed closing it along m = A / ||A|| (relative to the car's faces for the car), a the
    deceleration one UAV guarantees (``brake_decel``; pair and link rows count on it alone: a
    team-mate whose fallback gave its pair row up, or whose link row took slack, connectivity
    being soft, does not brake for it). With v-dot = (u - v) / tau (exact under
    `ShieldOptions.accel_bound`) and the distance convex along the motion, ``m . u <= m . v +
    tau a (gamma s_b / w - 1)`` keeps ``s_b = s - w^2 / (2 a)`` from decreasing faster than
    ``-gamma s_b``: at s_b = 0 it asks for a deceleration of exactly a. Rows not closing (w <=
    0) get +inf.
    """
    n = h.shape[0]
    out = np.full(n, np.inf)
    norm = np.sqrt(_rowdot(A, A))
    gap = np.zeros(n)
    for r in range(starts[1], ends[1]):
        gap[r] = math.sqrt(max(h[r] + standoff2, 0.0)) - standoff
    for r in range(starts[2], ends[2]):
        if target_frustum:  # a plane (convex at a corner): its distance along A
            gap[r] = h[r] / max(norm[r], 1e-12)
        else:
            gap[r] = math.sqrt(max(h[r] + clearance2, 0.0)) - clearance
    for r in range(starts[3], ends[3]):
        gap[r] = h[r]
    for r in range(starts[0], ends[0]):
        gap[r] = 0.5 * norm[r] - r_s
    for r in range(starts[4], ends[4]):
        gap[r] = r_c - 0.5 * norm[r]
    closing = _rowdot(A, dv) / np.maximum(norm, 1e-12)
    for f in (0, 4):
        if has_rho:
            for r in range(starts[f], ends[f]):
                gap[r] -= rho[index[r]]
                if has_sigma:
                    closing[r] += sigma[index[r]]
    last = starts[5]  # occlusion rows stay as they are
    ta = tau * a
    for r in range(n):
        w = closing[r]
        if r < last and w > 1e-9 and norm[r] > 1e-12:
            s_b = gap[r] - w * w / (2.0 * a)
            m_v = _dot3(A[r, 0], A[r, 1], A[r, 2], v[0], v[1], v[2]) / norm[r]
            out[r] = norm[r] * (m_v + ta * (gamma1[r] * s_b / w - 1.0))
    return out


@numba.njit(cache=True)
def _sign(x):  # pragma: no cover (compiled)
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@numba.njit(cache=True)
def car_relative_velocity(v, vq, grad, heading, growth):  # pragma: no cover (compiled)
    """The UAV's velocity relative to the car box's nearest face(s) (``grad``: grad h of its
    row): v - V_q, less each face's outward speed ``growth`` (box frame) along the gradient's
    signs, so that ``h-dot = grad h . dv`` and ``h-ddot = dv' H dv`` for a growing box."""
    dv = v - vq
    if growth[0] == 0.0 and growth[1] == 0.0 and growth[2] == 0.0:
        return dv
    c, s = math.cos(heading), math.sin(heading)
    wx = _sign(c * grad[0] + s * grad[1]) * growth[0]
    wy = _sign(-s * grad[0] + c * grad[1]) * growth[1]
    wz = _sign(grad[2]) * growth[2]
    dv[0] -= c * wx - s * wy
    dv[1] -= s * wx + c * wy
    dv[2] -= wz
    return dv


@numba.njit(cache=True)
def target_curvature(heading, grad, dv, h, clearance2, frustum):  # pragma: no cover (compiled)
    """dv' H dv of the car's row (`barrier_rows.target_row`), in the car's frame (its box is
    axis-aligned there); dv the velocity relative to the car's faces.

    Outside the box: the box row's 2 sum of dv_a^2 over the axes of its gradient, the frustum's
    0 (convex: a safe bound). Inside, both hold `barrier_rows.box_sdist`'s ``-e_xy (t +
    reach)`` (per clearance in the frustum), whose Hessian gives ``-2 dv_z (n . dv)``, n the
    nearest side's outward normal (its least value ``-2 |dv_z| ||dv_xy||`` where the gradient
    does not show n)."""
    c, s = math.cos(heading), math.sin(heading)
    g = (c * grad[0] + s * grad[1], -s * grad[0] + c * grad[1], grad[2])
    d = (c * dv[0] + s * dv[1], -s * dv[0] + c * dv[1], dv[2])
    inside = g[2] > 1.0 if frustum else h + clearance2 < 0.0
    if inside:
        scale = 2.0 / math.sqrt(clearance2) if frustum else 2.0
        if g[0] != 0.0 or g[1] != 0.0:
            return -scale * d[2] * (_sign(g[0]) * d[0] + _sign(g[1]) * d[1])
        return -scale * abs(d[2]) * math.sqrt(d[0] * d[0] + d[1] * d[1])
    if frustum:
        return 0.0
    big = max(abs(g[0]), abs(g[1]), abs(g[2]), 1e-300)
    out = 0.0
    for a in range(3):
        if abs(g[a]) > 1e-12 * big:
            out += d[a] * d[a]
    return 2.0 * out


@numba.njit(cache=True)
def second_order_rows(
    A, h, b, margin, kind, index, sizes, v, nb_v, vq, heading, growth, frustum, has_rho, rho,
    has_sigma, sigma, params,
):  # fmt: skip  # pragma: no cover (compiled)
    """`second_order_b` from the context's values: the rows' gradients times ``v``, the car
    row's relative velocity (`car_relative_velocity`) and curvature (`target_curvature`), for
    a car box moving at ``vq`` with yaw ``heading`` and faces growing at ``growth``;
    ``params`` = [lag_tau, gamma_s, gamma_c, gamma_obstacle, gamma_z,
    clearance, clearance^2, standoff, standoff^2, box obstacles, R_s, R_c, alpha_v,
    brake_decel] (`cbf.RowBuilder.second_order_params`)."""
    n = h.shape[0]
    grad_v = np.empty(n)
    for r in range(n):
        grad_v[r] = -(A[r, 0] * v[0] + A[r, 1] * v[1] + A[r, 2] * v[2])
    dv_t = np.zeros(3)
    curv_t = 0.0
    frustum = sizes[2] > 0 and frustum
    if sizes[2]:
        t = sizes[0] + sizes[1]
        grad_t = -A[t]
        dv_t = car_relative_velocity(v, vq, grad_t, heading, growth)
        curv_t = target_curvature(heading, grad_t, dv_t, h[t], params[6], frustum)
    return second_order_b(
        A, h, b, margin, kind, index, sizes, v, nb_v, grad_v, dv_t, curv_t, frustum, has_rho,
        rho, has_sigma, sigma, params[0], params[1], params[2], params[3], params[4], params[5],
        params[6], params[7], params[8], params[9] > 0.5, params[10], params[11], params[12],
        params[13],
    )  # fmt: skip
