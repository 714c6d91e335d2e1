"""Every bad input to step() raises a clear error and leaves the env exactly as it was."""

from __future__ import annotations

import copy

import numpy as np
import pytest

AGENTS = ["uav_0", "uav_1", "uav_2"]
GOOD = np.array([0.05, -0.02, 0.1, 0.03], np.float32)


def _snapshot(env) -> dict:
    snap = env.snapshot()
    return {
        "position": snap.positions,
        "yaw": snap.yaws,
        "velocity": snap.velocities,
        "yaw_rate": snap.yaw_rates,
        "num_cycles": env.num_cycles,
        "target": snap.target_center,
        "target_heading": snap.target_heading,
        "rng": copy.deepcopy(env.np_random.bit_generator.state),
        "agents": list(env.agents),
        "alive": snap.alive,
    }


def _assert_unchanged(before: dict, after: dict) -> None:
    assert before.keys() == after.keys()
    for key, value in before.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(after[key], value, err_msg=key)
        else:
            assert after[key] == value, key


def _ready(make_env, steps: int = 3, **kw):
    """An env a few steps into an episode, and a twin that will only see the good actions."""
    env, twin = make_env(**kw), make_env(**kw)
    for e in (env, twin):
        e.reset(seed=5)
        for _ in range(steps):
            e.step({a: GOOD for a in e.agents})
    return env, twin


def _same_next_step(env, twin) -> None:
    """After the rejected call, a good step gives bit-identical results to the untouched twin."""
    out = env.step({a: GOOD for a in env.agents})
    ref = twin.step({a: GOOD for a in twin.agents})
    for got, want in zip(out, ref, strict=True):
        assert got.keys() == want.keys()
    for a in out[0]:
        np.testing.assert_array_equal(out[0][a], ref[0][a])
        assert out[1][a] == ref[1][a]
        assert out[4][a]["n_clipped_actions"] == ref[4][a]["n_clipped_actions"]
        assert out[4][a]["measurement"] == ref[4][a]["measurement"]


BAD_ACTIONS = [
    (np.array([np.nan, 0, 0, 0]), ValueError, "not finite"),
    (np.array([0, np.inf, 0, 0]), ValueError, "not finite"),
    (np.array([0, 0, -np.inf, 0]), ValueError, "not finite"),
    ([0.0, 0.0, float("nan"), 0.0], ValueError, "not finite"),
    (np.zeros(3), ValueError, r"shape \(3,\).*expected \(4,\)"),
    (np.zeros((2, 2)), ValueError, r"shape \(2, 2\).*expected \(4,\)"),
    (np.zeros(5), ValueError, r"shape \(5,\)"),
    (np.float32(0.5), ValueError, r"shape \(\)"),
    ([[0.1, 0.2, 0.3, 0.4]], ValueError, r"shape \(1, 4\)"),
    ("fast", ValueError, "cannot be read as 4 floats"),
    (object(), ValueError, "cannot be read as 4 floats"),
    ({"v": 1.0}, ValueError, "cannot be read as 4 floats"),
    (None, ValueError, "cannot be read as 4 floats|shape"),
    ([0.1, "x", 0.0, 0.0], ValueError, "cannot be read as 4 floats"),
]


@pytest.mark.parametrize(("bad", "error", "pattern"), BAD_ACTIONS)
@pytest.mark.parametrize("who", ["uav_0", "uav_2"])
def test_bad_action_values_raise_and_change_nothing(make_env, bad, error, pattern, who):
    env, twin = _ready(make_env)
    before = _snapshot(env)
    actions = {a: GOOD for a in env.agents}
    actions[who] = bad
    with pytest.raises(error, match=pattern) as exc:
        env.step(actions)
    assert who in str(exc.value)  # the message names the offending agent
    _assert_unchanged(before, _snapshot(env))
    _same_next_step(env, twin)


@pytest.mark.parametrize(("bad", "error", "pattern"), BAD_ACTIONS)
def test_validate_actions_raises_the_same_errors_and_changes_nothing(make_env, bad, error, pattern):
    """The public check the shield wrapper uses: step()'s errors, without stepping."""
    env, twin = _ready(make_env)
    before = _snapshot(env)
    with pytest.raises(error, match=pattern) as exc:
        env.validate_actions({"uav_0": GOOD, "uav_1": bad, "uav_2": GOOD})
    assert "uav_1" in str(exc.value)
    u, clipped = env.validate_actions({a: GOOD for a in env.agents})
    np.testing.assert_array_equal(u, np.tile(GOOD.astype(np.float64), (3, 1)) * [10, 10, 10, 0.6])
    assert not clipped.any()
    _assert_unchanged(before, _snapshot(env))
    _same_next_step(env, twin)


def test_actions_not_a_dict(make_env):
    env, twin = _ready(make_env)
    before = _snapshot(env)
    for bad in ([GOOD, GOOD, GOOD], np.zeros((3, 4)), None):
        with pytest.raises(ValueError, match="must be a dict"):
            env.step(bad)
    _assert_unchanged(before, _snapshot(env))
    _same_next_step(env, twin)


def test_unknown_agent_key(make_env):
    env, twin = _ready(make_env)
    before = _snapshot(env)
    for key in ("uav_3", "agent_0", 0):
        actions = {a: GOOD for a in env.agents}
        actions[key] = GOOD
        with pytest.raises(KeyError, match="unknown agent"):
            env.step(actions)
    _assert_unchanged(before, _snapshot(env))
    _same_next_step(env, twin)


def test_missing_live_agent(make_env):
    env, twin = _ready(make_env)
    before = _snapshot(env)
    with pytest.raises(KeyError, match=r"no action for live agent.*uav_1"):
        env.step({"uav_0": GOOD, "uav_2": GOOD})
    with pytest.raises(KeyError, match="no action for live agent"):
        env.step({})
    _assert_unchanged(before, _snapshot(env))
    _same_next_step(env, twin)


def test_action_for_finished_agent(make_env):
    env = make_env(terminate_on_collision="agent")
    env.reset(seed=0)
    env.position[0, 2] = 0.2  # inside the ground's reach: uav_0 crashes on the next step
    _, _, term, _, infos = env.step({a: np.zeros(4) for a in env.agents})
    assert term == {"uav_0": True, "uav_1": False, "uav_2": False}
    assert infos["uav_0"]["collision_with"]["ground"]
    assert env.agents == ["uav_1", "uav_2"]
    before = _snapshot(env)
    with pytest.raises(KeyError, match=r"finished agent 'uav_0'"):
        env.step({a: GOOD for a in AGENTS})
    _assert_unchanged(before, _snapshot(env))
    # The live agents still step fine afterwards, and the finished one stays out.
    _, _, term, _, _ = env.step({"uav_1": GOOD, "uav_2": GOOD})
    assert set(term) == {"uav_1", "uav_2"}


def test_step_before_reset(make_env):
    env = make_env()
    with pytest.raises(RuntimeError, match="before reset"):
        env.step({a: GOOD for a in AGENTS})
    assert env.agents == [] and env.num_cycles == 0
    with pytest.raises(RuntimeError, match="before reset"):
        env.state()
    env.reset(seed=0)  # works normally afterwards
    env.step({a: GOOD for a in env.agents})
    assert env.num_cycles == 1


def test_step_after_episode_end(make_env):
    env = make_env(max_cycles=2)
    env.reset(seed=0)
    env.step({a: GOOD for a in env.agents})
    _, _, _, trunc, _ = env.step({a: GOOD for a in env.agents})
    assert all(trunc.values()) and env.agents == []
    before = _snapshot(env)
    for actions in ({a: GOOD for a in AGENTS}, {}):
        with pytest.raises(RuntimeError, match="episode is over"):
            env.step(actions)
    _assert_unchanged(before, _snapshot(env))
    env.reset(seed=0)
    assert env.agents == AGENTS


def test_step_after_all_terminated(make_env):
    env = make_env(terminate_on_collision="all")
    env.reset(seed=0)
    env.position[1, 2] = 0.1
    _, _, term, _, _ = env.step({a: np.zeros(4) for a in env.agents})
    assert all(term.values()) and env.agents == []
    before = _snapshot(env)
    with pytest.raises(RuntimeError, match="episode is over"):
        env.step({a: GOOD for a in AGENTS})
    _assert_unchanged(before, _snapshot(env))


def test_acceptable_action_types(make_env):
    """Lists, tuples, float64 and integer arrays are all read as 4 numbers."""
    env, twin = _ready(make_env)
    ref = twin.step({a: np.array([0, 0, 0, 0], np.float32) for a in twin.agents})
    out = env.step(
        {"uav_0": [0, 0, 0, 0], "uav_1": (0.0, 0.0, 0.0, 0.0), "uav_2": np.zeros(4, int)}
    )
    for a in AGENTS:
        np.testing.assert_array_equal(out[0][a], ref[0][a])


# ----------------------------------------------------------------------------- clipping
def test_out_of_range_actions_are_clipped_and_counted(make_env):
    env, twin = _ready(make_env, steps=1)
    big = np.array([2.0, -3.0, 0.5, 1.5])
    clipped = np.clip(big, -1.0, 1.0)
    counts = []
    for k in range(3):
        act_env = {a: GOOD for a in env.agents}
        act_twin = {a: GOOD for a in twin.agents}
        act_env["uav_1"] = big if k != 1 else clipped  # step 1: in range
        act_twin["uav_1"] = clipped
        out = env.step(act_env)
        ref = twin.step(act_twin)
        for a in AGENTS:
            np.testing.assert_array_equal(out[0][a], ref[0][a])
            assert out[1][a] == ref[1][a]
            np.testing.assert_array_equal(
                out[4][a]["own"]["position"], ref[4][a]["own"]["position"]
            )
            np.testing.assert_array_equal(
                out[4][a]["own"]["applied_u"], ref[4][a]["own"]["applied_u"]
            )
        info = out[4]["uav_1"]
        assert info["action_clipped"] is (k != 1)
        counts.append(info["n_clipped_actions"])
        assert out[4]["uav_0"]["action_clipped"] is False
        assert out[4]["uav_0"]["n_clipped_actions"] == 0
        assert ref[4]["uav_1"]["n_clipped_actions"] == 0
        # Table II scaling of the clipped action: [10, 10, 10, 0.6] * a.
        np.testing.assert_allclose(
            out[4]["uav_1"]["own"]["applied_u"], clipped * [10.0, 10.0, 10.0, 0.6], rtol=1e-12
        )
    assert counts == [1, 1, 2]
    # The counter restarts with the episode.
    _, infos = env.reset(seed=5)
    assert all(infos[a]["n_clipped_actions"] == 0 for a in AGENTS)


def test_slightly_out_of_range_counts_and_boundary_does_not(make_env):
    env = make_env()
    env.reset(seed=0)
    acts = {a: np.zeros(4) for a in env.agents}
    acts["uav_0"] = np.array([1.0, -1.0, 1.0, -1.0])  # on the boundary: fine
    acts["uav_2"] = np.array([0.0, 0.0, 0.0, 1.0 + 1e-6])
    _, _, _, _, infos = env.step(acts)
    assert infos["uav_0"]["action_clipped"] is False
    assert infos["uav_2"]["action_clipped"] is True
    assert infos["uav_2"]["n_clipped_actions"] == 1


@pytest.mark.parametrize(
    ("bad", "message"),
    [(np.zeros(3), r"has shape \(3,\)"), (np.array([0, 0, np.nan, 0]), "is not finite")],
)
@pytest.mark.parametrize("position", [0, 1, 2])
def test_aec_rejects_a_bad_action_when_its_agent_steps(bad, message, position):
    """The AEC env names the agent whose action is bad as it steps, and changes nothing."""
    from uavtrack_env import uavtrack_v0

    env = uavtrack_v0.env(scenario="A")
    env.reset(seed=0)
    for k, agent in enumerate(env.agent_iter()):
        if k < position:
            env.step(np.zeros(4, np.float32))
            continue
        with pytest.raises(ValueError, match=rf"action for '{agent}' {message}"):
            env.step(bad)
        assert env.agent_selection == agent  # still this agent's turn
        env.step(np.zeros(4, np.float32))
        break
    env.close()
