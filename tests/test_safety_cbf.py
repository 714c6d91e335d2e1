"""CBF rows (paper eqs. 20-45) against finite differences of their barrier functions."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from tests.conftest import car_h, car_inside, growing_car_case
from uavtrack_env.config import EnvConfig
from uavtrack_env.geometry import cam_to_world, segment_hits_boxes
from uavtrack_env.safety import SafetyContext, SafetyFilter, build_rows, check_eq28
from uavtrack_env.safety.barrier_rows import target_row
from uavtrack_env.safety.cbf import (
    CONNECT,
    FLOOR,
    OBSTACLE,
    OCCLUSION,
    TARGET,
    UAV,
    RowBuilder,
    h_box,
)
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.occlusion import occluder_points

EPS = 1e-6


def box_h(p, center, half, clearance, yaw=0.0, grounded=False):
    """Independent reference: squared distance to a (yawed) box minus clearance^2 (outside);
    inside minus the squared depth, or for a ``grounded`` box (the car) `car_inside`."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(p) - center
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
    out = np.maximum(np.abs(local) - half, 0.0)
    if (np.abs(local) < half).all():
        if grounded:
            return car_inside(p, center, half, clearance, yaw) - clearance**2
        depth = np.min(half - np.abs(local))
        return -(depth**2) - clearance**2
    return out @ out - clearance**2


def car_box_h(p, center, half, clearance, yaw=0.0):
    """`box_h` of the car's grounded box."""
    return box_h(p, center, half, clearance, yaw, grounded=True)


def occl_h(p, p_o, n, theta_star):
    d = p_o - p
    x = d @ n / (np.linalg.norm(d) * np.linalg.norm(n))
    return np.arccos(np.clip(x, -1, 1)) - theta_star


def random_context(rng, occlusion_model="paper", moving=True):
    p = np.array([0.0, 0.0, 3.0]) + rng.uniform(-1, 1, 3)
    nb = p + rng.uniform(-12, 12, (3, 3))
    centers = p + np.c_[rng.uniform(-8, 8, (5, 2)), rng.uniform(-2, 2, 5)]
    half = rng.uniform(0.3, 1.5, (5, 3))
    q = p + np.array([18.0, 0.0, -2.0]) + rng.uniform(-2, 2, 3)
    vq = rng.uniform(-3, 3, 3) if moving else np.zeros(3)
    return SafetyContext(
        position=p,
        yaw=rng.uniform(-np.pi, np.pi),
        neighbours=nb,
        obstacle_centers=centers,
        obstacle_half_extents=half,
        target_position=q,
        target_velocity=vq,
        target_heading=rng.uniform(-np.pi, np.pi),
    )


def fd_rate(h_of_t):
    """Central difference of h(t) at t = 0."""
    return (h_of_t(EPS) - h_of_t(-EPS)) / (2 * EPS)


def check_family(rows, kind, h_of, rng, trials=5):
    """For each row of `kind`: h matches h_of(0) and -A V + drift == d/dt h along V."""
    sel = np.flatnonzero(rows.kind == kind)
    assert len(sel) > 0, f"no rows of kind {kind}"
    for r in sel:
        j = rows.index[r]
        assert rows.h[r] == pytest.approx(h_of(j, np.zeros(3), 0.0), rel=1e-9, abs=1e-9)
        for _ in range(trials):
            V = rng.uniform(-10, 10, 3)
            fd = fd_rate(lambda t, j=j, V=V: h_of(j, V, t))
            assert -rows.A[r] @ V + rows.drift[r] == pytest.approx(fd, rel=1e-5, abs=1e-5)
        assert rows.b[r] == pytest.approx(
            rows.gamma[r] * rows.h[r] + rows.drift[r] - rows.margin[r], rel=1e-12
        )


@pytest.mark.parametrize("seed", range(6))
def test_collision_connectivity_floor_rows_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    cbf = CBFConfig().resolve()
    ctx = random_context(rng)
    rows = build_rows(ctx, cbf, connectivity_margin=0.3)
    p, nb = ctx.position, ctx.neighbours
    check_family(rows, UAV, lambda j, V, t: np.sum((p + t * V - nb[j]) ** 2) - cbf.r_s**2, rng)
    check_family(rows, CONNECT, lambda j, V, t: cbf.r_c**2 - np.sum((p + t * V - nb[j]) ** 2), rng)
    check_family(rows, FLOOR, lambda j, V, t: p[2] + t * V[2] - cbf.z_min, rng)
    # The distributed split (23)-(24) halves gamma_s; (32) halves gamma_c and carries the margin.
    assert np.allclose(rows.gamma[rows.kind == UAV], cbf.gamma_s / 2)
    assert np.allclose(rows.gamma[rows.kind == CONNECT], cbf.gamma_c / 2)
    assert np.allclose(rows.margin[rows.kind == CONNECT], 0.3)


@pytest.mark.parametrize("seed", range(6))
def test_obstacle_and_moving_target_rows_match_finite_differences(seed):
    rng = np.random.default_rng(100 + seed)
    cbf = CBFConfig().resolve()
    ctx = random_context(rng)
    # put the UAV inside one obstacle to exercise the penetration branch too
    centers = ctx.obstacle_centers.copy()
    centers[0] = ctx.position + rng.uniform(-0.1, 0.1, 3)
    ctx = dataclasses.replace(
        ctx, obstacle_centers=centers, obstacle_half_extents=np.full((5, 3), 1.0)
    )
    p, c = ctx.position, ctx.obstacle_centers
    half, cl = ctx.obstacle_half_extents, cbf.obstacle_clearance
    rows = build_rows(ctx, cbf, obstacle_model="box")
    check_family(rows, OBSTACLE, lambda j, V, t: box_h(p + t * V, c[j], half[j], cl), rng)
    assert rows.h[rows.kind == OBSTACLE][0] < 0  # inside
    q, vq, hq, th = (
        ctx.target_position,
        ctx.target_velocity,
        ctx.target_half_extents,
        ctx.target_heading,
    )
    check_family(rows, TARGET, lambda j, V, t: car_box_h(p + t * V, q + t * vq, hq, cl, th), rng)
    assert rows.drift[rows.kind == TARGET][0] != 0.0  # the target's motion enters b

    rows = build_rows(ctx, cbf, obstacle_model="point")
    check_family(rows, OBSTACLE, lambda j, V, t: np.sum((p + t * V - c[j]) ** 2) - cbf.r_s**2, rng)


@pytest.mark.parametrize("frustum", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_a_growing_car_box_row_matches_finite_differences(seed, frustum):
    """A box whose faces move out at a speed per axis (a stale car's reachable set): drift =
    d/dt h, of the box and of its frustum, with the box growing, from beside, above, a corner
    and inside."""
    rng = np.random.default_rng(900 + seed)
    cbf = CBFConfig().resolve()
    cl = cbf.obstacle_clearance
    q, th, half, growth, p = growing_car_case(rng)
    vq = rng.uniform(-1, 1, 3)
    ctx = SafetyContext(
        position=p,
        yaw=0.0,
        target_position=q,
        target_velocity=vq,
        target_half_extents=half,
        target_heading=th,
        target_growth=growth,
        target_frustum=frustum,
    )
    rows = build_rows(ctx, cbf)
    ref = car_h if frustum else car_box_h
    check_family(
        rows,
        TARGET,
        lambda j, V, t: ref(p + t * V, q + t * vq, half + t * growth, cl, th),
        rng,
    )


def test_target_row_near_box_surface_and_rotated():
    """A UAV beside the long side of a yawed car at half its height, in closed form: the box's
    h = gap^2 - c^2 with its gradient away from the car; the frustum's h = gap - half height -
    sqrt(2) c with its gradient half away from the car, half up."""
    cbf = CBFConfig().resolve()
    heading = 0.7
    left = np.array([-np.sin(heading), np.cos(heading), 0.0])  # car's +y axis in the world
    gap = 1.5
    p = left * (0.9 + gap) + np.array([0.0, 0.0, 0.75])
    ctx = SafetyContext(position=p, yaw=0.0, target_position=[0, 0, 0.75], target_heading=heading)
    rows = build_rows(ctx, cbf)
    r = np.flatnonzero(rows.kind == TARGET)[0]
    assert rows.h[r] == pytest.approx(gap**2 - cbf.obstacle_clearance**2)
    assert np.allclose(-rows.A[r], 2 * gap * left)
    rows = build_rows(dataclasses.replace(ctx, target_frustum=True), cbf)
    assert rows.h[r] == pytest.approx(gap - 0.75 - np.sqrt(2) * cbf.obstacle_clearance)
    assert np.allclose(-rows.A[r], left + [0, 0, 1])


@pytest.mark.parametrize("car_speed", [0.5, 0.8, 1.5, 3.0])
@pytest.mark.parametrize("start", [0.02, 0.3, 1.0])
def test_a_uav_between_the_car_and_an_obstacle_climbs_out(car_speed, start):
    """Closed loop: a UAV at half the car's height, ``start`` m outside the car's clearance on
    its path, a wall just behind it, and a command towards the car and down. Beside the car's
    box its barrier's gradient is horizontal, like the wall's and opposed to it: once the car
    is near no command keeps both, and giving the car's row up would let the car run into the
    UAV. The certificate is then made again with the car's frustum, which climbing raises: no
    fallback, the wall's clearance kept, and the UAV never touches the car (it may cross the
    car's pad) and goes over it."""
    cbf = CBFConfig().resolve()
    cl, dt, radius = cbf.obstacle_clearance, 1.0 / 80.0, EnvConfig().uav_radius
    half = np.array([2.3, 0.9, 0.75])
    q, vq = np.array([0.0, 0.0, 0.75]), np.array([car_speed, 0.0, 0.0])  # driving at the UAV
    p = np.array([half[0] + cl + start, 0.0, 0.75])
    wall_c, wall_h = np.array([p[0] + cl + 0.02 + 1.0, 0.0, 3.0]), np.array([1.0, 5.0, 3.0])
    shield = SafetyFilter(cbf)
    towards = cam_to_world(0.0).T @ np.array([-2.0, 0.0, -1.0])  # world velocity -> camera
    over = False
    for _ in range(400):
        ctx = SafetyContext(
            position=p, yaw=0.0, target_position=q, target_velocity=vq, target_heading=0.0,
            obstacle_centers=wall_c[None], obstacle_half_extents=wall_h[None],
        )  # fmt: skip
        u_safe, report = shield.certify(np.r_[towards, 0.0], ctx)
        assert report.status != "fallback", report
        p = p + dt * (cam_to_world(0.0) @ u_safe[:3])
        q = q + dt * vq
        assert box_h(p, q, half, radius) > 0.0 and box_h(p, wall_c, wall_h, cl) >= -1e-6
        over |= p[2] > q[2] + half[2] + radius and abs(p[0] - q[0]) < half[0]
    assert over  # it went over the car


@pytest.mark.parametrize("model", ["paper", "moving-target"])
@pytest.mark.parametrize("seed", range(6))
def test_occlusion_rows_match_finite_differences(model, seed):
    rng = np.random.default_rng(200 + seed)
    cbf = CBFConfig(
        occlusion_model=model, occlusion_point="centre", occlusion_size_margin=False
    ).resolve()
    ctx = random_context(rng, occlusion_model=model, moving=True)
    rows = build_rows(ctx, cbf)
    p, c, q, vq = ctx.position, ctx.obstacle_centers, ctx.target_position, ctx.target_velocity
    n0 = q - p
    ts = cbf.theta_star
    if model == "paper":  # (43): n held fixed, only the UAV moves
        h_of = lambda j, V, t: occl_h(p + t * V, c[j], n0, ts)  # noqa: E731
    else:  # n = (q + t V_q) - (p + t V)
        h_of = lambda j, V, t: occl_h(p + t * V, c[j], q + t * vq - (p + t * V), ts)  # noqa: E731
    check_family(rows, OCCLUSION, h_of, rng)
    if model == "paper":
        # The printed A of (45): -1/sqrt(1-x^2) (n/(|d||n|) - d cos(theta)/|d|^2).
        for r in np.flatnonzero(rows.kind == OCCLUSION):
            d = c[rows.index[r]] - p
            x = d @ n0 / (np.linalg.norm(d) * np.linalg.norm(n0))
            a45 = (-1 / np.sqrt(1 - x * x)) * (
                n0 / (np.linalg.norm(d) * np.linalg.norm(n0)) - d * x / (d @ d)
            )
            assert np.allclose(rows.A[r], a45, rtol=1e-9, atol=1e-12)
            assert rows.b[r] == pytest.approx(cbf.gamma_o * rows.h[r])
    else:
        assert np.any(rows.drift[rows.kind == OCCLUSION] != 0.0)


def axis_occl_h(p, center, half, n, theta_star):
    """Independent h of the 'axis' occluder with the size margin: min over the box's vertical
    axis of theta, minus theta* and the angular radius asin(r_xy / b), b the horizontal distance
    to the axis."""

    def theta(z):
        return occl_h(p, np.array([center[0], center[1], z]), n, 0.0)

    lo, hi = center[2] - half[2], center[2] + half[2]
    res = minimize_scalar(theta, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
    z = min((lo, hi, res.x), key=theta)
    b = np.hypot(center[0] - p[0], center[1] - p[1])
    return theta(z) - theta_star - np.arcsin(min(np.hypot(half[0], half[1]) / b, 0.99))


def edges_occl_h(p, center, half, n, theta_star, over=False):
    """Independent h of the 'edges' occluder: the least theta over the box's 12 edges, each
    minimised numerically, minus theta*; with the sight line through the box, minus the least
    theta over the edges of its outline seen from p (one of the edge's two faces towards p;
    every edge from inside the box), and with ``over`` over those of them on the top face if
    there are any."""
    corners = [center + half * (2 * np.array(s) - 1) for s in np.ndindex(2, 2, 2)]
    inside = segment_hits_boxes(p, p + n, center[None], half[None])[0]
    within = (np.abs(p - center) <= half).all()
    top = center[2] + half[2]
    best, best_top = np.inf, np.inf
    for a in corners:
        for b in corners:
            if np.count_nonzero(a != b) != 1:  # an edge joins corners differing on one axis
                continue
            faces = [(k, np.sign(a[k] - center[k])) for k in range(3) if a[k] == b[k]]
            towards = [sg * (p[k] - center[k]) > half[k] for k, sg in faces]
            if inside and not within and sum(towards) != 1:
                continue
            seg = lambda t, a=a, b=b: occl_h(p, a + t * (b - a), n, 0.0)  # noqa: E731
            res = minimize_scalar(seg, bounds=(0, 1), method="bounded", options={"xatol": 1e-12})
            least = min(seg(0.0), seg(1.0), seg(res.x))
            best = min(best, least)
            if a[2] == top and b[2] == top:
                best_top = min(best_top, least)
    if over and inside and best_top < np.inf:
        best = best_top
    return (-best if inside else best) - theta_star


BOX_OCCLUDERS = {
    # point: (CBFConfig overrides, independent h, seed base, seeds)
    "axis": ({"occlusion_size_margin": True}, axis_occl_h, 300, 6),
    "edges": ({}, edges_occl_h, 400, 3),
}


@pytest.mark.parametrize("model", ["paper", "moving-target"])
@pytest.mark.parametrize(
    ("point", "seed"), [(pt, k) for pt, spec in BOX_OCCLUDERS.items() for k in range(spec[3])]
)
def test_box_occluder_rows_match_finite_differences(point, seed, model):
    """The 'axis' occluder (closest point of the box's axis, here with the cone widened by the
    box's angular radius) and the 'edges' occluder (least angle over the 12 edges): h equals an
    independent minimisation and its rows the finite-difference rate."""
    overrides, h_fn, base, _ = BOX_OCCLUDERS[point]
    rng = np.random.default_rng(base + seed)
    cbf = CBFConfig(occlusion_model=model, occlusion_point=point, **overrides).resolve()
    ctx = random_context(rng, occlusion_model=model, moving=True)
    rows = build_rows(ctx, cbf)
    p, c, hx = ctx.position, ctx.obstacle_centers, ctx.obstacle_half_extents
    q, vq, ts = ctx.target_position, ctx.target_velocity, cbf.theta_star
    if model == "paper":
        h_of = lambda j, V, t: h_fn(p + t * V, c[j], hx[j], q - p, ts)  # noqa: E731
    else:
        h_of = lambda j, V, t: h_fn(p + t * V, c[j], hx[j], q + t * vq - (p + t * V), ts)  # noqa: E731
    check_family(rows, OCCLUSION, h_of, rng)


def piercing_context(rng, occlusion_model):
    """A UAV low among boxes, most of them on its sight line to the car (the line goes through
    them), one of them around the UAV itself; the car moving."""
    p = np.array([0.0, 0.0, 0.5]) + rng.uniform(-1, 1, 3) * [1, 1, 0.3]
    q = p + np.array([14.0, 0.0, 0.2]) + rng.uniform(-2, 2, 3) * [1, 1, 0.1]
    along = rng.uniform(0.15, 0.9, (5, 1)) * (q - p)
    centers = p + along + rng.uniform(-0.4, 0.4, (5, 3)) * [1, 1, 0.2]
    half = rng.uniform([0.3, 0.3, 0.4], [1.5, 1.5, 2.0], (5, 3))
    centers[0], half[0] = p + rng.uniform(-0.2, 0.2, 3), rng.uniform(0.4, 1.0, 3)
    return SafetyContext(
        position=p, yaw=0.0, obstacle_centers=centers, obstacle_half_extents=half,
        target_position=q, target_velocity=rng.uniform(-3, 3, 3) * [1, 1, 0],
        target_heading=0.0,
    )  # fmt: skip


@pytest.mark.parametrize("model", ["paper", "moving-target"])
@pytest.mark.parametrize("seed", range(4))
def test_over_the_top_rows_match_finite_differences(model, seed):
    """`RowBuilder` with ``over_the_top``: for a box the sight line goes through, h is minus
    the least angle to the top-face edges of its outline (an independent minimisation) and
    its row the finite-difference rate; for the other boxes the rows are the 'edges' rows.
    Climbing raises such a row's h, where the plain row's gradient is often level."""
    rng = np.random.default_rng(700 + seed)
    cbf = CBFConfig(occlusion_model=model, occlusion_point="edges").resolve()
    ctx = piercing_context(rng, model)
    builder = RowBuilder(cbf)
    rows, over = builder(ctx), builder(ctx, over_the_top=True)
    p, c, hx = ctx.position, ctx.obstacle_centers, ctx.obstacle_half_extents
    q, vq, ts = ctx.target_position, ctx.target_velocity, cbf.theta_star
    if model == "paper":
        h_of = lambda j, V, t: edges_occl_h(p + t * V, c[j], hx[j], q - p, ts, True)  # noqa: E731
    else:
        h_of = lambda j, V, t: edges_occl_h(  # noqa: E731
            p + t * V, c[j], hx[j], q + t * vq - (p + t * V), ts, True
        )
    check_family(over, OCCLUSION, h_of, rng)
    np.testing.assert_array_equal(over.kind, rows.kind)
    pierced = segment_hits_boxes(p, q, c, hx)
    assert pierced[1:].sum() >= 2 and pierced[0]  # the cases the rows differ in
    for r in np.flatnonzero(over.kind == OCCLUSION):
        j = over.index[r]
        if not pierced[j]:
            np.testing.assert_array_equal(over.A[r], rows.A[r])
            assert over.h[r] == rows.h[r]
        elif p[2] < c[j, 2] + hx[j, 2]:  # under the top: climbing leads out
            assert over.A[r, 2] < 0.0 and over.h[r] <= -ts


@pytest.mark.parametrize("model", ["paper", "moving-target"])
@pytest.mark.parametrize("seed", range(4))
def test_team_mate_occluder_rows_match_finite_differences(model, seed):
    """Team-mates occlude as boxes of half size ``team_mate_radius`` + their message ball,
    moving at their velocities: h equals the independent 'edges' minimisation and -A V + drift
    the finite-difference rate with the UAV, the team-mate (and for 'moving-target' the car)
    moving. The rows are named by the team-mate's id; a radius of 0 (the paper) has none."""
    rng = np.random.default_rng(600 + seed)
    radius, rho = 0.25, np.array([0.0, 0.4, 0.0])
    cbf = CBFConfig(occlusion_model=model, occlusion_point="edges", team_mate_radius=radius)
    p = np.array([0.0, 0.0, 3.0])
    q = np.array([15.0, 0.0, 0.75]) + rng.uniform(-2, 2, 3) * [1, 1, 0]
    along = np.array([0.3, 0.55, 0.7])[:, None] * (q - p)  # on or near the sight line
    nb = p + along + rng.uniform(-1.5, 1.5, (3, 3))
    nb_v = rng.uniform(-3, 3, (3, 3))
    ctx = SafetyContext(
        position=p, yaw=0.0, neighbours=nb, neighbour_velocities=nb_v, neighbour_radius=rho,
        neighbour_ids=(4, 7, 9), target_position=q, target_velocity=rng.uniform(-2, 2, 3),
        target_heading=0.0,
    )  # fmt: skip
    rows = build_rows(ctx, cbf.resolve())
    mates = np.flatnonzero((rows.kind == OCCLUSION) & (rows.index < 0))
    assert len(mates) == 3
    vq, ts = ctx.target_velocity, cbf.theta_star
    for r in mates:
        j = -rows.index[r] - 1
        half = np.full(3, radius + rho[j])
        if model == "paper":
            n = lambda t, V: q - p  # noqa: E731
        else:
            n = lambda t, V: q + t * vq - (p + t * V)  # noqa: E731

        def h_of(V, t, j=j, half=half, n=n):
            return edges_occl_h(p + t * V, nb[j] + t * nb_v[j], half, n(t, V), ts)

        assert rows.h[r] == pytest.approx(h_of(np.zeros(3), 0.0), abs=1e-9)
        for _ in range(3):
            V = rng.uniform(-10, 10, 3)
            fd = fd_rate(lambda t, V=V, h_of=h_of: h_of(V, t))
            assert -rows.A[r] @ V + rows.drift[r] == pytest.approx(fd, rel=1e-5, abs=1e-5)
    names = rows.names(ctx.neighbour_ids)
    assert sorted(names[r] for r in mates) == [f"occlusion:uav:{i}" for i in (4, 7, 9)]
    paper = build_rows(ctx, dataclasses.replace(cbf, team_mate_radius=0.0).resolve())
    assert not (paper.index[paper.kind == OCCLUSION] < 0).any()
    assert paper.size == rows.size - 3


@pytest.mark.parametrize("seed", range(20))
def test_edges_occluder_has_the_least_angle_of_the_box(seed):
    """Where the sight line misses the box, no point of its surface is closer in angle to the
    line of sight than the 'edges' point, and the point lies on the box's surface."""
    rng = np.random.default_rng(500 + seed)
    p, q = rng.uniform(-6, 6, 3), rng.uniform(-6, 6, 3)
    center, half = rng.uniform(-4, 4, 3), rng.uniform(0.2, 2.0, 3)
    n = q - p
    point = occluder_points(p, center[None], half[None], q, "edges")[0]
    local = np.abs(point - center) / half
    assert local.max() == pytest.approx(1.0) and np.count_nonzero(np.isclose(local, 1.0)) >= 2
    grid = np.linspace(-1.0, 1.0, 61)
    cube = np.stack(np.meshgrid(grid, grid, grid, indexing="ij"), -1).reshape(-1, 3)
    surface = center + half * cube[(np.abs(cube) == 1.0).any(axis=1)]
    d = surface - p
    angles = np.arccos(np.clip(d @ n / (np.linalg.norm(d, axis=1) * np.linalg.norm(n)), -1, 1))
    ray_hits_box = angles.min() < 0.05 or (np.abs(p - center) < half).all()
    if not ray_hits_box:
        assert occl_h(p, point, n, 0.0) <= angles.min() + 1e-9
        assert occl_h(p, point, n, 0.0) >= angles.min() - 0.02  # grid spacing


def test_neighbour_sets_follow_the_paper():
    """N_si within D_s (27), N_ci within R_c (34), N_oi = obstacles closer than the target (39)."""
    cbf = CBFConfig(r_s=2.0, d_s=10.0, r_c=20.0, gamma_s=3.0)
    ctx = SafetyContext(
        position=[0, 0, 3],
        yaw=0.0,
        neighbours=[[5, 0, 3], [15, 0, 3], [25, 0, 3]],
        obstacle_centers=[[4, 0.5, 3], [30, 0, 3]],
        obstacle_half_extents=[[0.5, 0.5, 0.5]] * 2,
        target_position=[12, 0, 1],
    )
    rows = build_rows(ctx, cbf)
    names = rows.names()
    assert [n for n in names if n.startswith("uav")] == ["uav:0"]
    assert [n for n in names if n.startswith("connect")] == ["connect:0", "connect:1"]
    assert [n for n in names if n.startswith("occlusion")] == ["occlusion:0"]
    assert {"target", "floor", "obstacle:0", "obstacle:1"} <= set(names)
    rows = build_rows(dataclasses.replace(ctx, neighbour_ids=(7, 8, 9)), cbf)
    assert "uav:7" in rows.names(neighbour_ids=(7, 8, 9))


def test_eq28_is_enforced():
    with pytest.raises(ValueError, match=r"eq. \(28\)"):
        CBFConfig(gamma_s=0.1).resolve()
    bad = CBFConfig().resolve()
    object.__setattr__(bad, "gamma_s", 0.01)  # bypass the dataclass check: the filter re-checks
    with pytest.raises(ValueError, match=r"eq. \(28\)"):
        check_eq28(bad)
    with pytest.raises(ValueError, match=r"eq. \(28\)"):
        SafetyFilter(cbf=bad)
    with pytest.raises(ValueError, match="dt"):
        SafetyFilter(cbf=CBFConfig(gamma_z=200.0))  # gamma dt > 1 breaks discrete invariance


@pytest.mark.parametrize(
    "kwargs",
    [
        {"position": [0, 0]},
        {"position": [0, np.nan, 1]},
        {"yaw": np.inf},
        {"neighbours": [[1, 2]]},
        {"neighbours": [[1, 2, np.nan]]},
        {"obstacle_centers": [[1, 2, 3]], "obstacle_half_extents": [[1, 1, 1], [1, 1, 1]]},
        {"obstacle_centers": [[1, 2, 3]], "obstacle_half_extents": [[1, -1, 1]]},
        {"target_position": [1, 2]},
        {"target_velocity": [np.nan, 0, 0], "target_position": [1, 2, 3]},
        {"neighbours": [[1, 2, 3]], "neighbour_ids": (1, 2)},
        {"target_growth": [1.0, -0.5, 0.0]},
        {"target_growth": [1.0, 1.0]},
        {"target_growth": np.inf},
        {"target_frustum": "yes"},
    ],
)
def test_context_rejects_bad_input(kwargs):
    base = {"position": [0, 0, 3], "yaw": 0.0}
    with pytest.raises(ValueError):
        SafetyContext(**{**base, **kwargs})


def test_edges_occluder_sees_a_cube_whose_axis_point_misses():
    """Scenario B0, UAV3 at 18.7 s with cbf.occlusion_model="moving-target":
    a 1 m cube beside and below the UAV hides the car's lower far corner. Its axis point lies
    outside the theta* cone, so the 'axis' barrier is satisfied; its nearest top edge lies
    inside, so the 'edges' barrier is violated, as it should be."""
    p = np.array([3.684, -3.408, 1.324])
    q = np.array([8.173, -2.587, 0.75])  # car centre
    center, half = np.array([5.0, -4.0, 0.5]), np.array([0.5, 0.5, 0.5])
    corner = np.array([9.77, -3.75, 0.15])  # a ray-cast sample point of the car
    assert segment_hits_boxes(p, corner, center[None], half[None])[
        0
    ]  # the cube hides part of the car
    ts = CBFConfig().theta_star
    axis = occluder_points(p, center[None], half[None], q, "axis")[0]
    edges = occluder_points(p, center[None], half[None], q, "edges")[0]
    assert occl_h(p, axis, q - p, ts) > 0.0  # 34.5 deg: the axis barrier sees no danger
    assert occl_h(p, edges, q - p, ts) < -np.radians(10)  # 13.4 deg, deep inside the cone


@pytest.mark.parametrize("seed", range(8))
def test_edges_h_falls_as_the_sight_line_goes_into_the_box(seed):
    """Sweeping the UAV sideways so that its sight line crosses a box: the 'edges' h is
    continuous, below -theta* exactly while the line passes through the box, and least where
    the line is deepest in it (theta is minus the angle to the box's outline there)."""
    rng = np.random.default_rng(900 + seed)
    center, half = rng.uniform(-1, 1, 3) + [6.0, 0.0, 2.0], rng.uniform(0.3, 1.0, 3)
    q = np.array([14.0, 0.0, 0.75]) + rng.uniform(-1, 1, 3) * [1, 1, 0]
    cbf = CBFConfig(occlusion_point="edges").resolve()
    ts = cbf.theta_star
    aim = center + rng.uniform(-0.3, 0.3, 3) * half  # a point of the box the sweep passes
    hs, hits = [], []
    for y in np.linspace(-4.0, 4.0, 801):
        p = q + (aim - q) * 2.0 + [0.0, y, 0.0]  # sight line from p passes aim at y = 0
        ctx = SafetyContext(
            position=p, yaw=0.0, target_position=q, target_heading=0.0,
            obstacle_centers=center[None], obstacle_half_extents=half[None],
        )  # fmt: skip
        rows = build_rows(ctx, cbf)
        occl = rows.h[rows.kind == OCCLUSION]
        hs.append(occl[0] if len(occl) else np.nan)
        hits.append(segment_hits_boxes(p, q, center[None], half[None])[0])
    hs, hits = np.array(hs), np.array(hits)
    assert hits.any() and not hits.all() and not np.isnan(hs[hits]).any()
    assert (hs[hits] < -ts).all()
    seen = ~np.isnan(hs)
    assert (hs[seen & ~hits] >= -ts - 1e-9).all()
    assert np.abs(np.diff(hs[seen])).max() < 0.05  # continuous across the box's outline
    least, through = np.nanargmin(hs), np.flatnonzero(hits)
    assert through[0] < least < through[-1]  # inside the box, not on its outline
    assert hs[least] < min(hs[through[0]], hs[through[-1]]) - 1e-3


@pytest.mark.parametrize("frustum", [False, True])
@pytest.mark.parametrize("z", [0.3, 1.5, 1.74])
def test_inside_the_car_box_the_way_out_is_up_and_out(z, frustum):
    """A UAV inside the car's box (which the car may fill up to its top) is sent up or out
    through the nearest side, never down and never further in, even just under the top: h is
    -e_xy (t + clearance) - clearance^2 (e_xy = 2.6 m inside the nearest side, t under the top),
    per clearance in the frustum; over the top the frustum sends it straight up."""
    cbf = CBFConfig().resolve()
    cl, z0 = cbf.obstacle_clearance, np.zeros(3)
    q, half = np.array([0.0, 0.0, 0.75]), np.array([3.0, 3.0, 1.0])
    p = np.array([0.1, -0.4, z])
    ax, ay, az, h, _drift = target_row(p, q, z0, half, 0.0, cl, z0, frustum)
    inside = -2.6 * (1.75 - z + cl)
    if frustum:
        assert h == pytest.approx(z - 1.75 - np.sqrt(2) * cl + inside / cl)
        assert h == pytest.approx(car_h(p, q, half, cl))
    else:
        assert h == pytest.approx(inside - cl**2)
        assert h == pytest.approx(h_box(p, q, half, cl, grounded=True)[0])
    assert az < 0  # -grad h . V <= b: climbing helps
    assert ax == 0 and ay > 0  # and so does leaving through the nearest side, -y
    for inward in ([0.0, 1.0, 0.0], [0.0, 0.0, -1.0]):  # away from the nearest side, down
        assert target_row(p + 0.01 * np.array(inward), q, z0, half, 0.0, cl, z0, frustum)[3] < h
    for top in (1.76, 4.0):  # over the footprint, above the top
        ax, ay, az, h, _drift = target_row(
            p * [1, 1, 0] + [0, 0, top], q, z0, half, 0.0, cl, z0, True
        )
        assert h == pytest.approx(top - 1.75 - np.sqrt(2) * cl)
        assert az == -1.0 and ax == 0 and ay == 0


def test_the_car_frustum_keeps_the_clearance_from_the_box():
    """Every point the car's row allows (h >= 0) is at least the clearance from the box, and
    points at the box's clearance straight above it are allowed only sqrt(2) clearance up."""
    rng = np.random.default_rng(5)
    cl = CBFConfig().resolve().obstacle_clearance
    q, half, th = np.array([1.0, -2.0, 0.8]), np.array([2.5, 1.2, 0.8]), 0.4
    pts = q + rng.uniform(-8, 8, (20000, 3)) * [1, 1, 0.5] + [0, 0, 2.0]
    allowed = [p for p in pts if car_h(p, q, half, cl, th) >= 0.0]
    assert len(allowed) > 1000
    dist = [np.sqrt(max(box_h(p, q, half, 0.0, th), 0.0)) for p in allowed]
    assert min(dist) >= cl - 1e-9
    top = q + [0.0, 0.0, half[2]]
    assert car_h(top + [0, 0, np.sqrt(2) * cl], q, half, cl, th) == pytest.approx(0.0)
