"""Occlusion rows (37)-(45): occluder points and the angle barrier's rows, compiled with numba.

The occlusion family is the costliest part of a UAV's rows (a least-angle search over up to 12
box edges per obstacle, every step, for every UAV), so its geometry runs as scalar loops compiled
by numba (`cache=True`: compiled once per machine, then loaded). The formulas are those of the
docstrings below; tests/test_safety_cbf.py checks the rows against finite differences of
``theta - theta*`` and the occluder points against a dense search.
"""

from __future__ import annotations

import math

import numba
import numpy as np

POINT_MODES = ("centre", "axis", "edges")
"""`CBFConfig.occlusion_point` values, indexed by the kernels' ``mode``."""
OVER_THE_TOP = len(POINT_MODES)
"""The kernels' ``mode`` for 'edges' whose sight line through a box leaves it over the box's
top: of its outline, only the edges of the top face (`SafetyFilter.climb_over_occluders`)."""


def _edge_geometry() -> tuple[np.ndarray, np.ndarray]:
    """The 12 edges of a unit box: start corner signs (12, 3) and the axis each runs along."""
    starts, axes = [], []
    for k in range(3):
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                sign = [s1, s2]
                sign.insert(k, -1.0)
                starts.append(sign)
                axes.append(k)
    return np.array(starts), np.array(axes)


_EDGE_START, _EDGE_AXIS = _edge_geometry()


@numba.njit(cache=True)
def _pierces(p, n, reach, c, half):  # pragma: no cover (compiled)
    """Whether the sight line p + t n, 0 <= t <= reach (``n`` unit), passes through the box."""
    lo, hi = 0.0, reach
    for a in range(3):
        if abs(n[a]) < 1e-12:
            if abs(p[a] - c[a]) > half[a]:
                return False
            continue
        t1 = (c[a] - half[a] - p[a]) / n[a]
        t2 = (c[a] + half[a] - p[a]) / n[a]
        lo, hi = max(lo, min(t1, t2)), min(hi, max(t1, t2))
    return lo <= hi


@numba.njit(cache=True)
def _on_outline(p, c, half, k):  # pragma: no cover (compiled)
    """Whether edge k is on the box's outline seen from p: of the two faces it joins, exactly
    one faces p."""
    facing = 0
    for a in range(3):
        if a != _EDGE_AXIS[k]:
            s = _EDGE_START[k, a]
            facing += s * (p[a] - c[a]) > half[a]
    return facing == 1


@numba.njit(cache=True)
def _on_top(k):  # pragma: no cover (compiled)
    """Whether edge k is an edge of the box's top face."""
    return _EDGE_AXIS[k] != 2 and _EDGE_START[k, 2] > 0.0


@numba.njit(cache=True)
def _occluder_point(p, n, reach, c, half, mode):  # pragma: no cover (compiled)
    """(p_o of one box (`occluder_points`), whether the sight line goes through the box);
    ``n`` is the unit sight line, ``reach`` the distance to the car. Through the box, 'edges'
    takes the least-angle point of the box's outline (`_on_outline`), `OVER_THE_TOP` that of
    the outline's top-face edges (of every top-face edge from inside the box), or of the whole
    outline if none of its edges is on the top face."""
    out = np.empty(3)
    if mode == 0:
        out[:] = c
        return out, False
    if mode == 1:
        # the vertical axis: with t = z - p_z, cos = (a + t n_z) / sqrt(b^2 + t^2), a the
        # horizontal part of (c - p).n and b the horizontal distance; stationary at n_z b^2 / a
        wx, wy = c[0] - p[0], c[1] - p[1]
        a = wx * n[0] + wy * n[1]
        b2 = wx * wx + wy * wy
        lo, hi = c[2] - half[2] - p[2], c[2] + half[2] - p[2]
        safe_a = a if abs(a) > 1e-12 else 1e-12
        best_t, best_cos = 0.0, -np.inf
        for i in range(3):
            if i == 0:
                t = lo
            elif i == 1:
                t = hi
            else:
                t = min(max(n[2] * b2 / safe_a, lo), hi)
            cos = (a + t * n[2]) / math.sqrt(b2 + t * t + 1e-300)
            if cos > best_cos:
                best_cos, best_t = cos, t
        out[0], out[1], out[2] = c[0], c[1], p[2] + best_t
        return out, False
    # edges p + w + t e, t in [0, L] (e a unit axis): cos = (a + b t) / sqrt(c0 + 2 c1 t + t^2)
    # with a = w.n, b = e.n, c0 = |w|^2, c1 = w.e; its only stationary point is
    # t = (a c1 - b c0) / (b c1 - a), so the largest cos is there (clipped) or at an end.
    inside = _pierces(p, n, reach, c, half)
    # from a UAV inside the box no face faces it and every edge stays a candidate
    outline = inside and not (np.abs(p - c) <= half).all()
    over = inside and mode == OVER_THE_TOP
    best_cos, top_cos = -np.inf, -np.inf
    top = np.empty(3)
    for k in range(12):
        if outline and not _on_outline(p, c, half, k):
            continue
        on_top = over and _on_top(k)
        ax = _EDGE_AXIS[k]
        s0 = c[0] + _EDGE_START[k, 0] * half[0]
        s1 = c[1] + _EDGE_START[k, 1] * half[1]
        s2 = c[2] + _EDGE_START[k, 2] * half[2]
        w0, w1, w2 = s0 - p[0], s1 - p[1], s2 - p[2]
        length = 2.0 * half[ax]
        a = w0 * n[0] + w1 * n[1] + w2 * n[2]
        b = n[ax]
        c0 = w0 * w0 + w1 * w1 + w2 * w2
        c1 = w0 if ax == 0 else (w1 if ax == 1 else w2)
        den = b * c1 - a
        safe = den if abs(den) > 1e-12 else 1e-12
        for i in range(3):
            if i == 0:
                t = 0.0
            elif i == 1:
                t = length
            else:
                t = min(max((a * c1 - b * c0) / safe, 0.0), length)
            cos = (a + b * t) / math.sqrt(max(c0 + 2.0 * c1 * t + t * t, 1e-300))
            if cos > best_cos:
                best_cos = cos
                out[0], out[1], out[2] = s0, s1, s2
                out[ax] += t
            if on_top and cos > top_cos:
                top_cos = cos
                top[0], top[1], top[2] = s0, s1, s2
                top[ax] += t
    return (top if top_cos > -np.inf else out), inside


@numba.njit(cache=True)
def _points(p, centers, half, q, mode):  # pragma: no cover (compiled)
    n = q - p
    reach = math.sqrt(n @ n)
    n = n / max(reach, 1e-12)
    out = np.empty_like(centers)
    for j in range(centers.shape[0]):
        out[j] = _occluder_point(p, n, reach, centers[j], half[j], mode)[0]
    return out


def occluder_points(
    p: np.ndarray, centers: np.ndarray, half: np.ndarray, q: np.ndarray, mode: str
) -> np.ndarray:
    """p_o^j of eq. (38) per obstacle: its centre (paper), or the point of least angle to the
    line of sight n = q - p on the box's vertical axis ('axis') or on its 12 edges ('edges').

    theta is then the minimum over that set. Its gradient at the minimiser is the gradient of
    theta at that fixed point (Danskin), so the occlusion rows stay exact. The 'edges' minimum is
    the least angle of the whole box whenever the sight line misses the box (the angle is
    quasi-convex on each face plane, so a face's minimum lies on its boundary). Where the line
    goes through the box, 'edges' takes the least-angle point of the box's outline seen from p
    (the edges of which exactly one of the two faces they join faces p): the way out of the box.
    """
    centers = np.asarray(centers, float).reshape(-1, 3)
    half = np.asarray(half, float).reshape(-1, 3)
    p, q = np.asarray(p, float), np.asarray(q, float)
    return _points(p, centers, half, q, POINT_MODES.index(mode))


@numba.njit(cache=True)
def occlusion_family(
    p, q, vq, centers, half, velocity, theta_star, mode, moving_target, size_margin
):  # pragma: no cover (compiled)
    """Occlusion rows (41)-(45) of the boxes ``centers`` +- ``half`` moving at ``velocity``
    (zeros: the paper's static obstacles): (A, h, drift, index).

    A row exists for box j when its occluder point p_o^j (`occluder_points`, ``mode`` an index of
    `POINT_MODES`) is in N_oi = {||p_o^j - p|| <= ||n||}, n = q - p (36); boxes whose nearest
    possible point is farther than the car are skipped before their point is searched.

    With x = cos(theta) = d.n / (|d||n|) and d = p_o - p, (41) reads
    ``theta-dot = -(dx/dd . d-dot + dx/dn . n-dot) / sin(theta)``, where
    ``dx/dd = n/(|d||n|) - x d/|d|^2`` and ``dx/dn = d/(|d||n|) - x n/|n|^2``.

    * paper (43): n-dot = 0 and d-dot = -V, so A = -(1/sin) dx/dd and b = gamma_o h (45).
    * ``moving_target``: n-dot = V_q - V, so A = -(1/sin)(dx/dd + dx/dn) and the target term
      ``drift = -(1/sin) dx/dn . V_q`` goes to b.
    * a moving box (a team-mate, not in the paper): d-dot = V_j - V adds
      ``-(1/sin) dx/dd . V_j`` to the drift.

    ``size_margin`` (not in the paper): h = theta - theta* - beta, beta = asin(r_j / b_j) the
    box's angular radius (r_j its horizontal half-diagonal, b_j the horizontal distance to its
    axis, clipped at 0.99); A gains d beta/dp = r w / (b^3 sqrt(1 - r^2/b^2)), w the horizontal
    part of d. theta = 0 or pi makes 1/sin singular and is clamped.

    'edges' with the sight line through the box (not in the paper): theta is minus the angle to
    the box's outline, so h falls the deeper the line goes and its gradient points the line out
    (the unsigned least angle to the edges grows again inside the box, towards its middle).
    """
    m = centers.shape[0]
    A = np.empty((m, 3))
    h = np.empty(m)
    drift = np.zeros(m)
    index = np.empty(m, np.int64)
    n = q - p
    nn2 = n @ n
    if nn2 < 1e-18:
        return A[:0], h[:0], drift[:0], index[:0]
    reach = math.sqrt(nn2)
    unit = n / max(reach, 1e-12)
    nvq = n @ vq
    k = 0
    for j in range(m):
        c, hf = centers[j], half[j]
        dc = c - p
        if math.sqrt(dc @ dc) - math.sqrt(hf @ hf) > reach:
            continue
        point, inside = _occluder_point(p, unit, reach, c, hf, mode)
        d = point - p
        nd2 = d @ d
        if not (nd2 <= nn2 and nd2 > 1e-18):
            continue
        inv_dn = 1.0 / math.sqrt(nd2 * nn2)
        x = min(max((d @ n) * inv_dn, -1.0), 1.0)
        inv_sin = 1.0 / math.sqrt(max(1.0 - x * x, 1e-12))
        theta = math.acos(x)
        hj = (-theta if inside else theta) - theta_star
        k_n = inv_sin * inv_dn  # A = -k_n n + k_d d for the paper's model
        k_d = inv_sin * x / nd2
        if moving_target:
            k_nn = inv_sin * x / nn2
            A[k] = (k_d - k_n) * d - (k_n - k_nn) * n
            drift[k] = -k_n * (d @ vq) + k_nn * nvq
        else:
            A[k] = k_d * d - k_n * n
        vj = velocity[j]
        if vj[0] != 0.0 or vj[1] != 0.0 or vj[2] != 0.0:
            drift[k] += k_d * (d @ vj) - k_n * (n @ vj)
        if inside:  # theta = -(angle to the outline): its rate changes sign too
            A[k] = -A[k]
            drift[k] = -drift[k]
        if size_margin:
            b2 = max(d[0] * d[0] + d[1] * d[1], 1e-18)
            ratio = math.hypot(hf[0], hf[1]) / math.sqrt(b2)
            if ratio >= 0.99:
                hj -= math.asin(0.99)
            else:
                hj -= math.asin(ratio)
                k_b = ratio / (b2 * math.sqrt(1.0 - ratio * ratio))
                A[k, 0] += k_b * d[0]
                A[k, 1] += k_b * d[1]
        h[k] = hj
        index[k] = j
        k += 1
    return A[:k], h[:k], drift[:k], index[:k]
