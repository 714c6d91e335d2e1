"""The first-order rows of the collision, obstacle, car, floor and connectivity families.

Each row is ``A V <= gamma h + drift - margin`` (`cbf` module docstring); this module gives A, h
and drift, `cbf.RowBuilder` adds the family's gamma and margin. The rows of one UAV are a few
dozen scalars, rebuilt for every UAV at 80 Hz, so they are computed in one numba-compiled pass
(`cache=True`: compiled once per machine, then loaded) instead of dozens of tiny numpy calls.
tests/test_safety_cbf.py checks them against finite differences of their barrier functions.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from uavtrack_env.safety.occlusion import occlusion_family

N_FAMILIES = 5
"""uav, obstacle, target, floor, connect: the order of `first_order_rows`' families."""
CAP_ROWS = 6
"""Rows of the speed cap (`first_order_rows`): the box |V_x|, |V_y|, |V_z| <= S / sqrt(3)."""


@numba.njit(cache=True)
def box_sdist(lx, ly, lz, hx, hy, hz, grounded, reach=0.0):  # pragma: no cover (compiled)
    """Signed squared distance from a point (box coordinates) to a box of half sizes h, and its
    gradient: (d2, gx, gy, gz).

    Outside: ``dist^2`` with gradient ``2 (p - closest point)``. Inside (penetration depth e to
    the nearest face with outward normal n): ``-e^2`` with gradient ``2 e n``. The function is
    C^1 across the surface (value and gradient both vanish there). ``grounded``: the box stands
    on the ground (the car, `target_row`): inside it is ``-e_xy (t + reach)``, t the depth under
    the top and e_xy the depth inside the nearest side (outward normal n_xy), with gradient
    ``((t + reach) n_xy, e_xy)``: 0 on the sides, and both climbing and moving out raise it,
    moving in lowers it even just under the top (the car may stand anywhere in the box and
    reach its top; the bottom is never the way out). It jumps up through the top.
    """
    ex, ey, ez = abs(lx) - hx, abs(ly) - hy, abs(lz) - hz
    if max(ex, ey, ez) < 0.0 and grounded:
        top, side = hz - lz + reach, -max(ex, ey)
        if ex >= ey:  # the nearest side, the first axis on ties (numpy's argmax)
            return -top * side, math.copysign(top, lx), 0.0, side
        return -top * side, 0.0, math.copysign(top, ly), side
    if max(ex, ey, ez) < 0.0:
        depth = -max(ex, ey, ez)
        gx = gy = gz = 0.0
        if ex >= ey and ex >= ez:  # the nearest face, first axis on ties (numpy's argmax)
            gx = math.copysign(2.0 * depth, lx)
        elif ey >= ez:
            gy = math.copysign(2.0 * depth, ly)
        else:
            gz = math.copysign(2.0 * depth, lz)
        return -depth * depth, gx, gy, gz
    ox, oy, oz = max(ex, 0.0), max(ey, 0.0), max(ez, 0.0)
    d2 = ox * ox + oy * oy + oz * oz
    return d2, math.copysign(2.0 * ox, lx), math.copysign(2.0 * oy, ly), math.copysign(2.0 * oz, lz)


@numba.njit(cache=True)
def box_sdists(local, half, grounded, reach=0.0):  # pragma: no cover (compiled)
    """`box_sdist` of points (m, 3) in box coordinates against half sizes (m, 3) or (1, 3)."""
    m = local.shape[0]
    out = np.empty(m)
    for j in range(m):
        hj = half[j if half.shape[0] > 1 else 0]
        out[j] = box_sdist(
            local[j, 0], local[j, 1], local[j, 2], hj[0], hj[1], hj[2], grounded, reach
        )[0]
    return out


_SQRT2 = math.sqrt(2.0)


@numba.njit(cache=True)
def target_row(p, q, vq, half, heading, clearance, growth, frustum):  # pragma: no cover (compiled)
    """The car, a box at q with yaw ``heading`` standing on the ground and moving at V_q:
    (-grad h, h, drift).

    A tracked car: h = sdist(p, box)^2 - clearance^2 (`box_sdist`, grounded, ``reach`` =
    clearance: from inside, the way out is up and out, never further in). A stale car
    (``frustum``, its box the growing reachable set of `onboard.car_box`): ``h = d_xy + (z -
    z_top) - sqrt(2) clearance``, d_xy the horizontal distance to the footprint (0 over it),
    z_top the top; inside the box plus `box_sdist`'s inside per clearance. The frustum's zero
    set keeps at least ``clearance`` from the box (beside it d_xy >= sqrt(2) clearance + z_top
    - z; above it d_xy + z - z_top >= sqrt(2) clearance implies a distance >= clearance), and
    climbing always raises it (grad_z h >= 1): a UAV beside a growing box keeps its row by
    climbing instead of being pushed sideways, away from its team-mates, for as long as the car
    stays lost. Outside the box both are convex in p, so the rows' linearisation is
    conservative in discrete time there; inside, ``-e_xy (t + reach)`` is a saddle
    (`second_order.target_curvature` counts it).

    h-dot = grad h . (V - V_q) for a translating box (its heading rate neglected), so ``drift =
    -grad h . V_q``; faces moving outwards at ``growth`` (3,) m/s along the box's axes close in
    at ``sum_a |grad_a h| growth_a`` in the box's frame (exact: d/dt of h as the half sizes grow).
    """
    c, s = math.cos(heading), math.sin(heading)
    dx, dy, dz = p[0] - q[0], p[1] - q[1], p[2] - q[2]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    if frustum:
        ox, oy = max(abs(lx) - half[0], 0.0), max(abs(ly) - half[1], 0.0)
        dxy = math.sqrt(ox * ox + oy * oy)
        gx_l = gy_l = 0.0
        if dxy > 0.0:
            gx_l, gy_l = math.copysign(ox / dxy, lx), math.copysign(oy / dxy, ly)
        gz = 1.0
        h = dxy + dz - half[2] - _SQRT2 * clearance
        if dxy == 0.0 and dz < half[2]:  # over the footprint, under the top: maybe inside
            inside, gxi, gyi, gzi = box_sdist(
                lx, ly, dz, half[0], half[1], half[2], True, clearance
            )
            if inside < 0.0:  # the box's inside, per clearance
                h += inside / clearance
                gx_l, gy_l, gz = gxi / clearance, gyi / clearance, 1.0 + gzi / clearance
    else:
        d2, gx_l, gy_l, gz = box_sdist(lx, ly, dz, half[0], half[1], half[2], True, clearance)
        h = d2 - clearance * clearance
    gx, gy = c * gx_l - s * gy_l, s * gx_l + c * gy_l
    drift = -(gx * vq[0] + gy * vq[1] + gz * vq[2])
    drift -= abs(gx_l) * growth[0] + abs(gy_l) * growth[1] + abs(gz) * growth[2]
    return -gx, -gy, -gz, h, drift


@numba.njit(cache=True)
def _way_out(x, q, c, s, half, clearance, top):  # pragma: no cover (compiled)
    """`make_way`'s climb for a UAV at ``x``: 0 unless within ``clearance`` of the box."""
    dx, dy, dz = x[0] - q[0], x[1] - q[1], x[2] - q[2]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    d2 = box_sdist(lx, ly, dz, half[0], half[1], half[2], True)[0]
    inside = clearance - (math.sqrt(d2) if d2 >= 0.0 else -math.sqrt(-d2))
    if inside <= 0.0:
        return 0.0
    ox, oy = max(abs(lx) - half[0], 0.0), max(abs(ly) - half[1], 0.0)
    return max(0.0, min(inside, top - x[2] - math.sqrt(ox * ox + oy * oy)))


@numba.njit(cache=True)
def make_way(p, nb, rho, q, half, heading, clearance, r_s):  # pragma: no cover (compiled)
    """The radii ``rho`` (k,) of the team-mates at ``nb`` (k, 3) of the UAV at ``p``, each grown
    by how much more it must climb than this UAV to leave the car's box (centre q, half extents
    ``half``, yaw ``heading``, standing on the ground), where this UAV is over its way out (not
    in the paper).

    A UAV that the car's box has caught (it grew over the UAV, or a team-mate pressed it in)
    leaves it by climbing (the frustum of `target_row`), which a team-mate above it blocks: that
    team-mate's pair row holds only its half (23). Treating the caught UAV as anywhere within
    the grown ball, the team-mate's own rows make it back off by the way out the caught one
    needs. A UAV's climb is ``min(clearance - sdist, climb to the frustum's zero set)`` while it
    is within ``clearance`` of the box (0 at the clearance, then deeper inside it): of two
    caught UAVs the higher one makes way for the lower. The growth is tapered to 0 over a
    ``clearance`` as this UAV comes level with the team-mate or beyond R_s beside it, so that
    team-mates not in the way keep their rows and none changes at once.
    """
    out = rho.copy()
    c, s = math.cos(heading), math.sin(heading)
    top = q[2] + half[2] + _SQRT2 * clearance
    own = _way_out(p, q, c, s, half, clearance, top)
    for j in range(nb.shape[0]):
        way = _way_out(nb[j], q, c, s, half, clearance, top) - own
        if way > 0.0:
            dx, dy = p[0] - nb[j, 0], p[1] - nb[j, 1]
            over = min(max((r_s + clearance - math.sqrt(dx * dx + dy * dy)) / clearance, 0.0), 1.0)
            above = min(max((p[2] - nb[j, 2]) / clearance, 0.0), 1.0)
            out[j] += way * over * above
    return out


@numba.njit(cache=True)
def first_order_rows(
    p,
    nb,
    rho,
    centers,
    half,
    box_model,
    car,
    q,
    vq,
    car_half,
    heading,
    growth,
    frustum,
    d_s,
    r_s,
    r_c,
    alpha_v,
    clearance,
    z_min,
    gamma_uav,
    cap_rho,
):  # pragma: no cover (compiled)
    """Rows of the families uav, obstacle, target, floor, connect (in that order): (A, h, drift,
    index, sizes).

    * uav (20)-(25), j in N_si = {||p - p_j|| <= D_s}: ``A = -2 (p - p_j)``, h = ||d||^2 - R_s^2
      (halved rate, the distributed split (23)-(24): UAV j enforces the mirrored half; h is
      convex, so forward Euler needs no margin).
    * obstacle: boxes (``box_model``; not in the paper), h = sdist(p, box)^2 - clearance^2,
      A = -grad h; or the paper's points (IV-A), h = ||p - p_o||^2 - R_s^2. Static: no drift.
    * target (if ``car``): `target_row` (a box, or for a stale car a frustum over it).
    * floor (not in the paper): h = z - z_min, A = (0, 0, -1) (linear: exact in discrete time).
    * connect (29)-(34), j in N_ci = {||p - p_j|| <= R_c}: ``A = 2 (p - p_j)``, h = R_c^2 -
      ||d||^2 (concave: `cbf.RowBuilder` subtracts the discrete-time margin).

    A neighbour known only within ``rho_j`` of ``nb_j`` (a lost message; `onboard.NeighbourTable`)
    gets its rows' worst case over that ball: h from the least (uav) or greatest (connect)
    possible distance, ``(||d|| -+ rho)^2``, and the drift ``-2 rho alpha_v`` for the unknown
    part of ``-+2 (p - p_j) . V`` (``||V|| <= alpha_v``); it keeps its rows while it may be in
    the set. Each UAV's half still bounds its true share, so the halves sum to (22)/(31).

    ``cap_rho`` (k,) (first-order rows; empty: none): the radii of the lost messages alone,
    without `make_way`'s growth, and a speed cap ``S <= alpha_v`` for them (``gamma_uav``: the
    uav rows' rate). The drift bounds ``2 e . V`` (``||e|| <= rho``) by ``2 rho S``, S keeping
    ``V = 0`` inside the rows of every team-mate with a lost message, so its ball never makes
    them infeasible however long its messages are lost. Their h is at least 0: the true pair is
    outside R_s while the promise holds, whatever part of the ball reaches inside. S is the
    least ``gamma_uav h / (2 rho)`` of those rows, at most alpha_v; below alpha_v the cap is
    `CAP_ROWS` more uav rows (the box that fits in the ball ``||V|| <= S``; index: the team-mate
    whose row set it), and the connect rows' drift counts on S too. Every message heard: no
    change. A ball that swallows the UAV stops it (S = 0): any motion may close on the team-mate.
    """
    k, m = nb.shape[0], centers.shape[0]
    size = 2 * k + m + 2 + CAP_ROWS
    A = np.zeros((size, 3))
    h = np.empty(size)
    drift = np.zeros(size)
    index = np.zeros(size, np.int64)
    sizes = np.zeros(N_FAMILIES, np.int64)
    uncertain = False
    for j in range(k):
        uncertain |= rho[j] != 0.0
    d = np.empty((k, 3))
    d2 = np.empty(k)
    for j in range(k):
        for i in range(3):
            d[j, i] = p[i] - nb[j, i]
        d2[j] = d[j, 0] * d[j, 0] + d[j, 1] * d[j, 1] + d[j, 2] * d[j, 2]
    r = 0
    for j in range(k):  # uav
        dist = math.sqrt(d2[j])
        if (dist - rho[j] <= d_s) if uncertain else (d2[j] <= d_s * d_s):
            A[r] = -2.0 * d[j]
            if rho[j] > 0.0:
                near = max(dist - rho[j], 0.0)
                h[r] = near * near - r_s * r_s
                if cap_rho.shape[0] > 0 and cap_rho[j] > 0.0:
                    h[r] = max(h[r], 0.0)
            else:
                h[r] = d2[j] - r_s * r_s
            index[r] = j
            r += 1
    speed, bind = alpha_v, -1
    if cap_rho.shape[0] > 0:
        for row in range(r):
            j = index[row]
            if cap_rho[j] > 0.0:
                s = gamma_uav * h[row] / (2.0 * rho[j]) * (1.0 - 1e-9)  # b stays >= 0 at V = 0
                if s < speed:
                    speed, bind = s, row
    for row in range(r):
        drift[row] = -2.0 * speed * rho[index[row]]
    if bind >= 0:
        side = speed / math.sqrt(3.0)
        for axis in range(3):
            for sign in (1.0, -1.0):
                A[r, axis] = sign
                h[r] = h[bind]
                drift[r] = side - gamma_uav * h[bind]
                index[r] = index[bind]
                r += 1
    sizes[0] = r
    for j in range(m):  # obstacle
        lx, ly, lz = p[0] - centers[j, 0], p[1] - centers[j, 1], p[2] - centers[j, 2]
        if box_model:
            dd, gx, gy, gz = box_sdist(lx, ly, lz, half[j, 0], half[j, 1], half[j, 2], False)
            A[r, 0], A[r, 1], A[r, 2] = -gx, -gy, -gz
            h[r] = dd - clearance * clearance
        else:
            A[r, 0], A[r, 1], A[r, 2] = -2.0 * lx, -2.0 * ly, -2.0 * lz
            h[r] = lx * lx + ly * ly + lz * lz - r_s * r_s
        index[r] = j
        r += 1
    sizes[1] = m
    if car:
        A[r, 0], A[r, 1], A[r, 2], h[r], drift[r] = target_row(
            p, q, vq, car_half, heading, clearance, growth, frustum
        )
        r += 1
        sizes[2] = 1
    A[r, 2] = -1.0  # floor
    h[r] = p[2] - z_min
    r += 1
    sizes[3] = 1
    start = r
    for j in range(k):  # connect
        dist = math.sqrt(d2[j])
        if (dist - rho[j] <= r_c) if uncertain else (d2[j] <= r_c * r_c):
            A[r] = 2.0 * d[j]
            if rho[j] > 0.0:
                far = dist + rho[j]
                h[r] = r_c * r_c - far * far
            else:
                h[r] = r_c * r_c - d2[j]
            drift[r] = -2.0 * speed * rho[j]
            index[r] = j
            r += 1
    sizes[4] = r - start
    return A[:r], h[:r], drift[:r], index[:r], sizes


@numba.njit(cache=True)
def all_rows(
    p,
    nb,
    rho,
    centers,
    half,
    box_model,
    car,
    q,
    vq,
    car_half,
    heading,
    growth,
    frustum,
    d_s,
    r_s,
    r_c,
    alpha_v,
    clearance,
    z_min,
    occlusion,
    theta_star,
    mode,
    moving_target,
    size_margin,
    gammas,
    margins,
    cap_rho,
    nb_v,
    mate_half,
):  # pragma: no cover (compiled)
    """`first_order_rows` (``cap_rho``: its speed cap's radii, for first-order rows) and, with
    ``occlusion``, `occlusion_family`'s rows after them, as one stack with each row's rate and
    margin (``gammas``, ``margins``: one per family) and ``b = gamma h + drift - margin``: (A,
    floats, ints, sizes), floats = [b, h, gamma, drift, margin] (5, n) and ints = [kind, index]
    (2, n), sizes per family (the 6th: occlusion).

    With ``mate_half`` > 0 (not in the paper) the team-mates occlude too: team-mate j is a box
    of half size ``mate_half + rho_j`` at ``nb[j]`` moving at ``nb_v[j]``, its occlusion row
    after the obstacles' with index ``-(j + 1)``.
    Four arrays, not nine: returning each array to Python costs about as much as building it."""
    A1, h1, drift1, index1, sizes1 = first_order_rows(
        p,
        nb,
        rho,
        centers,
        half,
        box_model,
        car,
        q,
        vq,
        car_half,
        heading,
        growth,
        frustum,
        d_s,
        r_s,
        r_c,
        alpha_v,
        clearance,
        z_min,
        gammas[0],
        cap_rho,
    )
    A2, h2, drift2, index2 = A1[:0], h1[:0], drift1[:0], index1[:0]
    if occlusion:
        A2, h2, drift2, index2 = occlusion_family(
            p, q, vq, centers, half, np.zeros_like(centers), theta_star, mode, moving_target,
            size_margin,
        )  # fmt: skip
        k = nb.shape[0]
        if mate_half > 0.0 and k > 0:
            grown = np.empty((k, 3))
            for j in range(k):
                grown[j, :] = mate_half + rho[j]
            A3, h3, drift3, index3 = occlusion_family(
                p, q, vq, nb, grown, nb_v, theta_star, mode, moving_target, size_margin
            )
            A2 = np.concatenate((A2, A3))
            h2 = np.concatenate((h2, h3))
            drift2 = np.concatenate((drift2, drift3))
            index2 = np.concatenate((index2, -(index3 + 1)))
    n1, n2 = h1.shape[0], h2.shape[0]
    n = n1 + n2
    sizes = np.empty(N_FAMILIES + 1, np.int64)
    sizes[:N_FAMILIES] = sizes1
    sizes[N_FAMILIES] = n2
    A = np.empty((n, 3))
    floats = np.empty((5, n))
    ints = np.empty((2, n), np.int64)
    b, h, gamma, drift, margin = floats[0], floats[1], floats[2], floats[3], floats[4]
    kind, index = ints[0], ints[1]
    A[:n1], h[:n1], drift[:n1], index[:n1] = A1, h1, drift1, index1
    A[n1:], h[n1:], drift[n1:], index[n1:] = A2, h2, drift2, index2
    r = 0
    for f in range(N_FAMILIES + 1):
        for _ in range(sizes[f]):
            gamma[r], margin[r], kind[r] = gammas[f], margins[f], f
            r += 1
    for j in range(n):
        b[j] = gamma[j] * h[j] + drift[j] - margin[j]
    return A, floats, ints, sizes
