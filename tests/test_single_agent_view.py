"""SingleAgentView: Gymnasium's and SB3's checkers, episode ends, others' policies."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

from uavtrack_env import uavtrack_v0
from uavtrack_env.wrappers import CBFShield, SingleAgentView

sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")


@pytest.fixture
def make_view():
    made = []

    def factory(shield: bool = False, agent: str = "uav_0", others="hover", **kwargs):
        kwargs.setdefault("scenario", "random")
        kwargs.setdefault("max_cycles", 50)
        raw = uavtrack_v0.parallel_env(**kwargs)
        made.append(raw)
        env = CBFShield(raw) if shield else raw
        return SingleAgentView(env, agent=agent, others=others)

    yield factory
    for env in made:
        env.close()


def _check_quietly(check, view) -> None:
    """Run a checker; any warning it emits flags an API problem."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check(view)
    messages = [str(w.message) for w in caught]
    assert not messages, messages


@pytest.mark.parametrize("others", ["hover", "expert"])
@pytest.mark.parametrize("shield", [False, True])
def test_gymnasium_check_env(make_view, others, shield):
    view = make_view(shield=shield, others=others)
    _check_quietly(lambda v: gym_check_env(v, skip_render_check=True, skip_close_check=True), view)


@pytest.mark.parametrize("others", ["hover", "expert"])
def test_sb3_check_env(make_view, others):
    view = make_view(shield=True, others=others)
    _check_quietly(lambda v: sb3_checker.check_env(v, warn=True), view)


def test_spaces_are_the_envs(make_view):
    view = make_view(agent="uav_1")
    assert isinstance(view, gymnasium.Env)
    assert view.observation_space is view.env.observation_space("uav_1")
    assert view.action_space is view.env.action_space("uav_1")


def test_step_returns_the_agents_view_and_others_follow_callable(make_view):
    calls = []

    def others(obs, infos):
        calls.append((sorted(obs), sorted(infos)))
        return {a: np.array([0.0, 0.0, 0.5, 0.0]) for a in obs}  # forward at 5 m/s

    view = make_view(agent="uav_2", others=others, n_uavs=3)
    view.reset(seed=4)
    raw = view.env
    start = raw.position.copy()
    obs2, reward, terminated, truncated, info2 = view.step(np.zeros(4, np.float32))
    assert calls == [(["uav_0", "uav_1"], ["uav_0", "uav_1", "uav_2"])]
    np.testing.assert_array_equal(raw.position[2], start[2])  # the agent hovered
    moved = np.linalg.norm(raw.position[:2] - start[:2], axis=1)
    np.testing.assert_allclose(moved, 5.0 / 80.0, rtol=1e-9)  # the others flew at 5 m/s
    assert obs2.shape == view.observation_space.shape and obs2 in view.observation_space
    assert isinstance(reward, float) and reward == pytest.approx(
        math.exp(info2["reward_tracking"] + info2["reward_effort"])  # exp(-c), the RL default
    )
    assert terminated is False and truncated is False


def test_episode_ends_for_the_agent_and_continues_without_others(make_view):
    """Team-mates diving into the ground die first; the agent goes on alone until truncation."""

    def dive(obs, infos):
        return {a: np.array([0.0, 1.0, 0.0, 0.0]) for a in obs}  # v_cy = +10 m/s: down

    view = make_view(others=dive, max_cycles=60, terminate_on_collision="agent")
    view.reset(seed=1)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _obs, _r, terminated, truncated, _info = view.step(np.zeros(4))
        steps += 1
        if steps == 30:
            assert view.env.agents == ["uav_0"]  # the others crashed, the agent flies on
    assert truncated and not terminated and steps == 60
    with pytest.raises(RuntimeError, match="reset"):
        view.step(np.zeros(4))


def test_agent_termination_ends_its_episode(make_view):
    view = make_view(max_cycles=200, terminate_on_collision="agent")
    view.reset(seed=1)
    steps = 0
    while steps < 200:
        steps += 1
        _obs, _r, terminated, truncated, info = view.step(np.array([0.0, 1.0, 0.0, 0.0]))
        if terminated:
            break
    assert terminated and not truncated and info["violations"]["collision"]
    assert steps < 40  # from ~2 m altitude at 10 m/s


def test_bad_action_raises_and_changes_nothing(make_view):
    view = make_view(others="expert")
    with pytest.raises(RuntimeError, match=r"step\(\) called before reset\(\)"):
        view.step(np.zeros(4))
    view.reset(seed=0)
    before = view.env.position.copy()
    estimate = view.expert.onboard["uav_1"].estimate
    with pytest.raises(ValueError, match="not finite"):
        view.step(np.array([np.nan, 0, 0, 0]))
    with pytest.raises(ValueError, match="shape"):
        view.step(np.zeros(5))
    np.testing.assert_array_equal(view.env.position, before)
    assert view.expert.onboard["uav_1"].estimate is estimate
    view.step(np.zeros(4))


def test_bad_arguments(make_view):
    raw = uavtrack_v0.parallel_env(scenario="A")
    try:
        with pytest.raises(ValueError, match="unknown agent"):
            SingleAgentView(raw, agent="uav_7")
        with pytest.raises(ValueError, match="others"):
            SingleAgentView(raw, others="chase")
    finally:
        raw.close()


def test_render_forwards(make_view):
    view = make_view(render_mode="rgb_array")
    view.reset(seed=0)
    frame = view.render()
    assert isinstance(frame, np.ndarray) and frame.ndim == 3 and frame.dtype == np.uint8
