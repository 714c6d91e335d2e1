"""Behaviour cloning: expert demonstrations, the actor fit, and the critic-only warm-up."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import gymnasium
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from baselines.compare import load_run
from tests.test_train_ppo import SMOKE
from train import bc, ppo
from uavtrack_env import uavtrack_v0
from uavtrack_env.expert import ExpertPolicy


def _small_world():
    return uavtrack_v0.parallel_env(scenario="random", max_cycles=40)


@pytest.mark.slow
def test_collect_records_the_experts_actions():
    obs, actions = bc.collect(_small_world, episodes=2, seed=7, progress=False)
    assert obs.shape == (2 * 40 * 3, _small_world().observation_space("uav_0").shape[0])
    assert actions.shape == (240, 4) and obs.dtype == actions.dtype == np.float32
    assert np.all(np.abs(actions) <= 1.0) and np.abs(actions).max() > 0
    # replaying the first episode by hand gives the same pairs (same seed, deterministic expert)
    env = _small_world()
    o, infos = env.reset(seed=7)
    expert = ExpertPolicy.from_env(env)
    for k in range(40):
        acts = expert(o, infos)
        for i, a in enumerate(env.agents):
            np.testing.assert_array_equal(obs[3 * k + i], o[a])
            np.testing.assert_array_equal(actions[3 * k + i], acts[a])
        o, _, _, _, infos = env.step(acts)
    with pytest.raises(ValueError, match="episodes"):
        bc.collect(_small_world, episodes=0, seed=0)
    with pytest.raises(ValueError, match="workers"):
        bc.collect(_small_world, episodes=1, seed=0, workers=0)


@pytest.mark.slow
def test_collect_in_processes_records_the_same_demonstrations():
    """Two worker processes give the pairs of one, in the same order (episodes by seed)."""
    make = functools.partial(uavtrack_v0.parallel_env, scenario="random", max_cycles=30)
    serial = bc.collect(make, episodes=3, seed=11, progress=False)
    parallel = bc.collect(make, episodes=3, seed=11, progress=False, workers=2)
    for a, b in zip(serial, parallel, strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(serial[0]) == 3 * 30 * 3


class _Box(gymnasium.Env):
    observation_space = gymnasium.spaces.Box(-10, 10, (5,), np.float32)
    action_space = gymnasium.spaces.Box(-1, 1, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        return np.zeros(5, np.float32), {}

    def step(self, action):
        return np.zeros(5, np.float32), 0.0, True, False, {}


@pytest.mark.slow
def test_pretrain_fits_a_known_linear_map_and_sets_the_normaliser():
    rng = np.random.default_rng(0)
    obs = (rng.normal(size=(4000, 5)) * [1, 2, 3, 4, 5] + [5, 0, -5, 1, 2]).astype(np.float32)
    W = rng.uniform(-0.05, 0.05, (5, 2))
    actions = ((obs - obs.mean(0)) / obs.std(0) @ W).astype(np.float32)
    vec = VecNormalize(DummyVecEnv([_Box]), norm_reward=False)
    model = PPO("MlpPolicy", vec, seed=0, device="cpu")
    stats = bc.pretrain(model, vec, obs, actions, epochs=40, progress=False)
    np.testing.assert_allclose(vec.obs_rms.mean, obs.mean(0), rtol=1e-5)
    np.testing.assert_allclose(vec.obs_rms.var, obs.var(0), rtol=1e-4)
    assert stats["bc_val_loss"] < 0.05 < stats["bc_val_loss_first_epoch"]
    with torch.no_grad():
        x = torch.as_tensor(vec.normalize_obs(obs[:200]))
        pred = model.policy.get_distribution(x).distribution.mean.numpy()
    assert np.sqrt(np.mean((pred - actions[:200]) ** 2)) < 0.25 * actions.std()


@pytest.mark.slow
def test_the_annealed_fit_ends_closer_to_the_map_than_the_constant_rate_one():
    """With noisy labels and a large step, constant-rate Adam ends wherever its last steps
    wandered; annealed to 0 it settles. Both start from the same actor and see the same batches."""
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(4096, 5)).astype(np.float32)
    W = rng.uniform(-0.5, 0.5, (5, 2))
    clean = np.tanh(obs @ W)
    actions = (clean + rng.normal(scale=0.5, size=clean.shape)).astype(np.float32)
    errors = {}
    for schedule in bc.SCHEDULES:
        model = PPO("MlpPolicy", DummyVecEnv([_Box]), seed=0, device="cpu")
        bc.pretrain(
            model, None, obs, actions, epochs=8, learning_rate=3e-2, schedule=schedule,
            progress=False,
        )  # fmt: skip
        with torch.no_grad():
            pred = model.policy.get_distribution(torch.as_tensor(obs)).distribution.mean
        errors[schedule] = float(np.mean((pred.numpy() - clean) ** 2))
    assert errors["cosine"] < 0.5 * errors["constant"], errors
    with pytest.raises(ValueError, match="schedule must be one of"):
        bc.pretrain(model, None, obs, actions, schedule="linear", progress=False)


@pytest.mark.slow
def test_value_warmup_freezes_the_actor_and_trains_the_critic(tmp_path):
    """With the warm-up covering all steps, PPO changes the critic but not the cloned actor."""
    out = tmp_path / "run"
    ppo.main(
        ["--no-shield", "--timesteps", "768", "--out", str(out), *SMOKE]
        + ["--bc-episodes", "1", "--bc-epochs", "2", "--value-warmup", "768"]
    )
    saved = json.loads((out / "args.json").read_text())
    assert saved["bc_samples"] == 100 * 3 and (out / "demos.npz").exists()
    cloned = PPO.load(out / "checkpoints" / "ppo_0_steps.zip", device="cpu").policy
    trained = PPO.load(out / "model.zip", device="cpu")
    assert trained.num_timesteps == 768
    actor = [
        *trained.policy.mlp_extractor.policy_net.parameters(),
        *trained.policy.action_net.parameters(),
        trained.policy.log_std,
    ]
    before = [
        *cloned.mlp_extractor.policy_net.parameters(),
        *cloned.action_net.parameters(),
        cloned.log_std,
    ]
    for a, b in zip(actor, before, strict=True):
        assert torch.equal(a, b)
    # baselines.compare can evaluate the cloned policy (checkpoint 0) as its own entrant
    policy, run_args = load_run(out, cloned=True)
    assert run_args["bc_episodes"] == 1
    obs = {"uav_0": np.zeros(policy.model.observation_space.shape, np.float32)}
    with torch.no_grad():
        x = torch.as_tensor(policy.obs_normalizer.normalize_obs(obs["uav_0"][None]))
        expect = cloned.get_distribution(x).distribution.mean.numpy()[0]
    np.testing.assert_allclose(policy(obs, {})["uav_0"], np.clip(expect, -1, 1), atol=1e-6)
    critic = [
        *trained.policy.value_net.parameters(),
        *trained.policy.mlp_extractor.value_net.parameters(),
    ]
    critic0 = [*cloned.value_net.parameters(), *cloned.mlp_extractor.value_net.parameters()]
    assert any(not torch.equal(a, b) for a, b in zip(critic, critic0, strict=True))


def test_without_warmup_ppo_moves_the_actor(tmp_path):
    """The control case of the test above: the same run with no warm-up changes the actor."""
    out = tmp_path / "run"
    ppo.main(
        ["--no-shield", "--timesteps", "384", "--out", str(out), *SMOKE]
        + ["--bc-episodes", "1", "--bc-epochs", "1", "--value-warmup", "0"]
    )
    cloned = PPO.load(out / "checkpoints" / "ppo_0_steps.zip", device="cpu").policy
    trained = PPO.load(out / "model.zip", device="cpu").policy
    a = torch.cat([p.flatten() for p in trained.action_net.parameters()])
    b = torch.cat([p.flatten() for p in cloned.action_net.parameters()])
    assert not torch.equal(a, b)


def _cloning_loss(model, normalizer, obs, actions) -> float:
    y = torch.as_tensor(actions)
    with torch.no_grad():
        x = torch.as_tensor(normalizer.normalize_obs(obs), dtype=torch.float32)
        return float(bc.cloning_loss(model.policy, x, y, y.std(dim=0).clamp_min(1e-3)))


@pytest.mark.slow
def test_anchor_steps_keep_fitting_the_demonstrations(tmp_path):
    """With PPO's own step size at 0, only the anchor moves the actor: the loss must fall (it
    waits out the critic warm-up, whose frozen actor it must not touch)."""
    import pickle

    out = tmp_path / "run"
    ppo.main(
        ["--no-shield", "--timesteps", "768", "--out", str(out), *SMOKE]
        + ["--bc-episodes", "1", "--bc-epochs", "1", "--value-warmup", "384"]
        + ["--learning-rate", "0", "--bc-anchor", "40"]
    )
    with np.load(out / "demos.npz") as d:
        obs, actions = d["obs"], d["actions"]
    with (out / "vecnormalize.pkl").open("rb") as f:
        norm = pickle.load(f)
    before = _cloning_loss(PPO.load(out / "checkpoints" / "ppo_0_steps.zip"), norm, obs, actions)
    after = _cloning_loss(PPO.load(out / "model.zip"), norm, obs, actions)
    assert after < 0.8 * before
    with pytest.raises(ValueError, match="bc-anchor needs"):
        ppo.main(["--no-shield", "--timesteps", "384", "--out", str(tmp_path / "x"), *SMOKE]
                 + ["--bc-anchor", "5"])  # fmt: skip


@pytest.mark.slow
def test_dagger_labels_the_learners_states_with_the_experts_actions(tmp_path, capsys):
    """One DAgger round in train.ppo adds one episode of labels; `collect` with a learner
    records the states the learner visits (replayed by hand) and the expert's actions there."""
    out = tmp_path / "run"
    ppo.main(
        ["--shield", "--timesteps", "384", "--out", str(out), *SMOKE]
        + ["--bc-episodes", "1", "--bc-epochs", "1", "--dagger-rounds", "1"]
        + ["--dagger-episodes", "1", "--value-warmup", "0"]
    )
    saved = json.loads((out / "args.json").read_text())
    assert saved["bc_samples"] == 2 * 100 * 3  # the demonstrations and one round of labels
    with np.load(out / "demos.npz") as demos, np.load(out / "dagger.npz") as all_labels:
        np.testing.assert_array_equal(all_labels["obs"][:300], demos["obs"])
        assert len(all_labels["actions"]) == 600
    capsys.readouterr()
    resume = ["--resume", str(out), "--timesteps", "192", "--bc-episodes", "1", "--bc-anchor", "1"]
    ppo.main([*SMOKE, *resume])
    assert f"600 samples from {out / 'dagger.npz'}" in capsys.readouterr().out  # the anchor's

    ck = out / "checkpoints"
    learner = bc.Learner(ck / "ppo_0_steps.zip", ck / "ppo_vecnormalize_0_steps.pkl")
    obs, labels = bc.collect(_small_world, episodes=1, seed=3, progress=False, learner=learner)
    expert_obs, _ = bc.collect(_small_world, episodes=1, seed=3, progress=False)
    assert obs.shape == expert_obs.shape == (120, obs.shape[1])
    assert not np.array_equal(obs, expert_obs)  # the learner's states, not the expert's
    env = _small_world()
    o, infos = env.reset(seed=3)
    expert, acting = ExpertPolicy.from_env(env), learner.policy()
    for k in range(40):
        want = expert(o, infos)
        acts = acting(o, infos)
        for i, a in enumerate(env.agents):
            np.testing.assert_array_equal(obs[3 * k + i], o[a])
            np.testing.assert_array_equal(labels[3 * k + i], want[a])
        o, _, _, _, infos = env.step(acts)
        expert.applied(acts)
    own = np.concatenate([acting({"uav_0": row}, {})["uav_0"][None] for row in obs])
    assert not np.allclose(labels, own)  # the expert's actions, not the learner's


class _Ramp(_Box):
    """Observations that grow every step, so running statistics would move."""

    t = 0.0

    def step(self, action):
        self.t += 1.0
        return np.full(5, self.t, np.float32), 1.0, False, False, {}


def test_frozen_observation_statistics_stay_put_and_survive_a_save(tmp_path):
    vec = VecNormalize(DummyVecEnv([_Ramp]))
    vec.reset()
    for _ in range(3):
        vec.step(np.zeros((1, 2), np.float32))
    bc.freeze_observation_statistics(vec)
    mean, var, count = vec.obs_rms.mean.copy(), vec.obs_rms.var.copy(), vec.obs_rms.count
    returns_count = vec.ret_rms.count
    for _ in range(5):
        obs = vec.step(np.zeros((1, 2), np.float32))[0]
    np.testing.assert_array_equal(vec.obs_rms.mean, mean)
    np.testing.assert_array_equal(vec.obs_rms.var, var)
    assert vec.obs_rms.count == count
    assert vec.ret_rms.count > returns_count  # the reward's statistics still run
    np.testing.assert_allclose(obs[0], np.clip((8.0 - mean) / np.sqrt(var + 1e-8), -10, 10))
    bc.freeze_observation_statistics(vec)  # a second freeze keeps the same statistics
    np.testing.assert_array_equal(vec.obs_rms.mean, mean)
    vec.save(str(tmp_path / "norm.pkl"))
    loaded = VecNormalize.load(str(tmp_path / "norm.pkl"), DummyVecEnv([_Ramp]))
    loaded.reset()
    loaded.step(np.zeros((1, 2), np.float32))
    np.testing.assert_array_equal(loaded.obs_rms.mean, mean)
    # the control: unfrozen statistics move on the same stream
    moving = VecNormalize(DummyVecEnv([_Ramp]))
    moving.reset()
    before = moving.obs_rms.mean.copy()
    moving.step(np.zeros((1, 2), np.float32))
    assert not np.array_equal(moving.obs_rms.mean, before)


@pytest.mark.slow
def test_freeze_obs_stats_keeps_the_demonstrations_statistics_through_ppo(tmp_path):
    import pickle

    out = tmp_path / "run"
    ppo.main(
        ["--no-shield", "--timesteps", "384", "--out", str(out), *SMOKE]
        + ["--bc-episodes", "1", "--bc-epochs", "1", "--freeze-obs-stats"]
    )
    with np.load(out / "demos.npz") as d:
        obs = d["obs"]
    with (out / "vecnormalize.pkl").open("rb") as f:
        norm = pickle.load(f)
    np.testing.assert_allclose(norm.obs_rms.mean, obs.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(norm.obs_rms.var, obs.var(0), rtol=1e-4, atol=1e-9)
    assert norm.obs_rms.count == len(obs)
