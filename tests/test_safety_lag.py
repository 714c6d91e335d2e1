"""Second-order CBF rows for a velocity-lag plant (``ShieldOptions.lag_tau``; not in the paper).

Each row must equal tau (psi-dot + psi / tau) with psi = h-dot + gamma1 h along the lag dynamics
v-dot = (u - v) / tau (finite differences), and in closed loop with the env's lag model the
barriers must stay >= 0 where the first-order rows of the paper let them go negative.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import car_h, growing_car_case
from uavtrack_env.config import DynamicsConfig
from uavtrack_env.dynamics import integrate
from uavtrack_env.geometry import world_to_cam_vec
from uavtrack_env.safety import SafetyContext, SafetyFilter, build_rows
from uavtrack_env.safety.cbf import (
    CONNECT,
    DEFAULT_CAR_HALF_EXTENTS,
    FLOOR,
    OBSTACLE,
    TARGET,
    UAV,
    h_box,
)
from uavtrack_env.safety.config import CBFConfig

TAU = 0.25
EPS = 1e-4
CBF = CBFConfig().resolve()


def hocbf_rate(h_of_t, gamma1: float) -> float:
    """tau (psi-dot + psi / tau) at t = 0 with psi = h-dot + gamma1 h (central differences)."""
    h0, hp, hm = h_of_t(0.0), h_of_t(EPS), h_of_t(-EPS)
    hdot, hddot = (hp - hm) / (2 * EPS), (hp - 2 * h0 + hm) / EPS**2
    return TAU * hddot + (TAU * gamma1 + 1.0) * hdot + gamma1 * h0


def path(p, v, u):
    """Position along the lag dynamics from (p, v) under the constant command u (2nd order)."""
    a = (u - v) / TAU
    return lambda t: p + v * t + 0.5 * a * t * t


def rows_of(ctx, kind):
    rows = build_rows(ctx, CBF, lag_tau=TAU)
    sel = np.flatnonzero(rows.kind == kind)
    assert len(sel) > 0, f"no rows of kind {kind}"
    return rows, sel


def pair_case(rng: np.random.Generator):
    """Two UAVs' positions, velocities, commands and the contexts each one sees."""
    p = [rng.uniform(-2, 2, 3) + [0, 0, 3], None]
    p[1] = p[0] + rng.normal(size=3) * 2.5
    v = [rng.uniform(-3, 3, 3) for _ in range(2)]
    u = [rng.uniform(-5, 5, 3) for _ in range(2)]
    ctx = [
        SafetyContext(
            position=p[i],
            yaw=0.0,
            neighbours=[p[1 - i]],
            velocity=v[i],
            neighbour_velocities=[v[1 - i]],
        )
        for i in range(2)
    ]
    return p, v, u, ctx


PAIR_GAMMA = {UAV: CBF.gamma_s, CONNECT: CBF.gamma_c}


def pair_rate(p, v, u, kind) -> float:
    """The HOCBF condition of the pair's collision (20) or connectivity (29) barrier when the
    two UAVs fly the commands ``u`` from (p, v)."""
    traj = [path(p[i], v[i], u[i]) for i in range(2)]

    def h(t):
        d2 = np.sum((traj[0](t) - traj[1](t)) ** 2)
        return d2 - CBF.r_s**2 if kind == UAV else CBF.r_c**2 - d2

    return hocbf_rate(h, PAIR_GAMMA[kind])


def own_slack(ctx, kind, u) -> float:
    """b - A u of the pair row of ``kind`` (without the margin)."""
    rows, sel = rows_of(ctx, kind)
    r = sel[0]
    return rows.b[r] + rows.margin[r] - rows.A[r] @ u


@pytest.mark.parametrize("seed", range(12))
def test_pair_rows_split_the_second_order_condition(seed):
    """UAV-UAV (20) and connectivity (29), each UAV using only its own command: the two rows
    add up to the HOCBF condition of the pair (the split of (23)) while the pair needs no
    braking; when it does (need < 0), each row alone is the whole condition with the
    team-mate's command at its velocity (each UAV brakes for the pair)."""
    rng = np.random.default_rng(600 + seed)
    p, v, u, ctx = pair_case(rng)
    for kind in (UAV, CONNECT):
        rate = pair_rate(p, v, u, kind)
        need = pair_rate(p, v, v, kind)  # the condition with both commands at their velocities
        total = sum(own_slack(ctx[i], kind, u[i]) for i in range(2))
        if need >= 0.0:
            assert total == pytest.approx(rate, rel=1e-5, abs=1e-5)
        else:  # each row asks for the whole braking: both rows met leave the pair -need > 0
            assert rate == pytest.approx(total - need, rel=1e-5, abs=1e-5)
            for i in range(2):
                alone = [u[0], u[1]]
                alone[1 - i] = v[1 - i]
                assert own_slack(ctx[i], kind, u[i]) == pytest.approx(
                    pair_rate(p, v, alone, kind), rel=1e-5, abs=1e-5
                )


def test_one_uav_keeps_a_closing_pair_safe_when_its_team_mate_cannot_brake():
    """Two UAVs closing fast at R_s + 1 m; one is pinned (its command stays at its velocity,
    as when a fallback gives its pair row up). The other's row alone keeps the pair's
    condition: the closest command meeting it, applied with the pinned one coasting, gives a
    non-negative HOCBF rate."""
    p = [np.array([0.0, 0.0, 3.0]), np.array([CBF.r_s + 1.0, 0.0, 3.0])]
    v = [np.array([2.0, 0.0, 0.0]), np.zeros(3)]
    ctx = SafetyContext(
        position=p[0], yaw=0.0, neighbours=[p[1]], velocity=v[0], neighbour_velocities=[v[1]]
    )
    rows, sel = rows_of(ctx, UAV)
    a, b = rows.A[sel[0]], rows.b[sel[0]] + rows.margin[sel[0]]
    u0 = v[0] - (a @ v[0] - b) / (a @ a) * a  # the projection of coasting onto the row
    assert pair_rate(p, v, v, UAV) < 0.0  # the pair must brake
    assert pair_rate(p, v, [u0, v[1]], UAV) >= -1e-6


@pytest.mark.parametrize("seed", range(5))
def test_static_and_target_rows_equal_the_second_order_condition(seed):
    """Box obstacles, the floor and the moving car: b - A u = tau (psi-dot + psi / tau)."""
    rng = np.random.default_rng(700 + seed)
    p = rng.uniform(-1, 1, 3) + [0, 0, 3]
    v, u = rng.uniform(-3, 3, 3), rng.uniform(-5, 5, 3)
    centers = p + rng.uniform(-3, 3, (3, 3))
    half = rng.uniform(0.3, 1.2, (3, 3))
    q, vq, heading = p + rng.uniform(-4, 4, 3), rng.uniform(-2, 2, 3), rng.uniform(-3, 3)
    ctx = SafetyContext(
        position=p,
        yaw=0.0,
        obstacle_centers=centers,
        obstacle_half_extents=half,
        target_position=q,
        target_velocity=vq,
        target_heading=heading,
        velocity=v,
    )
    me = path(p, v, u)
    c = CBF.obstacle_clearance
    car = np.array(DEFAULT_CAR_HALF_EXTENTS)
    cases = {
        OBSTACLE: (CBF.gamma_obstacle, lambda j, t: h_box(me(t), centers[j], half[j], c)[0]),
        FLOOR: (CBF.gamma_z, lambda j, t: me(t)[2] - CBF.z_min),
        TARGET: (
            CBF.gamma_obstacle,
            lambda j, t: h_box(me(t), q + vq * t, car, c, heading, grounded=True)[0],
        ),
    }
    for kind, (gamma1, h_of) in cases.items():
        rows, sel = rows_of(ctx, kind)
        for r in sel:
            j = rows.index[r]
            expected = hocbf_rate(lambda t, j=j, h_of=h_of: h_of(j, t), gamma1)
            assert rows.b[r] - rows.A[r] @ u == pytest.approx(expected, rel=1e-5, abs=1e-5)


def _at_corner(p, q, half, heading) -> bool:
    """p is beside a corner of the footprint (outside it along both axes)."""
    c, s = np.cos(heading), np.sin(heading)
    d = p - q
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    return bool((np.abs(local) > half[:2]).all())


@pytest.mark.parametrize("frustum", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_a_growing_car_box_row_equals_the_second_order_condition(seed, frustum):
    """A stale car's box with faces moving out per axis: b - A u = tau (psi-dot + psi / tau)
    with h of the growing box, or of its frustum (no curvature: exact beside a face and over
    the footprint, at most that beside a corner, where the frustum is convex)."""
    rng = np.random.default_rng(750 + seed)
    q, heading, half, growth, p = growing_car_case(rng)
    v, u = rng.uniform(-3, 3, 3), rng.uniform(-5, 5, 3)
    ctx = SafetyContext(
        position=p,
        yaw=0.0,
        target_position=q,
        target_half_extents=half,
        target_heading=heading,
        target_growth=growth,
        target_frustum=frustum,
        velocity=v,
    )
    me, cl = path(p, v, u), CBF.obstacle_clearance
    rows, sel = rows_of(ctx, TARGET)

    def h_of(t: float) -> float:
        args = (me(t), q, half + growth * t, cl, heading)
        return car_h(*args) if frustum else h_box(*args, grounded=True)[0]

    expected = hocbf_rate(h_of, CBF.gamma_obstacle)
    r = sel[0]
    got = rows.b[r] - rows.A[r] @ u
    if frustum and _at_corner(p, q, half, heading):
        assert got <= expected + 1e-5
    else:
        assert got == pytest.approx(expected, rel=1e-5, abs=1e-5)


def test_second_order_rows_need_the_velocity():
    ctx = SafetyContext(position=[0, 0, 3], yaw=0.0)
    with pytest.raises(ValueError, match="velocity"):
        build_rows(ctx, CBF, lag_tau=TAU)
    with pytest.raises(ValueError, match="lag_tau"):
        SafetyFilter(lag_tau=-1.0)
    with pytest.raises(ValueError, match="neighbour_velocities"):
        SafetyContext(position=[0, 0, 3], yaw=0.0, neighbours=[[1, 0, 3]], neighbour_velocities=[])


def _closed_loop(lag_tau: float, speed: float, scenario: str) -> float:
    """Least barrier value over 2,000 steps of the env's lag model under a nominal that drives
    into the danger: two UAVs head-on ('pair'), a dive ('floor'), a box ram ('box')."""
    dyn, dt = DynamicsConfig(model="lag"), 1.0 / 80.0
    shield = SafetyFilter(lag_tau=lag_tau)
    n = 2 if scenario == "pair" else 1
    pos = np.array([[0.0, 0.0, 3.0], [8.0, 0.3, 3.0]])[:n]
    yaw, vel, w = np.zeros(n), np.zeros((n, 3)), np.zeros(n)
    prev = pos.copy()
    box_c, box_h = np.array([[6.0, 0.2, 1.0]]), np.array([[1.0, 1.0, 1.0]])
    worst = np.inf
    for _ in range(2000):
        us = []
        for i in range(n):
            if scenario == "pair":
                goal = pos[1 - i]
                ctx = SafetyContext(
                    position=pos[i],
                    yaw=yaw[i],
                    neighbours=[pos[1 - i]],
                    velocity=vel[i],
                    neighbour_velocities=[(pos[1 - i] - prev[1 - i]) / dt],
                )
            else:
                goal = box_c[0] if scenario == "box" else np.array([0.0, 0.0, -5.0])
                ctx = SafetyContext(
                    position=pos[i],
                    yaw=yaw[i],
                    obstacle_centers=box_c,
                    obstacle_half_extents=box_h,
                    velocity=vel[i],
                )
            d = (goal - pos[i]) / np.linalg.norm(goal - pos[i])
            u, _ = shield.certify(np.r_[world_to_cam_vec(speed * d, yaw[i]), 0.0], ctx)
            us.append(u)
        prev = pos.copy()
        pos, yaw, vel, w = integrate(pos, yaw, vel, w, np.array(us), dyn, dt)
        if scenario == "pair":
            h = np.sum((pos[0] - pos[1]) ** 2) - CBF.r_s**2
        elif scenario == "box":
            h = h_box(pos[0], box_c, box_h, CBF.obstacle_clearance)[0]
        else:
            h = pos[0, 2] - CBF.z_min
        worst = min(worst, float(h))
    return worst


@pytest.mark.parametrize("scenario", [pytest.param("pair", marks=pytest.mark.slow), "box", "floor"])
def test_second_order_rows_keep_the_lagged_plant_safe(scenario):
    """With the env's lag (tau = 0.25 s, |a| <= 6 m/s^2) the first-order rows let every barrier
    go negative; the second-order rows keep it >= 0."""
    assert _closed_loop(0.0, 5.0, scenario) < -0.05
    for speed in (1.0, 5.0):
        assert _closed_loop(TAU, speed, scenario) >= -1e-9


@pytest.mark.parametrize("speed", [3.0, 5.0])
def test_a_uav_stops_short_of_a_team_mate_that_does_not_brake(speed):
    """Under the env's lag model a shielded UAV flies at ``speed`` at a hovering team-mate that
    does not brake for the pair (a fallback gave its pair row up): it stops outside R_s."""
    dyn, dt = DynamicsConfig(model="lag"), 1.0 / 80.0
    shield = SafetyFilter(lag_tau=TAU, accel_bound=dyn.a_max)
    pos = np.array([[0.0, 0.0, 3.0], [8.0, 0.3, 3.0]])
    yaw, vel, w = np.zeros(2), np.zeros((2, 3)), np.zeros(2)
    worst = np.inf
    for _ in range(600):
        ctx = SafetyContext(
            position=pos[0], yaw=0.0, neighbours=[pos[1]], velocity=vel[0],
            neighbour_velocities=[vel[1]],
        )  # fmt: skip
        d = (pos[1] - pos[0]) / np.linalg.norm(pos[1] - pos[0])
        u, _ = shield.certify(np.r_[world_to_cam_vec(speed * d, 0.0), 0.0], ctx)
        pos, yaw, vel, w = integrate(pos, yaw, vel, w, np.array([u, np.zeros(4)]), dyn, dt)
        worst = min(worst, float(np.linalg.norm(pos[0] - pos[1])))
    assert CBF.r_s <= worst < CBF.r_s + 1.0  # it came close, and stopped outside R_s


def test_a_pair_braking_row_counts_on_one_uavs_deceleration():
    """A UAV closing at 3 m/s on a team-mate at rest 3 m outside R_s: its pair row is the
    braking-distance row with its own deceleration a (`RowBuilder.brake_decel`), s_b = s - w^2
    / (2 a), not with the pair's 2a (the team-mate may have given the row up), which here
    would be looser than the second-order row."""
    w, gap = 3.0, 3.0
    ctx = SafetyContext(
        position=[0.0, 0.0, 3.0], yaw=0.0, neighbours=[[CBF.r_s + gap, 0.0, 3.0]],
        velocity=[w, 0.0, 0.0], neighbour_velocities=[[0.0, 0.0, 0.0]],
    )  # fmt: skip
    shield = SafetyFilter(lag_tau=TAU, accel_bound=6.0)
    rows = shield.rows(ctx)
    r = np.flatnonzero(rows.kind == UAV)[0]
    a, norm, gamma = shield.row_builder.brake_decel, np.linalg.norm(rows.A[r]), CBF.gamma_s
    assert norm == pytest.approx(2 * (CBF.r_s + gap)) and shield.cbf.gamma_s == gamma
    s = CBF.r_s + gap - shield.cbf.r_s  # the shield's R_s carries its margin
    one, both = (
        norm * (w + TAU * a * (gamma * (s - w * w / (2 * d)) / w - 1.0)) for d in (a, 2 * a)
    )
    second = SafetyFilter(lag_tau=TAU).rows(ctx)  # no braking rows
    assert one < second.b[r] + second.margin[r] < both
    assert rows.b[r] + rows.margin[r] == pytest.approx(one, rel=1e-12)


def test_a_link_braking_row_counts_on_one_uavs_deceleration():
    """A UAV leaving at 3 m/s a team-mate at rest 4 m inside R_c: its link row is the
    braking-distance row with its own deceleration a, s_b = s - w^2 / (2 a), not 2a (looser
    here, and tighter than the second-order row). A team-mate whose link row takes slack
    (connectivity is soft) does not brake for it."""
    w, gap = 3.0, 4.0
    ctx = SafetyContext(
        position=[0.0, 0.0, 3.0], yaw=0.0, neighbours=[[CBF.r_c - gap, 0.0, 3.0]],
        velocity=[-w, 0.0, 0.0], neighbour_velocities=[[0.0, 0.0, 0.0]],
    )  # fmt: skip
    shield = SafetyFilter(lag_tau=TAU, accel_bound=6.0)
    rows = shield.rows(ctx)
    r = np.flatnonzero(rows.kind == CONNECT)[0]
    a, norm, gamma = shield.row_builder.brake_decel, np.linalg.norm(rows.A[r]), CBF.gamma_c
    assert norm == pytest.approx(2 * (CBF.r_c - gap))
    s = shield.cbf.r_c - (CBF.r_c - gap)  # the shield's R_c carries its margin
    one, both = (
        norm * (w + TAU * a * (gamma * (s - w * w / (2 * d)) / w - 1.0)) for d in (a, 2 * a)
    )
    second = SafetyFilter(lag_tau=TAU).rows(ctx)  # no braking rows
    assert one < both < second.b[r] + second.margin[r]
    assert rows.b[r] + rows.margin[r] == pytest.approx(one, rel=1e-12)
