"""The expert's planning threads (the same actions as one thread, clear errors for bad counts)
and the runner's real-time factor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from baselines import evaluate
from uavtrack_env import uavtrack_v0
from uavtrack_env.expert import ExpertPolicy, default_threads
from uavtrack_env.runner import run_episode


def test_threaded_expert_equals_sequential_expert_bit_for_bit():
    """Planned in 3 threads or one after the other, every action of a closed loop on B (boxes,
    safety rows in the plan, the CBF-QP active) is the same, and so is the episode."""
    env = uavtrack_v0.parallel_env(**evaluate.world_kwargs("B", 0, 160, render=False))
    obs, infos = env.reset(seed=0)
    one = ExpertPolicy.from_env(env, threads=1)
    three = ExpertPolicy.from_env(env, threads=3)
    steps = 0
    try:
        while env.agents:
            a, b = one(obs, infos), three(obs, infos)
            assert list(a) == list(b) == list(obs)
            for agent in a:
                np.testing.assert_array_equal(a[agent], b[agent])
            obs, _, _, _, infos = env.step(a)
            steps += 1
        assert three._pool is not None  # the threads ran
    finally:
        three.close()
        env.close()
    assert steps == 160
    assert three._pool is None and len(three.timings["nmpc"]) == len(one.timings["nmpc"])


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_bad_thread_count_is_rejected(bad):
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=5)
    env.reset(seed=0)
    try:
        with pytest.raises(ValueError, match="threads must be an integer >= 1 or None"):
            ExpertPolicy.from_env(env, threads=bad)
    finally:
        env.close()


def test_default_threads_one_per_uav_at_most_the_cpus():
    assert default_threads(1) == 1
    assert 1 <= default_threads(3) <= 3
    assert default_threads(100) >= default_threads(3)


def test_evaluate_rejects_bad_threads(capsys):
    with pytest.raises(SystemExit):
        evaluate.parse_args(["--threads", "0"])
    assert "--threads must be an integer >= 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize("steps", [1, 3])
def test_real_time_factor_leaves_out_the_first_step(steps):
    """The first step (one-off builds, the cold solve) is `startup_s`, apart from the rate."""
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=steps)
    policy = ExpertPolicy(env.possible_agents, env.config, threads=1)
    try:
        m = run_episode(env, policy, seed=0, steps=steps).metrics
    finally:
        env.close()
    assert m["startup_s"] > 0
    if steps == 1:
        assert math.isnan(m["real_time_factor"])
    else:
        assert math.isfinite(m["real_time_factor"]) and m["real_time_factor"] > 0
