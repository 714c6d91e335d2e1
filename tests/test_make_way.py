"""A team-mate the car's box has caught is given a way out (`barrier_rows.make_way`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from baselines import shield_adversary as sa
from uavtrack_env.presets import expert_config
from uavtrack_env.safety import SafetyContext, SafetyFilter
from uavtrack_env.safety.barrier_rows import make_way
from uavtrack_env.safety.cbf import UAV

Q, HALF, CL, R_S = np.array([0.0, 0.0, 0.75]), np.array([3.0, 3.0, 1.0]), 0.75, 2.0
"""A car box with its top at 1.75 m, the clearance and R_s."""
TOP = 1.75 + math.sqrt(2.0) * CL
"""Height of the car frustum's zero set over the footprint."""


def _grown(p, nb, rho=None):
    nb = np.asarray(nb, float)
    rho = np.zeros(len(nb)) if rho is None else np.asarray(rho, float)
    return make_way(np.asarray(p, float), nb, rho, Q, HALF, 0.0, CL, R_S) - rho


def test_a_uav_over_a_caught_team_mate_counts_its_way_out():
    """From 3.5 m over the box: a team-mate 1 m up inside it grows by its climb to the frustum
    (depth inside its nearest side and under the top ample); one beside the box within the
    clearance but 3.3 m to the side, one far away and one level with the UAV keep their radii;
    one 2.45 m beside grows by the 0.4 of its way out that the taper from R_s to R_s + clearance
    leaves."""
    p = [0.3, 0.2, 3.5]
    nb = [[0.3, 0.2, 1.0], [8.0, 0.2, 1.0], [0.3, 3.5, 1.0], [2.75, 0.2, 1.0], [0.3, 1.4, 3.5]]
    inside_d = CL + math.sqrt(0.25 * 0.75)  # 0.25 m inside its nearest side, 0.75 m under the top
    want = [TOP - 1.0, 0.0, 0.0, 0.4 * min(inside_d, TOP - 1.0), 0.0]
    np.testing.assert_allclose(_grown(p, nb), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(_grown(p, nb, [0.5, 0.0, 0.1, 0.0, 0.2]), want, atol=1e-12)


def test_of_two_caught_uavs_the_higher_makes_way_for_the_lower():
    high, low = [0.3, 0.2, 1.5], [0.3, 0.2, 0.5]
    assert _grown(high, [low])[0] == pytest.approx((TOP - 0.5) - (TOP - 1.5))
    assert _grown(low, [high])[0] == 0.0


def test_the_uav_over_a_caught_team_mate_backs_off_and_one_aside_does_not():
    """A hover 2.05 m over a team-mate inside the car's box (R_s 2 m): the pair row asks the UAV
    above to climb away, which it does not without `ShieldOptions.make_way`; a hover level with
    a team-mate 0.5 m inside the box and 2.05 m beside it, outside, is left alone."""
    for below, over, moves in (
        ([0.3, 0.2, 1.0], [0.3, 0.2, 3.05], True),
        ([2.5, 0.2, 1.0], [4.55, 0.2, 1.0], False),
    ):
        ctx = SafetyContext(
            position=over, yaw=0.0, neighbours=[below], target_position=Q,
            target_half_extents=HALF, target_heading=0.0,
        )  # fmt: skip
        with_way, without = SafetyFilter(make_way=True), SafetyFilter(make_way=False)
        rows = with_way.rows(ctx)
        assert with_way.cbf.r_s == R_S and with_way.cbf.obstacle_clearance == CL
        pair = rows.kind == UAV
        assert (rows.h[pair] < without.rows(ctx).h[pair]).all() == moves
        u, report = with_way.certify(np.zeros(4), ctx)
        assert (report.status != "nominal") == moves
        if moves:
            assert u[1] < 0.0  # camera y is down: it climbs away from the caught UAV
        assert without.certify(np.zeros(4), ctx)[1].status == "nominal"


@pytest.mark.slow
@pytest.mark.parametrize("dense", [False, True], ids=["default", "dense"])
def test_block_and_press_never_presses_a_uav_into_the_car(dense):
    """block-and-press under the lag model with every message heard (n = 6 and 10), 8 worlds of
    a seed no shield setting was chosen on, 400 steps: the car's box grows over UAVs posted in
    its path while team-mates press them down; none touches the car or a team-mate."""
    opts = sa.HarnessOptions(
        steps=400, seed=4242, progress=False,
        n_obstacles=(24, 48) if dense else None, corridor=1.5 if dense else None,
    )  # fmt: skip
    worlds = [w for w in sa.make_worlds(48, opts.seed) if w.dynamics == "lag" and w.drop == 0.0]
    worlds = [w for w in worlds if w.n > 3]
    assert len(worlds) == 8
    config = expert_config("tuned")
    for world in worlds:
        run = sa.run_one(world, "block-and-press", True, opts, config)
        assert run["counts"]["collision"] == 0 and run["counts"]["disconnection"] == 0, run
