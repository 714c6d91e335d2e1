"""baselines.report: docs/results pages from metrics.json + config.json (no simulation)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from baselines import report


def _uav(rms_u: float, rms_v: float, occlusion_ok: bool = True) -> dict:
    return {
        "rms_u_px": rms_u,
        "rms_v_px": rms_v,
        "occlusion_ok": occlusion_ok,
        "connectivity_ok": True,
        "collision_ok": True,
        "min_occlusion_angle_deg": 41.25,
        "max_blocked_fraction": 0.0 if occlusion_ok else 0.25,
    }


def _episode(scenario: str, init: int, rms_u: float, occlusion_ok: bool = True) -> dict:
    return {
        "scenario": scenario,
        "init": init,
        "seed": 0,
        "duration_s": 60.0,
        "dynamics": "lag",
        "uavs": {
            "uav_0": _uav(rms_u, 20.0, occlusion_ok),
            "uav_1": _uav(5.5, 6.25),
            "uav_2": _uav(10.5, 19.0),
        },
        "initial_conditions": {
            "uav_0": [0.0, 6.0, -1.57],
            "uav_1": [-6.0, 0.0, 0.0],
            "uav_2": [0.0, -6.0, 1.57],
        },
        "timing_ms": {"ukf": 1.25, "nmpc": 3.5, "qp": 1.0, "env": float("nan")},
    }


def _write(run_dir: Path, metrics: object, config: dict | None = None) -> None:
    run_dir.mkdir(parents=True)
    (run_dir / "metrics.json").write_text(json.dumps(metrics))
    if config is not None:
        (run_dir / "config.json").write_text(json.dumps(config))


def test_table6_page_has_rows_flags_paper_columns_and_stamp(tmp_path: Path) -> None:
    config = {
        "preset": "tuned",
        "command": ["python", "-m", "baselines.evaluate", "--all", "--out", "runs/t6"],
        "commit": "0123456789ab",
    }
    runs = [_episode("A", 0, 11.46), _episode("C", 1, 23.47, occlusion_ok=False)]
    _write(tmp_path / "table6-tuned", runs, config)
    (tmp_path / "notes.md").write_text("# Notes by hand\n\ntext\n")

    written = report.main(["--results", str(tmp_path)])

    assert tmp_path / "table6-tuned.md" in written
    page = (tmp_path / "table6-tuned.md").read_text()
    assert page.startswith("# table6-tuned\n")
    assert "preset `tuned`" in page and "dynamics lag" in page
    assert "| A0 | 1 | (0, 6, -1.57) | Y | Y | Y | 11.46 | 20.00 | 10.26 | 63.23 |" in page
    assert "| C1 | 1 | (0, 6, -1.57) | N | Y | Y | 23.47 | 20.00 | 34.69 | 110.17 |" in page
    assert "41.2 | 25 % |" in page
    assert "all Y: 5 of 6" in page
    assert "ukf 1.25, nmpc 3.50, qp 1.00" in page and "env" not in page.split("ms, range")[1]
    assert "Run: `python -m baselines.evaluate --all --out runs/t6`" in page
    assert "commit `0123456789ab`" in page

    index = (tmp_path / "README.md").read_text()
    row = "| [table6-tuned.md](table6-tuned.md) | table6-tuned | `table6-tuned/metrics.json` |"
    assert row in index
    assert "| [notes.md](notes.md) | Notes by hand | by hand |" in index


def test_single_episode_without_config_is_stamped_unknown(tmp_path: Path) -> None:
    episode = _episode("random", 0, 7.0)
    episode["seed"] = 1003
    _write(tmp_path / "r3", episode)

    report.generate(tmp_path)

    page = (tmp_path / "r3.md").read_text()
    assert "| random | 1 |" in page
    assert "paper U" not in page  # a random world has no paper row
    assert "seed 1003" in page and "preset `unknown`" in page
    assert "Run: `unknown`; commit `unknown`." in page


def test_config_key_of_metrics_stands_in_for_config_json(tmp_path: Path) -> None:
    episode = _episode("B", 0, 20.84)
    command = "python -m baselines.evaluate"
    episode["config"] = {"preset": "paper", "command": command, "commit": "c"}
    _write(tmp_path / "b0", episode)

    report.generate(tmp_path)

    page = (tmp_path / "b0.md").read_text()
    assert "preset `paper`" in page and "commit `c`" in page


def test_missing_directory_is_a_clear_error(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError, match="does not exist"):
        report.generate(missing)
    with pytest.raises(SystemExit, match=r"baselines.report: results directory .*nowhere"):
        report.main(["--results", str(missing)])


def test_metrics_without_episodes_is_a_clear_error(tmp_path: Path) -> None:
    _write(tmp_path / "bad", {"not": "an episode"})
    with pytest.raises(SystemExit, match="expected episode dicts"):
        report.main(["--results", str(tmp_path)])


def test_policy_comparison_uses_the_comparison_table(tmp_path: Path) -> None:
    runs = []
    for policy, rate in (("expert", 0.25), ("PPO", None)):
        episode = _episode("A", 0, 12.0)
        episode.update(
            policy=policy,
            violation_steps={"collision": 0, "disconnection": 0, "occlusion": 3},
            shield_intervention_rate=rate,
        )
        runs.append(episode)
    _write(tmp_path / "compare-paper", runs, {"preset": "tuned", "commit": "c"})

    report.generate(tmp_path)

    page = (tmp_path / "compare-paper.md").read_text()
    assert "| Policy | World | Episodes |" in page
    assert "| expert | A0 | 1 |" in page and "25.0 %" in page
    assert "| PPO | A0 | 1 |" in page
