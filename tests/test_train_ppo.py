"""PPO smoke runs (shielded and not): checkpoints, --resume step counts, metrics.json schema; the
shared episode runner's violation and intervention counts on a policy that dives into the ground."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from stable_baselines3 import PPO

from baselines.compare import comparison_table, make_eval_env, run_policy_episode
from tests.conftest import METRICS_UAV_KEYS
from train import ppo
from uavtrack_env.presets import expert_config

UAV_KEYS = METRICS_UAV_KEYS | {"theta_ok", "steps", "detection_kept_ok", "max_blocked_fraction"}
# 2 copies x 3 UAVs = 6 rows; 64 steps per rollout -> 384 agent-steps per rollout
SMOKE = [
    "--n-envs", "2", "--n-steps", "64", "--batch-size", "192", "--n-epochs", "1",
    "--max-cycles", "100", "--eval-duration", "0.25", "--eval-seeds", "1",
    "--checkpoint-freq", "384", "--no-progress", "--seed", "0", "--evaluate",
]  # fmt: skip


def _check_metrics(out, shielded: bool, calls: int = 1) -> None:
    runs = json.loads((out / "metrics.json").read_text())
    worlds = [("A", 0), ("A", 1), ("random", 0)]
    assert [(m["scenario"], m["init"]) for m in runs] == worlds * calls
    for m in runs:
        assert set(m["uavs"]) == {"uav_0", "uav_1", "uav_2"}
        for u in m["uavs"].values():
            assert set(u) == UAV_KEYS
        assert {"env", "policy"} <= set(m["timing_ms"])
        assert set(m["violations_per_1000_steps"]) == {"collision", "disconnection", "occlusion"}
        rate = m["shield_intervention_rate"]
        assert (rate is not None and 0.0 <= rate <= 1.0) if shielded else rate is None
        assert m["duration_s"] == pytest.approx(0.25)


@pytest.mark.slow
@pytest.mark.parametrize("shield", [False, True])
def test_smoke_checkpoint_and_resume(tmp_path, shield):
    out = tmp_path / "run"
    flag = "--shield" if shield else "--no-shield"
    ppo.main([flag, "--timesteps", "768", "--out", str(out), *SMOKE])
    ckpts = sorted(p.name for p in (out / "checkpoints").glob("ppo_*_steps.zip"))
    assert ckpts == ["ppo_384_steps.zip", "ppo_768_steps.zip"]
    assert (out / "checkpoints" / "ppo_vecnormalize_768_steps.pkl").exists()
    assert any((out / "tb").iterdir())
    _check_metrics(out, shield)
    before = PPO.load(out / "model.zip", device="cpu").num_timesteps
    assert before == 768
    counted = json.loads((out / "args.json").read_text())["training_violations"]
    assert 0 < counted["agent_steps"] <= 768
    assert 0 <= counted["collision"] <= counted["agent_steps"]
    if shield:  # the shield's guarantee, also in training
        assert counted["collision"] == 0 and counted["disconnection"] == 0
        assert counted["shield_active"] > 0
    else:
        assert counted["shield_active"] == 0
    events = (out / "violations.jsonl").read_text().splitlines()
    for name in ("collision", "disconnection", "occlusion"):  # one line per violating agent-step
        assert sum(name in json.loads(e)["violations"] for e in events) == counted[name]
    if not shield:
        return
    # resume: the env settings come from args.json, the step count continues
    ppo.main(["--resume", str(out), "--timesteps", "384", *SMOKE])
    after = PPO.load(out / "model.zip", device="cpu").num_timesteps
    assert after > before
    assert after == before + 384
    saved = json.loads((out / "args.json").read_text())
    assert saved["num_timesteps"] == 1152 and saved["shield"] is True
    assert [(c["from_timesteps"], c["to_timesteps"]) for c in saved["calls"]] == [
        (0, 768),
        (768, 1152),
    ]
    assert saved["training_violations"]["agent_steps"] == sum(
        c["training_violations"]["agent_steps"] for c in saved["calls"]
    )
    _check_metrics(out, shield, calls=2)  # the second evaluation is appended
    path, norm = ppo.last_checkpoint(out)
    assert path.name == "ppo_1152_steps.zip" and norm is not None
    assert PPO.load(path, device="cpu").num_timesteps == 1152


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="--out"):
        ppo.parse_args(["--timesteps", "10"])
    with pytest.raises(ValueError, match="eval-scenarios"):
        ppo.parse_args(["--out", str(tmp_path), "--eval-scenarios", "AD"])
    with pytest.raises(ValueError, match="no checkpoint"):
        ppo.last_checkpoint(tmp_path)
    with pytest.raises(ValueError, match="--bc-workers must be >= 1"):
        ppo.parse_args(["--out", str(tmp_path), "--bc-workers", "0"])
    with pytest.raises(ValueError, match=r"--bc-schedule takes one of .*'linear'"):
        ppo.parse_args(["--out", str(tmp_path), "--bc-schedule", "linear"])


def dive(obs, infos):
    """Full speed along camera +Y (down): the ground is 0.85 - 0.25 m below (section VI-A)."""
    return {a: np.array([0.0, 1.0, 0.0, 0.0], np.float32) for a in obs}


def test_episode_counts_on_a_ground_dive():
    env = make_eval_env("A", 0, 80, dynamics="integrator", shield=None, noise=False)
    m = run_policy_episode(env, dive, seed=0, steps=80, label="dive", dynamics="integrator")
    env.close()
    # 10 m/s down from 0.85 m: the sphere (r = 0.25) touches the ground after ~0.6/10 s = 4.8
    # steps at 80 Hz; terminate_on_collision='all' ends the episode on that step for all three.
    steps = m["agent_steps"] // 3
    assert 4 <= steps <= 7
    assert m["violation_steps"]["collision"] == 3
    assert m["violations_per_1000_steps"]["collision"] == pytest.approx(1000 * 3 / (3 * steps))
    assert not any(u["collision_ok"] for u in m["uavs"].values())
    assert m["shield_intervention_rate"] is None

    env = make_eval_env("A", 0, 80, dynamics="integrator", shield=expert_config(), noise=False)
    s = run_policy_episode(env, dive, seed=0, steps=80, label="dive+shield", dynamics="integrator")
    env.close()
    assert s["agent_steps"] == 3 * 80  # survives the whole second
    assert s["violation_steps"]["collision"] == 0
    assert all(u["collision_ok"] for u in s["uavs"].values())
    assert s["shield_intervention_rate"] > 0.5  # the dive must be corrected most of the time
    md = comparison_table([m, s]).splitlines()
    assert len(md) == 4 and "| dive | A0 | 1 |" in md[2] and "| 3 |" in md[2]
    assert math.isclose(s["duration_s"], 1.0)


def test_compare_cli_and_merge(tmp_path):
    """The compare CLI on a tiny budget writes its table; --merge joins two such runs."""
    from baselines import compare

    common = ["--duration", "0.1", "--no-progress", "--seeds", "1"]
    a = compare.main([*common, "--scenarios", "A", "--out", str(tmp_path / "a")])
    b = compare.main([*common, "--scenarios", "--out", str(tmp_path / "b")])
    assert [(m["scenario"], m["init"]) for m in a] == [("A", 0), ("A", 1), ("random", 0)]
    assert [m["scenario"] for m in b] == ["random"]
    merged = compare.main(["--merge", str(tmp_path / "a"), str(tmp_path / "b"),
                           "--out", str(tmp_path / "m")])  # fmt: skip
    assert merged == a + b
    table = (tmp_path / "m" / "compare.md").read_text()
    assert "| expert | A0 | 1 |" in table and "| expert | random | 2 |" in table
    with pytest.raises(SystemExit):
        compare.main([*common, "--no-expert", "--out", str(tmp_path / "c")])
    twice = compare.main(
        [*common[:3], "--seeds", "0", "--scenarios", "A", "--paper-episodes", "2",
         "--out", str(tmp_path / "d")]
    )  # fmt: skip
    assert [(m["scenario"], m["init"]) for m in twice] == [("A", 0)] * 2 + [("A", 1)] * 2
    first, second = (m["uavs"]["uav_0"]["rms_u_px"] for m in twice[:2])
    assert first != second  # other noise draws
    assert "| expert | A0 | 2 |" in (tmp_path / "d" / "compare.md").read_text()
    with pytest.raises(SystemExit):
        compare.main([*common, "--paper-episodes", "0", "--out", str(tmp_path / "e")])
