"""The skipped PyBullet queries (`uavtrack_env.broadphase`) answer as PyBullet does.

Every UAV whose rays are skipped is checked against PyBullet's own rays, every world whose
contact query is skipped against PyBullet's contacts, on poses built to graze obstacles, the car,
the ground and other UAVs; and whole rollouts are bit-identical with the skipping on and off.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from uavtrack_env import uavtrack_v0
from uavtrack_env.broadphase import (
    CONTACT_MARGIN,
    RAY_MARGIN,
    Bodies,
    contacts_in_doubt,
    known_answers,
)
from uavtrack_env.sensors import _to_world
from uavtrack_env.target import CAR_HALF_EXTENTS

CLUTTER = {"n_obstacles": (14, 20), "extent": 14.0, "corridor": 1.0, "height": (0.5, 3.0)}


def _grazing_poses(env, rng: np.random.Generator, ends: np.ndarray) -> np.ndarray:
    """n UAV positions, some near something (an obstacle's face or the sight line past it, the
    car, the ground or another UAV's ray to one of the car's samples ``ends``, at distances
    around the margins), the rest in the open."""
    lay, n = env.layout, env.config.n_uavs
    car = env.target.center()
    centers = np.asarray(lay.obstacle_centers, float).reshape(-1, 3)
    half = np.asarray(lay.obstacle_half_extents, float).reshape(-1, 3)
    out = np.empty((n, 3))
    grazing = rng.integers(n + 1)  # the others fly in the open, 3-8 m up
    for i in range(n):
        kind = rng.integers(6) if i < grazing else 5
        gap = rng.choice([-0.2, -1e-3, 0.0, 1e-4, RAY_MARGIN, 0.01, 0.3, CONTACT_MARGIN, 1.0])
        if kind == 0 and len(centers):  # behind an obstacle, the sight line grazing its edge
            j = rng.integers(len(centers))
            corner = centers[j] + half[j] * rng.choice([-1.0, 1.0], 3)
            corner[2] = min(max(corner[2], 0.3), 3.0)
            away = corner - car
            out[i] = corner + away / np.linalg.norm(away) * rng.uniform(0.1, 4.0)
            out[i] += rng.normal(0.0, 0.3, 3) * gap
        elif kind == 1 and len(centers):  # at an obstacle's face
            j = rng.integers(len(centers))
            axis = rng.integers(3)
            p = centers[j] + rng.uniform(-1, 1, 3) * half[j]
            p[axis] = centers[j][axis] + np.sign(rng.normal()) * (
                half[j][axis] + env.config.uav_radius + gap
            )
            out[i] = p
        elif kind == 2:  # at the car
            axis = rng.integers(2)
            p = car + rng.uniform(-1, 1, 3) * CAR_HALF_EXTENTS
            p[axis] = car[axis] + np.sign(rng.normal()) * (
                CAR_HALF_EXTENTS[axis] + env.config.uav_radius + gap
            )
            out[i] = p
        elif kind == 3:  # at the ground
            out[i] = [*rng.uniform(-8, 8, 2), env.config.uav_radius + gap]
        elif kind == 4 and i:  # at the surface of UAV i - 1's ray to a sample
            ray = ends[rng.integers(len(ends))] - out[i - 1]
            side = np.cross(ray, rng.normal(size=3))
            side /= np.linalg.norm(side)
            out[i] = out[i - 1] + rng.uniform(0.05, 0.6) * ray
            out[i] += side * (env.config.uav_radius + rng.choice([-2, -1, 0, 1, 2]) * gap)
            if rng.random() < 0.3:  # or overlapping UAV i - 1, its rays starting inside
                out[i] = out[i - 1] + side * rng.uniform(0.0, 2.0 * env.config.uav_radius)
        else:
            out[i] = [*(car[:2] + rng.uniform(-12, 12, 2)), rng.uniform(3.0, 8.0)]
    return out


@pytest.mark.parametrize("seed", range(6))
def test_skipped_rays_and_contacts_are_what_pybullet_reports(seed):
    env = uavtrack_v0.parallel_env(scenario="random", n_uavs=6, random_world=CLUTTER).unwrapped
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    det, world, s = env.detector, env.world, env.detector._n_samples
    reached = blocked = skipped_contacts = 0
    for _ in range(60):
        heading = np.array([env.target.heading])
        ends = _to_world(det._local[1 : 1 + s], env.target.center()[None], heading)[0]
        env.position = _grazing_poses(env, rng, ends)
        env.alive = rng.random(6) > 0.15
        world.set_poses(env.position, env.yaw, env.alive, env.target.center(), env.target.heading)
        m_fast = env._sense()  # a batch of one world
        bodies = Bodies(
            env.alive[None], env._obstacles.centers, env._obstacles.half_extents,
            env.config.uav_radius,
        )  # fmt: skip
        radius = float(np.linalg.norm(ends - env.target.center(), axis=1).max())
        car = float(np.linalg.norm(CAR_HALF_EXTENTS))
        reaches, unknown, in_doubt = known_answers(
            env.position[None], env.target.center()[None], ends[None], radius, car, bodies
        )
        reaches, unknown = reaches[0], unknown[0]
        assert in_doubt.tolist() == ([0] if unknown.any() else [])
        reach = world.rays_reach_target(np.repeat(env.position, s, 0), np.tile(ends, (6, 1)))
        proven = ~unknown
        np.testing.assert_array_equal(reach.reshape(6, s)[proven], reaches[proven])
        reached += int(reaches.sum())
        blocked += int((proven & ~reaches).sum())
        exact = world.contacts(6)
        skipped_contacts += not contacts_in_doubt(
            m_fast.obstacle_clearance, m_fast.target_clearance,
            env.position[None, :, 2], env.config.uav_radius, env.alive[None],
        )[0]  # fmt: skip
        for key, hit in exact.items():
            np.testing.assert_array_equal(m_fast.contacts[key][0] & env.alive, hit & env.alive, key)
    env.close()
    # the poses are near things on purpose, yet many UAVs and worlds still skip their queries
    assert reached >= 1000
    assert blocked >= 5
    assert skipped_contacts >= 3


def _fingerprint(skip: bool, seed: int, steps: int, **config) -> tuple[str, int]:
    env = uavtrack_v0.parallel_env(skip_proven_queries=skip, **config)
    rng = np.random.default_rng(seed)
    obs, infos = env.reset(seed=seed)
    h = hashlib.sha256()
    occluded = 0
    held = {a: rng.uniform(-1, 1, 4) for a in env.possible_agents}
    for t in range(steps):
        if not env.agents:
            obs, infos = env.reset()
        if t % 25 == 0:
            held = {a: rng.uniform(-1, 1, 4) for a in env.possible_agents}
        obs, rewards, term, trunc, infos = env.step({a: held[a] for a in env.agents})
        for a in sorted(obs):
            info = infos[a]
            occluded += info["violations"]["occlusion"]
            h.update(obs[a].tobytes())
            h.update(np.float64(rewards[a]).tobytes())
            h.update(repr((term[a], trunc[a], info["costs"], info["collision_with"])).encode())
            h.update(repr(info["measurement"]).encode())
            h.update(np.float64(info["truth"]["blocked_fraction"]).tobytes())
    env.close()
    return h.hexdigest(), occluded


@pytest.mark.parametrize(
    "config",
    [
        {"scenario": "random", "n_uavs": 6, "random_world": CLUTTER,
         "terminate_on_collision": "never"},
        {"scenario": "random", "n_uavs": 4, "random_world": CLUTTER, "dynamics": {"model": "lag"},
         "comms": {"drop_prob": 0.3}},
        {"scenario": "C", "terminate_on_collision": "agent"},
    ],
)  # fmt: skip
def test_rollouts_are_bit_identical_with_and_without_the_skipped_queries(config):
    fast, occluded = _fingerprint(True, 3, 400, **config)
    exact, _ = _fingerprint(False, 3, 400, **config)
    assert fast == exact
    if config.get("terminate_on_collision") == "never":
        assert occluded > 0  # the rollouts did hide the car, so the kept rays mattered


def test_vector_env_worlds_are_bit_identical_with_and_without_the_skipped_queries():
    outs = []
    for skip in (True, False):
        env = uavtrack_v0.vector_env(
            4, scenario="random", n_uavs=3, random_world=CLUTTER, skip_proven_queries=skip,
            terminate_on_collision="agent",
        )  # fmt: skip
        rng = np.random.default_rng(1)
        obs, _ = env.reset(seed=5)
        steps = [obs.copy()]
        for _ in range(200):
            out = env.step(rng.uniform(-1, 1, env.action_space.shape))
            steps += [out[0].copy(), out[1].copy(), out[2].copy(), out[4]["cost"].copy()]
        env.close()
        outs.append(steps)
    for a, b in zip(*outs, strict=True):
        np.testing.assert_array_equal(a, b)
