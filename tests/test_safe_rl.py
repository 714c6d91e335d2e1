"""The cost API: per-constraint costs in every info, and Safety-Gymnasium's step signature."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from uavtrack_env import uavtrack_v0
from uavtrack_env.wrappers import CBFShield, SafeRLParallelEnv
from uavtrack_env.wrappers.safe_rl import COST_KEYS


@pytest.fixture
def dive():
    """Three UAVs diving into the ground: collisions (and so costs) within a second."""
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=200, terminate_on_collision="agent")
    yield env
    env.close()


def _dive_actions(env):
    return {a: np.array([0.0, 1.0, 0.0, 0.0], np.float32) for a in env.agents}  # v_cy: down


def test_costs_are_the_violations_as_floats_and_cost_is_their_sum(dive):
    _obs, infos = dive.reset(seed=0)
    seen = set()
    while dive.agents:
        _o, _r, _t, _tr, infos = dive.step(_dive_actions(dive))
        for info in infos.values():
            assert set(info["costs"]) == set(COST_KEYS)
            for key in COST_KEYS:
                assert info["costs"][key] == float(info["violations"][key])
                if info["violations"][key]:
                    seen.add(key)
            assert info["cost"] == sum(info["costs"].values())
    assert "collision" in seen


def test_safe_rl_step_returns_the_cost_and_sums_the_episode(dive):
    env = SafeRLParallelEnv(dive)
    env.reset(seed=0)
    sums = dict.fromkeys((*COST_KEYS, "cost"), 0.0)
    episode = {}
    while env.agents:
        obs, rewards, costs, terms, truncs, infos = env.step(_dive_actions(env))
        assert set(costs) == set(rewards) == set(obs) == set(infos)
        for agent, info in infos.items():
            assert costs[agent] == info["cost"]
            if agent == "uav_0":
                for key in COST_KEYS:
                    sums[key] += info["costs"][key]
                sums["cost"] += costs[agent]
            if terms[agent] or truncs[agent]:
                episode[agent] = info["episode_costs"]
    assert set(episode) == set(env.possible_agents)
    ep = episode["uav_0"]
    assert ep["collision"] >= 1.0
    assert {k: ep[k] for k in sums} == sums
    assert ep["cost_rate"] == pytest.approx(ep["cost"] / ep["steps"])


def test_safe_rl_wraps_the_shield_and_keeps_the_api():
    env = SafeRLParallelEnv(CBFShield(uavtrack_v0.parallel_env(scenario="A", max_cycles=40)))
    try:
        env.reset(seed=1)
        out = env.step({a: np.ones(4, np.float32) for a in env.agents})  # full speed
        assert len(out) == 6 and all(c == 0.0 for c in out[2].values())  # the shield is on
        assert "shield" in out[5]["uav_0"]
        assert env.observation_space("uav_0") == env.env.observation_space("uav_0")
    finally:
        env.close()
    with pytest.raises(TypeError, match="UAVTrackEnv"):
        SafeRLParallelEnv(object())


def test_the_plain_env_passes_the_parallel_api_test_with_costs():
    env = uavtrack_v0.parallel_env(scenario="random", max_cycles=30)
    try:
        parallel_api_test(env, num_cycles=30)
    finally:
        env.close()
