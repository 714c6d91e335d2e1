"""The CBFShield adversary harness (`baselines.shield_adversary`): its parts, and a few worlds.

The fast tests check the harness (valid actions from every family, the search, the margins, the
report). The slow ones run the families that press the shield hardest on three grid cells:
unshielded they must violate (the adversaries are real); shielded they must not.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from baselines import shield_adversary as sa
from uavtrack_env.geometry import cam_to_world
from uavtrack_env.presets import expert_config


@pytest.fixture(scope="module")
def small_env():
    world = sa.WorldSpec(0, 3, "integrator", 0.0, 7)
    env = sa.make_env(world, 12, None)
    yield env
    env.close()


# ---------------------------------------------------------------------------- harness parts
def test_worlds_spread_over_the_grid():
    worlds = sa.make_worlds(60, seed=10)
    cells = {}
    for w in worlds:
        cells[w.cell] = cells.get(w.cell, 0) + 1
    assert len(cells) == 12 and set(cells.values()) == {5}
    assert len({w.seed for w in worlds}) == 60 and worlds[0].seed == 10


@pytest.mark.parametrize("family", sorted(sa.FAMILIES))
def test_every_family_returns_valid_actions_for_the_live_agents(small_env, family):
    env = small_env
    _obs, infos = env.reset(seed=3)
    policy = sa.FAMILIES[family](env, np.random.default_rng(0))
    for _ in range(12):
        if not env.agents:
            break
        actions = policy(_obs, infos)
        assert sorted(actions) == sorted(env.agents)
        for a in actions.values():
            a = np.asarray(a)
            assert a.shape == (4,) and np.all(np.isfinite(a)) and np.all(np.abs(a) <= 1.0)
        _obs, _r, _t, _tr, infos = env.step(actions)


_MIXED_ACTIONS = """
import numpy as np
from baselines import shield_adversary as sa
env = sa.make_env(sa.WorldSpec(0, 6, "integrator", 0.0, 7), 12, None)
obs, infos = env.reset(seed=3)
policy = sa.FAMILIES["mixed"](env, np.random.default_rng(5))
out = []
for _ in range(8):
    actions = policy(obs, infos)
    out.append(np.concatenate([actions[a] for a in sorted(actions)]))
    obs, _r, _t, _tr, infos = env.step(actions)
print(np.concatenate(out).tobytes().hex())
"""


def test_the_mixed_family_is_the_same_in_every_process():
    """`mixed` builds its families in a fixed order, so that its draws from the one generator
    do not follow a set's order, which Python's string hashing changes between processes."""
    import os
    import subprocess
    import sys

    runs = []
    for hash_seed in ("1", "2", "3"):
        done = subprocess.run(
            [sys.executable, "-c", _MIXED_ACTIONS], capture_output=True, text=True, check=True,
            env={**os.environ, "PYTHONHASHSEED": hash_seed},
        )  # fmt: skip
        runs.append(done.stdout.strip().splitlines()[-1])
    assert runs[0] == runs[1] == runs[2]


def test_sequence_policy_plays_its_knots_in_equal_pieces(small_env):
    env = small_env
    env.reset(seed=0)
    knots = 0.1 * np.arange(3)[:, None, None] + 0.2 * np.arange(4)[None, :, None] + np.zeros(4)
    policy = sa.sequence_policy(env, knots, steps=8)
    played = [policy({}, {})["uav_1"] for _ in range(10)]
    expected = 0.1 + 0.2 * np.array([0, 0, 1, 1, 2, 2, 3, 3, 3, 3])
    np.testing.assert_allclose(np.array(played), np.repeat(expected[:, None], 4, axis=1))


def test_cem_lowers_a_toy_objective():
    target = np.array([[[0.6, -0.4, 0.8, -0.7]], [[-0.5, 0.3, 0.9, 0.2]]])

    def f(x):
        return float(np.sum((x - target) ** 2)), x.sum()

    opts = sa.SearchOptions(population=12, iterations=6, elite=3)
    out = sa.cem_minimize(f, target.shape, np.random.default_rng(0), opts)
    assert out.evaluations == 72 and out.history[-1] < out.history[0]
    assert all(b <= a for a, b in zip(out.history, out.history[1:], strict=False))
    assert out.best_value < 0.1 * f(np.zeros_like(target))[0]
    assert out.best_payload == pytest.approx(out.best_x.sum())


def test_link_margin_is_the_longest_spanning_tree_edge():
    pts = np.array([[0.0, 0, 0], [5, 0, 0], [17, 0, 0], [5, 3, 0]])
    assert sa.link_margin(pts, 20.0) == pytest.approx(8.0)
    assert sa.link_margin(pts[:1], 20.0) == math.inf


def _record(family, shielded, collisions, cell=(3, "lag", 0.5)):
    n, dyn, drop = cell
    counts = dict.fromkeys(sa.KINDS, 0)
    counts.update(collision=collisions, uav=collisions)
    return {
        "family": family,
        "shielded": shielded,
        "cell": f"n{n}-{dyn}-drop{drop:g}",
        "n": n,
        "dynamics": dyn,
        "drop": drop,
        "agent_steps": 1000,
        "counts": counts,
        "least": {"uav": -0.5 if collisions else 0.3, **dict.fromkeys(sa.CONSTRAINTS[1:], 1.0)},
        "statuses": {"optimal": 900, "fallback": 100} if shielded else {},
    }


def test_report_tables_and_failures():
    records = [
        _record("seek-uav", True, 2),
        _record("seek-uav", False, 3),
        _record("flee", True, 0, (6, "integrator", 0.0)),
        _record("flee", False, 1, (6, "integrator", 0.0)),
    ]
    records[2]["counts"]["occlusion"] = 7  # soft: counted, not a failure
    summary = sa.summarize(records)
    uav = summary["families"]["seek-uav"]["shielded"]
    assert uav["per_million"]["uav"] == pytest.approx(2000.0)
    assert uav["least"]["uav"] == -0.5 and uav["statuses"]["fallback"] == 100
    assert summary["failures"] == [["seek-uav", "n3-lag-drop0.5"]]
    report = sa.format_report(summary, {"command": "python -m x", "worlds": 2, "steps": 5})
    assert "| seek-uav (shielded) | 1000 | 2000 | 2000 | 0 |" in report
    assert "| n6-integrator-drop0 | 1000 | 0 | 0 | 0 | 0 | 0 | 0 | 7000 |" in report
    assert "- seek-uav in n3-lag-drop0.5" in report
    assert "fallback: 100" in report


def test_cli_options():
    opts = sa.parse_args(["--worlds", "3", "--families", "flee", "cem", "--no-search"])
    assert opts.worlds == 3 and sa.selected_families(opts) == ["flee"]
    assert sa.selected_families(sa.parse_args([])) == list(sa.ALL_FAMILIES)
    with pytest.raises(SystemExit):
        sa.parse_args(["--families", "nope"])
    assert opts.random_world() == {}
    dense = sa.parse_args(["--obstacles", "24", "48", "--corridor", "1.5"])
    assert dense.random_world() == {"n_obstacles": (24, 48), "corridor": 1.5}
    for bad in (
        ["--obstacles", "9", "3"], ["--corridor", "-1"], ["--obstacles", "4"],
        ["--team-sizes", "0"], ["--drops", "1.0"], ["--drops", "-0.1"],
    ):  # fmt: skip
        with pytest.raises(SystemExit):
            sa.parse_args(bad)


def test_car_speed_and_start_offset_reach_the_world_and_the_report():
    opts = sa.parse_args(["--car-speed", "2", "3", "--start-offset", "3"])
    assert opts.random_world() == {"target_speed": (2.0, 3.0), "start_offset": 3.0}
    assert sa._density({"car_speed": (2.0, 3.0), "start_offset": 3.0}) == (
        " (car at 2-3 m/s, starts 3 m off formation)"
    )
    for bad in (["--car-speed", "3", "2"], ["--start-offset", "-1"]):
        with pytest.raises(SystemExit):
            sa.parse_args(bad)


def test_the_grid_takes_other_team_sizes_and_drops():
    opts = sa.parse_args(["--team-sizes", "20", "--drops", "0.9", "0.99", "--worlds", "5"])
    worlds = opts.grid_worlds()
    assert [w.cell for w in worlds] == [
        "n20-integrator-drop0.9", "n20-integrator-drop0.99", "n20-lag-drop0.9",
        "n20-lag-drop0.99", "n20-integrator-drop0.9",
    ]  # fmt: skip
    assert [w.seed for w in worlds] == list(range(5))
    assert sa.make_worlds(12) == sa.make_worlds(12, 0, (3, 6, 10), (0.0, 0.5))


def test_dense_worlds_reach_the_env_and_the_report():
    opts = sa.HarnessOptions(n_obstacles=(30, 34), corridor=1.2)
    env = sa.make_env(sa.make_worlds(1, seed=4)[0], 5, None, opts.random_world())
    try:
        env.reset(seed=4)
        layout = env.unwrapped.layout
        # placement may reject a few boxes, never add: more than the default 16 shows the option
        assert 16 < len(layout.obstacle_centers) <= 34
        assert env.unwrapped.config.random_world.corridor == 1.2
    finally:
        env.close()
    meta = {"worlds": 1, "steps": 5, "n_obstacles": [30, 34], "corridor": 1.2}
    assert "1 worlds (30-34 obstacles, corridor 1.2 m) x 5 steps" in sa.format_report(
        sa.summarize([]), meta
    )


def test_block_car_posts_the_team_low_in_front_of_the_car():
    """block-car's posts lie ahead of the car's front, at most 1.5 m beside its centre line and
    under its roof; each UAV flies straight at its post and turns to face the car."""
    world = sa.WorldSpec(0, 3, "integrator", 0.0, 14)
    starts = {"n_obstacles": (0, 0), "start_heading_offset": 0.6}  # off-formation headings
    env = sa.make_env(world, 400, None, starts)

    def errors(infos):
        posts, out = policy.posts(infos), {}
        for a, post in posts.items():
            own = infos[a]["own"]
            to_car = infos[a]["truth"]["target_position"][:2] - own["position"][:2]
            turn = math.atan2(to_car[1], to_car[0]) - own["yaw"]
            out[a] = (np.linalg.norm(post - own["position"]), abs(math.remainder(turn, math.tau)))
        return out

    try:
        obs, infos = env.reset(seed=14)
        policy = sa.FAMILIES["block-car"](env, np.random.default_rng(2))
        first = errors(infos)
        assert min(e[1] for e in first.values()) > 0.15  # seed 14: 0.18-0.57 rad
        for _ in range(16):  # 0.2 s from the formation start: nobody is near anything yet
            before = errors(infos)
            obs, _r, _t, _tr, infos = env.step(policy(obs, infos))
            for a, (gap, _turn) in errors(infos).items():
                assert gap < before[a][0] - 0.005  # closing on the post
        assert all(errors(infos)[a][1] < 0.8 * first[a][1] for a in first)  # facing the car
        heading = env.unwrapped.target.heading
        forward = np.array([math.cos(heading), math.sin(heading)])
        left = np.array([-forward[1], forward[0]])
        posts = policy.posts(infos)
        assert sorted(posts) == sorted(env.possible_agents)
        for a, post in posts.items():
            rel = post[:2] - infos[a]["truth"]["target_position"][:2]
            assert sa.CAR_HALF_EXTENTS[0] + 0.2 <= rel @ forward <= sa.CAR_HALF_EXTENTS[0] + 3.0
            assert abs(rel @ left) <= 1.5 and 0.3 <= post[2] <= 1.2
    finally:
        env.close()


def test_block_and_press_sends_the_odd_agents_at_their_partners():
    """block-and-press: the even agents fly block-car's posts; each odd one flies at full command
    at the point 0.5 m above the even agent before it."""
    world = sa.WorldSpec(0, 3, "integrator", 0.0, 14)
    env = sa.make_env(world, 400, None, {"n_obstacles": (0, 0)})
    try:
        obs, infos = env.reset(seed=14)
        press = sa.FAMILIES["block-and-press"](env, np.random.default_rng(2))
        block = sa.FAMILIES["block-car"](env, np.random.default_rng(2))
        pressed, plain = press(obs, infos), block(obs, infos)
        for a in ("uav_0", "uav_2"):
            np.testing.assert_array_equal(pressed[a], plain[a])
        own = infos["uav_1"]["own"]
        goal = infos["uav_0"]["own"]["position"] + [0.0, 0.0, 0.5]
        way = cam_to_world(own["yaw"]) @ pressed["uav_1"][:3]
        aim = goal - own["position"]
        assert way @ aim / (np.linalg.norm(way) * np.linalg.norm(aim)) > 1 - 1e-9
        assert np.abs(pressed["uav_1"][:3]).max() == pytest.approx(1.0)
    finally:
        env.close()


# ------------------------------------------------------------------------ a few worlds
STEPS = 200
CELLS = {
    "n3-integrator-drop0": sa.WorldSpec(0, 3, "integrator", 0.0, 101),
    "n6-lag-drop0.5": sa.WorldSpec(1, 6, "lag", 0.5, 102),
    "n3-lag-drop0": sa.WorldSpec(2, 3, "lag", 0.0, 103),
    # World 5 of the harness's grid: spin-climb with half the messages lost
    "n6-integrator-drop0.5": sa.WorldSpec(5, 6, "integrator", 0.5, 5),
}
HARD = ("seek-uav", "seek-ground", "spin-climb", "flee")
"""Hostile families: seeking team-mates and the ground, climbing while spinning, fleeing."""


@functools.cache
def _run(cell: str, family: str, shielded: bool) -> dict:
    opts = sa.HarnessOptions(steps=STEPS, progress=False)
    return sa.run_one(CELLS[cell], family, shielded, opts, expert_config("tuned"))


CASES = [(c, f) for c in CELLS for f in HARD]


@pytest.mark.slow
@pytest.mark.parametrize(("cell", "family"), CASES)
def test_unshielded_adversary_violates(cell, family):
    run = _run(cell, family, False)
    assert run["counts"]["collision"] + run["counts"]["disconnection"] > 0, run


@pytest.mark.slow
@pytest.mark.parametrize(("cell", "family"), CASES)
def test_shielded_run_has_no_violation(cell, family):
    run = _run(cell, family, True)
    assert run["counts"]["collision"] == 0 and run["counts"]["disconnection"] == 0, run
    assert run["agent_steps"] == STEPS * CELLS[cell].n  # nobody was terminated


@pytest.mark.slow
def test_a_pinned_uav_does_not_let_its_team_mate_in():
    """World 54 of the harness's grid (n = 6, lag, no drops): seeking the nearest obstacle pins
    one UAV between a team-mate, an obstacle and the floor, and its fallback gives up the row
    of a second team-mate closing in; that team-mate brakes for the pair on its own."""
    world = sa.WorldSpec(54, 6, "lag", 0.0, 54)
    opts = sa.HarnessOptions(steps=STEPS, progress=False)
    run = sa.run_one(world, "seek-obstacle", True, opts, expert_config("tuned"))
    assert run["statuses"].get("fallback", 0) > 0  # the pinned case does occur
    assert run["counts"]["collision"] == 0 and run["least"]["uav"] >= 0.0, run


@pytest.mark.slow
@pytest.mark.parametrize(
    ("world", "family", "base"),
    [
        (sa.WorldSpec(12, 3, "integrator", 0.0, 777012), "flee", 777000),
        (sa.WorldSpec(1, 3, "integrator", 0.5, 777001), "spin-dive", 777000),
        (sa.WorldSpec(26, 3, "lag", 0.0, 777026), "seek-obstacle", 777000),
        (sa.WorldSpec(13, 3, "integrator", 0.5, 888013), "spin-dive", 888000),
    ],
)
def test_an_unseen_car_does_not_split_the_team(world, family, base):
    """Worlds where the car stays unseen for seconds: its reachable set grows, and a UAV beside
    it keeps the car's row by climbing (the frustum) instead of sideways, away from its
    team-mates, over 400 steps (5 s)."""
    opts = sa.HarnessOptions(steps=400, seed=base, progress=False)
    run = sa.run_one(world, family, True, opts, expert_config("tuned"))
    assert run["counts"]["collision"] == 0 and run["counts"]["disconnection"] == 0, run
    assert run["least"]["link"] >= 0.0


@pytest.mark.slow
def test_a_crowd_over_a_lost_car_does_not_press_a_uav_into_it():
    """Ten UAVs under the lag model all seek the car and lose it from above: their rows conflict
    and fallbacks give the car's row up, but the lost car's rising box lifts the crowd, so no
    UAV is pressed into the car."""
    opts = sa.HarnessOptions(steps=400, seed=888000, progress=False)
    world = sa.WorldSpec(22, 10, "lag", 0.0, 888022)
    run = sa.run_one(world, "seek-car", True, opts, expert_config("tuned"))
    assert run["statuses"].get("fallback", 0) > 0  # the conflicting rows do occur
    assert run["counts"]["collision"] == 0 and run["least"]["car"] > 0.0, run


@pytest.mark.slow
@pytest.mark.parametrize("world", sa.make_worlds(12), ids=lambda w: w.cell)
def test_uavs_posted_in_the_cars_path_among_dense_obstacles_are_never_hit(world):
    """block-car on dense worlds (24-48 obstacles, a 1.5 m corridor), one per grid cell, 400
    steps: UAVs held low in front of the car, often with a box behind them. The shield lets
    nobody collide. Without `SafetyFilter.climb_over_car` the car hits a UAV in the
    n10-lag-drop0.5 world: its fallback gives the car's box row up."""
    opts = sa.HarnessOptions(steps=400, progress=False, n_obstacles=(24, 48), corridor=1.5)
    run = sa.run_one(world, "block-car", True, opts, expert_config("tuned"))
    assert run["counts"]["collision"] == 0 and run["counts"]["disconnection"] == 0, run
    assert run["least"]["car"] > 0.0 and run["agent_steps"] == 400 * world.n
    if world.n == 10 and world.dynamics == "lag":
        assert run["statuses"].get("fallback", 0) > 0  # the rows do conflict


@pytest.mark.slow
@pytest.mark.parametrize(
    ("index", "dense"), [(19, True), (35, True), (47, True), (59, True), (59, False), (71, False)]
)
def test_a_team_mate_pressing_from_a_lost_message_does_not_push_a_uav_into_the_car(index, dense):
    """block-and-press, lag dynamics, half the messages lost, on worlds of seed 100 where a
    frustum certificate that gives the car up before the rows of team-mates known only within a
    ball lets the car touch the pressed UAV: those rows go with the car's, and nobody collides."""
    world = sa.make_worlds(index + 1, seed=100)[index]
    assert world.dynamics == "lag" and world.drop == 0.5
    density = {"n_obstacles": (24, 48), "corridor": 1.5} if dense else {}
    opts = sa.HarnessOptions(steps=400, seed=100, progress=False, **density)
    run = sa.run_one(world, "block-and-press", True, opts, expert_config("tuned"))
    assert run["counts"]["collision"] == 0 and run["counts"]["disconnection"] == 0, run
    assert run["least"]["car"] > 0.0 and run["least"]["uav"] > 0.0


@pytest.mark.slow
@pytest.mark.parametrize("family", ["random-held", "mixed"])
@pytest.mark.parametrize(
    ("world", "timeout"),
    [
        (sa.WorldSpec(6, 20, "integrator", 0.9, 4106), 0.5),
        (sa.WorldSpec(1, 10, "integrator", 0.99, 4101), 3.0),
    ],
    ids=lambda x: x.cell if isinstance(x, sa.WorldSpec) else f"timeout{x:g}",
)
def test_a_team_that_loses_most_messages_keeps_apart(world, timeout, family):
    """20 UAVs in formation hearing 10 % of their messages, and 10 hearing 1 % that keep a
    silent team-mate for 3 s: a team-mate's ball soon swallows a UAV, whose rows then stop it
    (the speed cap) instead of a fallback giving the pair up. Without the cap two UAVs of the
    n = 20 world come within R_s."""
    from uavtrack_env.presets import expert_config_from

    config = expert_config_from("tuned", [f"margins.message_timeout={timeout}"])
    opts = sa.HarnessOptions(steps=300, seed=4100, progress=False)
    run = sa.run_one(world, family, True, opts, config)
    assert run["counts"]["collision"] == 0 and run["least"]["uav"] > 0.0, run
