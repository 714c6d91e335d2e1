"""RLlib scale-out (train/rllib_ppo.py): the PettingZoo wrapper, its infos, a tiny PPO run."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray.rllib", reason="ray[rllib] is not installed (pip install .[rllib])")
pytest.importorskip("torch", reason="torch is not installed (pip install .[rllib])")

from ray.rllib.env.multi_agent_env import MultiAgentEnv
from ray.rllib.utils.pre_checks.env import check_multiagent_environments

from train import rllib_ppo
from uavtrack_env import parallel_env

HAVE_SHIELD = os.path.exists(
    os.path.join(os.path.dirname(__file__), "..", "uavtrack_env", "wrappers", "shield.py")
)
ENV_KW = {"scenario": "random", "n_uavs": 3, "max_cycles": 6}
SHIELD_MODES = [
    False,
    pytest.param(True, marks=pytest.mark.skipif(not HAVE_SHIELD, reason="no shield")),
]


def _actions(env, rng):
    return {a: rng.uniform(-1, 1, 4).astype(np.float32) for a in env.par_env.agents}


@pytest.mark.parametrize("shield", SHIELD_MODES)
def test_wrapper_builds_and_steps(shield):
    env = rllib_ppo.make_rllib_env({"shield": shield, "env_kwargs": ENV_KW})
    raw = parallel_env(**ENV_KW)
    assert isinstance(env, MultiAgentEnv)
    assert env.agents == env.possible_agents == ["uav_0", "uav_1", "uav_2"]
    for a in env.agents:
        obs_space, act_space = env.get_observation_space(a), env.get_action_space(a)
        assert obs_space == raw.observation_space(a)
        assert obs_space.dtype == np.float32 and obs_space.shape == (raw.n_obs,)
        assert act_space.dtype == np.float32 and act_space.shape == (4,)
        assert np.all(act_space.low == -1) and np.all(act_space.high == 1)

    obs, infos = env.reset(seed=3)
    raw_obs, _ = raw.reset(seed=3)
    assert sorted(obs) == sorted(infos) == env.agents
    rng = np.random.default_rng(0)
    n_steps = 0
    for _ in range(ENV_KW["max_cycles"]):
        for a, o in obs.items():
            assert o.dtype == np.float32
            assert env.get_observation_space(a).contains(o)
        if not shield:  # the wrapper changes nothing: same observations as the bare env
            for a in obs:
                np.testing.assert_array_equal(obs[a], raw_obs[a])
        acts = _actions(env, rng)
        obs, rew, term, trunc, infos = env.step(acts)
        n_steps += 1
        if not shield:
            raw_obs, *_ = raw.step(acts)
        assert "__all__" in term and "__all__" in trunc
        for a in obs:
            assert isinstance(rew[a], float) and math.isfinite(rew[a])
            info = infos[a]
            # slim infos: only finite floats, nothing RLlib has to batch as objects
            assert all(isinstance(v, float) and math.isfinite(v) for v in info.values())
            assert info["cost"] == info["collision"] + info["disconnection"] + info["occlusion"]
            if shield:
                assert info["shield_active"] in (0.0, 1.0)
                assert info["shield_correction_norm"] >= 0.0
                assert info["shield_active"] == float(info["shield_correction_norm"] > 0.0)
            else:
                assert "shield_active" not in info
        if term["__all__"] or trunc["__all__"]:
            break
    # max_cycles reached (or the team collided): the episode is over for RLlib
    assert term["__all__"] or trunc["__all__"]
    if not term["__all__"]:
        assert n_steps == ENV_KW["max_cycles"]
    env.close()
    raw.close()


def test_rllib_env_checker_accepts_raw_and_slim_infos():
    for slim in (True, False):
        env = rllib_ppo.make_rllib_env({"shield": False, "slim_infos": slim, "env_kwargs": ENV_KW})
        check_multiagent_environments(env)  # raises ValueError on a malformed env
        env.close()


def test_slim_info_against_hand_built_info():
    info = {
        "cost": 2.0,
        "violations": {"collision": True, "disconnection": np.bool_(True), "occlusion": False},
        "reward_tracking": -1.5,
        "reward_effort": np.float64(-0.25),
        "measurement": {"u": None, "depth": None},
        "own": {"position": np.ones(3)},
        "truth": {"features": np.zeros(4), "depth_error": None},
        "shield": {"active": True, "correction_norm": 0.5, "status": "fallback", "slack": None},
    }
    out = rllib_ppo.slim_info(info)
    assert out == {
        "cost": 2.0,
        "collision": 1.0,
        "disconnection": 1.0,
        "occlusion": 0.0,
        "reward_tracking": -1.5,
        "reward_effort": -0.25,
        "shield_active": 1.0,
        "shield_fallback": 1.0,
        "shield_correction_norm": 0.5,
        "shield_slack": 0.0,
    }
    # an array report is reduced to its norm (3-4-5), a NaN to 0
    info["shield"] = {"active": False, "correction_norm": np.array([3.0, 4.0]), "slack": math.nan}
    out = rllib_ppo.slim_info(info)
    assert out["shield_correction_norm"] == 5.0 and out["shield_slack"] == 0.0
    assert out["shield_fallback"] == 0.0 and out["shield_active"] == 0.0


def test_bad_settings_raise():
    with pytest.raises(ValueError, match="unknown env_config"):
        rllib_ppo.make_parallel_env({"shields": True})
    with pytest.raises(ValueError, match="num_env_runners"):
        rllib_ppo.build_config(rllib_ppo.RLlibPPOConfig(num_env_runners=-1))
    with pytest.raises(ValueError, match="--hidden"):
        rllib_ppo._parse_hidden("64,x")


def test_shared_policy_config():
    cfg = rllib_ppo.build_config(rllib_ppo.RLlibPPOConfig(shield=False))
    assert set(cfg.policies) == {rllib_ppo.POLICY_ID}
    for agent in ("uav_0", "uav_7"):
        assert cfg.policy_mapping_fn(agent, None) == rllib_ppo.POLICY_ID
    assert cfg.enable_rl_module_and_learner and cfg.enable_env_runner_and_connector_v2


def test_summarize_hand_built_result():
    result = {
        "training_iteration": 3,
        "num_env_steps_sampled_lifetime": 1200,
        "env_runners": {
            "episode_return_mean": -4.5,
            "uavtrack_collision_agent_steps": 2.0,
            "uavtrack_shield_intervention_rate": 0.25,
            "num_episodes": 7,
        },
    }
    out = rllib_ppo.summarize(result)
    assert math.isnan(out.pop("episode_len_mean"))
    assert out == {
        "iteration": 3.0,
        "env_steps": 1200.0,
        "episode_return_mean": -4.5,
        "collision_agent_steps": 2.0,
        "shield_intervention_rate": 0.25,
    }


@pytest.fixture(scope="module")
def local_ray():
    import ray

    rllib_ppo.init_ray(None, num_cpus=1)
    yield
    ray.shutdown()


@pytest.mark.slow
@pytest.mark.parametrize("shield", [HAVE_SHIELD])
def test_tiny_training_writes_checkpoint(local_ray, tmp_path, shield, monkeypatch):
    import torch

    batch = 60
    cfg = rllib_ppo.RLlibPPOConfig(
        shield=shield,
        num_env_runners=0,
        train_batch_size=batch,
        minibatch_size=30,
        num_epochs=1,
        hidden=(16,),
        env_kwargs={"scenario": "random", "max_cycles": 20},
    )
    threads = torch.get_num_threads()
    checkpoint, history = rllib_ppo.train(
        cfg, iterations=1, out=tmp_path, log=lambda _: None, video_every=1, video_seconds=0.1
    )
    assert [p.name for p in (tmp_path / "videos").iterdir()] == ["iteration-1-episode-0.mp4"]
    assert torch.get_num_threads() == threads  # the driver's setting is restored
    assert len(history) == 1 and history[0]["iteration"] == 1
    assert history[0]["env_steps"] >= batch
    assert (checkpoint / "rllib_checkpoint.json").is_file()
    lines = (tmp_path / "progress.jsonl").read_text().splitlines()
    assert [json.loads(x)["iteration"] for x in lines] == [1]
    record = json.loads((tmp_path / "config.json").read_text())
    assert record["rllib"]["shield"] is shield and record["expert"]["cbf"]["gamma_s"] == 3.0
    assert record["env"]["max_cycles"] == 20 and record["commit"]
    if shield:
        assert 0.0 <= history[0]["shield_intervention_rate"] <= 1.0
    # per-agent return, as train.ppo logs it: 20 steps of exp(-c) in (0, 1] at most (no penalty
    # for a shielded run), and the team's sum over 3 agents
    per_agent = history[0]["agent_return_mean"]
    assert per_agent == pytest.approx(history[0]["episode_return_mean"] / 3)
    if shield:
        assert 0.0 < per_agent <= 20.0

    # the saved shared module maps an env observation to a 4-d Gaussian (mean, log std)
    module = rllib_ppo.load_policy(checkpoint)
    env = parallel_env(scenario="random", max_cycles=20)
    obs, _ = env.reset(seed=1)
    batch_obs = torch.as_tensor(np.stack([obs[a] for a in env.agents]))
    out = module.forward_inference({"obs": batch_obs})
    dist = out["action_dist_inputs"]
    assert dist.shape == (3, 8) and torch.isfinite(dist).all()
    env.close()
    with pytest.raises(ValueError, match="not a checkpoint"):
        rllib_ppo.load_policy(tmp_path)
    monkeypatch.chdir(Path(checkpoint).parent)  # a relative path loads too
    assert rllib_ppo.load_policy(Path(checkpoint).name) is not None

    # baselines.compare evaluates the run like an SB3 one, with the saved observation filter
    from baselines import compare

    policy, _ = rllib_ppo.load_run(tmp_path)
    stats = policy.filters["uav_0"].running_stats
    assert stats.n >= batch // 3 and np.any(stats.std != 1.0)  # statistics, not defaults
    np.testing.assert_allclose(policy.filters["uav_0"](stats.mean, update=False), 0.0, atol=1e-5)
    tiny = ["--scenarios", "--seeds", "1", "--duration", "0.1", "--no-progress"]
    tiny += ["--out", str(tmp_path / "cmp")]
    runs = compare.main(["--no-expert", "--run", str(tmp_path), *tiny])
    label = "RLlib PPO + shield" if shield else "RLlib PPO"
    assert [m["policy"] for m in runs] == [label]
    assert (runs[0]["shield_intervention_rate"] is not None) is shield
