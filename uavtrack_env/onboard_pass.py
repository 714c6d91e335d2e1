"""The onboard stacks of a team as arrays: what every UAV takes from a step, in one compiled call.

After the team's UKFs have stepped (`estimation.bank.TrackerBank`), `observe_pass` does for
every UAV that observed: the spells of detector boxes cut by the image border, its team-mates'
messages (the reachable-set bounds of `onboard.NeighbourTable`), the car's exclusion box
(`car_box_arrays`, the arithmetic of `onboard.car_box`) and all its CBF rows (`all_rows` and,
under the lag model, `second_order_rows`, as `safety.cbf.RowBuilder` builds them from a
`SafetyContext`). `observe_step` runs the UKF step (`estimation.bank._bank_step`) and then
`observe_pass` in one call; `observe_frame_step` first builds the input rows and the heard
messages from the env's frame arrays (the shields' route). Per-UAV Python then only wraps slices
of the outputs, lazily (`onboard.OnboardAgent.rows`, ``.context``, ``.belief``).

`TeamState` holds what those steps remember, for every slot of a team (or of K teams): the
neighbour tables, the cut-box spells, the car box's anchor, and each world's obstacle map.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from .estimation.bank import _bank_step
from .safety.barrier_rows import CAP_ROWS, N_FAMILIES, all_rows, make_way
from .safety.cbf import CONNECT, CBFRows
from .safety.qp_arrays import family_lows
from .safety.second_order import second_order_rows
from .target import CAR_HALF_EXTENTS

CAR_DIAG = math.hypot(*CAR_HALF_EXTENTS[:2].tolist())
"""The car footprint's half diagonal (m)."""
CAR_HALF_HEIGHT = float(CAR_HALF_EXTENTS[2])

BOX_COLUMNS = 13
"""`car_box_arrays`'s output row: centre (3), velocity (3), half extents (3), growth (3), stale."""


@numba.njit(cache=True)
def car_box_arrays(
    q, vq, var, steps_since, anchor_q, anchor_var, has_anchor, t_u, t_v, params, out
):  # pragma: no cover (compiled)
    """`onboard.car_box` on arrays: the estimate's position ``q``, velocity ``vq``, position
    variances ``var`` (P[4,4], P[5,5], P[6,6]) and steps since its last detection; the anchor's
    position and variances (``has_anchor``); the cut-box times (s). ``params`` = [target_margin,
    target_sigmas, target_margin_max, target_stale_after, car_on_ground, car_speed, dt]. Writes a
    `BOX_COLUMNS` row into ``out``."""
    margin, sigmas, margin_max, stale_after = params[0], params[1], params[2], params[3]
    on_ground, car_speed, dt = params[4] > 0.5, params[5], params[6]
    diag, c = CAR_DIAG, CAR_HALF_HEIGHT
    stale = steps_since * dt - stale_after
    use_anchor = not (stale <= 0.0 or not has_anchor)
    rq = anchor_q if use_anchor else q
    rv = anchor_var if use_anchor else var
    sigma_p = math.sqrt(max(rv[0], rv[1], rv[2], 0.0))
    pad = min(margin + sigmas * sigma_p, margin_max)
    hxy, hz = diag + pad, c + pad
    g_xy = g_z = 0.0
    bias_speed = 2.0 * car_speed
    if t_u > 0.0:
        hxy += min(bias_speed * t_u, diag)
        g_xy += bias_speed if bias_speed * t_u < diag else 0.0
    if t_v > 0.0:
        hz += min(bias_speed * t_v, c)
        g_z += bias_speed if bias_speed * t_v < c else 0.0
    if on_ground:  # the box spans [<= 0, the car's height + target_margin]
        top, z = 2.0 * c + margin, rq[2]
        hz, g_z = max(top - z, z), 0.0
    if stale > 0.0:  # the reachable set from the anchor, its top included
        hxy += car_speed * stale
        hz += car_speed * stale
        g_xy += car_speed
        g_z += car_speed
    for a in range(3):
        out[a] = rq[a]
        out[3 + a] = 0.0 if stale > 0.0 else vq[a]
    out[6], out[7], out[8] = hxy, hxy, hz
    out[9], out[10], out[11] = g_xy, g_xy, g_z
    out[12] = 1.0 if stale > 0.0 else 0.0


@numba.njit(cache=True)
def take_messages(
    ks, pos, p, v, v_err, age, known, dt, accel, speed, timeout
):  # pragma: no cover (compiled)
    """`NeighbourTable.update` on its arrays, in place: messages ``pos[i]`` from team-mate
    ``ks[i]``."""
    for j in range(age.shape[0]):
        age[j] += 1
    for i in range(ks.shape[0]):
        k = ks[i]
        if known[k]:
            gap = age[k]
            for a in range(3):
                v[k, a] = (pos[i, a] - p[k, a]) / (gap * dt)
            v_err[k] = 0.5 * accel * (gap - 1) * dt
        else:  # first heard: its velocity is unknown within the speed bound
            for a in range(3):
                v[k, a] = 0.0
            v_err[k] = speed
        for a in range(3):
            p[k, a] = pos[i, a]
        age[k] = 0
        known[k] = True
    for j in range(age.shape[0]):
        known[j] = known[j] and age[j] < timeout


@numba.njit(cache=True)
def believe(known, p, v, v_err, age, dt, speed, accel):  # pragma: no cover (compiled)
    """`NeighbourTable.belief`'s arrays for the ``known`` team-mates (``accel`` < 0: none), in
    three blocks (each array returned to Python costs ~0.5 us): [indices, ages] (2, m),
    [positions, velocities] (2, m, 3) and [position radii, velocity radii] (2, m)."""
    ks = np.flatnonzero(known)
    m = ks.shape[0]
    ints = np.empty((2, m), np.int64)
    motion = np.empty((2, m, 3))
    radii = np.zeros((2, m))
    pos, vel, radius, vel_radius = motion[0], motion[1], radii[0], radii[1]
    for i in range(m):
        k = ks[i]
        ints[0, i], ints[1, i] = k, age[k]
        t = age[k] * dt
        for a in range(3):
            vel[i, a] = v[k, a]
            pos[i, a] = p[k, a]
        radius[i] = speed * t
        if accel >= 0.0:
            err = v_err[k]
            s = math.sqrt(v[k, 0] * v[k, 0] + v[k, 1] * v[k, 1] + v[k, 2] * v[k, 2])
            # forward Euler, p(k+1) = p(k) + v(k+1) dt: the drift is a sum, not an integral
            propagated = 0.5 * accel * t * (t + dt) + err * t
            radius[i] = min((speed + s) * t, propagated)
            for a in range(3):
                pos[i, a] = p[k, a] + v[k, a] * t
            vel_radius[i] = min(err + accel * t, 2.0 * speed)
    return ints, motion, radii


@numba.njit(cache=True)
def take_and_believe(
    ks, pos, p, v, v_err, age, known, dt, accel, speed, timeout, believe_accel
):  # pragma: no cover (compiled)
    """`take_messages`, then `believe`: one step of `NeighbourTable.take`."""
    take_messages(ks, pos, p, v, v_err, age, known, dt, accel, speed, timeout)
    return believe(known, p, v, v_err, age, dt, speed, believe_accel)


@numba.njit(cache=True)
def _input_row(
    i, detected, u, v, depth, psi, truncated, position, yaw, velocity, yaw_rate, row
):  # pragma: no cover (compiled)
    """UAV i's `bank.INPUT_COLUMNS` row of flat arrays (N, ...) into ``row``."""
    for a in range(3):
        row[a] = position[i, a]
        row[4 + a] = velocity[i, a]
    row[3], row[7] = yaw[i], yaw_rate[i]
    if detected[i]:
        row[8], row[9], row[10], row[11], row[12] = 1.0, u[i], v[i], depth[i], psi[i]
        row[13] = 1.0 if truncated[i, 0] else 0.0
        row[14] = 1.0 if truncated[i, 1] else 0.0
    else:
        row[8:] = 0.0
        row[11] = 1.0


@numba.njit(cache=True)
def input_rows_of(
    detected, u, v, depth, psi, truncated, position, yaw, velocity, yaw_rate
):  # pragma: no cover (compiled)
    """`onboard.input_rows` of flat arrays (N, ...): (N, 15) `bank.INPUT_COLUMNS` rows."""
    out = np.empty((detected.shape[0], 15))
    for i in range(detected.shape[0]):
        _input_row(
            i, detected, u, v, depth, psi, truncated, position, yaw, velocity, yaw_rate, out[i]
        )
    return out


def max_rows(n_mates: int, n_obstacles: int) -> int:
    """The most CBF rows one UAV can have: uav, connect and occlusion per team-mate, obstacle
    and occlusion per box, the car, the floor and the speed cap."""
    return 3 * n_mates + 2 * n_obstacles + 2 + CAP_ROWS


@numba.njit(cache=True)
def observe_pass(
    slots, team_n, data, heard, sent, est_slots, est_x, est_P, est_ready, est_counts,
    nb_p, nb_v, nb_err, nb_age, nb_known, uncut, cut_steps, anchor, has_anchor, obs_c, obs_h,
    obs_n, table_p, box_p, row_p, flags, gammas, margins, second_p,
    out_A, out_f, out_i, out_start, out_sizes, out_belief_i, out_belief_f, out_box, out_lows,
):  # fmt: skip  # pragma: no cover (compiled)
    """One step of what the UAVs ``slots`` (slot = world team_n + index in its team) know,
    in place, and their rows.

    Inputs per UAV j: its `bank.INPUT_COLUMNS` row ``data[j]`` (own state, detector flags); the
    messages it heard, ``heard[j, i]`` from team member i of its world w, with position
    ``sent[w, i]``; its estimate: row ``est_slots[j]`` of a `estimation.bank.TrackerBank`'s state
    (x, P, ready, counts: steps since detection first). State per slot: the neighbour tables
    ``nb_*`` (`NeighbourTable`), the cut-box spells ``uncut``/``cut_steps``, the car box's
    ``anchor`` (position, variances); per world: obstacles ``obs_c/obs_h[:obs_n]``.

    ``table_p`` = [dt, accel (the lag model's a_max, 0: none), speed bound, timeout, believe's
    accel (-1: none)]; ``box_p``: `car_box_arrays`'s params then [recovery steps, pad cut
    boxes]; ``row_p`` = [d_s, r_s, r_c, alpha_v, clearance, z_min, theta*, point mode, team-mates'
    occluder half size];
    ``flags`` = [box obstacles, car as obstacle, occlusion rows, moving-target occlusion,
    occlusion size margin, make way] (`safety.cbf.RowBuilder.pass_params`); ``second_p``:
    `second_order.second_order_rows`' params (lag_tau > 0: the rows are second order).

    Outputs: the rows of UAV j at ``out_start[j]:out_start[j + 1]`` of ``out_A`` (., 3),
    ``out_f`` (5, .) = [b, h, gamma, drift, margin] and ``out_i`` (2, .) = [kind, index], its
    family sizes ``out_sizes[j]``; its believed team-mates ``out_belief_i[j]`` = [count, table
    indices..., ages...] and ``out_belief_f[j]`` = [positions (3 k), velocities (3 k), radii
    (k), velocity radii (k)]; its car box ``out_box[j]`` (`BOX_COLUMNS`, NaN without estimate);
    the least h of each row family, then of the hard rows, ``out_lows[j]`` (`family_lows`).
    """
    dt, accel, speed = table_p[0], table_p[1], table_p[2]
    timeout, believe_accel = int(table_p[3]), table_p[4]
    recovery, pad_cut = int(box_p[7]), box_p[8] > 0.5
    box_model, car_rows, occlusion = flags[0], flags[1], flags[2]
    moving, size_margin, way = flags[3], flags[4], flags[5]
    d_s, r_s, r_c, alpha_v = row_p[0], row_p[1], row_p[2], row_p[3]
    clearance, z_min, theta_star, mode = row_p[4], row_p[5], row_p[6], int(row_p[7])
    mate_half = row_p[8]
    zeros3 = np.zeros(3)
    r = 0
    for j in range(slots.shape[0]):
        s = slots[j]
        w, me = s // team_n, s % team_n
        row = data[j]
        detected = row[8] > 0.5
        for axis in range(2):  # the spells of boxes cut by the image border (`car_box`)
            if detected:
                uncut[s, axis] = 0 if row[13 + axis] > 0.5 else min(uncut[s, axis] + 1, recovery)
            cut_steps[s, axis] = cut_steps[s, axis] + 1 if uncut[s, axis] < recovery else 0
        count = 0
        for i in range(team_n):
            count += i != me and heard[j, i]
        ks, pos = np.empty(count, np.int64), np.empty((count, 3))
        count = 0
        for i in range(team_n):
            if i != me and heard[j, i]:
                ks[count] = i - (i > me)  # the index in its table, which skips itself
                pos[count] = sent[w, i]
                count += 1
        ints, motion, radii = take_and_believe(
            ks, pos, nb_p[s], nb_v[s], nb_err[s], nb_age[s], nb_known[s], dt, accel, speed,
            timeout, believe_accel,
        )  # fmt: skip
        k = ints.shape[1]
        out_belief_i[j, 0] = k
        out_belief_i[j, 1 : 1 + k] = ints[0]
        out_belief_i[j, 1 + k : 1 + 2 * k] = ints[1]
        out_belief_f[j, : 3 * k] = motion[0].ravel()
        out_belief_f[j, 3 * k : 6 * k] = motion[1].ravel()
        out_belief_f[j, 6 * k : 7 * k] = radii[0]
        out_belief_f[j, 7 * k : 8 * k] = radii[1]
        box = out_box[j]
        e = est_slots[j]
        car = est_ready[e]
        if car:
            t_u = cut_steps[s, 0] * dt if pad_cut else 0.0
            t_v = cut_steps[s, 1] * dt if pad_cut else 0.0
            var = np.empty(3)
            for a in range(3):
                var[a] = est_P[e, 4 + a, 4 + a]
            car_box_arrays(
                est_x[e, 4:7], est_x[e, 7:10], var, est_counts[e, 0], anchor[s, :3],
                anchor[s, 3:], has_anchor[s], t_u, t_v, box_p, box,
            )  # fmt: skip
            if box[12] == 0.0:  # a fresh box: the anchor of a later reachable set
                anchor[s, :3] = est_x[e, 4:7]
                anchor[s, 3:] = var
                has_anchor[s] = True
            q, vq, half, growth = box[0:3], box[3:6], box[6:9], box[9:12]
        else:
            box[:] = np.nan
            q, vq, half, growth = zeros3, zeros3, zeros3, zeros3
        m = obs_n[w]
        centers, halves = obs_c[w, :m], obs_h[w, :m]
        rho = radii[0]
        if way and car and car_rows and k:
            rho = make_way(row[0:3], motion[0], rho, q, half, 0.0, clearance, r_s)
        A, floats, ints2, sizes = all_rows(
            row[0:3], motion[0], rho, centers, halves, box_model, car and car_rows,
            q, vq, half, 0.0, growth, car and box[12] > 0.5, d_s, r_s, r_c, alpha_v, clearance,
            z_min, car and occlusion, theta_star, mode, moving, size_margin, gammas,
            margins, radii[0] if second_p[0] <= 0.0 else radii[0][:0],
            motion[1] if second_p[0] > 0.0 else np.zeros_like(motion[1]), mate_half,
        )  # fmt: skip
        if second_p[0] > 0.0:
            floats[0] = second_order_rows(
                A, floats[1], floats[0], floats[4], ints2[0], ints2[1], sizes, row[4:7],
                motion[1], vq, 0.0, growth, car and box[12] > 0.5, True, rho, True,
                radii[1], second_p,
            )  # fmt: skip
        n = A.shape[0]
        out_start[j] = r
        out_A[r : r + n] = A
        out_f[:, r : r + n] = floats
        out_i[:, r : r + n] = ints2
        out_sizes[j, : N_FAMILIES + 1] = sizes
        out_lows[j] = family_lows(ints2[0], floats[1], N_FAMILIES + 1, CONNECT)
        r += n
    out_start[slots.shape[0]] = r


@numba.njit(cache=True)
def observe_step(
    slots, team_n, data, heard, sent, bank_args, out_x, out_P, team_arrays, params, outs
):  # fmt: skip  # pragma: no cover (compiled)
    """The UAVs' UKF step (`estimation.bank._bank_step` with the bank's ``kernel_args``; bank
    slot = team slot) and then their `observe_pass` (``team_arrays``: `TeamState.arrays`,
    ``params``: its table_p to second_p, ``outs``: its outputs), in one compiled call."""
    _bank_step(slots, data, *bank_args, out_x, out_P)
    x, P, ready, counts = bank_args[0], bank_args[1], bank_args[2], bank_args[4]
    observe_pass(
        slots, team_n, data, heard, sent, slots, x, P, ready, counts, *team_arrays, *params,
        *outs,
    )  # fmt: skip


@numba.njit(cache=True)
def observe_frame_step(
    uavs, frame, slots, team_n, data, received, sent, bank_args, out_x, out_P, team_arrays,
    params, outs,
):  # fmt: skip  # pragma: no cover (compiled)
    """`observe_step` of the UAVs ``uavs`` of a frame, with `observe_step`'s arguments but for
    ``data``, which it fills (row j is UAV ``uavs[j]``'s of ``frame`` = (detected, u, v, depth,
    psi, truncated, position, yaw, velocity, yaw_rate), flat arrays (N, ...), `input_rows_of`),
    and ``received`` (N, team_n) in place of ``heard``: UAV j heard ``received[uavs[j]]``."""
    heard = np.empty((uavs.shape[0], received.shape[1]), np.bool_)
    for j in range(uavs.shape[0]):
        _input_row(uavs[j], *frame, data[j])
        heard[j] = received[uavs[j]]
    observe_step(
        slots, team_n, data, heard, sent, bank_args, out_x, out_P, team_arrays, params, outs
    )


class PassOutput(NamedTuple):
    """`observe_pass`'s input rows and outputs for m UAVs (its docstring)."""

    data: np.ndarray
    """(m, 15) the UAVs' `estimation.bank.INPUT_COLUMNS` rows."""
    A: np.ndarray
    floats: np.ndarray
    ints: np.ndarray
    start: np.ndarray
    sizes: np.ndarray
    belief_ints: np.ndarray
    belief_floats: np.ndarray
    box: np.ndarray
    lows: np.ndarray

    def rows(self, j: int) -> CBFRows:
        """UAV j's rows (views of the arrays)."""
        a, b = self.start[j], self.start[j + 1]
        f, i = self.floats[:, a:b], self.ints[:, a:b]
        return CBFRows(self.A[a:b], f[0], f[1], f[2], f[3], f[4], i[0], i[1])

    @classmethod
    def allocate(cls, data: np.ndarray, n_mates: int, n_obstacles: int) -> PassOutput:
        """Room for the outputs of ``len(data)`` UAVs."""
        m = len(data)
        rows = m * max_rows(n_mates, n_obstacles)
        return cls(
            data, np.empty((rows, 3)), np.empty((5, rows)), np.empty((2, rows), np.int64),
            np.empty(m + 1, np.int64), np.zeros((m, N_FAMILIES + 1), np.int64),
            np.zeros((m, 1 + 2 * n_mates), np.int64), np.zeros((m, 8 * n_mates)),
            np.empty((m, BOX_COLUMNS)), np.empty((m, N_FAMILIES + 2)),
        )  # fmt: skip


class TeamState:
    """What the onboard stacks of ``size`` slots (``worlds`` teams of ``n`` UAVs, slot = world
    n + index) remember between steps, as arrays `observe_pass` updates in place."""

    def __init__(self, n: int, worlds: int = 1) -> None:
        self.n, self.worlds = n, worlds
        size, mates = n * worlds, max(n - 1, 0)
        self.nb_p = np.zeros((size, mates, 3))
        self.nb_v = np.zeros((size, mates, 3))
        self.nb_err = np.zeros((size, mates))
        self.nb_age = np.zeros((size, mates), np.int64)
        self.nb_known = np.zeros((size, mates), bool)
        self.uncut = np.zeros((size, 2), np.int64)
        self.cut_steps = np.zeros((size, 2), np.int64)
        self.anchor = np.zeros((size, 6))
        self.has_anchor = np.zeros(size, bool)
        self.obs_c = np.zeros((worlds, 0, 3))
        self.obs_h = np.zeros((worlds, 0, 3))
        self.obs_n = np.zeros(worlds, np.int64)

    def arrays(self) -> tuple[np.ndarray, ...]:
        """`observe_pass`'s state arguments, nb_p to obs_n."""
        return (
            self.nb_p, self.nb_v, self.nb_err, self.nb_age, self.nb_known, self.uncut,
            self.cut_steps, self.anchor, self.has_anchor, self.obs_c, self.obs_h, self.obs_n,
        )  # fmt: skip

    def set_map(self, world: int, centers: np.ndarray, half: np.ndarray) -> None:
        """World ``world``'s known obstacles (m, 3) centres and half extents."""
        m = len(centers)
        if m > self.obs_c.shape[1]:
            grown = np.zeros((self.worlds, m, 3)), np.zeros((self.worlds, m, 3))
            grown[0][:, : self.obs_c.shape[1]] = self.obs_c
            grown[1][:, : self.obs_h.shape[1]] = self.obs_h
            self.obs_c, self.obs_h = grown
        self.obs_c[world, :m], self.obs_h[world, :m] = centers, half
        self.obs_n[world] = m
