"""The batched core's per-step arithmetic as numba kernels, over K worlds of n UAVs.

Each kernel computes, in one compiled loop, what `core` and `sensors.Detector` define: the same
expressions in the same order (IEEE arithmetic, the platform's libm for sin, cos, atan2, acos),
so that their results equal the numpy formulation bit for bit
(`tests/test_core_kernels.py`). They exist because a step of a few UAVs is hundreds of numpy
calls on tiny arrays otherwise: the interpreter, not the arithmetic, sets the env's speed.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _wrap(a: float) -> float:  # pragma: no cover (compiled)
    """`geometry.wrap_angle` of one value: (-pi, pi]."""
    return math.pi - (math.pi - a) % (2.0 * math.pi)


@numba.njit(cache=True, inline="always")
def _norm3(x: float, y: float, z: float) -> float:  # pragma: no cover (compiled)
    return math.sqrt(x * x + y * y + z * z)


@numba.njit(cache=True)
def integrate(
    position, yaw, velocity, yaw_rate, alive, u, lag, tau, a_max, yaw_gain, dt
):  # pragma: no cover (compiled)
    """`dynamics.integrate` of K worlds (position, velocity (K, n, 3); yaw, yaw rate, alive
    (K, n); u (K, n, 4), zero for finished UAVs): the new state and the applied u. ``lag``
    selects the lag model, ``yaw_gain`` = min(1, dt / yaw_tau)."""
    K, n = yaw.shape
    new_p, new_v = np.empty((K, n, 3)), np.empty((K, n, 3))
    new_yaw, new_w, applied = np.empty((K, n)), np.empty((K, n)), np.zeros((K, n, 4))
    for k in range(K):
        for i in range(n):
            if alive[k, i]:
                for c in range(4):
                    applied[k, i, c] = u[k, i, c]
            X, Y, Z, w_cmd = applied[k, i, 0], applied[k, i, 1], applied[k, i, 2], -applied[k, i, 3]
            c, s = math.cos(yaw[k, i]), math.sin(yaw[k, i])
            vx, vy, vz = s * X + c * Z, -c * X + s * Z, -Y  # eq. (3): camera to global frame
            w = w_cmd
            if lag:
                ax = (vx - velocity[k, i, 0]) / tau
                ay = (vy - velocity[k, i, 1]) / tau
                az = (vz - velocity[k, i, 2]) / tau
                scale = min(1.0, a_max / max(_norm3(ax, ay, az), 1e-12))
                vx = velocity[k, i, 0] + ax * scale * dt
                vy = velocity[k, i, 1] + ay * scale * dt
                vz = velocity[k, i, 2] + az * scale * dt
                w = yaw_rate[k, i] + (w_cmd - yaw_rate[k, i]) * yaw_gain
            new_v[k, i, 0], new_v[k, i, 1], new_v[k, i, 2], new_w[k, i] = vx, vy, vz, w
            new_p[k, i, 0] = position[k, i, 0] + vx * dt
            new_p[k, i, 1] = position[k, i, 1] + vy * dt
            new_p[k, i, 2] = position[k, i, 2] + vz * dt
            new_yaw[k, i] = _wrap(yaw[k, i] + w * dt)
    return new_p, new_yaw, new_v, new_w, applied


@numba.njit(cache=True)
def scaled_actions(a, scale):  # pragma: no cover (compiled)
    """Finite normalised actions (rows, 4) clipped to [-1, 1] and scaled to SI units by Table II
    (``scale``, (4,)); and (rows,) bool: the row left [-1, 1]."""
    rows = a.shape[0]
    u, clipped = np.empty((rows, 4)), np.zeros(rows, np.bool_)
    for i in range(rows):
        for c in range(4):
            x = a[i, c]
            if abs(x) > 1.0:
                clipped[i] = True
            u[i, c] = min(max(x, -1.0), 1.0) * scale[c]
    return u, clipped


@numba.njit(cache=True)
def received(dist, alive, draws, drop_prob, r_c):  # pragma: no cover (compiled)
    """`sensors.receive_batch`'s mask of K worlds: UAV i hears UAV j (i != j, both alive) when
    they are within ``r_c`` and the message's draw is not below ``drop_prob``."""
    K, n = alive.shape
    out = np.zeros((K, n, n), np.bool_)
    for k in range(K):
        for i in range(n):
            for j in range(n):
                out[k, i, j] = (
                    i != j
                    and dist[k, i, j] <= r_c
                    and not draws[k, i, j] < drop_prob
                    and alive[k, i]
                    and alive[k, j]
                )
    return out


@numba.njit(cache=True)
def detector_frame(
    local, centers, target_yaws, headings, positions, yaws, camera, n_samples
):  # pragma: no cover (compiled)
    """The noise-free part of `Detector.detect_batch`: the car's points (``local`` (P, 3): the
    centre, ``n_samples`` ray-cast samples, the 8 box corners) placed at each world's car
    (centres (K, 3), yaws (K,)), projected into each UAV's camera (positions (K, n, 3), yaws
    (K, n); ``camera`` = [fx, fy, cu, cv, width, height, near]), the box from the corners and psi
    of eq. (4) (headings (K,)).

    Returns (rows (5, B): box u, box v, optical depth Z of the centre, psi, and the box centre's
    u where every corner is in front (else the centre's projection); its v in row 4 is returned
    in ``box_center``), true_features (B, 4), box_center (B, 2), flags (2, B) bool (centre in
    front, all corners in front), truncated (B, 2) bool, in_image (B, s) bool of the samples,
    samples (K, s, 3) in the world. B = K n, UAV-major within a world.
    """
    fx, fy, cu, cv, width, height, near = (
        camera[0], camera[1], camera[2], camera[3], camera[4], camera[5], camera[6],
    )  # fmt: skip
    K, n = yaws.shape
    P = local.shape[0]
    s = n_samples
    B = K * n
    points = np.empty((K, P, 3))
    for k in range(K):
        c, sn = math.cos(target_yaws[k]), math.sin(target_yaws[k])
        for p in range(P):
            x, y = local[p, 0], local[p, 1]
            points[k, p, 0] = (c * x - sn * y) + centers[k, 0]
            points[k, p, 1] = (sn * x + c * y) + centers[k, 1]
            points[k, p, 2] = local[p, 2] + centers[k, 2]
    rows = np.empty((5, B))
    true = np.empty((B, 4))
    box_center = np.empty((B, 2))
    flags = np.empty((2, B), np.bool_)
    truncated = np.empty((B, 2), np.bool_)
    in_image = np.empty((B, s), np.bool_)
    for k in range(K):
        for i in range(n):
            b = k * n + i
            c, sn = math.cos(yaws[k, i]), math.sin(yaws[k, i])
            px, py, pz = positions[k, i, 0], positions[k, i, 1], positions[k, i, 2]
            umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
            cut_u = cut_v = False
            all_front = True
            for p in range(P):
                d0 = points[k, p, 0] - px
                d1 = points[k, p, 1] - py
                d2 = points[k, p, 2] - pz
                X = sn * d0 - c * d1  # camera frame, see geometry.world_to_cam_vec
                Y = -d2
                Z = c * d0 + sn * d1
                front = Z > near
                Zs = Z if front else np.inf
                pu = fx * X / Zs + cu
                pv = fy * Y / Zs + cv
                if p == 0:
                    z0 = 1e-9 if abs(Z) < 1e-9 else Z
                    true[b, 0] = X / z0
                    true[b, 1] = Y / z0
                    true[b, 2] = 1.0 / z0
                    rows[2, b] = Z
                    flags[0, b] = front
                elif p <= s:
                    in_image[b, p - 1] = (
                        front and pu >= 0 and pu < width and pv >= 0 and pv < height
                    )
                else:  # a corner of the box, clipped to the image
                    all_front = all_front and front
                    qu = min(max(pu, 0.0), width)
                    qv = min(max(pv, 0.0), height)
                    cut_u = cut_u or qu != pu
                    cut_v = cut_v or qv != pv
                    umin, umax = min(umin, qu), max(umax, qu)
                    vmin, vmax = min(vmin, qv), max(vmax, qv)
            psi = _wrap(math.atan2(py - centers[k, 1], px - centers[k, 0]) - headings[k])
            true[b, 3] = psi
            rows[3, b] = psi
            box_u, box_v = 0.5 * (umin + umax), 0.5 * (vmin + vmax)
            rows[0, b], rows[1, b] = box_u, box_v
            flags[1, b] = all_front
            truncated[b, 0], truncated[b, 1] = cut_u, cut_v
            box_center[b, 0] = box_u if all_front else fx * true[b, 0] + cu
            box_center[b, 1] = box_v if all_front else fy * true[b, 1] + cv
            rows[4, b] = box_center[b, 0]
    return rows, true, box_center, flags, truncated, in_image, points[:, 1 : 1 + s].copy()


@numba.njit(cache=True)
def detector_measure(
    rows, all_front, in_image, reach, noise, dropout_draws, settings
):  # pragma: no cover (compiled)
    """The detector's report from `detector_frame`'s ``rows`` and flags, the rays' answers
    ``reach`` (B, s) and the world's draws (``noise`` (B, 4) standard normal, ``dropout_draws``
    (B,) uniform); ``settings`` = [min_visible_fraction, dropout_prob, pixel, depth and psi noise
    std, near].

    Returns (values (6, B): u, v, depth, psi (NaN where not detected), visible and blocked
    fractions; detected (B,) bool)."""
    min_visible, dropout, std_px, std_depth, std_psi, near = (
        settings[0], settings[1], settings[2], settings[3], settings[4], settings[5],
    )  # fmt: skip
    B, s = reach.shape
    out = np.empty((6, B))
    detected = np.empty(B, np.bool_)
    for b in range(B):
        seen = hit = 0
        for j in range(s):
            if reach[b, j]:
                hit += 1
                if in_image[b, j]:
                    seen += 1
        visible = seen / s
        ok = all_front[b] and visible >= min_visible and not dropout_draws[b] < dropout
        detected[b] = ok
        out[4, b] = visible
        out[5, b] = 1.0 - hit / s
        if ok:
            out[0, b] = rows[0, b] + std_px * noise[b, 0]
            out[1, b] = rows[1, b] + std_px * noise[b, 1]
            out[2, b] = max(rows[2, b] + std_depth * noise[b, 2], near)
            out[3, b] = _wrap(rows[3, b] + std_psi * noise[b, 3])
        else:
            out[0, b] = out[1, b] = out[2, b] = out[3, b] = np.nan
    return out, detected


@numba.njit(cache=True)
def sense_geometry(
    position,
    alive,
    centers,
    headings,
    car_half,
    ob_centers,
    ob_half,
    present,
    uav_radius,
    contact_margin,
):  # pragma: no cover (compiled)
    """`core.sense`'s distances: position (K, n, 3), alive (K, n), the cars' centres (K, 3) and
    headings (K,), the car's half extents (3,), the obstacles (K, M, 3) with ``present`` (K, M).

    Returns (pair (K, n, n) inter-UAV distances, nearest_uav (K, n) (inf: none alive),
    clearance (K, n, M) from each UAV's sphere to each obstacle (inf: padding), nearest_obstacle
    (K, n), target_clearance (K, n) to the car's oriented box, theta (K, n, M) of eq. (38),
    in_noi (K, n, M) membership of N_oi (39), touch (K,): some alive UAV is within
    ``contact_margin`` of an obstacle, the car or the ground)."""
    K, n = alive.shape
    M = ob_centers.shape[1]
    pair = np.empty((K, n, n))
    nearest_uav = np.full((K, n), np.inf)
    clearance = np.empty((K, n, M))
    nearest_obstacle = np.full((K, n), np.inf)
    target_clearance = np.empty((K, n))
    theta = np.empty((K, n, M))
    in_noi = np.empty((K, n, M), np.bool_)
    touch = np.zeros(K, np.bool_)
    for k in range(K):
        c, sn = math.cos(headings[k]), math.sin(headings[k])
        for i in range(n):
            p0, p1, p2 = position[k, i, 0], position[k, i, 1], position[k, i, 2]
            for j in range(n):
                d = _norm3(p0 - position[k, j, 0], p1 - position[k, j, 1], p2 - position[k, j, 2])
                pair[k, i, j] = d
                if j != i and alive[k, i] and alive[k, j] and d < nearest_uav[k, i]:
                    nearest_uav[k, i] = d
            l0, l1, l2 = p0 - centers[k, 0], p1 - centers[k, 1], p2 - centers[k, 2]
            x = abs(c * l0 + sn * l1) - car_half[0]
            y = abs(-sn * l0 + c * l1) - car_half[1]
            z = abs(l2) - car_half[2]
            tc = _norm3(max(x, 0.0), max(y, 0.0), max(z, 0.0)) - uav_radius
            target_clearance[k, i] = tc
            n0, n1, n2 = centers[k, 0] - p0, centers[k, 1] - p1, centers[k, 2] - p2
            n_len = _norm3(n0, n1, n2)
            near = tc <= contact_margin or p2 - uav_radius <= contact_margin
            for m in range(M):
                o0, o1, o2 = ob_centers[k, m, 0], ob_centers[k, m, 1], ob_centers[k, m, 2]
                x = abs(p0 - o0) - ob_half[k, m, 0]
                y = abs(p1 - o1) - ob_half[k, m, 1]
                z = abs(p2 - o2) - ob_half[k, m, 2]
                dist = _norm3(max(x, 0.0), max(y, 0.0), max(z, 0.0))
                cl = dist - uav_radius if present[k, m] else np.inf
                clearance[k, i, m] = cl
                nearest_obstacle[k, i] = min(nearest_obstacle[k, i], cl)
                near = near or cl <= contact_margin
                d0, d1, d2 = o0 - p0, o1 - p1, o2 - p2
                d_len = _norm3(d0, d1, d2)
                cos = (d0 * n0 + d1 * n1 + d2 * n2) / (d_len * n_len)
                theta[k, i, m] = math.acos(min(max(cos, -1.0), 1.0))
                in_noi[k, i, m] = d_len <= n_len and present[k, m]
            touch[k] = touch[k] or (near and alive[k, i])
    return (
        pair, nearest_uav, clearance, nearest_obstacle, target_clearance, theta, in_noi, touch,
    )  # fmt: skip


@numba.njit(cache=True)
def observation(
    u, v, depth, psi, visible, detected, position, yaw, velocity, yaw_rate, references,
    received, pair, clearance, ob_centers, ob_half, present, camera, n_neighbours, n_obstacles,
    low, high,
):  # pragma: no cover (compiled)  # fmt: skip
    """`core.observation`: every UAV's observation (K, n, D) float32, clipped to [low, high].

    The detector's report (u, v, depth, psi, visible fraction, detected: (K, n)); the state
    (K, n, ...); references (K, n, 4); received and pair (K, n, n); clearance (K, n, M) and
    the obstacles (K, M, 3); ``camera`` = [fx, fy, cu, cv]. Blocks: own (19), the
    ``n_neighbours`` nearest received team-mates (4 each), the ``n_obstacles`` nearest
    obstacles (7 each), ties broken by index (a stable sort)."""
    fx, fy, cu, cv = camera[0], camera[1], camera[2], camera[3]
    K, n = yaw.shape
    M = clearance.shape[2]
    D = 19 + 4 * n_neighbours + 7 * n_obstacles
    obs = np.zeros((K, n, D), np.float32)
    row = np.empty(D)
    key = np.empty(max(n, M))
    order = np.empty(max(n, M), np.int64)
    for k in range(K):
        for i in range(n):
            row[:] = 0.0
            if detected[k, i]:
                row[0] = (u[k, i] - cu) / fx
                row[1] = (v[k, i] - cv) / fy
                row[2] = 1.0 / depth[k, i]
                row[3] = math.sin(psi[k, i])
                row[4] = math.cos(psi[k, i])
            row[5] = 1.0 if detected[k, i] else 0.0
            row[6] = visible[k, i]
            c, sn = math.cos(yaw[k, i]), math.sin(yaw[k, i])
            x, y, z = velocity[k, i, 0], velocity[k, i, 1], velocity[k, i, 2]
            row[7], row[8], row[9] = sn * x - c * y, -z, c * x + sn * y
            row[10] = -yaw_rate[k, i]
            row[11], row[12] = sn, c
            row[13] = position[k, i, 2]
            row[14], row[15], row[16] = (
                references[k, i, 0],
                references[k, i, 1],
                references[k, i, 2],
            )
            row[17], row[18] = math.sin(references[k, i, 3]), math.cos(references[k, i, 3])
            at = 19
            if n_neighbours:
                for j in range(n):
                    key[j] = pair[k, i, j] if received[k, i, j] else np.inf
                _stable_order(key, order, n)
                for r in range(min(n, n_neighbours)):
                    j = order[r]
                    heard = 1.0 if key[j] < np.inf else 0.0
                    x = position[k, j, 0] - position[k, i, 0]
                    y = position[k, j, 1] - position[k, i, 1]
                    z = position[k, j, 2] - position[k, i, 2]
                    # times the mask, not skipped: an unheard slot holds signed zeros
                    row[at] = (sn * x - c * y) * heard
                    row[at + 1] = -z * heard
                    row[at + 2] = (c * x + sn * y) * heard
                    row[at + 3] = heard
                    at += 4
                at = 19 + 4 * n_neighbours
            if n_obstacles:
                for m in range(M):
                    key[m] = clearance[k, i, m]
                _stable_order(key, order, M)
                for r in range(min(M, n_obstacles)):
                    m = order[r]
                    if present[k, m]:
                        x = ob_centers[k, m, 0] - position[k, i, 0]
                        y = ob_centers[k, m, 1] - position[k, i, 1]
                        z = ob_centers[k, m, 2] - position[k, i, 2]
                        row[at], row[at + 1], row[at + 2] = sn * x - c * y, -z, c * x + sn * y
                        row[at + 3] = ob_half[k, m, 0]
                        row[at + 4] = ob_half[k, m, 1]
                        row[at + 5] = ob_half[k, m, 2]
                        row[at + 6] = 1.0
                    at += 7
            for f in range(D):
                obs[k, i, f] = min(max(row[f], low[f]), high[f])
    return obs


@numba.njit(cache=True, inline="always")
def _stable_order(key, order, m):  # pragma: no cover (compiled)
    """``order[:m]`` = the indices of ``key[:m]`` sorted ascending, ties by index (insertion
    sort: m is a team or an obstacle count)."""
    for a in range(m):
        order[a] = a
        j = a
        while j > 0 and key[order[j - 1]] > key[a]:
            order[j] = order[j - 1]
            j -= 1
        order[j] = a


@numba.njit(cache=True)
def score(
    true, references, in_front, detected, u, ground, obstacle, target, nearest_uav, alive,
    pair, blocked, q, r, cap, settings,
):  # pragma: no cover (compiled)  # fmt: skip
    """`core.score`: the reward terms of eq. (18) and the violations, (K, n) each.

    true features, references and u (K, n, 4); flags, contacts, nearest_uav and blocked (K, n);
    pair (K, n, n); q, r and the feature errors' caps ``cap`` (4,); ``settings`` = [lost_penalty,
    R_s, R_c, collision_penalty, the blocked fraction above which a UAV is occluded, 1 for
    r = exp(-c) (0: -c)].

    Returns (values (3, K, n): tracking, effort, reward; flags (3, K, n) bool: collided, too
    close to a team-mate, occluded; disconnected (K,) bool: the alive UAVs' graph with edges
    <= R_c is split)."""
    lost, r_s, r_c, penalty, occluded_above, exp_shape = (
        settings[0], settings[1], settings[2], settings[3], settings[4], settings[5] != 0.0,
    )  # fmt: skip
    K, n = alive.shape
    values = np.empty((3, K, n))
    flags = np.empty((3, K, n), np.bool_)
    disconnected = np.zeros(K, np.bool_)
    reached = np.empty(n, np.bool_)
    stack = np.empty(n, np.int64)
    e = np.empty(4)
    for k in range(K):
        for i in range(n):
            for a in range(4):
                e[a] = true[k, i, a] - references[k, i, a]
            e[3] = _wrap(e[3])
            for a in range(4):
                e[a] = min(max(e[a], -cap[a]), cap[a])
            if not in_front[k, i]:
                for a in range(3):
                    e[a] = cap[a]
            tracking = e[0] * e[0] * q[0] + e[1] * e[1] * q[1]
            tracking = tracking + e[2] * e[2] * q[2] + e[3] * e[3] * q[3]
            tracking = tracking + lost * (0.0 if detected[k, i] else 1.0)
            effort = u[k, i, 0] * u[k, i, 0] * r[0] + u[k, i, 1] * u[k, i, 1] * r[1]
            effort = effort + u[k, i, 2] * u[k, i, 2] * r[2] + u[k, i, 3] * u[k, i, 3] * r[3]
            too_close = nearest_uav[k, i] < r_s
            collided = (ground[k, i] or obstacle[k, i] or target[k, i] or too_close) and alive[k, i]
            c = tracking + effort
            reward = math.exp(-c) if exp_shape else -c
            values[0, k, i], values[1, k, i] = tracking, effort
            values[2, k, i] = reward - penalty * (1.0 if collided else 0.0)
            flags[0, k, i], flags[1, k, i] = collided, too_close
            flags[2, k, i] = blocked[k, i] > occluded_above
        # the alive UAVs' graph: a search from the first alive one reaches every alive one
        reached[:] = False
        top, first = 0, -1
        for i in range(n):
            if alive[k, i]:
                first = i
                break
        if first >= 0:
            reached[first] = True
            stack[0] = first
            top = 1
        while top:
            top -= 1
            i = stack[top]
            for j in range(n):
                if alive[k, j] and not reached[j] and pair[k, i, j] <= r_c:
                    reached[j] = True
                    stack[top] = j
                    top += 1
        for i in range(n):
            if alive[k, i] and not reached[i]:
                disconnected[k] = True
    return values, flags, disconnected
