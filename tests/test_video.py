"""RecordVideo: MP4s of a ParallelEnv's episodes; ``baselines.evaluate --video``."""

from __future__ import annotations

import numpy as np
import pytest

from uavtrack_env.wrappers import CBFShield, RecordVideo

imageio = pytest.importorskip("imageio.v2")
pytest.importorskip("imageio_ffmpeg")


def _frames(path) -> tuple[int, dict]:
    reader = imageio.get_reader(path)
    meta = reader.get_meta_data()
    count = sum(1 for _ in reader)
    reader.close()
    return count, meta


def _episode(env, seed: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed)
    seen = [obs["uav_0"]]
    while env.agents:
        obs, *_ = env.step({a: np.full(4, 0.1, np.float32) for a in env.agents})
        if "uav_0" in obs:
            seen.append(obs["uav_0"])
    return seen


def test_chosen_episodes_are_written_with_one_frame_per_k_steps(tmp_path, make_env):
    raw = make_env(scenario="random", max_cycles=24, render_mode="rgb_array")
    env = RecordVideo(raw, tmp_path, episode_trigger=lambda k: k != 1, frame_every=4)
    for seed in range(3):
        _episode(env, seed)
    env.close()
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["uavtrack-episode-0.mp4", "uavtrack-episode-2.mp4"]
    count, meta = _frames(tmp_path / names[0])
    assert count == 1 + 24 // 4  # the reset frame, then every 4th step
    assert meta["fps"] == pytest.approx(20.0) and meta["size"] == (672, 480)


def test_recording_changes_nothing_in_the_rollout(tmp_path, make_env):
    kw = {"scenario": "random", "max_cycles": 12, "render_mode": "rgb_array"}
    plain = _episode(make_env(**kw), seed=5)
    recorded = _episode(RecordVideo(make_env(**kw), tmp_path / "a"), seed=5)
    assert len(plain) == len(recorded) == 13
    np.testing.assert_array_equal(np.stack(recorded), np.stack(plain))
    shielded = _episode(CBFShield(make_env(**kw)), seed=5)
    recorded = _episode(RecordVideo(CBFShield(make_env(**kw)), tmp_path / "b"), seed=5)
    np.testing.assert_array_equal(np.stack(recorded), np.stack(shielded))


def test_bad_arguments_raise(tmp_path, make_env):
    with pytest.raises(ValueError, match="render_mode='rgb_array'"):
        RecordVideo(make_env(), tmp_path)
    with pytest.raises(ValueError, match="frame_every"):
        RecordVideo(make_env(render_mode="rgb_array"), tmp_path, frame_every=0)


def test_evaluate_writes_the_episode_video(tmp_path):
    from baselines import evaluate

    evaluate.main(["--scenario", "A", "--duration", "0.2", "--no-figures", "--video",
                   "--no-progress", "--out", str(tmp_path)])  # fmt: skip
    count, _ = _frames(tmp_path / "video-episode-0.mp4")
    assert count == 1 + 16 // 4
    assert (tmp_path / "metrics.json").exists()
