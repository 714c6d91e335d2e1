"""Reward shapes: exp(-c) for RL by default, the paper's -c (eq. 18) with defaults="paper", the
collision penalty, and what a collision ends."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uavtrack_env.config import RewardConfig


def _rollout(env, steps: int, down_speed: float = 0.0):
    """Step with uav_0 descending (Y down) at ``down_speed`` (normalised) until it ends."""
    env.reset(seed=3)
    out = []
    for _ in range(steps):
        acts = {a: np.zeros(4, np.float32) for a in env.agents}
        acts["uav_0"] = np.array([0.0, down_speed, 0.02, 0.0], np.float32)
        _, rew, term, _, infos = env.step(acts)
        out.append((rew, infos))
        if any(term.values()):
            break
    return out


def test_paper_defaults_give_minus_the_stage_cost_and_end_the_team(make_env):
    env = make_env(defaults="paper")
    assert env.config.terminate_on_collision == "all"
    assert env.config.reward.collision_penalty == 0.0
    assert env.config.reward.image_point == "center"  # eq. (18)'s feature
    for rew, infos in _rollout(env, 20):
        for a, r in rew.items():
            assert r == pytest.approx(infos[a]["reward_tracking"] + infos[a]["reward_effort"])
            assert r <= 0.0


def test_rl_defaults_reward_exp_with_a_penalty_and_end_only_the_colliding_uav(make_env):
    env = make_env()
    assert env.config.reward.shape == "exp" and env.config.reward.collision_penalty == 10.0
    assert env.config.reward.image_point == "box"
    steps = _rollout(env, 40, down_speed=0.29)  # uav_0 hits the ground
    rew, infos = steps[-1]
    assert infos["uav_0"]["violations"]["collision"]
    c = -(infos["uav_0"]["reward_tracking"] + infos["uav_0"]["reward_effort"])
    assert rew["uav_0"] == pytest.approx(math.exp(-c) - 10.0)
    assert env.agents == ["uav_1", "uav_2"]  # the team flies on


def test_explicit_fields_override_the_named_defaults(make_env):
    env = make_env(defaults="paper", reward={"lost_penalty": 2.0}, terminate_on_collision="agent")
    cfg = env.config
    assert cfg.reward.shape == "cost" and cfg.reward.lost_penalty == 2.0
    assert cfg.terminate_on_collision == "agent"
    assert make_env(defaults="paper", reward={"shape": "exp"}).config.reward.shape == "exp"
    with pytest.raises(ValueError, match="unknown defaults 'gym'"):
        make_env(defaults="gym")


def test_never_terminate_keeps_the_crashed_uav_and_charges_every_step_in_collision(make_env):
    env = make_env(terminate_on_collision="never", max_cycles=80)
    env.reset(seed=3)
    costs, ended = [], False
    for _ in range(60):
        acts = {a: np.zeros(4, np.float32) for a in env.agents}
        acts["uav_0"] = np.array([0.0, 0.29, 0.02, 0.0], np.float32)
        _, rew, term, _, infos = env.step(acts)
        ended |= any(term.values())
        info = infos["uav_0"]
        costs.append(info["costs"]["collision"])
        assert info["cost"] == sum(info["costs"].values())
        if info["violations"]["collision"]:
            c = -(info["reward_tracking"] + info["reward_effort"])
            assert rew["uav_0"] == pytest.approx(math.exp(-c) - 10.0)
    assert not ended and env.agents == ["uav_0", "uav_1", "uav_2"]
    first = costs.index(1.0)
    assert first > 10 and all(c == 1.0 for c in costs[first:])  # below ground from then on


def test_exp_reward_is_exp_of_minus_the_stage_cost(make_env):
    steps = _rollout(make_env(reward={"shape": "exp"}), 20)
    rewards = []
    for rew, infos in steps:
        for a, r in rew.items():
            c = -(infos[a]["reward_tracking"] + infos[a]["reward_effort"])
            assert r == pytest.approx(math.exp(-c), rel=1e-12)
            rewards.append(r)
    assert 0.0 < min(rewards) and max(rewards) <= 1.0


@pytest.mark.parametrize("shape", ["cost", "exp"])
def test_collision_penalty_is_charged_once_on_the_colliding_step(make_env, shape):
    env = make_env(
        reward={"shape": shape, "collision_penalty": 50.0}, terminate_on_collision="agent"
    )
    steps = _rollout(env, 40, down_speed=0.29)  # uav_0 hits the ground (cf. test_env_sensors)
    assert steps[-1][1]["uav_0"]["collision_with"]["ground"]
    assert len(steps) > 10
    for k, (rew, infos) in enumerate(steps):
        c = -(infos["uav_0"]["reward_tracking"] + infos["uav_0"]["reward_effort"])
        base = -c if shape == "cost" else math.exp(-c)
        collided = k == len(steps) - 1
        assert infos["uav_0"]["violations"]["collision"] is collided
        assert rew["uav_0"] == pytest.approx(base - 50.0 * collided)


def _tracking_from_truth(env, infos: dict, point: str) -> dict[str, float]:
    """q . e^2 of eq. (18) rebuilt from the info's truth: x1, x2 from the pixel error of the
    chosen point over the focal lengths, x3 and psi from the features and the reference."""
    cam, q = env.config.camera, np.asarray(env.config.reward.q)
    out = {}
    for a, info in infos.items():
        truth, ref = info["truth"], info["reference"]
        px = truth["pixel_error"] if point == "box" else truth["center_pixel_error"]
        e3 = truth["features"][2] - ref[2]
        e4 = (truth["features"][3] - ref[3] + math.pi) % (2 * math.pi) - math.pi
        e = np.array([px[0] / cam.fx, px[1] / cam.fy, e3, e4])
        out[a] = float((q * e**2).sum())
    return out


@pytest.mark.parametrize("point", ["center", "box"])
def test_image_point_picks_the_point_the_reward_scores(make_env, point):
    """``reward.image_point``: 'box' (the RL default) scores the noise-free bounding box's
    centre (the point of the RMS metrics), 'center' the projection of the car's centre; closed
    form from the info's truth; the two differ, so scoring the wrong point fails."""
    assert RewardConfig().image_point == "box"
    env = make_env(scenario="A", reward={"image_point": point, "q": (30.0, 30.0, 100.0, 1.0)})
    env.reset(seed=0)
    gaps = []
    for _ in range(40):
        _, _, _, _, infos = env.step({a: np.zeros(4, np.float32) for a in env.agents})
        ours = _tracking_from_truth(env, infos, point)
        other = _tracking_from_truth(env, infos, "center" if point == "box" else "box")
        for a, info in infos.items():
            assert info["measurement"]["detected"]
            assert -info["reward_tracking"] == pytest.approx(ours[a], rel=1e-9, abs=1e-12)
            gaps.append(abs(ours[a] - other[a]))
    assert max(gaps) > 1e-3


@pytest.mark.parametrize(
    "kwargs, match",
    [({"shape": "linear"}, "shape must be"), ({"collision_penalty": -1.0}, "collision_penalty")],
)
def test_bad_reward_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RewardConfig(**kwargs)


def _components_reference(dist: np.ndarray, alive: np.ndarray, r_c: float) -> bool:
    """Connectivity of the alive UAVs by union-find (an independent reference)."""
    idx = [i for i in range(len(alive)) if alive[i]]
    parent = {i: i for i in idx}

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for a in idx:
        for b in idx:
            if dist[a, b] <= r_c:
                parent[root(a)] = root(b)
    return len({root(i) for i in idx}) <= 1


def test_connectivity_of_many_graphs_matches_union_find():
    from uavtrack_env.rewards import connected, connected_batch

    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 5, 8, 13):
        pts = rng.uniform(0.0, 10.0, (200, n, 3))
        dist = np.linalg.norm(pts[:, :, None] - pts[:, None], axis=-1)
        alive = rng.random((200, n)) < 0.8
        got = connected_batch(dist, alive, 5.0)
        want = [_components_reference(d, a, 5.0) for d, a in zip(dist, alive, strict=True)]
        np.testing.assert_array_equal(got, want)
        assert connected(dist[0], alive[0], 5.0) == want[0]
        if n >= 5:
            assert 0 < got.sum() < len(got)  # both outcomes occur
