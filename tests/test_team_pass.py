"""A team's onboard step in two compiled calls (`onboard.observe_team`, `onboard.certify_team`)
equals each UAV's own stack, UAV by UAV and bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uavtrack_env import uavtrack_v0
from uavtrack_env.onboard import certify_team, input_row, input_rows
from uavtrack_env.presets import expert_config
from uavtrack_env.wrappers import CBFShield

WORLD = {
    "scenario": "random",
    "n_uavs": 4,
    "max_cycles": 120,
    "detector": {"dropout_prob": 0.2},
    "comms": {"drop_prob": 0.3},
    "terminate_on_collision": "agent",
}


def _same_report(a, b) -> None:
    for name in ("status", "active", "correction_norm", "slack", "active_rows", "gave_up",
                 "hard_violation", "slack_per_row", "solver", "solver_calls"):  # fmt: skip
        assert getattr(a, name) == getattr(b, name), name
    assert a.family_minima() == b.family_minima()


@pytest.mark.parametrize("dynamics", ["integrator", "lag"])
def test_the_team_certifies_as_each_uav_alone(dynamics):
    """`certify_team` (the pass's own arrays, and rows gathered from several passes) gives every
    UAV the action and report its own `certify_trusted` gives, and its summary (the telemetry,
    read from the arrays, for one UAV or all) says what that report says, for commands the
    shield keeps and corrects (every status of the layers: tests/test_qp_layers.py)."""
    env = uavtrack_v0.parallel_env(**WORLD, dynamics={"model": dynamics})
    shield = CBFShield(env)
    _, infos = shield.reset(seed=11)
    rng = np.random.default_rng(2)
    scale = env.config.limits.scale
    statuses: list[str] = []
    while env.agents:
        agents = [shield.onboard[a] for a in infos]
        u = rng.uniform(-1.5, 1.5, (len(agents), 4)) * scale * rng.choice([0.02, 1.0])
        together = certify_team(agents, u)
        summaries = together.summaries()  # before any report
        assert summaries == [together.summary(j) for j in range(len(agents))]
        rows = [a.rows() for a in agents]
        own = [a.info["own"] for a in agents]
        gathered = agents[0].filter.certify_many(
            u, np.array([o["yaw"] for o in own]), np.array([o["velocity"] for o in own]), rows,
            [a.neighbour_ids() for a in agents],
        )  # fmt: skip
        for j, agent in enumerate(agents):
            alone, report = agent.certify_trusted(u[j])
            for done in (together, gathered):
                np.testing.assert_array_equal(done.action[j], alone)
                _same_report(done.report(j), report)
                assert done.changed[j] == report.active
                assert done.correction_norm[j] == report.correction_norm
                assert done.hard_violation[j] == report.hard_violation
                assert done.fallback[j] == (report.status == "fallback")
                assert done.min_hard_h()[j] == report.min_hard_h
            np.testing.assert_array_equal(together.report(j).rows.b, report.rows.b)
            min_h, min_hard_h = report.family_minima()
            assert summaries[j] == {
                "active": report.active, "correction_norm": report.correction_norm,
                "status": report.status, "active_rows": report.active_rows,
                "gave_up": report.gave_up, "slack": report.slack,
                "hard_violation": report.hard_violation, "min_h": min_h,
                "min_hard_h": min_hard_h,
            }  # fmt: skip
            statuses.append(report.status)
        infos = shield.step({a: rng.uniform(-1, 1, 4) for a in env.agents})[4]
    assert statuses.count("nominal") > 20 and len(statuses) - statuses.count("nominal") > 20
    env.close()


def test_trackers_outside_a_bank_feed_the_pass_alike():
    """With plain filterpy trackers (`UKFConfig.vectorized=False`) the pass takes the estimates
    from the trackers: the rows equal those `RowBuilder` builds from the same context, and the
    shield's actions stay within round-off of the bank's."""
    cfg = expert_config("tuned")
    plain = dataclasses.replace(cfg, ukf=dataclasses.replace(cfg.ukf, vectorized=False))
    envs = [uavtrack_v0.parallel_env(**WORLD) for _ in range(2)]
    shields = [CBFShield(envs[0], cfg), CBFShield(envs[1], plain)]
    infos = [s.reset(seed=5)[1] for s in shields]
    rng = np.random.default_rng(3)
    compared = 0
    for _ in range(60):
        if not envs[1].agents:
            break
        for agent in infos[1]:
            onboard = shields[1].onboard[agent]
            assert onboard.tracker.bank is None
            mine, theirs = onboard.rows(), onboard.filter.rows(onboard.context())
            np.testing.assert_array_equal(mine.A, theirs.A)
            np.testing.assert_array_equal(mine.b, theirs.b)
            compared += onboard.tracker.has_estimate
        actions = {a: rng.uniform(-0.3, 0.3, 4) for a in envs[1].agents}
        outs = [s.step(dict(actions)) for s in shields]
        infos = [o[4] for o in outs]
        for a in infos[1]:
            np.testing.assert_allclose(
                infos[1][a]["shield"]["action"], infos[0][a]["shield"]["action"], atol=1e-6
            )
    assert compared > 50
    for env in envs:
        env.close()


def test_estimates_are_made_once_per_step():
    """A bank's estimate is made when first read, the same object on every read within its step,
    and a new one after the next step; earlier estimates keep their values."""
    env = uavtrack_v0.parallel_env(scenario="A")
    shield = CBFShield(env)
    shield.reset(seed=0)
    tracker = shield.onboard["uav_0"].tracker
    first = tracker.estimate
    assert first is not None and tracker.estimate is first and tracker.has_estimate
    kept = first.target_position.copy()
    shield.step({a: np.zeros(4) for a in env.agents})
    second = tracker.estimate
    assert second is not first and second is tracker.bank.estimates[tracker.slot]
    np.testing.assert_array_equal(first.target_position, kept)
    tracker.reset()
    assert tracker.estimate is None and not tracker.has_estimate
    env.close()


def test_input_rows_of_arrays_equal_those_of_infos():
    """`input_rows` (the detector's frame and the UAVs' state as arrays, the vector shield's
    route) gives each UAV the row `input_row` reads from its info, bit for bit, detected or
    not, with boxes cut by the image border."""
    env = uavtrack_v0.parallel_env(**WORLD)
    _, infos = env.reset(seed=4)
    rng = np.random.default_rng(5)
    detected = cut = 0
    for _ in range(80):
        state = (env.position, env.yaw, env.velocity, env.yaw_rate)
        rows = input_rows(env.last_detection, state)
        for agent, info in infos.items():
            np.testing.assert_array_equal(rows[env.possible_agents.index(agent)], input_row(info))
            detected += info["measurement"]["detected"]
            cut += bool(info["measurement"]["truncated_u"] or info["measurement"]["truncated_v"])
        if not env.agents:
            break
        infos = env.step({a: rng.uniform(-1, 1, 4) for a in env.agents})[4]
    assert detected > 50 and cut > 0
    env.close()


def test_a_lone_stack_takes_teams_of_any_size_a_shared_one_says_what_is_wrong():
    """An `OnboardAgent` built alone keeps a team state of its own, made anew for a team of
    another size; the stacks of `onboard_team` share one and refuse another team size with a
    clear error, changing nothing."""
    from uavtrack_env.onboard import OnboardAgent, onboard_team

    small = uavtrack_v0.parallel_env(scenario="random", n_uavs=3)
    large = uavtrack_v0.parallel_env(scenario="random", n_uavs=5)
    small.reset(seed=0)
    _, infos = large.reset(seed=1)
    cfg = expert_config("tuned")
    alone = OnboardAgent("uav_0", 0, small.config, cfg)
    alone.reset(small.layout, small.possible_agents)
    alone.reset(large.layout, large.possible_agents)
    alone.observe(infos["uav_0"])
    assert len(alone.belief.ids) <= 4 and alone.team.n == 5
    shared = onboard_team(small.possible_agents, small.config, cfg)[0][0]
    team = shared.team
    with pytest.raises(ValueError, match="holds teams of 3 UAVs"):
        shared.reset(large.layout, large.possible_agents)
    assert shared.team is team and team.n == 3
    small.close()
    large.close()


@pytest.mark.parametrize("worlds", [1, 3])
def test_one_compiled_call_per_team_equals_the_call_by_call_route(worlds, monkeypatch):
    """`observe_frame` (the input rows, the bank's UKF step and the pass in one compiled call)
    leaves every team's state, estimates and pass outputs bit-identical to the route that takes
    them call by call (`input_rows`, `TrackerBank.step`, `observe_pass`), for K worlds at once,
    with UAVs that left the team or come in any order, dropouts, lost messages and lag
    dynamics."""
    from uavtrack_env import onboard
    from uavtrack_env.onboard import observe_frame, onboard_team

    envs = [uavtrack_v0.parallel_env(**WORLD, dynamics={"model": "lag"}) for _ in range(worlds)]
    cfg = expert_config("tuned")
    teams = [onboard_team(envs[0].possible_agents, envs[0].config, cfg, worlds) for _ in range(2)]
    for k, env in enumerate(envs):
        env.reset(seed=20 + k)
        for team in teams:
            for agent in team[k]:
                agent.reset(env.layout, env.possible_agents)
    one_bank = onboard._one_bank
    rng = np.random.default_rng(6)
    n, compared = len(envs[0].possible_agents), 0
    for _ in range(90):
        live = [(k, env.possible_agents.index(a)) for k, env in enumerate(envs) for a in env.agents]
        if not live:
            break
        live = [live[j] for j in rng.permutation(len(live))]  # in any order
        ks, ids = np.array(live).T
        frame = [envs[k].last_detection for k in range(worlds)]
        det = type(frame[0])(*[np.stack([getattr(f, name) for f in frame]) for name in
                               frame[0].__dataclass_fields__])  # fmt: skip
        state = tuple(np.stack([getattr(e, name) for e in envs]) for name in
                      ("position", "yaw", "velocity", "yaw_rate"))  # fmt: skip
        received = np.stack([e.last_received for e in envs])
        outs = []
        for route, team in zip((one_bank, lambda agents: False), teams, strict=True):
            monkeypatch.setattr(onboard, "_one_bank", route)
            agents = [team[k][i] for k, i in live]
            observe_frame(agents, det, state, ks * n + ids, received, state[0])
            outs.append(agents[0]._seen[0])
        used = outs[0].start[-1]  # the rows written; room beyond them is not
        for a, b in zip(*[(o.A[:used], o.floats[:, :used], o.ints[:, :used], *o[4:], o.data)
                          for o in outs], strict=True):  # fmt: skip
            np.testing.assert_array_equal(a, b)
        for name, value in vars(teams[0][0][0].team).items():
            np.testing.assert_array_equal(value, vars(teams[1][0][0].team)[name], err_msg=name)
        banks = [team[0][0].tracker.bank for team in teams]
        for a, b in zip(banks[0].kernel_args, banks[1].kernel_args, strict=True):
            np.testing.assert_array_equal(a, b)
        compared += len(live)
        for env in envs:
            if env.agents:
                env.step({a: rng.uniform(-1, 1, 4) for a in env.agents})
    assert compared > 150 * worlds
    for env in envs:
        env.close()
