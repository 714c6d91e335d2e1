"""Shared-parameter PPO on the (optionally shielded) env with RLlib, locally or on a Ray cluster.

``python -m train.rllib_ppo --shield --iterations 20 --num-env-runners 2 --out runs/rllib``
trains one PPO policy (``"shared"``) for every UAV on RLlib's new API stack (RLModule, Learner,
EnvRunner, ConnectorV2). The env goes through ``ParallelPettingZooEnv`` (registered with
``ray.tune.registry.register_env``); ``--address ray://head:10001`` (Ray Client) or
``--address auto`` (on a cluster node) runs the same job on a cluster, otherwise a local Ray
instance with ``num_env_runners + num_learners + 1`` CPUs is started. See ``docs/rllib.md``.

The env's infos carry numpy arrays, nested dicts, ``None`` values and the ground truth (``truth``);
RLlib stores infos in every episode chunk it ships from the env runners to the driver, so by
default they are reduced to a flat dict of floats (``slim_info``) that the metrics callback reads.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from uavtrack_env.config import EnvConfig
from uavtrack_env.presets import (
    PRESETS,
    RL_PRESET,
    ExpertConfig,
    add_preset_arguments,
    expert_config_from,
)
from uavtrack_env.provenance import cli_command, config_record

from .world import TrainingWorld, add_world_arguments

ENV_NAME = "uavtrack_rllib"
"""Name under which ``make_rllib_env`` is registered with Ray Tune's registry."""
POLICY_ID = "shared"
"""The single policy (and RLModule) every agent maps to: shared parameters."""
VIOLATIONS = ("collision", "disconnection", "occlusion")


@dataclass(frozen=True)
class RLlibPPOConfig:
    """RLlib/PPO settings of this script (not from the paper: training hyper-parameters)."""

    shield: bool = True
    """Wrap the env in ``uavtrack_env.wrappers.CBFShield`` (the expert's CBF-QP (47))"""
    expert: ExpertConfig = field(default_factory=lambda: PRESETS[RL_PRESET])
    """The shield's settings (`uavtrack_env.presets`; the CLI's ``--preset`` and ``--set``)."""
    num_env_runners: int = 0
    """Remote EnvRunner actors; 0 samples in the driver process (no extra actor)."""
    num_envs_per_env_runner: int = 1
    """Env copies stepped in lock-step by each EnvRunner."""
    num_learners: int = 0
    """Remote Learner actors; 0 updates the network in the driver process."""
    torch_threads: int | None = 1
    """torch intra-op threads of the driver (which samples when ``num_env_runners == 0``): the
    forward pass on a batch of n_uavs rows is ~5x slower with 2 threads on a busy 2-core machine.
    Ray's actors already get ``OMP_NUM_THREADS = num_cpus``. None leaves torch's default."""
    train_batch_size: int = 4000
    """Env steps collected per training iteration (per Learner)."""
    minibatch_size: int = 512
    """SGD minibatch size."""
    num_epochs: int = 10
    """Passes over each train batch."""
    lr: float = 3.0e-4
    gamma: float = 0.99
    lambda_: float = 0.95
    """GAE lambda."""
    entropy_coeff: float = 0.0
    hidden: tuple[int, ...] = (128, 128)
    """Hidden layers of the shared MLP (policy and value function)."""
    seed: int = 0
    env_kwargs: Mapping[str, Any] = field(default_factory=lambda: TrainingWorld().env_kwargs())
    """Keyword arguments of ``uavtrack_env.parallel_env`` (fields of ``EnvConfig``); default:
    `train.world.TrainingWorld`, the world of `train.ppo`."""
    slim_infos: bool = True
    """Reduce infos to flat floats before RLlib sees them (see module docstring)."""
    normalize: bool = True
    """Running mean/std observation filter (RLlib's ``MeanStdFilter`` connector); the SB3 path
    uses ``VecNormalize`` for the same reason: observation entries range from 1e-2 to 1e2."""


# ---------------------------------------------------------------------- env path
def slim_info(info: Mapping[str, Any]) -> dict[str, float]:
    """The scalars of one agent's info that training needs: cost, violations, reward terms and
    the shield's report; arrays, ``None`` values and ``truth`` are dropped."""
    out: dict[str, float] = {"cost": float(info.get("cost", 0.0))}
    for name, hit in info.get("violations", {}).items():
        out[name] = float(bool(hit))
    for key in ("reward_tracking", "reward_effort"):
        if key in info:
            out[key] = float(info[key])
    shield = info.get("shield")
    if isinstance(shield, Mapping):
        out["shield_active"] = float(bool(shield.get("active", False)))
        out["shield_fallback"] = float(shield.get("status") == "fallback")
        for key in ("correction_norm", "slack"):
            value = shield.get(key)
            out[f"shield_{key}"] = _finite_float(value)
    return out


def _finite_float(value: Any) -> float:
    """A float for a scalar or array report (its norm); None or non-finite gives 0.0."""
    if value is None:
        return 0.0
    arr = np.asarray(value, dtype=float)
    x = float(np.linalg.norm(arr)) if arr.ndim else float(arr)
    return x if math.isfinite(x) else 0.0


class SlimInfos(BaseParallelWrapper):
    """ParallelEnv wrapper replacing each agent's info by ``slim_info(info)``."""

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs, infos = self.env.reset(seed=seed, options=options)
        return obs, {a: slim_info(i) for a, i in infos.items()}

    def step(self, actions: dict[str, Any]):
        obs, rew, term, trunc, infos = self.env.step(actions)
        return obs, rew, term, trunc, {a: slim_info(i) for a, i in infos.items()}


def make_parallel_env(env_config: Mapping[str, Any]) -> Any:
    """The PettingZoo ParallelEnv RLlib trains on: env, optional CBFShield, optional SlimInfos.

    ``env_config`` keys: ``shield`` (bool), ``expert`` (the shield's `ExpertConfig` or preset
    name; default 'tuned'), ``slim_infos`` (bool), ``env_kwargs`` (dict).
    """
    from uavtrack_env import parallel_env

    keys = {"shield", "expert", "slim_infos", "env_kwargs"}
    unknown = sorted(set(env_config) - keys)
    if unknown:
        raise ValueError(f"unknown env_config key(s) {unknown}; expected {sorted(keys)}")
    env = parallel_env(**dict(env_config.get("env_kwargs", {})))
    if env_config.get("shield", True):
        from uavtrack_env.wrappers.shield import CBFShield  # lazy: the shield is optional here

        env = CBFShield(env, env_config.get("expert"))
    if env_config.get("slim_infos", True):
        env = SlimInfos(env)
    return env


def make_rllib_env(env_config: Mapping[str, Any]) -> Any:
    """``ParallelPettingZooEnv`` around ``make_parallel_env``; agents in the env's order."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    par_env = make_parallel_env(env_config)
    env = ParallelPettingZooEnv(par_env)
    # RLlib's wrapper builds its agent list from a set; keep uav_0 ... uav_{n-1} order.
    env.agents = list(par_env.possible_agents)
    env.possible_agents = list(par_env.possible_agents)
    return env


def register() -> str:
    """Register ``make_rllib_env`` under ``ENV_NAME`` (idempotent) and return the name."""
    from ray.tune.registry import register_env

    register_env(ENV_NAME, make_rllib_env)
    return ENV_NAME


# ---------------------------------------------------------------------- metrics
def _on_episode_step(*, episode: Any, **_: Any) -> None:
    """Accumulate violations and shield interventions of the last env step."""
    data = episode.custom_data.setdefault("uavtrack", {"agent_steps": 0.0})
    for info in episode.get_infos(-1).values():
        if not info:
            continue
        if "violations" in info:  # raw env infos (slim_infos=False)
            info = slim_info(info)
        data["agent_steps"] += 1.0
        for key in (*VIOLATIONS, "shield_active", "shield_fallback", "shield_correction_norm"):
            if key in info:
                data[key] = data.get(key, 0.0) + float(info[key])


def _on_episode_end(*, episode: Any, metrics_logger: Any = None, **_: Any) -> None:
    """Log per-episode violation counts and the shield's intervention and fallback rates."""
    data = episode.custom_data.get("uavtrack")
    if metrics_logger is None or not data:
        return
    steps = max(data["agent_steps"], 1.0)
    agents = max(len(episode.agent_ids), 1)
    # per agent, as train.ppo's AgentVecMonitor reports it: the two trainers' returns compare
    metrics_logger.log_value(
        "uavtrack_agent_return_mean", episode.get_return() / agents, reduce="mean"
    )
    for key in VIOLATIONS:
        metrics_logger.log_value(f"uavtrack_{key}_agent_steps", data.get(key, 0.0), reduce="mean")
    if "shield_active" in data:
        metrics_logger.log_value(
            "uavtrack_shield_intervention_rate", data["shield_active"] / steps, reduce="mean"
        )
        metrics_logger.log_value(
            "uavtrack_shield_fallback_rate", data["shield_fallback"] / steps, reduce="mean"
        )
        metrics_logger.log_value(
            "uavtrack_shield_mean_correction",
            data["shield_correction_norm"] / steps,
            reduce="mean",
        )


# ---------------------------------------------------------------------- algorithm
def build_config(cfg: RLlibPPOConfig) -> Any:
    """RLlib ``PPOConfig`` (new API stack): one RLModule shared by all agents."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    if cfg.num_env_runners < 0 or cfg.num_learners < 0 or cfg.num_envs_per_env_runner < 1:
        raise ValueError(
            "num_env_runners and num_learners must be >= 0 and num_envs_per_env_runner >= 1, "
            f"got {cfg.num_env_runners}, {cfg.num_learners} and {cfg.num_envs_per_env_runner}"
        )
    if cfg.torch_threads is not None and cfg.torch_threads < 1:
        raise ValueError(f"torch_threads must be >= 1 or None, got {cfg.torch_threads}")
    if min(cfg.train_batch_size, cfg.minibatch_size, cfg.num_epochs) < 1:
        raise ValueError("train_batch_size, minibatch_size and num_epochs must be >= 1")
    env_config = {
        "shield": cfg.shield,
        "expert": cfg.expert,
        "slim_infos": cfg.slim_infos,
        "env_kwargs": dict(cfg.env_kwargs),
    }
    model = DefaultModelConfig(fcnet_hiddens=list(cfg.hidden), vf_share_layers=False)
    config = (
        PPOConfig()
        .environment(register(), env_config=env_config)
        .framework("torch")
        .env_runners(
            num_env_runners=cfg.num_env_runners,
            num_envs_per_env_runner=cfg.num_envs_per_env_runner,
            rollout_fragment_length="auto",
            env_to_module_connector=_obs_filter if cfg.normalize else None,
        )
        .learners(num_learners=cfg.num_learners)
        .multi_agent(policies={POLICY_ID}, policy_mapping_fn=_shared_policy)
        .rl_module(
            rl_module_spec=MultiRLModuleSpec(
                rl_module_specs={POLICY_ID: RLModuleSpec(model_config=model)}
            )
        )
        .training(
            train_batch_size_per_learner=cfg.train_batch_size,
            minibatch_size=cfg.minibatch_size,
            num_epochs=cfg.num_epochs,
            lr=cfg.lr,
            gamma=cfg.gamma,
            lambda_=cfg.lambda_,
            entropy_coeff=cfg.entropy_coeff,
        )
        .callbacks(on_episode_step=_on_episode_step, on_episode_end=_on_episode_end)
        .debugging(seed=cfg.seed)
    )
    return config


def _obs_filter(env: Any, spaces: Any = None, device: Any = None) -> Any:
    """Env-to-module connector piece: per-agent running mean/std of the observations."""
    from ray.rllib.connectors.env_to_module import MeanStdFilter

    return MeanStdFilter(multi_agent=True)


def _shared_policy(agent_id: str, episode: Any = None, **_: Any) -> str:
    """Every agent maps to the one shared policy (parameter sharing)."""
    return POLICY_ID


def init_ray(address: str | None, num_cpus: int, working_dir: str | None = None) -> None:
    """Connect to a cluster (``ray://host:10001`` or ``auto``) or start a small local Ray."""
    import ray

    if ray.is_initialized():
        return
    runtime_env = {"working_dir": working_dir} if working_dir else None
    if address:
        ray.init(address=address, runtime_env=runtime_env)
    else:
        ray.init(
            num_cpus=num_cpus,
            include_dashboard=False,
            runtime_env=runtime_env,
            log_to_driver=False,
        )


def summarize(result: Mapping[str, Any]) -> dict[str, float]:
    """The few numbers of an RLlib result dict worth printing (missing ones are NaN)."""
    runners = result.get("env_runners", {})
    out = {
        "iteration": float(result.get("training_iteration", math.nan)),
        "env_steps": float(result.get("num_env_steps_sampled_lifetime", math.nan)),
        "episode_return_mean": float(runners.get("episode_return_mean", math.nan)),
        "episode_len_mean": float(runners.get("episode_len_mean", math.nan)),
    }
    for key, value in runners.items():
        if key.startswith("uavtrack_"):
            out[key[len("uavtrack_") :]] = float(value)
    return out


def train(
    cfg: RLlibPPOConfig,
    iterations: int,
    out: str | Path,
    log: Callable[[str], None] = print,
    preset: str | None = None,
    overrides: Sequence[str] = (),
    command: str | None = None,
    video_every: int = 0,
    video_seconds: float = 10.0,
) -> tuple[Path, list[dict[str, float]]]:
    """Run ``iterations`` PPO iterations (Ray must be initialised), save a checkpoint in ``out``.

    ``preset`` and ``overrides`` (its ``--set``) name ``cfg.expert`` in ``config.json``, from which
    ``baselines.compare`` rebuilds the run's shield. Returns the checkpoint directory and one
    summary per iteration (also in ``progress.jsonl``).
    Every ``video_every`` iterations (0: never), a video of the policy so far in ``out/videos``
    (`train.video.record_policy`, from a checkpoint in ``out/video-checkpoint``).
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    import torch

    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    threads = torch.get_num_threads()
    if cfg.torch_threads is not None:
        torch.set_num_threads(cfg.torch_threads)
    history: list[dict[str, float]] = []
    algo = None
    try:
        algo = build_config(cfg).build_algo()
        with open(out / "progress.jsonl", "a") as fh:
            for _ in range(iterations):
                t0 = time.perf_counter()
                summary = summarize(algo.train())
                summary["seconds"] = time.perf_counter() - t0
                history.append(summary)
                fh.write(json.dumps(summary) + "\n")
                fh.flush()
                log(" ".join(f"{k}={v:.4g}" for k, v in summary.items()))
                if video_every > 0 and len(history) % video_every == 0:
                    log(f"video: {_video(algo, cfg, out, len(history), video_seconds)}")
        checkpoint = Path(algo.save_to_path(str(out / "checkpoint")))
    finally:
        if algo is not None:
            algo.stop()
        torch.set_num_threads(threads)  # restore: the caller's process keeps its setting
    settings = {**asdict(cfg), "hidden": list(cfg.hidden), "env_kwargs": dict(cfg.env_kwargs)}
    del settings["expert"]
    record = config_record(
        preset,
        EnvConfig.from_kwargs(**dict(cfg.env_kwargs)),
        cfg.expert,
        command,
        iterations=iterations,
        set=list(overrides),
        rllib=settings,
    )
    (out / "config.json").write_text(json.dumps(record, indent=2))
    return checkpoint, history


def _video(algo: Any, cfg: RLlibPPOConfig, out: Path, iteration: int, seconds: float) -> Path:
    """A video of the algorithm's current policy (`RLlibPolicy` of a fresh checkpoint)."""
    from .video import record_policy

    checkpoint = Path(algo.save_to_path(str(out / "video-checkpoint")))
    dynamics = dict(cfg.env_kwargs).get("dynamics", {}).get("model", "integrator")
    return record_policy(
        RLlibPolicy(checkpoint),
        out / "videos",
        f"iteration-{iteration}",
        shield=cfg.expert if cfg.shield else None,
        dynamics=dynamics,
        seconds=seconds,
    )


def load_policy(checkpoint: str | Path) -> Any:
    """The shared RLModule (torch) from a checkpoint written by ``train`` (any path)."""
    from ray.rllib.core.rl_module.rl_module import RLModule

    # absolute: RLlib reads the path as a URI, and a relative one has no scheme
    path = Path(checkpoint).resolve() / "learner_group" / "learner" / "rl_module" / POLICY_ID
    if not path.is_dir():
        raise ValueError(f"{checkpoint} is not a checkpoint of train.rllib_ppo (no {path})")
    return RLModule.from_checkpoint(str(path))


class RLlibPolicy:
    """A ``train.rllib_ppo`` checkpoint as ``policy(obs, infos) -> {agent: action}``: each
    agent's observation through its saved ``MeanStdFilter`` statistics (if the run normalised),
    then the shared module's mean action (deterministic), clipped to [-1, 1]."""

    def __init__(self, checkpoint: str | Path) -> None:
        self.module = load_policy(checkpoint)
        self.filters = _saved_filters(Path(checkpoint).resolve())

    def __call__(self, obs: Mapping[str, np.ndarray], infos: Any) -> dict[str, np.ndarray]:
        import torch

        agents = list(obs)
        if not agents:
            return {}
        rows = []
        for a in agents:
            x = np.asarray(obs[a], np.float32)
            if a in self.filters:
                x = self.filters[a](x, update=False)
            rows.append(np.asarray(x, np.float32))
        with torch.no_grad():
            out = self.module.forward_inference({"obs": torch.as_tensor(np.stack(rows))})
        mean = out["action_dist_inputs"][:, :4].numpy()
        actions = np.clip(mean, -1.0, 1.0).astype(np.float32)
        return dict(zip(agents, actions, strict=True))


def _saved_filters(checkpoint: Path) -> dict[str, Any]:
    """The per-agent observation filters of a checkpoint (empty if the run did not normalise)."""
    import pickle

    from ray.rllib.utils.filter import MeanStdFilter, RunningStat

    path = checkpoint / "env_runner" / "env_to_module_connector" / "MeanStdFilter" / "state.pkl"
    if not path.exists():
        return {}
    with path.open("rb") as fh:
        state = pickle.load(fh)
    filters = {}
    for agent, s in state.items():
        f = MeanStdFilter(tuple(s["shape"]), demean=s["de_mean_to_zero"], destd=s["de_std_to_one"])
        f.clip = s["clip_by_value"]
        (stats,) = s["running_stats"]  # one flat Box observation
        f.running_stats = RunningStat.from_state(stats)
        filters[agent] = f
    return filters


def load_run(run_dir: str | Path) -> tuple[RLlibPolicy, dict]:
    """The policy of a ``train.rllib_ppo`` output directory and its config.json."""
    run_dir = Path(run_dir)
    if not (run_dir / "checkpoint").is_dir() or not (run_dir / "config.json").is_file():
        raise ValueError(
            f"{run_dir} is not an output directory of train.rllib_ppo "
            "(expected checkpoint/ and config.json)"
        )
    record = json.loads((run_dir / "config.json").read_text())
    return RLlibPolicy(run_dir / "checkpoint"), record


# ---------------------------------------------------------------------- CLI
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m train.rllib_ppo", description=__doc__.split("\n")[0]
    )
    p.add_argument("--shield", action=argparse.BooleanOptionalAction, default=True)
    add_preset_arguments(p, RL_PRESET)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--num-env-runners", type=int, default=0)
    p.add_argument("--num-envs-per-env-runner", type=int, default=1)
    p.add_argument("--num-learners", type=int, default=0, help="remote Learner actors")
    p.add_argument("--torch-threads", type=int, default=1, help="torch threads of the driver")
    p.add_argument("--out", required=True, help="directory for the checkpoint and progress.jsonl")
    p.add_argument("--address", default=None, help="ray://host:10001 or auto; default: local Ray")
    p.add_argument(
        "--working-dir",
        default=None,
        help="ship this directory to the cluster (runtime_env working_dir) if the package is "
        "not installed on its nodes",
    )
    p.add_argument("--train-batch-size", type=int, default=4000)
    p.add_argument("--minibatch-size", type=int, default=512)
    p.add_argument("--num-epochs", type=int, default=10)
    p.add_argument("--lr", type=float, default=3.0e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--normalize",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="running mean/std observation filter",
    )
    p.add_argument("--hidden", default="128,128", help="hidden layer sizes of the shared MLP")
    p.add_argument(
        "--video-every",
        type=int,
        default=0,
        help="iterations between videos of the policy in OUT/videos (0: none; the video extra)",
    )
    p.add_argument("--video-seconds", type=float, default=10.0, help="length of each video (s)")
    add_world_arguments(p)
    args = p.parse_args(argv)
    if args.video_every < 0 or not args.video_seconds > 0:
        p.error("--video-every must be >= 0 and --video-seconds > 0")
    return args


def _parse_hidden(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(x) for x in text.split(","))
    except ValueError:
        sizes = ()
    if not sizes or min(sizes) < 1:
        raise ValueError(f"--hidden takes positive layer sizes like '128,128', got {text!r}")
    return sizes


def main(argv: Sequence[str] | None = None) -> Path:
    import ray

    args = parse_args(argv)
    cfg = RLlibPPOConfig(
        shield=args.shield,
        expert=expert_config_from(args.preset, args.set),
        num_env_runners=args.num_env_runners,
        num_envs_per_env_runner=args.num_envs_per_env_runner,
        num_learners=args.num_learners,
        torch_threads=args.torch_threads,
        train_batch_size=args.train_batch_size,
        minibatch_size=args.minibatch_size,
        num_epochs=args.num_epochs,
        lr=args.lr,
        seed=args.seed,
        hidden=_parse_hidden(args.hidden),
        normalize=args.normalize,
        env_kwargs=TrainingWorld.from_fields(args).env_kwargs(),
    )
    cpus = args.num_env_runners + args.num_learners + 1
    init_ray(args.address, num_cpus=cpus, working_dir=args.working_dir)
    try:
        command = cli_command("train.rllib_ppo", None if argv is None else list(argv))
        checkpoint, _ = train(
            cfg,
            args.iterations,
            args.out,
            preset=args.preset,
            overrides=args.set,
            command=command,
            video_every=args.video_every,
            video_seconds=args.video_seconds,
        )
    finally:
        ray.shutdown()
    print(f"checkpoint: {checkpoint}")
    return checkpoint


if __name__ == "__main__":
    main()
