"""The env's PyBullet client: released by close() or by garbage collection, never shared by a
copy; every info value finite, also for a UAV alone."""

from __future__ import annotations

import copy
import functools
import gc
import math
import pickle

import numpy as np
import pybullet as p
import pytest

from uavtrack_env import uavtrack_v0
from uavtrack_env.infos import NOTHING_NEAR
from uavtrack_env.wrappers import CBFShield


def _connected(cid: int) -> bool:
    return bool(p.getConnectionInfo(physicsClientId=cid)["isConnected"])


def test_an_env_dropped_without_close_frees_its_client():
    cids = []
    for seed in range(20):
        env = uavtrack_v0.parallel_env(scenario="random")
        env.reset(seed=seed)
        cids.append(env.unwrapped.world.cid)
        assert _connected(cids[-1])
        del env
    gc.collect()
    assert not any(_connected(c) for c in cids)


def test_close_frees_the_client_once():
    env = uavtrack_v0.parallel_env(scenario="A")
    cid = env.unwrapped.world.cid
    env.close()
    assert not _connected(cid)
    env.close()  # a second close is harmless


@pytest.mark.parametrize("wrapped", [False, True])
def test_a_closed_env_refuses_to_step_reset_or_render(wrapped):
    env = uavtrack_v0.parallel_env(scenario="A", render_mode="rgb_array")
    target = CBFShield(env) if wrapped else env
    target.reset(seed=0)
    actions = {a: np.zeros(4, np.float32) for a in env.agents}
    target.close()
    calls = {"step": lambda: target.step(actions), "reset": lambda: target.reset(seed=1)}
    calls["render"] = env.render
    for name, call in calls.items():
        with pytest.raises(RuntimeError, match=rf"{name}\(\) called after close\(\).*new one"):
            call()
    assert env.num_cycles == 0


def test_a_closed_vector_env_refuses_to_step_or_reset():
    v = uavtrack_v0.vector_env(2, scenario="A")
    v.reset(seed=0)
    v.close()
    with pytest.raises(RuntimeError, match=r"step\(\) called after close\(\).*vector_env"):
        v.step(np.zeros((2, 3, 4)))
    with pytest.raises(RuntimeError, match=r"reset\(\) called after close\(\).*vector_env"):
        v.reset(seed=1)
    v.close()


@pytest.mark.parametrize(
    ("how", "wrapped"),
    [("deepcopy", False), ("copy", False), ("pickle", False), ("deepcopy", True), ("pickle", True)],
)
def test_a_live_env_cannot_be_copied_or_pickled(how, wrapped):
    env = uavtrack_v0.parallel_env(scenario="A")
    env.reset(seed=0)
    target = CBFShield(env) if wrapped else env
    fn = {"deepcopy": copy.deepcopy, "copy": copy.copy, "pickle": pickle.dumps}[how]
    with pytest.raises(TypeError, match=r"PyBullet client.*cannot be copied or pickled"):
        fn(target)
    env.step({a: np.zeros(4, np.float32) for a in env.agents})  # still usable
    env.close()


def test_the_constructor_pickles_for_worker_processes():
    make = pickle.loads(
        pickle.dumps(functools.partial(uavtrack_v0.parallel_env, scenario="random", n_uavs=4))
    )
    env = make()
    assert len(env.reset(seed=1)[0]) == 4
    env.close()


def _nonfinite(tree, path=""):
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _nonfinite(v, f"{path}.{k}")
    elif isinstance(tree, float | np.floating) and not math.isfinite(tree):
        yield path
    elif isinstance(tree, np.ndarray) and tree.dtype.kind == "f" and not np.isfinite(tree).all():
        yield path


@pytest.mark.parametrize("n_uavs", [1, 2])
def test_every_info_value_is_finite_for_a_uav_alone(n_uavs):
    """Alone from the start, or after the other UAV dived into the ground."""
    env = uavtrack_v0.parallel_env(scenario="random", n_uavs=n_uavs, terminate_on_collision="agent")
    _, infos = env.reset(seed=3)
    dive = np.array([0.0, 1.0, 0.0, 0.0], np.float32)  # camera Y points down
    alone = 0
    for _ in range(400):
        for agent, info in infos.items():
            assert not list(_nonfinite(info)), (agent, list(_nonfinite(info)))
            alone += info["truth"]["nearest_uav_distance"] == NOTHING_NEAR
        if not env.agents:
            break
        actions = {a: dive if a == "uav_1" else np.zeros(4, np.float32) for a in env.agents}
        infos = env.step(actions)[4]
    assert alone > 0
    env.close()
