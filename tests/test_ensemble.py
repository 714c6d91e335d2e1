"""`baselines.compare.EnsemblePolicy` and ``--ensemble``: several runs evaluated as the mean of
their actions."""

from __future__ import annotations

import json

import numpy as np
import pytest

from baselines import compare
from baselines.compare import EnsemblePolicy
from uavtrack_env.presets import PRESETS, RL_PRESET, expert_config_from


class _Constant:
    """A stand-in member: a fixed action per agent; counts its resets."""

    def __init__(self, action: list[float]) -> None:
        self.action = np.array(action, np.float32)
        self.resets = 0

    def reset(self, layout=None) -> None:
        self.resets += 1

    def __call__(self, obs: dict, infos: dict) -> dict:
        return {a: self.action * (1 + k) for k, a in enumerate(obs)}


def test_the_ensemble_acts_the_mean_of_its_members_and_resets_them():
    a, b = _Constant([1.0, -1.0, 0.5, 0.0]), _Constant([0.0, 0.0, -0.5, -1.0])
    policy = EnsemblePolicy([a, b, lambda obs, infos: {k: np.zeros(4) for k in obs}])
    acts = policy({"uav_0": None, "uav_1": None}, {})
    np.testing.assert_allclose(acts["uav_0"], [1 / 3, -1 / 3, 0.0, -1 / 3], rtol=1e-6)
    np.testing.assert_allclose(acts["uav_1"], [2 / 3, -2 / 3, 0.0, -2 / 3], rtol=1e-6)
    assert acts["uav_0"].dtype == np.float32
    policy.reset()  # the member without a history is skipped
    assert (a.resets, b.resets) == (1, 1)
    with pytest.raises(ValueError, match="at least one member"):
        EnsemblePolicy([])


def _run_dir(path, seed: int, shield: bool, **saved):
    """A train.ppo-shaped output directory holding an untrained SB3 model (``saved``: more
    args.json entries)."""
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO

    from uavtrack_env.wrappers.sb3 import VectorSharedPolicyVecEnv

    path.mkdir()
    vec = VectorSharedPolicyVecEnv(1, scenario="random", max_cycles=20)
    PPO("MlpPolicy", vec, seed=seed, device="cpu").save(path / "model.zip")
    vec.close()
    record = {"shield": shield, "lagrangian": False, "frame_stack": 1, "num_timesteps": 0, **saved}
    (path / "args.json").write_text(json.dumps(record))
    return path


def test_compare_evaluates_runs_as_one_ensemble(tmp_path):
    dirs = [_run_dir(tmp_path / f"s{k}", k, shield=False) for k in range(2)]
    label, shielded, policy = compare.load_ensemble(dirs)
    assert (label, shielded) == ("PPO ensemble of 2", False)
    members = [compare.load_run(d)[0] for d in dirs]
    obs = {"uav_0": np.linspace(-1, 1, members[0].model.observation_space.shape[0])}
    obs = {k: v.astype(np.float32) for k, v in obs.items()}
    mean = (members[0](obs, {})["uav_0"] + members[1](obs, {})["uav_0"]) / 2
    assert not np.allclose(members[0](obs, {})["uav_0"], members[1](obs, {})["uav_0"])
    np.testing.assert_allclose(policy(obs, {})["uav_0"], mean, rtol=1e-6)
    tiny = ["--scenarios", "--seeds", "1", "--duration", "0.1", "--no-progress"]
    argv = ["--no-expert", "--ensemble", *map(str, dirs), *tiny, "--out", str(tmp_path / "c")]
    runs = compare.main(argv)
    assert [m["policy"] for m in runs] == ["PPO ensemble of 2"]
    assert runs[0]["shield_intervention_rate"] is None
    assert "ensemble: 0 agent-steps, 0 agent-steps" in (tmp_path / "c" / "compare.md").read_text()


def test_an_ensemble_must_agree_on_the_shield_and_have_two_runs(tmp_path):
    shielded = _run_dir(tmp_path / "a", 0, shield=True)
    plain = _run_dir(tmp_path / "b", 1, shield=False)
    assert compare.load_ensemble([shielded, shielded])[:2] == ("PPO ensemble of 2 + shield", True)
    with pytest.raises(ValueError, match="all be shielded or all unshielded"):
        compare.load_ensemble([shielded, plain])
    with pytest.raises(ValueError, match="at least two run directories"):
        compare.load_ensemble([shielded])


def test_a_shielded_run_is_evaluated_behind_the_shield_it_trained_with(tmp_path):
    """`run_shield` rebuilds a run's shield from its preset and --set (train.ppo's args.json,
    train.rllib_ppo's config.json; no preset: the trainers' default); compare's own --preset
    and --set configure the expert only."""
    sets = ["cbf.gamma_o=0.5"]
    run = _run_dir(tmp_path / "a", 0, shield=True, preset="tuned", set=sets)
    want = expert_config_from("tuned", sets)
    assert compare.run_shield(run) == want
    older = _run_dir(tmp_path / "b", 1, shield=True)  # args.json without a preset: tuned's
    assert compare.run_shield(older) == PRESETS["tuned"]
    rllib = tmp_path / "rllib"
    rllib.mkdir()
    (rllib / "config.json").write_text(json.dumps({"preset": "paper", "set": sets}))
    assert compare.run_shield(rllib) == expert_config_from("paper", sets)
    (rllib / "config.json").write_text(json.dumps({"preset": None}))  # train() told no preset
    assert compare.run_shield(rllib) == PRESETS[RL_PRESET]
    args = compare.parse_args(["--no-expert", "--run", str(run), "--set", "cbf.gamma_o=0.2"])
    [(label, shield, _)] = compare._entrants(args, expert_config_from("tuned", args.set))
    assert label == "PPO + shield" and shield == want
    plain = _run_dir(tmp_path / "c", 2, shield=False, preset="tuned")
    args = compare.parse_args(["--run", str(plain)])
    assert [shield for _, shield, _ in compare._entrants(args, want)] == [None, None]


def test_an_ensemble_must_share_one_shield(tmp_path):
    a = _run_dir(tmp_path / "a", 0, shield=True, preset="tuned")
    b = _run_dir(tmp_path / "b", 1, shield=True, preset="rl")
    c = _run_dir(tmp_path / "c", 2, shield=True)  # older: no preset, tuned's
    d = _run_dir(tmp_path / "d", 3, shield=True, preset="tuned", set=["cbf.team_mate_radius=none"])
    assert compare.load_ensemble([a, c])[1] is True
    assert compare.load_ensemble([b, d])[1] is True  # the same shield, named two ways
    with pytest.raises(ValueError, match="share one shield"):
        compare.load_ensemble([a, b])
