"""Frame-stacked policies (``train.ppo --frame-stack K``): the ParallelEnv side stacks exactly as
SB3's VecFrameStack does in training, and a stacked run clones, trains and evaluates."""

from __future__ import annotations

import functools
import json

import gymnasium
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack

from baselines.compare import load_run
from tests.test_train_ppo import SMOKE
from train import bc, ppo
from train.frames import FrameHistory
from uavtrack_env import uavtrack_v0


class _Counter(gymnasium.Env):
    """Observation (t, 10 + t, -t) at step t of an episode of ``length`` steps."""

    observation_space = gymnasium.spaces.Box(-100, 100, (3,), np.float32)
    action_space = gymnasium.spaces.Box(-1, 1, (1,), np.float32)

    def __init__(self, length: int) -> None:
        self.length = length
        self.t = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.t, 10 + self.t, -self.t], np.float32)

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), 0.0, self.t >= self.length, False, {}


def test_frame_history_stacks_as_vecframestack_does_across_episodes():
    lengths = (5, 5)  # a ParallelEnv's agents start their episodes together
    vec = VecFrameStack(DummyVecEnv([functools.partial(_Counter, n) for n in lengths]), 3)
    raw = [_Counter(n) for n in lengths]
    history = FrameHistory(3)
    stacked = vec.reset()
    obs = {f"a{i}": env.reset()[0] for i, env in enumerate(raw)}
    for _ in range(12):
        mine = history(obs)
        np.testing.assert_array_equal(np.stack([mine["a0"], mine["a1"]]), stacked)
        stacked, _, dones, _ = vec.step(np.zeros((2, 1), np.float32))
        for i, env in enumerate(raw):
            obs[f"a{i}"] = env.step(None)[0]
        if all(dones):  # DummyVecEnv reset the worlds; a new episode starts afresh
            obs = {f"a{i}": env.reset()[0] for i, env in enumerate(raw)}
            history.reset()
        assert any(dones) == all(dones)
    history.reset()
    first = history({"a0": np.ones(3, np.float32)})["a0"]
    np.testing.assert_array_equal(first, [0, 0, 0, 0, 0, 0, 1, 1, 1])


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2"])
def test_frame_history_rejects_a_bad_count(bad):
    with pytest.raises(ValueError, match="frames must be an integer >= 1"):
        FrameHistory(bad)
    with pytest.raises(ValueError, match="frames must be an integer >= 1"):
        bc.collect(_small_world, episodes=1, seed=0, frames=bad)


def _small_world():
    return uavtrack_v0.parallel_env(scenario="random", max_cycles=30)


@pytest.mark.slow
def test_stacked_demonstrations_hold_each_agents_previous_observation():
    single, actions = bc.collect(_small_world, episodes=1, seed=3, progress=False)
    pairs, actions2 = bc.collect(_small_world, episodes=1, seed=3, progress=False, frames=2)
    width = single.shape[1]
    assert pairs.shape == (len(single), 2 * width)
    np.testing.assert_array_equal(actions, actions2)
    np.testing.assert_array_equal(pairs[:, width:], single)  # the newest frame last
    np.testing.assert_array_equal(pairs[:3, :width], 0.0)  # nothing before the first step
    np.testing.assert_array_equal(pairs[3:, :width], single[:-3])  # 3 agents per step


@pytest.mark.slow
def test_a_frame_stacked_run_clones_trains_and_evaluates(tmp_path):
    out = tmp_path / "run"
    flags = ["--frame-stack", "2", "--bc-episodes", "1", "--bc-epochs", "1"]
    flags += ["--dagger-rounds", "1", "--dagger-episodes", "1", "--value-warmup", "0"]
    ppo.main(["--shield", "--timesteps", "384", "--out", str(out), *flags, *SMOKE])
    model = PPO.load(out / "model.zip", device="cpu")
    width = _small_world().observation_space("uav_0").shape[0]
    assert model.observation_space.shape == (2 * width,)
    with np.load(out / "dagger.npz") as d:
        assert d["obs"].shape[1] == 2 * width
    assert json.loads((out / "args.json").read_text())["frame_stack"] == 2
    policy, _ = load_run(out)
    assert policy.history.frames == 2
    assert len(json.loads((out / "metrics.json").read_text())) == 3
    # a resumed run keeps its input; demonstrations of another width are refused
    ppo.main(["--resume", str(out), "--timesteps", "384", "--frame-stack", "1", *SMOKE])
    assert PPO.load(out / "model.zip", device="cpu").observation_space.shape == (2 * width,)
    with pytest.raises(ValueError, match="width 126, but the policy's input is 63"):
        ppo.main(
            ["--out", str(tmp_path / "other"), "--bc-episodes", "1", "--bc-demos",
             str(out / "demos.npz"), "--timesteps", "384", *SMOKE]
        )  # fmt: skip


def test_bad_frame_stack_argument(tmp_path):
    with pytest.raises(ValueError, match="--frame-stack must be >= 1"):
        ppo.parse_args(["--out", str(tmp_path), "--frame-stack", "0"])


class _Recorder:
    """A stand-in SB3 model: remembers the inputs it is asked to act on."""

    def __init__(self) -> None:
        self.batches: list[np.ndarray] = []

    def predict(self, batch, deterministic=True):
        self.batches.append(np.array(batch))
        return np.zeros((len(batch), 4), np.float32), None


def test_an_sb3_policy_stacks_its_inputs_and_forgets_them_between_episodes():
    from baselines.compare import SB3Policy

    model = _Recorder()
    policy = SB3Policy(model, None, frames=2)
    first, second = np.full(3, 1.0, np.float32), np.full(3, 2.0, np.float32)
    policy({"uav_0": first}, {})
    policy({"uav_0": second}, {})
    policy.reset()  # `runner.run_episode` calls it after the env's reset
    policy({"uav_0": second}, {})
    np.testing.assert_array_equal(model.batches[0], [[0, 0, 0, 1, 1, 1]])
    np.testing.assert_array_equal(model.batches[1], [[1, 1, 1, 2, 2, 2]])
    np.testing.assert_array_equal(model.batches[2], [[0, 0, 0, 2, 2, 2]])
