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
        for u in rng.normal(size=(20, 3)):
            u *= rng.uniform(0.0, CBF.alpha_v) / np.linalg.norm(u)
            ok_believed = believed.A @ u <= believed.b + 1e-9
            ok_true = exact.A @ u <= exact.b + 1e-9
            for kind in (UAV, CONNECT):
                for r in np.flatnonzero(believed.kind == kind):
                    e = np.flatnonzero((exact.kind == kind) & (exact.index == believed.index[r]))
                    if len(e) and ok_believed[r]:
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
    assert sorted(rows.index[uav]) == [0, 1, 2]  # every team-mate within D_s
    stale = uav & (rows.index == 1)
    assert np.all(kind[stale] == TARGET) and np.all(kind[~stale] == rows.kind[~stale])
    assert np.count_nonzero(rows.kind == TARGET) == 1  # the car's row; rows not modified
    assert _stale_team_mates_with_car(rows, np.zeros(3)) is None
    assert _stale_team_mates_with_car(rows, None) is None
