"""Pair rows for team-mates known only within a ball (lost messages): the worst case over the
ball implies the row the UAV would build knowing the truth."""

from __future__ import annotations

import numpy as np
import pytest

from uavtrack_env.safety import CBFConfig, SafetyContext
from uavtrack_env.safety.cbf import CONNECT, UAV, RowBuilder

CBF = CBFConfig().resolve()


def _ball(rng, radius: np.ndarray) -> np.ndarray:
    """A point in each ball of the given radii, (k, 3)."""
    e = rng.normal(size=(len(radius), 3))
    return e * (radius * rng.random(len(radius)) / np.linalg.norm(e, axis=1))[:, None]


def _cap(rows) -> np.ndarray:
    """Positions of the speed cap's rows: the uav rows beyond one per team-mate."""
    uav = np.flatnonzero(rows.kind == UAV)
    return uav[len(set(rows.index[uav])) :]


def _implication_failures(lag_tau: float, robust: bool, trials: int = 600) -> tuple[int, int]:
    """(commands that satisfy the believed row but break the true one, commands compared)."""
    rng = np.random.default_rng(0)
    builder = RowBuilder(CBF, lag_tau=lag_tau)
    failures = compared = 0
    for _ in range(trials):
        p = np.r_[rng.uniform(-5, 5, 2), 5.0]
        true = p + rng.normal(size=(2, 3)) * rng.uniform(2.5, 15.0)
        v_true = rng.normal(size=(2, 3)) * 3.0
        rho = rng.uniform(0.0, 1.0, 2) * (rng.random(2) < 0.8)
        sigma = rng.uniform(0.0, 2.0, 2) * (rng.random(2) < 0.8)
        own = {"position": p, "yaw": 0.0, "velocity": rng.normal(size=3) * 3.0}
        believed = builder(
            SafetyContext(
                neighbours=true + _ball(rng, rho),
                neighbour_velocities=v_true + _ball(rng, sigma),
                neighbour_radius=rho if robust else None,
                neighbour_velocity_radius=sigma if robust else None,
                **own,
            )
        )
        exact = builder(SafetyContext(neighbours=true, neighbour_velocities=v_true, **own))
        cap = _cap(believed)
        for u in rng.normal(size=(20, 3)):
            u *= rng.uniform(0.0, CBF.alpha_v) / np.linalg.norm(u)
            ok_believed = believed.A @ u <= believed.b + 1e-9
            ok_true = exact.A @ u <= exact.b + 1e-9
            capped = ok_believed[cap].all()  # the speed cap the ball rows count on
            for kind in (UAV, CONNECT):
                for r in np.setdiff1d(np.flatnonzero(believed.kind == kind), cap):
                    e = np.flatnonzero((exact.kind == kind) & (exact.index == believed.index[r]))
                    if len(e) and ok_believed[r] and capped:
                        compared += 1
                        failures += not ok_true[e[0]]
    return failures, compared


@pytest.mark.parametrize("lag_tau", [0.0, 0.25], ids=["first-order", "second-order"])
def test_rows_over_the_reachable_ball_imply_the_true_rows(lag_tau):
    failures, compared = _implication_failures(lag_tau, robust=True)
    assert compared > 5000
    assert failures == 0
    # the same stale positions taken as exact do let unsafe commands through
    naive, _ = _implication_failures(lag_tau, robust=False)
    assert naive > 50


def test_a_fresh_message_gives_the_paper_rows():
    """Radius zero: rows (25) and (34) exactly as without the reachable-set fields."""
    rng = np.random.default_rng(3)
    ctx = {"position": [0, 0, 4], "yaw": 0.3, "velocity": [1, 2, 0]}
    nb, vel = rng.normal(size=(3, 3)) * 6 + [0, 0, 4], rng.normal(size=(3, 3))
    for tau in (0.0, 0.25):
        builder = RowBuilder(CBF, lag_tau=tau)
        plain = builder(SafetyContext(neighbours=nb, neighbour_velocities=vel, **ctx))
        zero = builder(
            SafetyContext(
                neighbours=nb,
                neighbour_velocities=vel,
                neighbour_radius=np.zeros(3),
                neighbour_velocity_radius=np.zeros(3),
                **ctx,
            )
        )
        np.testing.assert_array_equal(plain.A, zero.A)
        np.testing.assert_array_equal(plain.b, zero.b)


def test_bad_radius_is_refused():
    with pytest.raises(ValueError, match="neighbour_radius must hold 1 finite distances"):
        SafetyContext(position=[0, 0, 1], yaw=0.0, neighbours=[[3, 0, 1]], neighbour_radius=[-1])
    with pytest.raises(ValueError, match="neighbour_velocity_radius"):
        SafetyContext(
            position=[0, 0, 1],
            yaw=0.0,
            neighbours=[[3, 0, 1]],
            neighbour_velocity_radius=[np.nan],
        )


def test_the_frustum_certificate_gives_stale_team_mates_up_with_the_car():
    """`SafetyFilter.climb_over_car`'s layers: the uav row of a team-mate known only within a
    ball takes the car's priority, an exact team-mate's row keeps its own; rows unchanged."""
    from uavtrack_env.safety.cbf import TARGET
    from uavtrack_env.safety.shield import _stale_team_mates_with_car

    nb = np.array([[2.5, 0.0, 1.0], [0.0, 2.4, 1.2], [-2.2, 0.5, 1.0]])
    ctx = {
        "position": [0.0, 0.0, 1.0], "yaw": 0.0, "neighbours": nb,
        "target_position": [4.0, 3.0, 0.75], "target_velocity": [0.5, 0.0, 0.0],
        "target_heading": 0.0, "target_frustum": True,
    }  # fmt: skip
    builder = RowBuilder(CBF)
    rows = builder(SafetyContext(neighbour_radius=np.array([0.0, 0.4, 0.0]), **ctx))
    kind = _stale_team_mates_with_car(rows, np.array([0.0, 0.4, 0.0]))
    uav = rows.kind == UAV
    assert sorted(set(rows.index[uav])) == [0, 1, 2]  # every team-mate within D_s
    stale = uav & (rows.index == 1)
    assert np.all(kind[stale] == TARGET) and np.all(kind[~stale] == rows.kind[~stale])
    assert np.count_nonzero(rows.kind == TARGET) == 1  # the car's row; rows not modified
    assert _stale_team_mates_with_car(rows, np.zeros(3)) is None
    assert _stale_team_mates_with_car(rows, None) is None


def _one_ball(distance: float, rho: float, lag_tau: float = 0.0):
    """Rows of a UAV at rest with one team-mate ``distance`` m away in x, known within ``rho``."""
    ctx = SafetyContext(
        position=[0.0, 0.0, 3.0], yaw=0.4, velocity=np.zeros(3),
        neighbours=[[distance, 0.0, 3.0]], neighbour_velocities=np.zeros((1, 3)),
        neighbour_radius=[rho], neighbour_velocity_radius=[0.0],
    )  # fmt: skip
    return RowBuilder(CBF, lag_tau=lag_tau)(ctx)


def test_the_speed_cap_in_closed_form():
    """S = min(alpha_v, gamma h / (2 rho)), gamma the halved rate and h from the ball's nearest
    point (at least 0): above alpha_v the ball's row is the plain worst case and no cap; below,
    the row keeps b = gamma h - 2 rho S >= 0 and the cap is the box |V_i| <= S / sqrt(3)."""
    gamma, r_s, alpha = 0.5 * CBF.gamma_s, CBF.r_s, CBF.alpha_v
    # a far ball: h large enough that gamma h / (2 rho) > alpha_v
    rows = _one_ball(r_s + 3.0, 0.1)
    h = (r_s + 2.9) ** 2 - r_s**2
    assert gamma * h / 0.2 > alpha and len(_cap(rows)) == 0
    (r,) = np.flatnonzero(rows.kind == UAV)
    assert rows.b[r] == pytest.approx(gamma * h - 2 * 0.1 * alpha)
    # a near one: the cap binds
    distance, rho = r_s + 0.5, 0.3
    rows = _one_ball(distance, rho)
    h = (distance - rho) ** 2 - r_s**2
    speed = gamma * h / (2 * rho)
    assert 0.0 < speed < alpha
    cap = _cap(rows)
    assert len(cap) == 6
    np.testing.assert_allclose(np.abs(rows.A[cap]).sum(axis=0), [2.0, 2.0, 2.0])
    np.testing.assert_allclose(rows.b[cap], speed / np.sqrt(3.0))
    pair = np.setdiff1d(np.flatnonzero(rows.kind == UAV), cap)
    assert 0.0 <= rows.b[pair[0]] < 1e-9 * gamma * h + 1e-12
    connect = np.flatnonzero(rows.kind == CONNECT)
    assert rows.drift[connect] == pytest.approx(-2.0 * rho * speed)


@pytest.mark.parametrize("distance, rho", [(1.0, 3.0), (CBF.r_s + 0.2, 0.5), (0.0, 0.4)])
def test_a_ball_reaching_inside_r_s_stops_the_uav(distance, rho):
    """The team-mate may be anywhere in its ball, so any motion may close on it: the rows admit
    V = 0 and nothing else (S = 0), not a flight from the ball's centre, which the true
    team-mate need not be near and which no command may be fast enough for."""
    rows = _one_ball(distance, rho)
    uav = rows.kind == UAV
    assert np.all(rows.b[uav] >= 0.0)  # V = 0 meets every uav row
    np.testing.assert_allclose(rows.b[_cap(rows)], 0.0, atol=1e-12)
    for v in np.vstack([np.eye(3), -np.eye(3)]) * 1e-3:
        assert np.any(rows.A[uav] @ v > rows.b[uav])


def test_the_ball_rows_admit_rest_however_stale_the_message():
    """First-order rows: whatever the radii and wherever the team-mates outside R_s, V = 0 meets
    every uav row, so a lost message never makes them infeasible."""
    rng = np.random.default_rng(11)
    builder = RowBuilder(CBF)
    for _ in range(400):
        p = np.r_[rng.uniform(-3, 3, 2), 4.0]
        direction = rng.normal(size=(4, 3))
        direction /= np.linalg.norm(direction, axis=1)[:, None]
        nb = p + direction * rng.uniform(CBF.r_s, CBF.d_s + 2.0, (4, 1))
        rho = rng.uniform(0.0, 6.0, 4) * (rng.random(4) < 0.7)
        rows = builder(
            SafetyContext(
                position=p, yaw=0.0, neighbours=nb + _ball(rng, rho), neighbour_radius=rho
            )
        )
        ball = (rows.kind == UAV) & (rho[rows.index] > 0.0)
        assert np.all(rows.b[ball] >= 0.0)


def test_second_order_rows_have_no_speed_cap():
    """Under the lag model the rows bound the actual velocity, which a command cap cannot: the
    ball rows there are the plain worst case (`test_rows_over_the_reachable_ball_imply...`)."""
    rows = _one_ball(CBF.r_s + 0.5, 0.3, lag_tau=0.25)
    assert len(_cap(rows)) == 0
