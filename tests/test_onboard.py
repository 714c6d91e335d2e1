"""One onboard stack: the expert's and the shield's certify agree; a new layout reaches every
stateful part of the expert, the shield and the single-agent view."""

from __future__ import annotations

import numpy as np
import pytest

from uavtrack_env import uavtrack_v0
from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.onboard import observe_team
from uavtrack_env.wrappers import CBFShield, SingleAgentView

WORLD = {
    "scenario": "random",
    "n_uavs": 4,
    "max_cycles": 60,
    "dynamics": {"model": "lag"},
    "detector": {"dropout_prob": 0.2},
    "comms": {"drop_prob": 0.1},
    "terminate_on_collision": "agent",
}


@pytest.mark.filterwarnings("ignore:the shield certifies")
@pytest.mark.parametrize("preset", ["tuned", "paper"])
def test_expert_and_shield_certify_alike(preset):
    """Fed the same info stream, the expert's and the shield's stacks build identical rows and
    return identical safe actions for the same (hostile) nominal commands."""
    env = uavtrack_v0.parallel_env(**WORLD)
    shield = CBFShield(env, preset)
    _, infos = shield.reset(seed=7)
    expert = ExpertPolicy.from_env(env, preset)
    rng = np.random.default_rng(0)
    compared = 0
    while env.agents:
        # the shield observed the same infos in reset/step, as one team
        observe_team([expert.onboard[a] for a in infos], list(infos.values()))
        for agent in infos:
            mine, theirs = expert.onboard[agent], shield.onboard[agent]
            assert mine is not theirs
            rows_e, rows_s = mine.rows(), theirs.rows()
            np.testing.assert_array_equal(rows_e.A, rows_s.A)
            np.testing.assert_array_equal(rows_e.b, rows_s.b)
            np.testing.assert_array_equal(rows_e.h, rows_s.h)
            u_nominal = rng.uniform(-1.5, 1.5, 4) * env.config.limits.scale
            u_e, rep_e = mine.certify(u_nominal)
            u_s, rep_s = theirs.certify(u_nominal)
            np.testing.assert_array_equal(u_e, u_s)
            assert rep_e.status == rep_s.status and rep_e.active_rows == rep_s.active_rows
            compared += rep_e.active
        actions = {a: rng.uniform(-1, 1, 4).astype(np.float32) for a in env.agents}
        infos = shield.step(actions)[4]
    assert compared > 20  # the nominals were corrected, so the QPs were compared too
    env.close()


def test_an_agents_certify_equals_the_filters_checked_certify():
    """`OnboardAgent.certify` (the unchecked way for a finite command) returns what
    `SafetyFilter.certify` returns on the agent's context and rows, bit for bit; a NaN or a
    wrong shape gets the filter's clear error."""
    env = uavtrack_v0.parallel_env(**WORLD)
    shield = CBFShield(env)
    _, infos = shield.reset(seed=9)
    rng = np.random.default_rng(4)
    corrected = 0
    while env.agents:
        for agent in infos:
            onboard = shield.onboard[agent]
            u = rng.uniform(-1.5, 1.5, 4) * env.config.limits.scale * rng.choice([0.05, 1.0])
            mine, rep = onboard.certify(u)
            theirs, ref = onboard.filter.certify(u, onboard.context(), onboard.rows())
            np.testing.assert_array_equal(mine, theirs)
            assert (rep.status, rep.active_rows, rep.gave_up, rep.slack) == (
                ref.status,
                ref.active_rows,
                ref.gave_up,
                ref.slack,
            )
            corrected += rep.active
        infos = shield.step({a: rng.uniform(-1, 1, 4) for a in env.agents})[4]
    assert corrected > 20
    onboard = shield.onboard[env.possible_agents[0]]
    with pytest.raises(ValueError, match="must be finite"):
        onboard.certify(np.array([np.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        onboard.certify(np.zeros(3))
    env.close()


def _assert_knows_layout(expert: ExpertPolicy, layout) -> None:
    for i, agent in enumerate(expert.agent_names):
        onboard, planner = expert.onboard[agent], expert.planners[agent]
        np.testing.assert_array_equal(onboard.obstacle_centers, layout.obstacle_centers)
        np.testing.assert_array_equal(onboard.obstacle_half_extents, layout.obstacle_half_extents)
        np.testing.assert_array_equal(planner.viewpoint.centers, layout.obstacle_centers)
        np.testing.assert_array_equal(planner.viewpoint.half_extents, layout.obstacle_half_extents)
        np.testing.assert_array_equal(planner.reference, layout.references[i])
        assert onboard.estimate is None and planner.last_u.tolist() == [0.0] * 4


def test_a_new_layout_reaches_every_stateful_part():
    env = uavtrack_v0.parallel_env(scenario="random", max_cycles=30)
    obs, infos = env.reset(seed=1)
    expert = ExpertPolicy.from_env(env)
    first = env.layout
    for _ in range(5):
        obs, _, _, _, infos = env.step(expert(obs, infos))
    assert any(expert.onboard[a].estimate is not None for a in env.agents)
    env.reset(seed=2)
    assert env.layout.obstacle_centers.shape != first.obstacle_centers.shape or not np.array_equal(
        env.layout.obstacle_centers, first.obstacle_centers
    )
    expert.reset(env.layout)
    _assert_knows_layout(expert, env.layout)
    env.close()


def test_single_agent_view_hands_the_expert_each_new_map():
    """Regression: the team-mates' viewpoint planners must not keep the first world's boxes."""
    env = SingleAgentView(uavtrack_v0.parallel_env(scenario="random", max_cycles=20))
    env.reset(seed=1)
    maps = [env.env.unwrapped.layout]
    for seed in (2, 3):
        env.reset(seed=seed)
        maps.append(env.env.unwrapped.layout)
        _assert_knows_layout(env.expert, env.env.unwrapped.layout)
    assert not np.array_equal(maps[0].obstacle_centers, maps[1].obstacle_centers)
    env.close()


def test_shield_takes_each_new_map():
    env = CBFShield(uavtrack_v0.parallel_env(scenario="random", max_cycles=20))
    for seed in (1, 2):
        env.reset(seed=seed)
        layout = env.unwrapped.layout
        for agent in env.possible_agents:
            ctx = env.context(agent)
            np.testing.assert_array_equal(ctx.obstacle_centers, layout.obstacle_centers)
            np.testing.assert_array_equal(ctx.obstacle_half_extents, layout.obstacle_half_extents)
    env.close()


def test_expert_acts_only_after_a_layout():
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=5)
    _, infos = env.reset(seed=0)
    expert = ExpertPolicy(env.possible_agents, env.config)
    with pytest.raises(RuntimeError, match="reset"):
        expert.act("uav_0", infos["uav_0"])
    expert.reset(env.layout)
    assert expert.act("uav_0", infos["uav_0"]).shape == (4,)
    env.close()


@pytest.mark.filterwarnings("ignore:the shield certifies")
@pytest.mark.parametrize("dynamics", ["integrator", "lag"])
def test_lost_messages_keep_each_teammate_inside_its_reachable_set(dynamics):
    """With half the messages lost, every team-mate stays known, and its true position and
    velocity lie within the belief's radii (the reachable-set bound of `NeighbourTable`)."""
    env = CBFShield(
        uavtrack_v0.parallel_env(
            scenario="random",
            n_uavs=4,
            max_cycles=120,
            dynamics={"model": dynamics},
            comms={"drop_prob": 0.5},
        )
    )
    _, infos = env.reset(seed=4)
    rng = np.random.default_rng(1)
    stale, moving = 0, 0
    while env.agents:
        for agent in env.agents:
            belief = env.onboard[agent].belief
            assert len(belief.names) == 3  # nobody is forgotten for a lost message
            for k, name in enumerate(belief.names):
                truth = infos[name]["own"]
                err = np.linalg.norm(truth["position"] - belief.positions[k])
                assert err <= belief.position_radius[k] + 1e-9, (name, belief.ages[k], err)
                if dynamics == "lag":
                    dv = np.linalg.norm(truth["velocity"] - belief.velocities[k])
                    assert dv <= belief.velocity_radius[k] + 1e-9
                    moving += belief.ages[k] > 0 and np.abs(belief.velocities[k]).max() > 0.5
                stale += belief.ages[k] > 0
        actions = {a: rng.uniform(-1, 1, 4).astype(np.float32) for a in env.agents}
        infos = env.step(actions)[4]
    assert stale > 100  # many beliefs came from old messages
    if dynamics == "lag":
        assert moving > 20  # a missed message does not zero the velocity
    env.close()


def test_a_silent_teammate_is_forgotten_after_the_timeout():
    from uavtrack_env.onboard import NeighbourTable

    table = NeighbourTable(speed_bound=10.0, timeout=5)
    table.reset(["a", "b", "c"], np.array([[0, 0, 1], [3, 0, 1], [40, 0, 1]]), "a", r_c=20.0)
    assert table.belief().names == ("b",)  # c starts beyond R_c
    for step in range(1, 6):
        table.update({})
        belief = table.belief()
        if step < 5:
            assert belief.names == ("b",) and belief.ages[0] == step
            assert belief.position_radius[0] == pytest.approx(10.0 * step / 80.0)
    assert table.belief().names == ()
    table.update({"c": np.array([19.0, 0.0, 1.0])})
    assert table.belief().names == ("c",) and table.belief().position_radius[0] == 0.0


@pytest.mark.parametrize("accel_bound", [None, 6.0])
def test_take_is_update_then_belief(accel_bound):
    """`NeighbourTable.take` (one compiled call) believes what `update` then `belief` do, over
    a stream of dropped, delayed and returning messages."""
    from uavtrack_env.onboard import NeighbourTable

    names = ["a", "b", "c", "d"]
    start = np.array([[0, 0, 1], [3, 0, 1], [0, 4, 1], [6, 6, 1]], float)
    fused, split = (NeighbourTable(10.0, accel_bound, timeout=6) for _ in range(2))
    for table in (fused, split):
        table.reset(names, start, "a", r_c=20.0)
    rng = np.random.default_rng(0)
    pos = start.copy()
    for _ in range(200):
        pos += rng.uniform(-0.1, 0.1, pos.shape)
        messages = {n: pos[k].copy() for k, n in enumerate(names[1:], 1) if rng.random() < 0.6}
        got = fused.take(messages)
        split.update(messages)
        want = split.belief()
        assert got.names == want.names and got.ids == want.ids
        for field in ("positions", "velocities", "position_radius", "velocity_radius", "ages"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field))


@pytest.mark.filterwarnings("ignore:the shield certifies")
@pytest.mark.parametrize(("dynamics", "mate_radius"), [("lag", 0.0), ("lag", None),
                                                       ("integrator", None)])  # fmt: skip
def test_the_trusted_context_builds_the_rows_of_a_checked_one(dynamics, mate_radius):
    """The onboard stack builds its SafetyContext without re-checking the env's arrays; the
    same values through SafetyContext's checks give bit-identical rows to the compiled pass's.
    With ``cbf.team_mate_radius=None`` the team-mates occlude with the world's UAV radius, and
    the pass builds their occlusion rows as the row builder does."""
    import dataclasses

    from uavtrack_env.presets import expert_config
    from uavtrack_env.safety import SafetyContext

    env = uavtrack_v0.parallel_env(**{**WORLD, "uav_radius": 0.3, "dynamics": {"model": dynamics}})
    shield = CBFShield(env, expert_config("tuned", cbf={"team_mate_radius": mate_radius}))
    _, infos = shield.reset(seed=3)
    rng = np.random.default_rng(1)
    compared, mate_rows = 0, 0
    for _ in range(40):
        for agent in infos:
            onboard = shield.onboard[agent]
            assert onboard.cbf.team_mate_radius == (0.3 if mate_radius is None else 0.0)
            ctx = onboard.context()
            checked = SafetyContext(
                **{f.name: getattr(ctx, f.name) for f in dataclasses.fields(ctx)}
            )
            mine, theirs = onboard.rows(), onboard.filter.rows(checked)
            for name in ("A", "b", "h", "kind", "index"):
                np.testing.assert_array_equal(getattr(mine, name), getattr(theirs, name))
            compared += ctx.target_position is not None
            mate_rows += int(((mine.kind == 5) & (mine.index < 0)).sum())
        if not env.agents:
            break
        infos = shield.step({a: rng.uniform(-1, 1, 4) for a in env.agents})[4]
    assert compared > 20
    assert (mate_rows > 0) == (mate_radius is None)
    with pytest.raises(TypeError, match="no fields"):
        SafetyContext.trusted(position=np.zeros(3), yaw=0.0, speed=1.0)
    env.close()


def test_bank_trackers_equal_plain_filterpy_trackers_on_an_episode():
    """The trackers of a team's `TrackerBank` and plain-filterpy trackers (the preset's
    `UKFConfig` with ``vectorized=False``), fed the same infos of an episode with detector
    dropouts and crashing UAVs, hold the same estimates (to 1e-8) and start at the same
    detection."""
    import dataclasses

    from uavtrack_env.onboard import OnboardTracker, input_row, onboard_team, update_trackers
    from uavtrack_env.presets import expert_config

    env = uavtrack_v0.parallel_env(**WORLD)
    _, infos = env.reset(seed=3)
    names, cam = env.possible_agents, env.config.camera
    cfg = expert_config("tuned")
    team = [a.tracker for a in onboard_team(names, env.config, cfg)[0]]
    ukf = dataclasses.replace(cfg.ukf, vectorized=False)
    plain = [OnboardTracker(cam, ukf) for _ in names]
    assert all(t.bank is team[0].bank for t in team) and plain[0].bank is None
    rng = np.random.default_rng(1)
    compared = 0
    while env.agents:
        live = [names.index(a) for a in infos]
        data = np.array([input_row(info) for info in infos.values()])
        update_trackers([team[i] for i in live], data)
        update_trackers([plain[i] for i in live], data)
        for i in live:
            b, p = team[i].estimate, plain[i].estimate
            assert (b is None) == (p is None)
            if b is not None:
                assert (b.detected, b.steps_since_detection) == (
                    p.detected,
                    p.steps_since_detection,
                )
                np.testing.assert_allclose(b.s, p.s, atol=1e-8, rtol=0)
                np.testing.assert_allclose(b.target_position, p.target_position, atol=1e-8)
                np.testing.assert_allclose(b.covariance, p.covariance, atol=1e-8, rtol=0)
                compared += 1
        _, _, _, _, infos = env.step({a: rng.uniform(-1, 1, 4) for a in env.agents})
    assert compared > 100
    env.close()
