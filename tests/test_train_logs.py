"""PPO-Lagrangian's penalty and multiplier, the shield-intervention penalty, the exact step
budget, the learning-curve log, and the training world both trainers share."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from stable_baselines3.common.vec_env import DummyVecEnv

from train import ppo
from train.intervention import InterventionPenalty
from train.lagrangian import LagrangianConfig, LagrangianReward
from train.world import TrainingWorld
from uavtrack_env.presets import PRESETS, RL_PRESET
from uavtrack_env.wrappers.sb3 import AgentVecMonitor


class _CostlyEnv(gymnasium.Env):
    """Reward 0.5 and cost 1 on every step; episodes of 4 steps."""

    observation_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.zeros(1, np.float32), 0.5, self.t == 4, False, {"cost": 1.0}


def _vec(lam: float = 0.0, **kw) -> LagrangianReward:
    venv = AgentVecMonitor(DummyVecEnv([_CostlyEnv, _CostlyEnv]))
    return LagrangianReward(venv, LagrangianConfig(lambda_init=lam, **kw))


def test_penalised_reward_and_episode_cost():
    vec = _vec(lam=3.0)
    vec.reset()
    for _ in range(4):
        _, rewards, dones, infos = vec.step(np.zeros((2, 1), np.float32))
        np.testing.assert_allclose(rewards, (0.5 - 3.0 * 1.0) / (1.0 + 3.0))
    assert dones.all()
    assert [info["episode"]["c"] for info in infos] == [4.0, 4.0]
    assert [info["episode"]["r"] for info in infos] == [2.0, 2.0]  # the env's own return


def test_multiplier_ascends_on_excess_cost_and_stays_non_negative():
    vec = _vec(cost_limit=1.0, lambda_lr=0.1)
    assert vec.update([3.0, 5.0]) == pytest.approx(0.1 * (4.0 - 1.0))
    assert vec.update([]) == pytest.approx(0.3)  # no episode ended: no step
    assert vec.update([0.0, 0.0, 0.0]) == pytest.approx(0.2)
    assert vec.update([0.0] * 10) == pytest.approx(0.1)
    assert vec.update([0.0] * 10) == pytest.approx(0.0, abs=1e-12)
    assert vec.update([0.0]) == 0.0  # projected onto lambda >= 0


@pytest.mark.parametrize("kw", [{"cost_limit": -1.0}, {"lambda_lr": 0.0}, {"lambda_init": -0.1}])
def test_bad_lagrangian_settings_raise(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        LagrangianConfig(**kw)


class _CorrectedEnv(_CostlyEnv):
    """`_CostlyEnv` whose shield corrects every step by 0.25 m/s times the step count."""

    def step(self, action):
        obs, reward, term, trunc, info = super().step(action)
        return obs, reward, term, trunc, {**info, "shield": {"correction_norm": 0.25 * self.t}}


def test_intervention_penalty_charges_each_rows_correction():
    venv = AgentVecMonitor(DummyVecEnv([_CorrectedEnv, _CostlyEnv]))
    vec = InterventionPenalty(venv, 2.0)
    vec.reset()
    for t in range(1, 5):
        _, rewards, _, infos = vec.step(np.zeros((2, 1), np.float32))
        np.testing.assert_allclose(rewards, [0.5 - 2.0 * 0.25 * t, 0.5])  # no shield: unchanged
    assert [info["episode"]["r"] for info in infos] == [2.0, 2.0]  # the env's own return


def test_intervention_penalty_settings():
    with pytest.raises(ValueError, match="finite number >= 0"):
        InterventionPenalty(DummyVecEnv([_CostlyEnv]), -1.0)
    with pytest.raises(ValueError, match="add --shield"):
        ppo.parse_args(["--out", "x", "--no-shield", "--intervention-penalty", "1"])
    with pytest.raises(ValueError, match="finite number >= 0"):
        ppo.parse_args(["--out", "x", "--intervention-penalty", "nan"])
    args = ppo.parse_args(["--out", "x", "--intervention-penalty", "0.5", "--n-envs", "1"])
    assert isinstance(ppo.make_vec_env(args).venv, InterventionPenalty)  # under VecNormalize


def test_both_trainers_default_to_the_same_world():
    pytest.importorskip("ray")
    from train import rllib_ppo

    world = TrainingWorld().env_kwargs()
    assert ppo.world_settings(ppo.parse_args(["--out", "x"])) == world
    assert dict(rllib_ppo.RLlibPPOConfig().env_kwargs) == world
    cli = rllib_ppo.parse_args(["--out", "x"])
    assert TrainingWorld.from_fields(cli).env_kwargs() == world
    with pytest.raises(ValueError, match="terminate_on_collision"):
        ppo.parse_args(["--out", "x", "--terminate-on-collision", "sometimes"])


def test_image_weight_reaches_the_reward_weights():
    """``--image-weight`` sets Q_s's x1 and x2 weights of the reward (eq. 18) and keeps x3's and
    psi's (Table III); a negative weight is refused, naming the field."""
    from uavtrack_env.config import EnvConfig

    world = ppo.world_settings(ppo.parse_args(["--out", "x", "--image-weight", "30"]))
    assert EnvConfig.from_kwargs(**world).reward.q == (30.0, 30.0, 100.0, 1.0)
    assert EnvConfig.from_kwargs(**TrainingWorld().env_kwargs()).reward.q == (1.0, 1.0, 100.0, 1.0)
    for bad in ("-1", "nan"):
        with pytest.raises(ValueError, match="image_weight"):
            ppo.parse_args(["--out", "x", "--image-weight", bad])


def test_image_point_reaches_the_reward():
    """The reward scores the bounding box's centre by default and the car's centre with
    ``--image-point center``; an unknown point is refused, naming the field."""
    from uavtrack_env.config import EnvConfig

    world = ppo.world_settings(ppo.parse_args(["--out", "x", "--image-point", "center"]))
    assert EnvConfig.from_kwargs(**world).reward.image_point == "center"
    assert EnvConfig.from_kwargs(**TrainingWorld().env_kwargs()).reward.image_point == "box"
    with pytest.raises(ValueError, match="image_point"):
        ppo.parse_args(["--out", "x", "--image-point", "corner"])


@pytest.mark.parametrize(("saved", "expected"), [({}, "center"), ({"image_point": "box"}, "box")])
def test_resume_keeps_the_image_point_the_run_trained_with(tmp_path, saved, expected):
    """A run whose args.json predates ``image_point`` scored the car's centre; ``--resume``
    keeps that instead of taking the new default."""
    (tmp_path / "args.json").write_text(json.dumps({"image_weight": 30.0, **saved}))
    args = ppo.make_args(resume=tmp_path)
    assert args.image_point == expected and args.image_weight == 30.0 and args.out == tmp_path


def test_the_trainers_shield_covers_the_team_mates():
    """The trainers default to the rl preset: the env's occlusion cost counts a team-mate on the
    sight line, and that preset's rows cover them."""
    from train import rllib_ppo

    args = ppo.parse_args(["--out", "x"])
    assert args.preset == RL_PRESET == "rl"
    assert ppo.expert_settings(args) == PRESETS["rl"]
    assert ppo.expert_settings(args).cbf.team_mate_radius is None
    assert rllib_ppo.parse_args(["--out", "x"]).preset == "rl"
    assert rllib_ppo.RLlibPPOConfig().expert == PRESETS["rl"]


@pytest.mark.parametrize(
    ("saved", "expected"), [({}, "tuned"), ({"preset": "tuned"}, "tuned"), ({"preset": "rl"}, "rl")]
)
def test_resume_keeps_the_shield_the_run_trained_with(tmp_path, saved, expected):
    """A run trained on the tuned preset (or predating ``preset``) resumes on it."""
    (tmp_path / "args.json").write_text(json.dumps(saved))
    args = ppo.make_args(resume=tmp_path)
    assert args.preset == expected and ppo.expert_settings(args) == PRESETS[expected]


def test_world_density_options_reach_the_random_worlds():
    args = ppo.parse_args(
        ["--out", "x", "--min-obstacles", "24", "--max-obstacles", "48", "--corridor", "1.5"]
    )
    world = ppo.world_settings(args)["random_world"]
    assert world["n_obstacles"] == (24, 48) and world["corridor"] == 1.5
    with pytest.raises(ValueError, match="n_obstacles"):
        ppo.parse_args(["--out", "x", "--min-obstacles", "9", "--max-obstacles", "8"])
    with pytest.raises(ValueError, match="corridor"):
        ppo.parse_args(["--out", "x", "--corridor", "0"])


@pytest.mark.slow
def test_exact_budget_lagrangian_log_and_resume(tmp_path, capsys):
    out = tmp_path / "lag"
    common = [
        "--no-shield", "--n-envs", "2", "--n-steps", "64", "--batch-size", "192",
        "--n-epochs", "1", "--max-cycles", "40", "--no-progress", "--log-every", "1",
    ]  # fmt: skip
    lagrangian = ["--lagrangian", "--cost-limit", "0"]
    video = ["--video-every", "300", "--video-seconds", "0.1"]
    ppo.main([*common, *lagrangian, *video, "--timesteps", "500", "--out", str(out)])
    assert [p.name for p in (out / "videos").iterdir()] == ["step-300-episode-0.mp4"]
    saved = json.loads((out / "args.json").read_text())
    assert saved["num_timesteps"] == 504  # the first vector step (6 rows) at or past 500
    assert not (out / "metrics.json").exists()  # evaluation is opt-in
    lines = [ln for ln in capsys.readouterr().out.splitlines() if " steps | return" in ln]
    assert len(lines) >= 2 and all("lambda" in ln and "violations/1k" in ln for ln in lines)
    lam = saved["lagrangian_lambda"]
    assert lam >= 0.0
    ppo.main([*common, "--resume", str(out), "--timesteps", "300"])
    again = json.loads((out / "args.json").read_text())
    assert again["num_timesteps"] == 804 and again["lagrangian"] is True
    assert [c["from_timesteps"] for c in again["calls"]] == [0, 504]
    counted = [c["training_violations"]["agent_steps"] for c in again["calls"]]
    assert again["training_violations"]["agent_steps"] == sum(counted) > 0
    # baselines.compare names the run by its settings
    from baselines import compare

    tiny = ["--scenarios", "--seeds", "1", "--duration", "0.1", "--no-progress"]
    runs = compare.main(["--no-expert", "--run", str(out), *tiny, "--out", str(tmp_path / "c")])
    assert [m["policy"] for m in runs] == ["PPO-Lagrangian"]
    assert runs[0]["shield_intervention_rate"] is None
    with pytest.raises(ValueError, match=r"neither a train\.ppo run"):
        compare.load_any_run(tmp_path)


def test_console_return_is_the_mean_of_the_last_finished_episodes():
    """Each console line carries the last `recent` episodes' mean return and cost, also after
    a rollout in which no episode ended; TensorBoard's per-rollout numbers stay NaN there."""
    from train.callbacks import TrainingLog, format_row

    lines: list[str] = []
    log = TrainingLog(every=1, echo=lines.append, recent=3)
    log.num_timesteps = 0
    log._on_rollout_start()

    def rollout(episodes):
        log.locals = {"infos": [{"episode": {"r": r, "c": c}} for r, c in episodes]}
        log._on_step()
        row = log.row()
        lines.append(format_row(row))
        log._on_rollout_start()
        return row

    assert "return - | cost - (last 0 episodes)" in format_row(log.row())
    first = rollout([(1.0, 0.0), (3.0, 2.0)])
    assert first["recent_return"] == 2.0 and first["ep_return"] == 2.0
    quiet = rollout([])
    assert np.isnan(quiet["ep_return"]) and quiet["recent_return"] == 2.0
    assert "return 2.00 | cost 1.00 (last 2 episodes)" in lines[-1]
    rollout([(5.0, 1.0), (7.0, 1.0)])  # only the last 3 count: 3, 5, 7
    assert "return 5.00 | cost 1.33 (last 3 episodes)" in lines[-1]


def test_training_log_records_each_violating_agent_step_with_its_world_and_uav(tmp_path):
    from types import SimpleNamespace

    from train.callbacks import TrainingLog

    events = tmp_path / "violations.jsonl"
    log = TrainingLog(every=10**9, echo=None, events=events)
    log.model = SimpleNamespace(get_env=lambda: SimpleNamespace(n_agents=3))
    log.num_timesteps = 96
    log._on_training_start()
    clean = {"collision": False, "disconnection": False, "occlusion": False}
    infos = [{"violations": dict(clean)} for _ in range(6)]
    infos[4]["violations"]["occlusion"] = True  # world 1, UAV 1
    infos[5] = {"absorbing": True}
    infos[0]["violations"].update(collision=True, disconnection=True)
    log.locals = {"infos": infos}
    log._on_step()
    lines = [json.loads(x) for x in events.read_text().splitlines()]
    assert lines == [
        {"agent_steps": 96, "row": 0, "world": 0, "uav": 0,
         "violations": ["collision", "disconnection"]},
        {"agent_steps": 96, "row": 4, "world": 1, "uav": 1, "violations": ["occlusion"]},
    ]  # fmt: skip
    assert log.counts["occlusion"] == 1 and log.counts["agent_steps"] == 5
