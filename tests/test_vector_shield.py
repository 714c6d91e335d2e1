"""VectorCBFShield: world k equals CBFShield over a ParallelEnv seeded s + k; bad input; safety."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import step_both
from uavtrack_env import uavtrack_v0
from uavtrack_env.presets import expert_config
from uavtrack_env.wrappers import CBFShield, VectorCBFShield
from uavtrack_env.wrappers.sb3 import SharedPolicyVecEnv, VectorSharedPolicyVecEnv

CASES = {
    "drops": {"n_uavs": 3, "comms": {"drop_prob": 0.3}},
    "lag-n4": {"n_uavs": 4, "dynamics": {"model": "lag"}},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_world_k_equals_a_shielded_parallel_env_seeded_s_plus_k(case):
    """Certified actions, observations, rewards, ends and telemetry bit for bit, through wild
    actions (beyond [-1, 1]), crashes of unshielded-looking commands and autoresets."""
    K, seed = 3, 11
    cfg = {"scenario": "random", "max_cycles": 40, **CASES[case]}
    shielded = VectorCBFShield(uavtrack_v0.vector_env(K, **cfg))
    obs, _ = shielded.reset(seed=seed)
    singles = [CBFShield(uavtrack_v0.parallel_env(**cfg)) for _ in range(K)]
    for k, env in enumerate(singles):
        first, _ = env.reset(seed=seed + k)
        np.testing.assert_array_equal(obs[k], np.stack([first[a] for a in env.possible_agents]))
    names = shielded.possible_agents
    rng = np.random.default_rng(3)
    compared = resets = active = 0
    for _ in range(100):
        actions = rng.uniform(-1.6, 1.6, (K, len(names), 4))
        obs, rewards, terms, truncs, infos = shielded.step(actions)
        ended = infos.get("_final_obs", np.zeros(K, bool))
        for k, env in enumerate(singles):
            o, r, te, tr, inf = env.step(
                {a: actions[k, i] for i, a in enumerate(names) if a in env.agents}
            )
            last = infos["final_obs"][k] if ended[k] else obs[k]
            for i, a in enumerate(names):
                if a not in inf:
                    assert not infos["active"][k, i]
                    continue
                s = inf[a]["shield"]
                np.testing.assert_array_equal(infos["shield"]["action"][k, i], s["action"])
                np.testing.assert_array_equal(infos["shield"]["proposed"][k, i], s["proposed"])
                assert infos["shield"]["active"][k, i] == s["active"]
                assert infos["shield"]["correction_norm"][k, i] == s["correction_norm"]
                assert infos["shield"]["min_hard_h"][k, i] == s["min_hard_h"]
                assert infos["action_clipped"][k, i] == inf[a]["action_clipped"]
                np.testing.assert_array_equal(last[i], o[a])
                assert rewards[k, i] == np.float32(r[a])
                assert (terms[k, i], truncs[k, i]) == (te[a], tr[a])
                compared += 1
                active += s["active"]
            assert bool(ended[k]) == (not env.agents)
            if not env.agents:
                env.reset()  # seeded from its own stream, as the vector env's autoreset
                resets += 1
    assert resets >= 3 and active > 100 and compared > 500
    shielded.close()
    for env in singles:
        env.close()


def test_bad_input_raises_and_changes_nothing():
    cfg = {"scenario": "random", "max_cycles": 30}
    env = VectorCBFShield(uavtrack_v0.vector_env(2, **cfg))
    twin = VectorCBFShield(uavtrack_v0.vector_env(2, **cfg))
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros((2, 3, 4)))
    env.reset(seed=1)
    twin.reset(seed=1)
    good = np.full((2, 3, 4), 0.3)
    for bad, error in (
        (np.zeros((2, 3)), "shape"),
        (np.where(np.arange(4) == 2, np.nan, good), "not finite"),
        (np.full((2, 3, 4), np.inf), "not finite"),
    ):
        with pytest.raises(ValueError, match=error):
            env.step(bad)
    a, b = env.step(good), twin.step(good)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[4]["shield"]["action"], b[4]["shield"]["action"])
    with pytest.raises(TypeError, match="UAVTrackVectorEnv"):
        VectorCBFShield(uavtrack_v0.parallel_env())
    env.close()
    twin.close()


def test_random_policies_cause_no_collision_or_split_team():
    """Closed loop: uniform random and held extreme actions, lost messages, 6 worlds x 300
    steps; the unshielded twin collides."""
    cfg = {"scenario": "random", "max_cycles": 300, "comms": {"drop_prob": 0.3}}
    counts = {}
    for shield in (True, False):
        venv = uavtrack_v0.vector_env(6, **cfg)
        env = VectorCBFShield(venv) if shield else venv
        env.reset(seed=40)
        rng = np.random.default_rng(0)
        held = rng.choice([-1.0, 1.0], (6, 3, 4))
        total = {"collision": 0.0, "disconnection": 0.0}
        for t in range(300):
            if t % 40 == 0:
                held = rng.choice([-1.0, 1.0], (6, 3, 4))
            actions = np.where(np.arange(6)[:, None, None] % 2, held, rng.uniform(-1, 1, (6, 3, 4)))
            infos = env.step(actions)[4]
            for name in total:
                total[name] += infos["costs"][name].sum()
        counts[shield] = total
        env.close()
    assert counts[True] == {"collision": 0.0, "disconnection": 0.0}, counts
    assert counts[False]["collision"] > 0, counts


def test_shielded_vector_adapter_equals_shielded_copies_row_by_row():
    """The SB3 adapter with ``shield=`` gives `SharedPolicyVecEnv` over `CBFShield` copies'
    rows (observations, rewards, dones, intervention flags)."""
    kw = {"scenario": "random", "max_cycles": 25}
    copies = SharedPolicyVecEnv(
        lambda: CBFShield(uavtrack_v0.parallel_env(**kw), "tuned"), n_copies=2
    )
    worlds = VectorSharedPolicyVecEnv(2, shield="tuned", **kw)
    copies.seed(7)
    worlds.seed(7)
    np.testing.assert_array_equal(worlds.reset(), copies.reset())
    rng = np.random.default_rng(1)
    interventions = 0
    for _ in range(60):
        act = rng.uniform(-1.0, 1.0, (6, 4)).astype(np.float32)
        i1, i2 = step_both(worlds, copies, act)
        for a, b in zip(i1, i2, strict=True):
            if "shield" in b:
                assert a["shield"]["active"] == b["shield"]["active"]
                interventions += a["shield"]["active"]
    assert interventions > 20
    worlds.close()
    copies.close()


def test_full_infos_certify_the_same():
    """With ``full_infos`` the onboard stacks read the worlds' info dicts instead of the batch's
    arrays: the same certified actions and observations, through autoresets."""
    runs = []
    for full in (False, True):
        venv = uavtrack_v0.vector_env(2, full_infos=full, scenario="random", max_cycles=30)
        env = VectorCBFShield(venv)
        env.reset(seed=2)
        rng = np.random.default_rng(0)
        seen = []
        for _ in range(70):
            obs, *_, infos = env.step(rng.uniform(-1.0, 1.0, (2, 3, 4)))
            seen += [infos["shield"]["action"].copy(), obs.copy()]
        runs.append(seen)
        env.close()
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_config_is_the_expert_config():
    env = VectorCBFShield(uavtrack_v0.vector_env(1), "paper")
    assert env.config == expert_config("paper")
    assert env.vector.config.n_uavs == 3
    env.close()
