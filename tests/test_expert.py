"""The expert in closed loop and the evaluation CLI (short runs)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from baselines import evaluate
from tests.conftest import METRICS_UAV_KEYS
from uavtrack_env import uavtrack_v0
from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.presets import PRESETS


def test_evaluate_cli_writes_valid_metrics(tmp_path):
    out = tmp_path / "run"
    evaluate.main(["--scenario", "A", "--duration", "1.0", "--out", str(out), "--no-progress"])
    m = json.loads((out / "metrics.json").read_text())
    assert {"scenario", "init", "seed", "duration_s", "uavs", "timing_ms"} <= set(m)
    assert m["scenario"] == "A" and m["init"] == 0 and m["seed"] == 0
    cfg = m["config"]
    assert m["preset"] == cfg["preset"] == "tuned"  # the CLI's default preset
    assert cfg["expert"]["nmpc"]["safety_rows"] == 4
    assert cfg["expert"]["cbf"]["occlusion_model"] == "moving-target"
    assert cfg["expert"]["cbf"]["occlusion_point"] == "edges"
    assert cfg["expert"]["lag_aware"] is True and cfg["env"]["dynamics"]["model"] == "lag"
    assert cfg["command"].startswith("python -m ") and "--scenario A" in cfg["command"]
    assert cfg["commit"] and "casadi" in cfg["versions"]
    assert json.loads((out / "config.json").read_text()) == cfg
    assert m["real_time_factor"] > 0 and m["startup_s"] > 0
    assert m["duration_s"] == pytest.approx(1.0)
    assert set(m["uavs"]) == {"uav_0", "uav_1", "uav_2"}
    for r in m["uavs"].values():
        assert METRICS_UAV_KEYS <= set(r)
        assert all(math.isfinite(r[k]) for k in ("rms_u_px", "rms_v_px", "rms_depth_m"))
        assert r["collision_ok"] and r["connectivity_ok"]
        assert r["detected_fraction"] > 0.9
        assert 0.0 <= r["max_blocked_fraction"] <= 1.0
        assert r["occlusion_ok"] == (r["max_blocked_fraction"] == 0.0)
    assert {"ukf", "nmpc", "qp", "env"} <= set(m["timing_ms"])
    assert all(v > 0 for v in m["timing_ms"].values())
    assert (out / "table.md").read_text().count("| A0 |") == 3
    assert (out / "fig14_uav_distances.png").stat().st_size > 1000


def test_expert_never_reads_ground_truth():
    """The expert's actions do not change when info['truth'] is scrambled."""
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=40)
    obs, infos = env.reset(seed=3)
    a, b = ExpertPolicy.from_env(env), ExpertPolicy.from_env(env)
    while env.agents:
        act = a(obs, infos)
        scrambled = {k: {**v, "truth": None} for k, v in infos.items()}
        act_b = b(obs, scrambled)
        for agent in act:
            np.testing.assert_array_equal(act[agent], act_b[agent])
        obs, _, _, _, infos = env.step(act)


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["paper", "tuned"])
def test_expert_tracks_and_stays_safe_from_a_perturbed_start(preset: str):
    """Closed loop, 10 s of scenario A with the lag model: features converge, no violation."""
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=800, dynamics={"model": "lag"})
    obs, infos = env.reset(seed=1)
    expert = ExpertPolicy.from_env(env, preset)
    errors = []
    while env.agents:
        obs, _, term, _, infos = env.step(expert(obs, infos))
        assert not any(term.values())
        for info in infos.values():
            assert not any(info["violations"].values()), info["violations"]
        errors.append([infos[a]["truth"]["pixel_error"] for a in env.possible_agents])
    err = np.abs(np.array(errors))  # (T, 3, 2)
    start = err[0].max()
    assert start > 40.0  # the UAVs start low: a large V error to remove
    assert err[-80:].max() < 25.0  # last second: within 25 px in U and V
    env.close()


def test_evaluate_cli_builds_the_expert_from_preset_and_overrides():
    args = evaluate.parse_args(
        ["--preset", "paper", "--set", "cbf.gamma_o=0.5", "--set", "nmpc.horizon=20", "--jit"]
    )
    cfg = evaluate.expert_settings(args.preset, args.set, args.no_cbf, args.jit)
    assert cfg.cbf == dataclasses.replace(PRESETS["paper"].cbf, gamma_o=0.5)
    assert (cfg.cbf.occlusion_model, cfg.cbf.occlusion_point) == ("paper", "centre")
    assert cfg.nmpc.horizon == 20 and cfg.nmpc.jit and cfg.use_cbf
    assert not evaluate.expert_settings("tuned", [], True, False).use_cbf
    with pytest.raises(SystemExit):
        evaluate.parse_args(["--preset", "fastest"])


def test_lag_aware_expert_differences_messages_into_neighbour_velocities():
    """With lag_aware and the lag model, the shield gets second-order rows and each UAV's
    estimate of its neighbours' velocities, from consecutive messages, equals their velocity."""
    env = uavtrack_v0.parallel_env(scenario="A", max_cycles=20, dynamics={"model": "lag"})
    _, infos = env.reset(seed=2)
    expert = ExpertPolicy.from_env(env, "tuned")
    onboard = expert.onboard["uav_0"]
    assert onboard.filter.options.lag_tau == env.config.dynamics.tau
    rng = np.random.default_rng(0)
    for k in range(6):
        onboard.observe(infos["uav_0"])
        got = onboard.context().neighbour_velocities
        if k >= 2:  # the UAVs are moving and the previous messages are known
            for row, name in zip(got, infos["uav_0"]["neighbours"], strict=True):
                np.testing.assert_allclose(row, infos[name]["own"]["velocity"], atol=1e-9)
            assert np.abs(got).max() > 0.1
        actions = {a: rng.uniform(-1, 1, 4).astype(np.float32) for a in env.agents}
        infos = env.step(actions)[4]
    paper = ExpertPolicy.from_env(env, "paper")  # the paper's first-order rows
    assert paper.onboard["uav_0"].filter.options.lag_tau == 0.0
    env.close()


@pytest.mark.slow
@pytest.mark.parametrize(
    "rows, hidden",
    [
        ((), False),
        (("--set", "cbf.occlusion_model=paper", "--set", "cbf.occlusion_point=axis"), True),
    ],
    ids=["default-rows", "axis-rows-eq43"],
)
def test_default_occlusion_rows_keep_the_whole_car_visible_in_b0(tmp_path, rows, hidden):
    """Closed loop, B0's first 16 s: with evaluate's default rows (edges, moving target) no
    obstacle hides any of the car's 12 rays from any UAV; with eq. (43) on the boxes' axes a
    cube hides part of the car from UAV3 from 15.35 s (README, Table VI)."""
    out = tmp_path / "b0"
    argv = ["--scenario", "B", "--duration", "16", "--no-figures", "--no-progress"]
    evaluate.main([*argv, *rows, "--out", str(out)])
    uavs = json.loads((out / "metrics.json").read_text())["uavs"]
    blocked = {a: r["max_blocked_fraction"] for a, r in uavs.items()}
    assert all(r["collision_ok"] and r["connectivity_ok"] for r in uavs.values())
    if hidden:
        assert blocked["uav_2"] > 0.0, blocked
    else:
        assert max(blocked.values()) == 0.0, blocked
        assert all(r["occlusion_ok"] for r in uavs.values())


@pytest.mark.slow
def test_table_vi_rows_in_parallel_equal_the_rows_one_by_one(tmp_path):
    """``--all --workers 2`` (rows in spawned processes) writes the same metrics as
    ``--workers 1``, row for row, timings aside."""
    runs = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        argv = ["--all", "--duration", "0.5", "--no-figures", "--no-progress"]
        evaluate.main([*argv, "--out", str(out), "--workers", str(workers)])
        runs[workers] = json.loads((out / "metrics.json").read_text())
    assert [(m["scenario"], m["init"]) for m in runs[2]] == [(s, i) for s in "ABC" for i in (0, 1)]
    for a, b in zip(runs[1], runs[2], strict=True):
        assert a["uavs"] == b["uavs"]
        assert a["initial_conditions"] == b["initial_conditions"]


def test_workers_must_be_positive():
    with pytest.raises(SystemExit):
        evaluate.parse_args(["--all", "--workers", "0"])
