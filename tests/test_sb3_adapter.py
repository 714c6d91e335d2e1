"""SharedPolicyVecEnv: batching, per-agent ends, terminal observations and auto-reset, row by row
against a hand-built sequence; SB3's VecEnv contract (PPO.learn, VecMonitor, seeds)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from pettingzoo import ParallelEnv
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecNormalize
from stable_baselines3.common.vec_env.util import obs_space_info

from tests.conftest import step_both
from uavtrack_env import uavtrack_v0
from uavtrack_env.wrappers.sb3 import (
    AgentVecMonitor,
    SharedPolicyVecEnv,
    VectorSharedPolicyVecEnv,
)

NAN = float("nan")


class ScriptedEnv(ParallelEnv):
    """Three agents; obs = [episode, t, agent index]; reward = the agent's action[0].

    ``script[agent] = (t_end, terminated, truncated)``: the agent ends after step ``t_end``.
    Raises if it is given an action for an agent that is not live (the adapter must not send one).
    """

    metadata = {"name": "scripted_v0"}  # noqa: RUF012

    def __init__(self, script: dict[str, tuple[int, bool, bool]]) -> None:
        self.possible_agents = ["a", "b", "c"]
        self.script = script
        self.episode = 0
        self.seeds: list[int | None] = []
        self.render_mode = None
        self._obs = gymnasium.spaces.Box(-100.0, 100.0, (3,), np.float32)
        self._act = gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def observation_space(self, agent):
        return self._obs

    def action_space(self, agent):
        return self._act

    def render(self):
        return np.full((2, 2, 3), self.episode, np.uint8)

    def _o(self, agent):
        return np.array([self.episode, self.t, self.possible_agents.index(agent)], np.float32)

    def reset(self, seed=None, options=None):
        self.seeds.append(seed)
        self.episode += 1
        self.t = 0
        self.agents = self.possible_agents[:]
        return {a: self._o(a) for a in self.agents}, {a: {"seed": seed} for a in self.agents}

    def step(self, actions):
        if set(actions) != set(self.agents):
            raise AssertionError(f"actions for {sorted(actions)}, live {self.agents}")
        self.t += 1
        obs = {a: self._o(a) for a in self.agents}
        rew = {a: float(actions[a][0]) for a in self.agents}
        term, trunc = {}, {}
        for a in self.agents:
            t_end, te, tr = self.script[a]
            term[a], trunc[a] = (te, tr) if self.t == t_end else (False, False)
        infos = {a: {"t": self.t} for a in self.agents}
        self.agents = [a for a in self.agents if not (term[a] or trunc[a])]
        return obs, rew, term, trunc, infos


SCRIPTS = [
    # copy 0: b dies at 2, c is truncated alone at 3, a terminated and truncated at 5
    {"a": (5, True, True), "b": (2, True, False), "c": (3, False, True)},
    # copy 1: the whole team is truncated at 3
    {"a": (3, False, True), "b": (3, False, True), "c": (3, False, True)},
]


def make_vec() -> tuple[SharedPolicyVecEnv, list[ScriptedEnv]]:
    made: list[ScriptedEnv] = []

    def env_fn():
        made.append(ScriptedEnv(SCRIPTS[len(made)]))
        return made[-1]

    return SharedPolicyVecEnv(env_fn, n_copies=2), made


Z = [0.0, 0.0, 0.0]  # the absorbing observation
# Per step: expected obs rows, dones, TimeLimit.truncated (None: row not done), terminal obs,
# absorbing flags. Rows: copy0 a, b, c, copy1 a, b, c.
EXPECTED = [
    # step 1
    dict(
        obs=[[1, 1, 0], [1, 1, 1], [1, 1, 2], [1, 1, 0], [1, 1, 1], [1, 1, 2]],
        dones=[0, 0, 0, 0, 0, 0],
        tl=[None] * 6,
        term={},
        absorbing=[0, 0, 0, 0, 0, 0],
    ),
    # step 2: copy0 b terminated -> done once, then absorbing zeros
    dict(
        obs=[[1, 2, 0], Z, [1, 2, 2], [1, 2, 0], [1, 2, 1], [1, 2, 2]],
        dones=[0, 1, 0, 0, 0, 0],
        tl=[None, False, None, None, None, None],
        term={1: [1, 2, 1]},
        absorbing=[0, 0, 0, 0, 0, 0],
    ),
    # step 3: copy0 c truncated alone; copy1 all truncated -> reset obs of episode 2
    dict(
        obs=[[1, 3, 0], Z, Z, [2, 0, 0], [2, 0, 1], [2, 0, 2]],
        dones=[0, 0, 1, 1, 1, 1],
        tl=[None, None, True, True, True, True],
        term={2: [1, 3, 2], 3: [1, 3, 0], 4: [1, 3, 1], 5: [1, 3, 2]},
        absorbing=[0, 1, 0, 0, 0, 0],
    ),
    # step 4
    dict(
        obs=[[1, 4, 0], Z, Z, [2, 1, 0], [2, 1, 1], [2, 1, 2]],
        dones=[0, 0, 0, 0, 0, 0],
        tl=[None] * 6,
        term={},
        absorbing=[0, 1, 1, 0, 0, 0],
    ),
    # step 5: copy0 a terminated (and truncated: terminated wins); absorbing chains of b and c
    # end with a terminal done; the copy resets
    dict(
        obs=[[2, 0, 0], [2, 0, 1], [2, 0, 2], [2, 2, 0], [2, 2, 1], [2, 2, 2]],
        dones=[1, 1, 1, 0, 0, 0],
        tl=[False, False, False, None, None, None],
        term={0: [1, 5, 0], 1: Z, 2: Z},
        absorbing=[0, 1, 1, 0, 0, 0],
    ),
]


def test_hand_built_sequence_row_by_row():
    vec, made = make_vec()
    assert vec.num_envs == 6
    assert vec.seed(7) == [7, 8]
    obs = vec.reset()
    np.testing.assert_array_equal(obs, [[1, 0, j] for _ in range(2) for j in range(3)])
    assert [e.seeds for e in made] == [[7], [8]]
    assert vec.reset_infos[4] == {"seed": 8}
    actions = np.array([[r + 1.0, 0.0] for r in range(6)], np.float32)
    for step, exp in enumerate(EXPECTED, start=1):
        obs, rew, dones, infos = vec.step(actions)
        assert obs.shape == (6, 3) and obs.dtype == np.float32
        np.testing.assert_array_equal(obs, np.array(exp["obs"], np.float32), err_msg=f"{step}")
        np.testing.assert_array_equal(dones, np.array(exp["dones"], bool), err_msg=f"{step}")
        absorbing_before = [bool(x) for x in exp["absorbing"]]
        want_rew = [0.0 if absorbing_before[r] else r + 1.0 for r in range(6)]
        np.testing.assert_array_equal(rew, want_rew, err_msg=f"step {step}")
        for r in range(6):
            info = infos[r]
            assert bool(info.get("absorbing", False)) == absorbing_before[r], (step, r)
            if exp["tl"][r] is None:
                assert "terminal_observation" not in info, (step, r)
                assert "TimeLimit.truncated" not in info, (step, r)
            else:
                assert info["TimeLimit.truncated"] is exp["tl"][r], (step, r)
                np.testing.assert_array_equal(info["terminal_observation"], exp["term"][r])
            if not absorbing_before[r]:
                assert info["t"] == (step if r < 3 else (step - 1) % 3 + 1)
    # auto-resets after seed() use the copies' own RNG (no seed)
    assert [e.seeds for e in made] == [[7, None], [8, None]]


def test_monitor_ignores_absorbing_chains():
    vec, _ = make_vec()
    mon = AgentVecMonitor(vec)
    mon.reset()
    episodes = []
    for _ in range(5):
        _, _, _, infos = mon.step(np.ones((6, 2), np.float32))
        episodes += [(r, i["episode"]["l"]) for r, i in enumerate(infos) if "episode" in i]
    # real episodes only: b (2 steps), c (3), copy1's team (3 each), a (5); not b/c's padding
    assert sorted(episodes) == [(0, 5), (1, 2), (2, 3), (3, 3), (4, 3), (5, 3)]
    assert mon.episode_count == 6


def test_bad_input():
    vec, _ = make_vec()
    vec.reset()
    with pytest.raises(ValueError, match="one row per agent"):
        vec.step_async(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="out of range"):
        vec.get_attr("episode", indices=[6])
    with pytest.raises(ValueError, match="n_copies"):
        SharedPolicyVecEnv(lambda: ScriptedEnv(SCRIPTS[0]), n_copies=0)


def test_attr_methods_map_rows_to_copies():
    vec, made = make_vec()
    vec.reset()
    assert vec.get_attr("episode") == [1, 1, 1, 1, 1, 1]
    vec.set_attr("episode", 10, indices=[4, 5])
    assert made[0].episode == 1 and made[1].episode == 10
    # called once per copy, result repeated per row
    assert vec.env_method("reset", seed=3, indices=[3, 5])[0][1]["a"] == {"seed": 3}
    assert made[1].seeds == [None, 3] and made[0].seeds == [None]
    assert vec.env_is_wrapped(ScriptedEnv) == [True] * 6
    assert vec.env_is_wrapped(gymnasium.Wrapper, indices=0) == [False]
    frames = vec.get_images()  # one per copy, not per row
    assert [int(f[0, 0, 0]) for f in frames] == [1, 11]  # copy 1 was reset once more


def real_env(**kw):
    return uavtrack_v0.parallel_env(
        scenario="random", max_cycles=12, terminate_on_collision="agent", **kw
    )


def test_real_env_matches_direct_stepping():
    vec = SharedPolicyVecEnv(real_env, n_copies=2)
    assert isinstance(vec, VecEnv)
    keys, shapes, dtypes = obs_space_info(vec.observation_space)
    vec.seed(3)
    obs = vec.reset()
    assert obs.shape == (6, *shapes[keys[0]]) and obs.dtype == dtypes[keys[0]]
    direct = [real_env(), real_env()]
    dobs = [d.reset(seed=3 + k)[0] for k, d in enumerate(direct)]
    rng = np.random.default_rng(0)
    agents = direct[0].possible_agents
    for k in range(2):  # copy k was reset with seed 3 + k
        for j, a in enumerate(agents):
            np.testing.assert_array_equal(obs[3 * k + j], dobs[k][a])
    for step in range(1, 15):
        act = rng.uniform(-0.2, 0.2, (6, 4)).astype(np.float32)
        obs, rew, dones, infos = vec.step(act)
        for k, d in enumerate(direct):
            o, r, te, tr, _ = d.step({a: act[3 * k + j] for j, a in enumerate(agents)})
            for j, a in enumerate(agents):
                row = 3 * k + j
                assert rew[row] == pytest.approx(r[a], rel=1e-6)
                assert dones[row] == (te[a] or tr[a])
                if dones[row]:
                    np.testing.assert_array_equal(infos[row]["terminal_observation"], o[a])
                    assert infos[row]["TimeLimit.truncated"] == (tr[a] and not te[a])
                else:
                    np.testing.assert_array_equal(obs[row], o[a])
            if not d.agents:  # the adapter auto-reset: its rows hold a fresh reset obs
                o, _ = d.reset()
                for j, a in enumerate(agents):
                    np.testing.assert_array_equal(obs[3 * k + j], o[a])
        if step == 12:
            assert dones.all() and all(i["TimeLimit.truncated"] for i in infos)
    assert vec.observation_space.contains(obs[0])
    vec.close()
    for d in direct:
        d.close()


def _learn(seed: int) -> np.ndarray:
    vec = VecNormalize(AgentVecMonitor(SharedPolicyVecEnv(real_env, n_copies=2)))
    model = PPO(
        "MlpPolicy", vec, n_steps=16, batch_size=48, n_epochs=2, seed=seed, device="cpu", verbose=0
    )
    model.learn(total_timesteps=192)
    assert model.num_timesteps == 2 * 16 * 6  # two rollouts of 16 steps x 6 rows
    params = np.concatenate([p.detach().numpy().ravel() for p in model.policy.parameters()])
    vec.close()
    return params


@pytest.mark.slow
def test_ppo_learns_on_adapter_and_seeds_reproduce():
    a, b, c = _learn(1), _learn(1), _learn(2)
    assert np.all(np.isfinite(a))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("terminate", ["agent", "all"])
def test_vector_adapter_equals_the_parallel_env_adapter_row_by_row(terminate):
    """VectorSharedPolicyVecEnv (one batched step of all worlds) gives SharedPolicyVecEnv's
    rows: observations, rewards, dones, terminal observations, truncation flags, absorbing
    rows and costs, through crashes and auto-resets."""
    kw = {"scenario": "random", "max_cycles": 20, "terminate_on_collision": terminate}
    copies = SharedPolicyVecEnv(lambda: uavtrack_v0.parallel_env(**kw), n_copies=3)
    worlds = VectorSharedPolicyVecEnv(3, **kw)
    assert worlds.num_envs == copies.num_envs == 9
    assert worlds.observation_space == copies.observation_space
    copies.seed(5)
    worlds.seed(5)
    np.testing.assert_array_equal(worlds.reset(), copies.reset())
    rng = np.random.default_rng(0)
    crashed = absorbing = 0
    for _ in range(50):
        act = rng.uniform(-1.0, 1.0, (9, 4)).astype(np.float32)
        act[[0, 4], 1] = 1.0  # two UAVs dive: per-agent ends inside running worlds
        i1, i2 = step_both(worlds, copies, act)
        for a, b in zip(i1, i2, strict=True):
            assert a.get("absorbing", False) == b.get("absorbing", False)
            absorbing += a.get("absorbing", False)
            if "terminal_observation" in b:
                np.testing.assert_array_equal(a["terminal_observation"], b["terminal_observation"])
                assert a["TimeLimit.truncated"] == b["TimeLimit.truncated"]
            if "cost" in b:
                assert a["cost"] == b["cost"] and a["violations"] == b["violations"]
                crashed += b["violations"]["collision"]
    assert crashed and (absorbing or terminate == "all")
    worlds.close()
    copies.close()


def test_ppo_trains_on_the_vector_adapter():
    vec = AgentVecMonitor(VectorSharedPolicyVecEnv(2, scenario="random", max_cycles=12))
    vec.seed(0)
    model = PPO("MlpPolicy", vec, n_steps=16, batch_size=48, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=96)
    assert model.num_timesteps == 96
    assert all(np.isfinite(p.detach().numpy()).all() for p in model.policy.parameters())
    vec.close()
