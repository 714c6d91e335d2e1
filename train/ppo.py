"""Shared-parameter PPO (Stable-Baselines3, torch, CPU) on random worlds: shielded, unshielded
or PPO-Lagrangian.

    python -m train.ppo --shield --timesteps 200000 --seed 0 --out runs/ppo-shield
    python -m train.ppo --no-shield --timesteps 200000 --seed 0 --out runs/ppo
    python -m train.ppo --no-shield --lagrangian --cost-limit 25 --out runs/ppo-lag
    python -m train.ppo --timesteps 100000 --resume runs/ppo-shield     # 100k more steps

One policy drives every UAV: each agent of each world is one row of an SB3 VecEnv
(`uavtrack_env.wrappers.sb3`: `VectorSharedPolicyVecEnv`, all ``--n-envs`` worlds in one batched
step); with ``--shield`` every action passes the CBF-QP of ``--preset`` (default ``rl``: the
expert's rows with the team-mates as occluders too) in training (`VectorCBFShield`) and in
evaluation (`CBFShield`); with
``--lagrangian`` the cost is penalised by an adapted multiplier (`train.lagrangian`). Writes
into DIR: ``tb/``
(TensorBoard: ``rollout/ep_cost_mean``, ``safety/*_rate``, ``lagrangian/lambda``),
``checkpoints/`` (every ``--checkpoint-freq`` agent-steps, with the VecNormalize statistics),
``model.zip`` + ``vecnormalize.pkl`` (final), ``args.json`` (every call's steps, time and
violation counts under ``calls``), ``violations.jsonl`` (every violating agent-step: when, which
world and UAV, which violations; `train.callbacks.TrainingLog`) and, with ``--evaluate``,
``metrics.json`` (evaluation episodes in the schema of ``baselines/evaluate.py``; a resumed run
appends). The console shows a learning-curve line every ``--log-every`` agent-steps. Step counts
are agent-steps (SB3's ``num_timesteps``: rows x vector steps); ``--timesteps`` stops at the
first vector step that reaches it. A UAV whose episode ended keeps its row in the absorbing
state until its world resets: those rows count towards ``--timesteps`` but not towards
``training_violations``' ``agent_steps``, which counts the steps of UAVs still flying.

The world (`train.world.TrainingWorld`, shared with `train.rllib_ppo`): seeded random worlds, UAVs
started up to ``--start-offset`` m off formation, and the env's RL defaults: r = exp(-c) (c the
stage cost of eq. 18 on the bounding box's centre) minus a collision penalty, so that ending an
episode by crashing never pays, and a collision ends that UAV's episode only.

Warm start from the expert (``--bc-episodes N``): N expert episodes are recorded (in
``--bc-workers`` processes; cached in ``--bc-demos``), the actor is fitted to them (checkpoint
0), the critic alone trains for ``--value-warmup`` steps, then PPO fine-tunes, optionally with
``--bc-anchor`` cloning steps after every update. ``--dagger-rounds R`` refines the clone first:
in each round the cloned actor acts (through the shield with ``--shield``) on
``--dagger-episodes`` training worlds, the expert labels every state it visits, and the actor is
fitted again on all labels (kept in DIR/dagger.npz; the anchor then uses them all).
``--frame-stack K`` feeds the policy the last K observations (`train.frames`): one image shows
where the car is, two show how it moves. ``--linear-skip`` adds a linear map of the observation
to the actor's MLP output (`train.sb3_ppo.LinearSkipPolicy`). With
``--shield``, ``--intervention-penalty K`` charges K per m/s of the shield's correction
(`train.intervention`). The recipe of docs/results/rl-training.md: DAgger labels once, from a
run with ``--dagger-rounds 2 --dagger-episodes 60 --min-obstacles 24 --max-obstacles 48
--corridor 1.5`` (its DIR/dagger.npz), then each member on the default random worlds:

    python -m train.ppo --shield --frame-stack 2 --linear-skip --freeze-obs-stats \
        --bc-episodes 200 --bc-demos runs/labels/dagger.npz --bc-anchor 0 \
        --learning-rate 5e-5 --log-std-init -2 --target-kl 0.05 --image-weight 30 \
        --timesteps 3000000 --seed 1300 --out runs/ppo-shield
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from baselines.compare import SB3Policy, eval_worlds, make_eval_env, run_policy_episode
from baselines.evaluate import table
from uavtrack_env.config import DT
from uavtrack_env.presets import (
    RL_PRESET,
    ExpertConfig,
    add_preset_arguments,
    expert_config_from,
)
from uavtrack_env.provenance import cli_command, config_record

from .bc import SCHEDULES as BC_SCHEDULES
from .intervention import checked_coef
from .lagrangian import LagrangianConfig
from .world import WORLD_FIELDS, TrainingWorld

ENV_FIELDS = (
    "shield",
    "n_envs",
    "preset",
    "set",
    "lagrangian",
    "cost_limit",
    "lambda_lr",
    "intervention_penalty",
    "frame_stack",
    *WORLD_FIELDS,
)
"""Arguments that define the training env and the policy's input; ``--resume`` takes them from
the run's args.json."""
OLDER_RUNS = {"image_point": "center", "preset": "tuned"}
"""What a run whose args.json predates an env-defining field trained with, where that is not
the field's default (``--resume`` keeps it)."""
_WORLD_HELP = {f.name: f.metadata for f in dataclasses.fields(TrainingWorld)}
BC_STATS = ("bc_samples", "bc_val_loss_first_epoch", "bc_val_loss")
"""What `train.bc.pretrain` reports (kept in args.json across ``--resume``)."""
BC_SEED = 50_000
"""Demonstration worlds are seeded BC_SEED + seed + episode, apart from the evaluation seeds."""
DAGGER_SEED = 60_000
"""DAgger round r's worlds are seeded DAGGER_SEED + seed + r * dagger_episodes + episode."""
VIOLATIONS_FILE = "violations.jsonl"
"""DIR's log of every violating training agent-step (a resumed run appends)."""


@dataclass
class Args:
    """Command-line arguments (``--name-with-dashes``); each field's help is its metadata."""

    shield: bool = field(default=True, metadata={"help": "pass every action through CBFShield"})
    preset: str = field(
        default=RL_PRESET, metadata={"help": "the shield's and the expert's ExpertConfig"}
    )
    set: tuple[str, ...] = field(
        default=(), metadata={"help": "FIELD=VALUE overrides of the preset (repeatable)"}
    )
    timesteps: int = field(default=200_000, metadata={"help": "agent-steps to train (this call)"})
    seed: int = field(
        default=0,
        metadata={
            "help": "seed of torch, numpy and the worlds; world k starts from seed + k (SB3's "
            "convention), so runs meant to be independent need seeds at least --n-envs apart"
        },
    )
    out: Path | None = field(default=None, metadata={"help": "output dir (default: --resume)"})
    resume: Path | None = field(
        default=None, metadata={"help": "continue the run in DIR from its last checkpoint"}
    )
    n_envs: int = field(
        default=16, metadata={"help": "worlds in one batched step (rows = worlds x n_uavs)"}
    )
    n_uavs: int = field(default=TrainingWorld.n_uavs, metadata=_WORLD_HELP["n_uavs"])
    max_cycles: int = field(default=TrainingWorld.max_cycles, metadata=_WORLD_HELP["max_cycles"])
    terminate_on_collision: str = field(
        default=TrainingWorld.terminate_on_collision,
        metadata=_WORLD_HELP["terminate_on_collision"],
    )
    dynamics: str = field(default=TrainingWorld.dynamics, metadata=_WORLD_HELP["dynamics"])
    reward_shape: str = field(
        default=TrainingWorld.reward_shape, metadata=_WORLD_HELP["reward_shape"]
    )
    collision_penalty: float = field(
        default=TrainingWorld.collision_penalty, metadata=_WORLD_HELP["collision_penalty"]
    )
    image_weight: float = field(
        default=TrainingWorld.image_weight, metadata=_WORLD_HELP["image_weight"]
    )
    image_point: str = field(default=TrainingWorld.image_point, metadata=_WORLD_HELP["image_point"])
    n_steps: int = field(default=256, metadata={"help": "PPO rollout length per row"})
    batch_size: int = field(default=512, metadata={"help": "PPO minibatch size"})
    n_epochs: int = field(default=10, metadata={"help": "PPO epochs per rollout"})
    learning_rate: float = field(default=3e-4, metadata={"help": "Adam learning rate"})
    gamma: float = field(default=0.99, metadata={"help": "discount"})
    gae_lambda: float = field(default=0.95, metadata={"help": "GAE lambda"})
    clip_range: float = field(default=0.2, metadata={"help": "PPO clip range"})
    ent_coef: float = field(default=0.0, metadata={"help": "entropy bonus"})
    net_arch: str = field(default="128,128", metadata={"help": "hidden sizes of pi and vf"})
    linear_skip: bool = field(
        default=False,
        metadata={
            "help": "the actor's mean adds a linear map of the observation to its MLP's output "
            "(train.sb3_ppo.LinearSkipPolicy)"
        },
    )
    frame_stack: int = field(
        default=1,
        metadata={
            "help": "observations per policy input, oldest first (2: the car's motion in the "
            "image; SB3 VecFrameStack, train.frames)"
        },
    )
    log_std_init: float = field(
        default=-2.0,
        metadata={"help": "initial log std of the Gaussian policy (-2: 0.14, i.e. 1.4 m/s)"},
    )
    normalize: bool = field(
        default=True, metadata={"help": "VecNormalize observations and rewards"}
    )
    learn_certified: bool = field(
        default=False,
        metadata={
            "help": "--shield: PPO learns from the shield's certified actions, which the world "
            "executes, in place of the proposed ones (train.callbacks.CertifiedActions)"
        },
    )
    freeze_obs_stats: bool = field(
        default=False,
        metadata={
            "help": "keep VecNormalize's observation statistics fixed during PPO (after "
            "cloning: the demonstrations', on which the actor was fitted; train.bc)"
        },
    )
    bc_episodes: int = field(
        default=0,
        metadata={"help": "expert episodes for a behaviour-cloning warm start (0: from scratch)"},
    )
    bc_epochs: int = field(default=30, metadata={"help": "behaviour-cloning epochs"})
    bc_schedule: str = field(
        default="constant",
        metadata={
            "help": "behaviour-cloning learning rate: 'constant', or 'cosine' (annealed to 0 "
            "over the epochs: a lower held-out cloning loss, no closer tracking measured; "
            "docs/results/rl-training.md)"
        },
    )
    bc_workers: int = field(
        default=1,
        metadata={"help": "processes recording the expert episodes (the same demos for any)"},
    )
    bc_demos: Path | None = field(
        default=None,
        metadata={"help": "demonstrations .npz to reuse if it exists, else written there"},
    )
    dagger_rounds: int = field(
        default=0,
        metadata={
            "help": "DAgger rounds after cloning: the cloned actor acts (shielded with --shield), "
            "the expert labels its states, the actor is fitted again on all labels"
        },
    )
    dagger_episodes: int = field(
        default=60, metadata={"help": "training-world episodes per DAgger round"}
    )
    bc_anchor: int = field(
        default=0,
        metadata={"help": "cloning-loss minibatch steps after every PPO update (0: off)"},
    )
    start_offset: float = field(
        default=TrainingWorld.start_offset, metadata=_WORLD_HELP["start_offset"]
    )
    start_heading_offset: float = field(
        default=TrainingWorld.start_heading_offset, metadata=_WORLD_HELP["start_heading_offset"]
    )
    min_obstacles: int = field(
        default=TrainingWorld.min_obstacles, metadata=_WORLD_HELP["min_obstacles"]
    )
    max_obstacles: int = field(
        default=TrainingWorld.max_obstacles, metadata=_WORLD_HELP["max_obstacles"]
    )
    corridor: float = field(default=TrainingWorld.corridor, metadata=_WORLD_HELP["corridor"])
    value_warmup: int = field(
        default=100_000,
        metadata={"help": "agent-steps training only the critic after cloning (actor frozen)"},
    )
    target_kl: float = field(
        default=0.0, metadata={"help": "stop a PPO update's epochs beyond this KL (0: off)"}
    )
    checkpoint_freq: int = field(default=50_000, metadata={"help": "agent-steps between saves"})
    eval_scenarios: str = field(
        default="A", metadata={"help": "paper scenarios to evaluate on, e.g. 'A' or 'ABC'"}
    )
    eval_seeds: int = field(default=3, metadata={"help": "seeded random worlds to evaluate on"})
    eval_duration: float = field(default=60.0, metadata={"help": "evaluation episode length (s)"})
    lagrangian: bool = field(
        default=False,
        metadata={"help": "PPO-Lagrangian: penalise the cost with an adapted multiplier"},
    )
    cost_limit: float = field(
        default=LagrangianConfig.cost_limit,
        metadata={"help": "--lagrangian: episode cost per agent allowed (violating steps)"},
    )
    lambda_lr: float = field(
        default=LagrangianConfig.lambda_lr,
        metadata={"help": "--lagrangian: the multiplier's step size per rollout"},
    )
    intervention_penalty: float = field(
        default=0.0,
        metadata={
            "help": "--shield: reward subtracted per m/s of the shield's correction "
            "(train.intervention)"
        },
    )
    evaluate: bool = field(
        default=False,
        metadata={"help": "after training, evaluate on --eval-scenarios/--eval-seeds"},
    )
    log_every: int = field(
        default=10_000, metadata={"help": "agent-steps between learning-curve lines"}
    )
    video_every: int = field(
        default=0,
        metadata={"help": "agent-steps between videos of the policy in DIR/videos (0: none)"},
    )
    video_seconds: float = field(default=10.0, metadata={"help": "length of each video (s)"})
    threads: int = field(default=1, metadata={"help": "torch CPU threads"})
    progress: bool = field(default=True, metadata={"help": "show a progress bar"})


def parse_args(argv: list[str] | None = None) -> Args:
    """argparse from the `Args` dataclass; booleans get ``--x/--no-x``."""
    ap = argparse.ArgumentParser(
        prog="python -m train.ppo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_preset_arguments(ap, RL_PRESET)
    for f in dataclasses.fields(Args):
        if f.name in ("preset", "set"):
            continue
        flag = "--" + f.name.replace("_", "-")
        help_ = f"{f.metadata['help']} (default: {f.default})"
        if f.type in (bool, "bool"):
            ap.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_)
        else:
            kind = {"int": int, "float": float, "str": str}.get(str(f.type), Path)
            ap.add_argument(flag, type=kind, default=None, help=help_)
    ns = ap.parse_args(argv)
    given = {k: v for k, v in vars(ns).items() if v is not None}
    given["set"] = tuple(given.get("set", ()))
    return make_args(**given)


def make_args(**given: Any) -> Args:
    """`Args` with checks; with ``resume``, the env-defining fields come from its args.json."""
    if given.get("resume") is not None:
        saved = json.loads((Path(given["resume"]) / "args.json").read_text())
        for k in ENV_FIELDS:
            if k in saved:
                given[k] = saved[k]
            elif k in OLDER_RUNS:
                given[k] = OLDER_RUNS[k]
        given.setdefault("out", Path(given["resume"]))
    args = Args(**given)
    if args.out is None:
        raise ValueError("--out DIR is required (or --resume DIR)")
    args.out = Path(args.out)
    positive = (
        "timesteps", "n_envs", "n_uavs", "max_cycles", "n_steps", "batch_size", "log_every",
        "bc_workers", "frame_stack",
    )  # fmt: skip
    for name in positive:
        if int(getattr(args, name)) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
    if args.bc_anchor > 0 and args.bc_episodes < 1:
        raise ValueError("--bc-anchor needs demonstrations: set --bc-episodes")
    if args.learn_certified and not args.shield:
        raise ValueError("--learn-certified needs the shield's actions: set --shield")
    if args.dagger_rounds < 0 or args.dagger_episodes < 1:
        raise ValueError("--dagger-rounds must be >= 0 and --dagger-episodes >= 1")
    if args.bc_schedule not in BC_SCHEDULES:
        raise ValueError(f"--bc-schedule takes one of {BC_SCHEDULES}, got {args.bc_schedule!r}")
    if args.dagger_rounds > 0 and args.bc_episodes < 1:
        raise ValueError("--dagger-rounds refines a cloned actor: set --bc-episodes")
    if set(args.eval_scenarios) - set("ABC"):
        raise ValueError(f"--eval-scenarios takes letters of 'ABC', got {args.eval_scenarios!r}")
    if args.video_every < 0 or not args.video_seconds > 0:
        raise ValueError("--video-every must be >= 0 and --video-seconds > 0")
    if not args.eval_duration > 0:
        raise ValueError("--eval-duration must be > 0 s")
    checked_coef(args.intervention_penalty)
    if args.intervention_penalty > 0 and not args.shield:
        raise ValueError("--intervention-penalty charges the shield's corrections: add --shield")
    args.set = tuple(args.set)
    world_settings(args)  # a bad world option fails here, naming the EnvConfig field
    lagrangian_settings(args)
    expert_config_from(args.preset, list(args.set))  # a bad preset or --set fails here
    return args


def expert_settings(args: Args) -> ExpertConfig:
    """The shield's (and the demonstrating expert's) configuration."""
    return expert_config_from(args.preset, list(args.set))


def lagrangian_settings(args: Args, lambda_init: float = 0.0) -> LagrangianConfig:
    """The multiplier's settings (checked even without ``--lagrangian``)."""
    return LagrangianConfig(args.cost_limit, args.lambda_lr, lambda_init)


def world_settings(args: Args) -> dict[str, Any]:
    """The training world's env keyword arguments (`train.world.TrainingWorld`)."""
    return TrainingWorld.from_fields(args).env_kwargs()


# ------------------------------------------------------------------------ env
def env_fn(args: Args):
    """Factory of one unshielded training world (a ParallelEnv)."""
    from uavtrack_env import uavtrack_v0

    return functools.partial(uavtrack_v0.parallel_env, **world_settings(args))


def make_vec_env(args: Args, lambda_init: float = 0.0):
    """The rows' VecEnv -> AgentVecMonitor (-> InterventionPenalty) (-> LagrangianReward)
    (-> VecFrameStack) (-> VecNormalize), seeded.

    `VectorSharedPolicyVecEnv`: every world in one batched step, shielded by `VectorCBFShield`
    with ``--shield``."""
    from stable_baselines3.common.vec_env import VecFrameStack, VecNormalize

    from uavtrack_env.wrappers.sb3 import AgentVecMonitor, VectorSharedPolicyVecEnv

    from .intervention import InterventionPenalty
    from .lagrangian import LagrangianReward

    shield = expert_settings(args) if args.shield else None
    rows = VectorSharedPolicyVecEnv(args.n_envs, shield=shield, **world_settings(args))
    vec = AgentVecMonitor(rows)
    if args.intervention_penalty > 0:
        vec = InterventionPenalty(vec, args.intervention_penalty)
    if args.lagrangian:
        vec = LagrangianReward(vec, lagrangian_settings(args, lambda_init))
    if args.frame_stack > 1:
        vec = VecFrameStack(vec, args.frame_stack)
    if args.normalize:
        vec = VecNormalize(vec, gamma=args.gamma)
    vec.seed(args.seed)
    return vec


# ---------------------------------------------------------------- checkpoints
_CKPT = re.compile(r"ppo_(\d+)_steps\.zip$")


def last_checkpoint(run_dir: Path) -> tuple[Path, Path | None]:
    """(model zip, VecNormalize pickle or None) of the highest step count in DIR/checkpoints."""
    ckpts = [
        (int(m.group(1)), p)
        for p in (Path(run_dir) / "checkpoints").glob("ppo_*_steps.zip")
        if (m := _CKPT.search(p.name))
    ]
    if not ckpts:
        raise ValueError(f"no checkpoint ppo_<steps>_steps.zip in {run_dir}/checkpoints")
    steps, path = max(ckpts)
    norm = path.with_name(f"ppo_vecnormalize_{steps}_steps.pkl")
    return path, norm if norm.exists() else None


def save_checkpoint(model, vec, ckdir: Path) -> None:
    """Model and VecNormalize statistics under CheckpointCallback's names (for ``--resume``)."""
    from stable_baselines3.common.vec_env import VecNormalize

    model.save(ckdir / f"ppo_{model.num_timesteps}_steps.zip")
    if isinstance(vec, VecNormalize):
        vec.save(str(ckdir / f"ppo_vecnormalize_{model.num_timesteps}_steps.pkl"))


# ---------------------------------------------------------------------- train
def demonstrations(args: Args, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The expert's (observations, actions) on unshielded training worlds, cached in a .npz;
    a resumed run with DAgger labels (DIR/dagger.npz) takes those, as its anchor did.
    ``width``: the policy's input size (``--frame-stack`` observations), which a cached file
    must have."""
    from train import bc

    path = Path(args.bc_demos or args.out / "demos.npz")
    if args.resume is not None and (args.out / "dagger.npz").exists():
        path = args.out / "dagger.npz"
    if path.exists():
        with np.load(path) as d:
            obs, actions = d["obs"], d["actions"]
        if obs.shape[1] != width:
            raise ValueError(
                f"{path} holds observations of width {obs.shape[1]}, but the policy's input "
                f"is {width} (--frame-stack {args.frame_stack}); record the demonstrations "
                "again with another --bc-demos path"
            )
        print(f"behaviour cloning: {len(obs)} samples from {path}")
        return obs, actions
    make = env_fn(args)
    obs, actions = bc.collect(
        make, args.bc_episodes, BC_SEED + args.seed, args.progress, expert_settings(args),
        args.bc_workers, frames=args.frame_stack,
    )  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, obs=obs, actions=actions)
    return obs, actions


def train(args: Args):
    """Train (or resume) and save; returns the model and its VecEnv."""
    import torch
    from stable_baselines3.common.callbacks import CheckpointCallback
    from stable_baselines3.common.vec_env import VecNormalize

    from .callbacks import (
        CertifiedActions,
        StopAtTimesteps,
        TrainingLog,
        VideoEvery,
        progress_callback,
    )
    from .lagrangian import LagrangianReward, MultiplierUpdate

    torch.set_num_threads(args.threads)
    out = args.out
    ckdir = out / "checkpoints"
    ckdir.mkdir(parents=True, exist_ok=True)
    previous = _previous_calls(args)
    model, vec = model_and_env(args, previous.get("lagrangian_lambda", 0.0))
    if args.freeze_obs_stats and isinstance(vec, VecNormalize):
        from train.bc import freeze_observation_statistics

        freeze_observation_statistics(vec)
    bc_stats: dict = {}
    width = model.observation_space.shape[0]
    demos = demonstrations(args, width) if args.bc_episodes > 0 else None  # loaded once
    if args.resume is None and demos is not None:
        bc_stats = _clone_expert(args, model, vec, demos, ckdir)
        for r in range(args.dagger_rounds):
            demos = _dagger_round(args, r, demos, ckdir)
            bc_stats = _clone_expert(args, model, vec, demos, ckdir)
    ckpt = CheckpointCallback(
        save_freq=max(1, args.checkpoint_freq // vec.num_envs),
        save_path=str(ckdir),
        name_prefix="ppo",
        save_vecnormalize=True,
    )
    bar, rich_bar = progress_callback(args.progress)
    events = out / VIOLATIONS_FILE
    if args.resume is None or not events.exists():
        events.write_text("")  # a new run starts an empty log; a resumed one appends
    log = TrainingLog(args.log_every, echo=_echo(args.progress and not rich_bar), events=events)
    callbacks = [c for c in (ckpt, bar, StopAtTimesteps()) if c is not None]
    penalty = _wrapper(vec, LagrangianReward)
    if penalty is not None:
        callbacks.append(MultiplierUpdate(penalty))
        log.extra["lambda"] = lambda: penalty.lam
    callbacks.append(log)
    if args.learn_certified:
        callbacks.append(CertifiedActions())
    if args.video_every > 0:
        callbacks.append(VideoEvery(args.video_every, _video_recorder(args, vec)))
    if args.bc_anchor > 0:
        from train import bc

        callbacks.append(bc.anchor_callback(*demos, args.bc_anchor, seed=args.seed))
    t0 = time.perf_counter()
    start = model.num_timesteps
    _learn(args, model, callbacks, rich_bar, bool(bc_stats))
    elapsed = time.perf_counter() - t0
    _save_run(args, model, vec, ckdir)
    call = {
        "from_timesteps": int(start),
        "to_timesteps": int(model.num_timesteps),
        "train_seconds": elapsed,
        "agent_steps_per_s": (model.num_timesteps - start) / elapsed,
        "training_violations": log.totals,  # steps of flying UAVs in this call
    }
    calls = [*previous.get("calls", []), call]
    saved = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(args).items()}
    saved.update(
        num_timesteps=int(model.num_timesteps),
        this_call_timesteps=call["to_timesteps"] - call["from_timesteps"],
        train_seconds=sum(c["train_seconds"] for c in calls),
        agent_steps_per_s=call["agent_steps_per_s"],
        **{k: previous[k] for k in BC_STATS if k in previous},
        **bc_stats,
        training_violations={
            k: sum(c["training_violations"][k] for c in calls) for k in log.totals
        },
        calls=calls,
    )
    if penalty is not None:
        saved["lagrangian_lambda"] = penalty.lam
    (out / "args.json").write_text(json.dumps(saved, indent=2))
    (out / "config.json").write_text(json.dumps(run_record(args), indent=2))
    return model, vec


def _previous_calls(args: Args) -> dict:
    """args.json of the run ``--resume`` continues (empty for a new run)."""
    path = None if args.resume is None else Path(args.resume) / "args.json"
    if path is None or not path.exists():
        return {}
    saved = json.loads(path.read_text())
    if "calls" not in saved and "num_timesteps" in saved:  # a run of one call
        saved["calls"] = [
            {
                "from_timesteps": saved["num_timesteps"] - saved.get("this_call_timesteps", 0),
                "to_timesteps": saved["num_timesteps"],
                "train_seconds": saved.get("train_seconds", 0.0),
                "agent_steps_per_s": saved.get("agent_steps_per_s", 0.0),
                "training_violations": saved.get("training_violations", {}),
            }
        ]
    return saved


def _video_recorder(args: Args, vec):
    """`VideoEvery`'s action: the model's deterministic policy (observations normalised with
    the current statistics), shielded if the run is, in DIR/videos."""
    from stable_baselines3.common.vec_env import VecNormalize

    from .video import record_policy

    normalizer = vec if isinstance(vec, VecNormalize) else None
    shield = expert_settings(args) if args.shield else None

    def record(callback, name: str) -> None:
        policy = SB3Policy(callback.model, normalizer, args.frame_stack)
        path = record_policy(
            policy,
            args.out / "videos",
            name,
            shield=shield,
            dynamics=args.dynamics,
            seconds=args.video_seconds,
        )
        print(f"video: {path}")

    return record


def _echo(progress_bar: bool):
    """print, or tqdm.write while a tqdm bar is on the terminal."""
    if progress_bar:
        from tqdm import tqdm

        return tqdm.write
    return print


def _wrapper(vec, kind: type):
    """The first VecEnvWrapper of type ``kind`` in the chain below ``vec`` (or None)."""
    while vec is not None and not isinstance(vec, kind):
        vec = getattr(vec, "venv", None)
    return vec


def model_and_env(args: Args, lambda_init: float = 0.0):
    """The PPO model and its VecEnv: the last checkpoint of ``--resume`` (with its VecNormalize
    statistics and multiplier), else a new model with the command line's hyperparameters."""
    from stable_baselines3.common.vec_env import VecNormalize

    from train.sb3_ppo import OPTIMIZER_KWARGS, LinearSkipPolicy, SharedPPO

    out = args.out
    vec = make_vec_env(args, lambda_init)
    if args.resume is not None:
        path, norm = last_checkpoint(args.resume)
        if isinstance(vec, VecNormalize) and norm is not None:
            vec = VecNormalize.load(str(norm), vec.venv)
            vec.seed(args.seed)
        model = SharedPPO.load(path, env=vec, device="cpu", tensorboard_log=str(out / "tb"))
        print(f"resuming {path} at {model.num_timesteps} agent-steps")
        return model, vec
    hidden = [int(h) for h in args.net_arch.split(",") if h]
    model = SharedPPO(
        LinearSkipPolicy if args.linear_skip else "MlpPolicy",
        vec,
        n_steps=args.n_steps,
        batch_size=args.batch_size,
        n_epochs=args.n_epochs,
        learning_rate=args.learning_rate,
        gamma=args.gamma,
        gae_lambda=args.gae_lambda,
        clip_range=args.clip_range,
        ent_coef=args.ent_coef,
        target_kl=args.target_kl or None,
        policy_kwargs={
            "net_arch": {"pi": hidden, "vf": hidden},
            "log_std_init": args.log_std_init,
            "optimizer_kwargs": OPTIMIZER_KWARGS,
        },
        tensorboard_log=str(out / "tb"),
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    return model, vec


def _clone_expert(args: Args, model, vec, demos: tuple, ckdir: Path) -> dict:
    """Fit the actor to the expert's demonstrations and save it as the first checkpoint;
    returns the cloning statistics."""
    from stable_baselines3.common.vec_env import VecNormalize

    from train import bc

    obs, actions = demos
    normalizer = vec if isinstance(vec, VecNormalize) else None
    bc_stats = bc.pretrain(
        model,
        normalizer,
        obs,
        actions,
        epochs=args.bc_epochs,
        schedule=args.bc_schedule,
        seed=args.seed,
        progress=args.progress,
    )
    print("behaviour cloning: " + ", ".join(f"{k} {v:.4g}" for k, v in bc_stats.items()))
    save_checkpoint(model, vec, ckdir)  # the cloned policy, before any PPO step
    return bc_stats


def _dagger_round(args: Args, r: int, demos: tuple, ckdir: Path) -> tuple:
    """DAgger round ``r``: the latest cloned actor (checkpoint 0) acts on ``--dagger-episodes``
    training worlds, the expert labels every state; returns ``demos`` with these labels added
    (also written to DIR/dagger.npz)."""
    from train import bc

    shield = expert_settings(args) if args.shield else None
    learner = bc.Learner(
        ckdir / "ppo_0_steps.zip", ckdir / "ppo_vecnormalize_0_steps.pkl", shield,
        args.frame_stack,
    )  # fmt: skip
    seed = DAGGER_SEED + args.seed + r * args.dagger_episodes
    obs, actions = bc.collect(
        env_fn(args), args.dagger_episodes, seed, args.progress, expert_settings(args),
        args.bc_workers, learner, args.frame_stack,
    )  # fmt: skip
    print(f"DAgger round {r + 1}: {len(obs)} labelled states")
    demos = (np.concatenate([demos[0], obs]), np.concatenate([demos[1], actions]))
    np.savez_compressed(args.out / "dagger.npz", obs=demos[0], actions=demos[1])
    return demos


def _learn(args: Args, model, callbacks: list, rich_bar: bool, cloned: bool) -> None:
    """PPO for ``args.timesteps`` agent-steps; after cloning, the first ``--value-warmup`` of
    them train the critic alone (the actor's parameters frozen)."""
    phases = [(args.timesteps, ())]
    if cloned and args.value_warmup > 0:
        from train.bc import actor_parameters

        warm = min(args.value_warmup, args.timesteps)
        phases = [(warm, actor_parameters(model.policy)), (args.timesteps - warm, ())]
    for k, (steps, frozen) in enumerate(phases):
        if steps <= 0:
            continue
        for p in frozen:
            p.requires_grad_(False)
        model.learn(
            total_timesteps=steps,
            callback=callbacks,
            reset_num_timesteps=args.resume is None and k == 0,
            progress_bar=rich_bar,
            tb_log_name="PPO",
        )
        for p in frozen:
            p.requires_grad_(True)


def _save_run(args: Args, model, vec, ckdir: Path) -> None:
    """The final model and VecNormalize statistics, also as a checkpoint so that ``--resume``
    continues from the end."""
    from stable_baselines3.common.vec_env import VecNormalize

    model.save(args.out / "model.zip")
    if isinstance(vec, VecNormalize):
        vec.save(str(args.out / "vecnormalize.pkl"))
    save_checkpoint(model, vec, ckdir)


def run_record(args: Args) -> dict:
    """config.json: the training world, the shield's ExpertConfig, the arguments."""
    from uavtrack_env.config import EnvConfig

    args_dict = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    return config_record(
        args.preset,
        EnvConfig.from_kwargs(**world_settings(args)),
        expert_settings(args),
        cli_command("train.ppo", command_line(args)),
        args=args_dict,
    )


def command_line(args: Args) -> list[str]:
    """The arguments that reproduce ``args`` (the fields that differ from their defaults)."""
    argv = []
    for f in dataclasses.fields(Args):
        value = getattr(args, f.name)
        if f.name in ("resume", "timesteps") or value == f.default:
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            argv.append(flag if value else "--no-" + flag[2:])
        elif isinstance(value, tuple):
            argv += [x for item in value for x in (flag, str(item))]
        else:
            argv += [flag, str(value)]
    return argv


def policy_label(shield: bool, lagrangian: bool) -> str:
    """A run's name in tables: PPO or PPO-Lagrangian, with '+ shield' if shielded."""
    name = "PPO-Lagrangian" if lagrangian else "PPO"
    return f"{name} + shield" if shield else name


def evaluate_model(model, vec, args: Args) -> list[dict]:
    """Deterministic policy on the paper's scenarios and seeded random worlds (shielded if
    trained shielded) -> one metrics dict per episode, also written to DIR/metrics.json."""
    from stable_baselines3.common.vec_env import VecNormalize

    normalizer = vec if isinstance(vec, VecNormalize) else None
    if normalizer is not None:
        normalizer.training = False
    policy = SB3Policy(model, normalizer, args.frame_stack)
    steps = max(1, round(args.eval_duration / DT))
    label = policy_label(args.shield, args.lagrangian)
    shield = expert_settings(args) if args.shield else None
    record = run_record(args)
    runs = []
    for scenario, init, seed in eval_worlds(list(args.eval_scenarios), args.eval_seeds):
        env = make_eval_env(scenario, init, steps, dynamics=args.dynamics, shield=shield)
        m = run_policy_episode(
            env, policy, seed=seed, steps=steps, label=label, dynamics=args.dynamics
        )
        m.update(timesteps=int(model.num_timesteps), preset=args.preset, config=record)
        runs.append(m)
        env.close()
    path = args.out / "metrics.json"
    earlier = json.loads(path.read_text()) if path.exists() else []
    path.write_text(json.dumps(earlier + runs, indent=2))  # a resumed run appends
    return runs


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(argv)
    model, vec = train(args)
    print(f"trained to {model.num_timesteps} agent-steps; wrote {args.out}/ (model.zip, ...)")
    if not args.evaluate:
        vec.close()
        flag = "--ppo-shield" if args.shield else "--ppo"
        print(f"evaluate with --evaluate, or: python -m baselines.compare {flag} {args.out}")
        return []
    runs = evaluate_model(model, vec, args)
    vec.close()
    print(f"evaluation ({args.eval_duration:g} s episodes):")
    print(table(runs))
    for m in runs:
        v = m["violations_per_1000_steps"]
        rate = m["shield_intervention_rate"]
        print(
            f"{m['scenario']}{m['init']} seed {m['seed']}: violations/1000 agent-steps "
            + ", ".join(f"{k} {x:.1f}" for k, x in v.items())
            + ("" if rate is None else f"; shield active {100 * rate:.1f} %")
        )
    return runs


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
