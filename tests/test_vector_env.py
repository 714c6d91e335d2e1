"""vector_env: K worlds as arrays. World k equals a ParallelEnv seeded s + k; autoreset; arrays
of the right shapes; bad input raises and changes nothing."""

from __future__ import annotations

import numpy as np
import pytest

from uavtrack_env import uavtrack_v0

KW = {"scenario": "random", "max_cycles": 30}


def _actions(rng, k: int, n: int) -> np.ndarray:
    return rng.uniform(-1.2, 1.2, (k, n, 4)).astype(np.float32)


@pytest.fixture
def vec():
    made = []

    def factory(num_envs=3, **kw):
        env = uavtrack_v0.vector_env(num_envs, **{**KW, **kw})
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()


@pytest.mark.parametrize("full_infos", [True, False], ids=["world-by-world", "batched"])
@pytest.mark.parametrize("terminate", ["agent", "all", "never"])
def test_world_k_equals_a_parallel_env_seeded_s_plus_k(vec, make_env, terminate, full_infos):
    """Same observations, rewards, terminations, truncations and costs, with collisions, for
    the batched step and the world-by-world one (``full_infos``)."""
    k_worlds, seed, steps = 3, 11, 30
    v = vec(k_worlds, terminate_on_collision=terminate, full_infos=full_infos)
    rng = np.random.default_rng(0)
    actions = [_actions(rng, k_worlds, 3) for _ in range(steps)]
    for a in actions:
        a[1:, 0, 1] = 1.0  # uav_0 of worlds 1 and 2 dives into the ground
    obs, infos = v.reset(seed=seed)
    trace = [(obs, None, None, None, infos)]
    for a in actions:
        trace.append(v.step(a))
    ended_any = False
    for k in range(k_worlds):
        env = make_env(**KW, terminate_on_collision=terminate)
        o, _ = env.reset(seed=seed + k)
        np.testing.assert_allclose(trace[0][0][k], np.stack(list(o.values())), atol=1e-5)
        for t, a in enumerate(actions, start=1):
            vo, vr, vterm, vtrunc, vinfo = trace[t]
            if not env.agents:  # world k autoreset at step t - 1: compare its final step only
                break
            live = list(env.agents)
            o, r, term, trunc, info = env.step({ag: a[k, int(ag[4:])] for ag in live})
            final = vinfo.get("_final_obs", np.zeros(k_worlds, bool))[k]
            got_obs = vinfo["final_obs"][k] if final else vo[k]
            for ag in live:
                i_ = int(ag[4:])
                np.testing.assert_allclose(got_obs[i_], o[ag], atol=1e-5)
                assert vr[k, i_] == pytest.approx(r[ag], rel=1e-6, abs=1e-6)
                assert vterm[k, i_] == term[ag] and vtrunc[k, i_] == trunc[ag]
                assert vinfo["cost"][k, i_] == info[ag]["cost"]
                for name, c in info[ag]["costs"].items():
                    assert vinfo["costs"][name][k, i_] == c
            if full_infos:
                full = vinfo["agents"][k]
                assert full.keys() == info.keys()
                if final:
                    assert vinfo["reset_infos"][k].keys() == set(env.possible_agents)
                for ag in live:
                    assert full[ag]["violations"] == info[ag]["violations"]
                    own, ref = full[ag]["own"]["position"], info[ag]["own"]["position"]
                    np.testing.assert_array_equal(own, ref)
            ended_any |= any(term.values()) or any(i["cost"] > 0 for i in info.values())
            took_part = [f"uav_{j}" in live for j in range(3)]
            np.testing.assert_array_equal(vinfo["active"][k], took_part)
        env.close()
    assert ended_any  # the random actions did crash UAVs: the comparison covered terminations


@pytest.mark.parametrize(
    "kw",
    [
        {"n_uavs": 3, "terminate_on_collision": "agent"},
        {"n_uavs": 1, "terminate_on_collision": "all", "dynamics": {"model": "lag"}},
        {"n_uavs": 4, "n_obstacles_obs": 20, "comms": {"drop_prob": 0.3}},
        {"n_uavs": 3, "reward": {"image_point": "box", "q": (30.0, 30.0, 100.0, 1.0)}},
    ],
    ids=["n3", "n1-lag", "n4-more-obstacle-slots-than-obstacles", "n3-box-point-reward"],
)
def test_batched_step_equals_world_by_world_across_autoresets(vec, kw):
    """The batched core and the ParallelEnvs stepped one by one give the same arrays, bit for
    bit, over several autoresets of worlds with different obstacle counts."""
    k_worlds, steps = 5, 75
    fast = vec(k_worlds, **kw, max_cycles=25)
    slow = vec(k_worlds, **kw, max_cycles=25, full_infos=True)
    o1, _ = fast.reset(seed=3)
    o2, _ = slow.reset(seed=3)
    assert len(set(fast._obstacles.counts)) > 1  # padded obstacles are exercised
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    resets = 0
    for _ in range(steps):
        a = _actions(rng, k_worlds, fast.n_agents)
        out1, out2 = fast.step(a), slow.step(a)
        for x, y in zip(out1[:4], out2[:4], strict=True):
            np.testing.assert_array_equal(x, y)
        i1, i2 = out1[4], out2[4]
        for key in ("cost", "reward_tracking", "reward_effort", "action_clipped", "active"):
            np.testing.assert_array_equal(i1[key], i2[key])
        for name in i1["costs"]:
            np.testing.assert_array_equal(i1["costs"][name], i2["costs"][name])
        assert ("final_obs" in i1) == ("final_obs" in i2)
        if "final_obs" in i1:
            np.testing.assert_array_equal(i1["final_obs"], i2["final_obs"])
            np.testing.assert_array_equal(i1["_final_obs"], i2["_final_obs"])
            resets += int(i1["_final_obs"].sum())
    assert resets >= k_worlds * 2  # every world truncated at least twice


def test_shapes_dtypes_and_autoreset(vec):
    v = vec(2, max_cycles=5)
    obs, infos = v.reset(seed=0)
    n_obs = v.single_observation_space.shape[0]
    assert obs.shape == (2, 3, n_obs) and obs.dtype == np.float32
    assert v.action_space.shape == (2, 3, 4) and obs in v.observation_space
    for _ in range(5):
        obs, rew, term, trunc, infos = v.step(np.zeros((2, 3, 4), np.float32))
        assert rew.shape == term.shape == trunc.shape == infos["cost"].shape == (2, 3)
        assert rew.dtype == np.float32 and term.dtype == bool
    assert trunc.all() and infos["_final_obs"].all()  # both worlds ended at max_cycles ...
    assert infos["active"].all() and not np.array_equal(obs, infos["final_obs"])  # ... and reset
    infos = v.step(np.zeros((2, 3, 4), np.float32))[-1]
    assert "_final_obs" not in infos


def test_same_seed_same_rollout_bit_for_bit(vec):
    rng = np.random.default_rng(3)
    actions = [_actions(rng, 2, 3) for _ in range(40)]  # crosses an autoreset (max_cycles 30)
    runs = []
    for _ in range(2):
        v = vec(2)
        out = [v.reset(seed=5)[0]]
        out += [v.step(a)[0] for a in actions]
        runs.append(np.stack(out))
    np.testing.assert_array_equal(runs[0], runs[1])


@pytest.mark.parametrize(
    "bad, error, message",
    [
        (np.zeros((2, 3, 3)), ValueError, r"shape \(2, 3, 3\); expected \(2, 3, 4\)"),
        (np.zeros((3, 4)), ValueError, "expected \\(2, 3, 4\\)"),
        ("fast", ValueError, "float array of shape"),
    ],
)
def test_bad_actions_raise_and_change_nothing(vec, bad, error, message):
    v = vec(2)
    v.reset(seed=1)
    before = [e.position.copy() for e in v.envs]
    with pytest.raises(error, match=message):
        v.step(bad)
    for e, p in zip(v.envs, before, strict=True):
        np.testing.assert_array_equal(e.position, p)
        assert e.num_cycles == 0


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_non_finite_action_names_world_and_agent_and_changes_nothing(vec, value):
    v = vec(2)
    v.reset(seed=1)
    a = np.zeros((2, 3, 4))
    a[1, 2, 0] = value
    with pytest.raises(ValueError, match="world 1, agent 'uav_2' is not finite"):
        v.step(a)
    assert all(e.num_cycles == 0 for e in v.envs)


def test_inactive_rows_ignore_their_actions(vec):
    v = vec(1, terminate_on_collision="agent", max_cycles=200)
    v.reset(seed=3)
    dive = np.zeros((1, 3, 4))
    dive[0, 0, 1] = 1.0  # uav_0 down at 10 m/s: hits the ground
    for _ in range(40):
        _, rew, term, _, infos = v.step(dive)
        if term[0, 0]:
            break
    assert term[0, 0] and infos["active"][0, 1:].all()
    dive[0, 0] = np.nan  # ignored: uav_0 is out of the episode
    obs, rew, term, _, infos = v.step(dive)
    assert not infos["active"][0, 0] and rew[0, 0] == 0.0 and not obs[0, 0].any()


def test_step_before_reset_and_bad_construction(vec):
    v = vec(2)
    with pytest.raises(RuntimeError, match="before reset"):
        v.step(np.zeros((2, 3, 4)))
    with pytest.raises(ValueError, match="num_envs must be >= 1"):
        uavtrack_v0.vector_env(0)
    with pytest.raises(TypeError, match="num_envs must be an int"):
        uavtrack_v0.vector_env(2.5)
    with pytest.raises(TypeError, match="unknown argument"):
        uavtrack_v0.vector_env(2, n_drones=3)


def test_short_soak_every_value_finite_and_inside_the_space(vec):
    """Many autoresets of the batched step (the full soak: benchmarks/soak.py)."""
    v = vec(4, max_cycles=15, n_uavs=4)
    obs, _ = v.reset(seed=7)
    rng = np.random.default_rng(7)
    resets = 0
    for _ in range(150):
        obs, rewards, _t, _tr, infos = v.step(rng.uniform(-3.0, 3.0, v.action_space.shape))
        assert v.observation_space.contains(obs)
        assert np.isfinite(rewards).all()
        for key in ("cost", "reward_tracking", "reward_effort"):
            assert np.isfinite(infos[key]).all()
        resets += int(infos.get("_final_obs", np.zeros(4, bool)).sum())
    assert resets >= 4 * 9  # every world ended its 15-step episode at least 9 times
