"""Shared-parameter PPO (Stable-Baselines3, torch, CPU) on random worlds, shielded or not.

    python -m train.ppo --shield --timesteps 200000 --seed 0 --out runs/ppo-shield
    python -m train.ppo --no-shield --timesteps 200000 --seed 0 --out runs/ppo
    python -m train.ppo --timesteps 100000 --resume runs/ppo-shield     # 100k more steps

One policy drives every UAV (each agent of each env copy is one row of
`uavtrack_env.wrappers.sb3.SharedPolicyVecEnv`); with ``--shield`` every action passes the
expert's CBF-QP (`CBFShield`) in training and in evaluation. Writes into DIR: ``tb/``
(TensorBoard), ``checkpoints/`` (every ``--checkpoint-freq`` agent-steps, with the VecNormalize
statistics), ``model.zip`` + ``vecnormalize.pkl`` (final), ``args.json`` and ``metrics.json``
(a list of evaluation episodes in the schema of ``baselines/evaluate.py`` plus
``violations_per_1000_steps`` and ``shield_intervention_rate``). Step counts are agent-steps
(SB3's ``num_timesteps``: rows x vector steps).

Reward: ``exp(-c)`` per step (c the stage cost of eq. 18) minus a collision penalty, so that
ending an episode by crashing never pays (with the env's default ``-c``, unshielded PPO learned
to crash within 0.4 s). Training worlds start the UAVs up to ``--start-offset`` m off formation.

Warm start from the expert (``--bc-episodes N``): N expert episodes are recorded (cached in
``--bc-demos``), the actor is fitted to them (checkpoint 0), the critic alone trains for
``--value-warmup`` steps, then PPO fine-tunes, optionally with ``--bc-anchor`` cloning steps
after every update. The recipe used for the README's table:

    python -m train.ppo --shield --bc-episodes 60 --bc-anchor 10 --value-warmup 100000 \
        --target-kl 0.01 --learning-rate 5e-5 --log-std-init -3.5 --timesteps 800000 \
        --out runs/bcppo-shield
"""

from __future__ import annotations

import argparse
import dataclasses
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
    DEFAULT_PRESET,
    ExpertConfig,
    add_preset_arguments,
    expert_config_from,
)
from uavtrack_env.provenance import cli_command, config_record

ENV_FIELDS = (
    "shield",
    "n_uavs",
    "max_cycles",
    "terminate_on_collision",
    "dynamics",
    "n_envs",
    "reward_shape",
    "collision_penalty",
    "start_offset",
    "start_heading_offset",
    "preset",
    "set",
)
"""Arguments that define the training env; ``--resume`` takes them from the run's args.json."""
BC_SEED = 50_000
"""Demonstration worlds are seeded BC_SEED + seed + episode, apart from the evaluation seeds."""


@dataclass
class Args:
    """Command-line arguments (``--name-with-dashes``); each field's help is its metadata."""

    shield: bool = field(default=True, metadata={"help": "pass every action through CBFShield"})
    preset: str = field(
        default=DEFAULT_PRESET, metadata={"help": "the shield's and the expert's ExpertConfig"}
    )
    set: tuple[str, ...] = field(
        default=(), metadata={"help": "FIELD=VALUE overrides of the preset (repeatable)"}
    )
    timesteps: int = field(default=200_000, metadata={"help": "agent-steps to train (this call)"})
    seed: int = field(default=0, metadata={"help": "seed of torch, numpy and the env copies"})
    out: Path | None = field(default=None, metadata={"help": "output dir (default: --resume)"})
    resume: Path | None = field(
        default=None, metadata={"help": "continue the run in DIR from its last checkpoint"}
    )
    n_envs: int = field(default=4, metadata={"help": "env copies (rows = copies x n_uavs)"})
    n_uavs: int = field(default=3, metadata={"help": "UAVs per random world"})
    max_cycles: int = field(default=1200, metadata={"help": "training episode length (80 Hz)"})
    terminate_on_collision: str = field(
        default="all", metadata={"help": "'all' or 'agent' (SharedPolicyVecEnv pads dead rows)"}
    )
    dynamics: str = field(
        default="integrator", metadata={"help": "'integrator' (eq. 3, shield exact) or 'lag'"}
    )
    reward_shape: str = field(
        default="exp",
        metadata={"help": "'exp' (r = exp(-c) in (0, 1]: crashing never pays) or 'cost' (r = -c)"},
    )
    collision_penalty: float = field(
        default=10.0, metadata={"help": "reward subtracted on a UAV's collision step"}
    )
    n_steps: int = field(default=256, metadata={"help": "PPO rollout length per row"})
    batch_size: int = field(default=512, metadata={"help": "PPO minibatch size"})
    n_epochs: int = field(default=10, metadata={"help": "PPO epochs per rollout"})
    learning_rate: float = field(default=3e-4, metadata={"help": "Adam learning rate"})
    gamma: float = field(default=0.99, metadata={"help": "discount"})
    gae_lambda: float = field(default=0.95, metadata={"help": "GAE lambda"})
    clip_range: float = field(default=0.2, metadata={"help": "PPO clip range"})
    ent_coef: float = field(default=0.0, metadata={"help": "entropy bonus"})
    net_arch: str = field(default="128,128", metadata={"help": "hidden sizes of pi and vf"})
    log_std_init: float = field(
        default=-2.0,
        metadata={"help": "initial log std of the Gaussian policy (-2: 0.14, i.e. 1.4 m/s)"},
    )
    normalize: bool = field(
        default=True, metadata={"help": "VecNormalize observations and rewards"}
    )
    bc_episodes: int = field(
        default=0,
        metadata={"help": "expert episodes for a behaviour-cloning warm start (0: from scratch)"},
    )
    bc_epochs: int = field(default=30, metadata={"help": "behaviour-cloning epochs"})
    bc_demos: Path | None = field(
        default=None,
        metadata={"help": "demonstrations .npz to reuse if it exists, else written there"},
    )
    bc_anchor: int = field(
        default=0,
        metadata={"help": "cloning-loss minibatch steps after every PPO update (0: off)"},
    )
    start_offset: float = field(
        default=3.0, metadata={"help": "training worlds: UAV start offset from formation (m)"}
    )
    start_heading_offset: float = field(
        default=0.3, metadata={"help": "training worlds: start heading offset (rad)"}
    )
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
    threads: int = field(default=1, metadata={"help": "torch CPU threads"})
    progress: bool = field(default=True, metadata={"help": "show a progress bar"})


def parse_args(argv: list[str] | None = None) -> Args:
    """argparse from the `Args` dataclass; booleans get ``--x/--no-x``."""
    ap = argparse.ArgumentParser(
        prog="python -m train.ppo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_preset_arguments(ap)
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
            if k in saved:  # runs of older versions lack the newer fields
                given[k] = saved[k]
        given.setdefault("out", Path(given["resume"]))
    args = Args(**given)
    if args.out is None:
        raise ValueError("--out DIR is required (or --resume DIR)")
    args.out = Path(args.out)
    for name in ("timesteps", "n_envs", "n_uavs", "max_cycles", "n_steps", "batch_size"):
        if int(getattr(args, name)) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
    if args.terminate_on_collision not in ("all", "agent"):
        raise ValueError("--terminate-on-collision must be 'all' or 'agent'")
    if args.bc_anchor > 0 and args.bc_episodes < 1:
        raise ValueError("--bc-anchor needs demonstrations: set --bc-episodes")
    if args.reward_shape not in ("exp", "cost"):
        raise ValueError(f"--reward-shape must be 'exp' or 'cost', got {args.reward_shape!r}")
    if args.dynamics not in ("integrator", "lag"):
        raise ValueError("--dynamics must be 'integrator' or 'lag'")
    if set(args.eval_scenarios) - set("ABC"):
        raise ValueError(f"--eval-scenarios takes letters of 'ABC', got {args.eval_scenarios!r}")
    if not args.eval_duration > 0:
        raise ValueError("--eval-duration must be > 0 s")
    args.set = tuple(args.set)
    expert_config_from(args.preset, list(args.set))  # a bad preset or --set fails here
    return args


def expert_settings(args: Args) -> ExpertConfig:
    """The shield's (and the demonstrating expert's) configuration."""
    return expert_config_from(args.preset, list(args.set))


def world_settings(args: Args) -> dict[str, Any]:
    """The training world's env keyword arguments (EnvConfig fields)."""
    return {
        "scenario": "random",
        "n_uavs": args.n_uavs,
        "max_cycles": args.max_cycles,
        "terminate_on_collision": args.terminate_on_collision,
        "dynamics": {"model": args.dynamics},
        "reward": {"shape": args.reward_shape, "collision_penalty": args.collision_penalty},
        "random_world": {
            "start_offset": args.start_offset,
            "start_heading_offset": args.start_heading_offset,
        },
    }


# ------------------------------------------------------------------------ env
def env_fn(args: Args):
    """Factory of one training copy: a random world, shielded if asked."""
    from uavtrack_env import uavtrack_v0

    expert = expert_settings(args)
    kwargs = world_settings(args)

    def make():
        env = uavtrack_v0.parallel_env(**kwargs)
        if args.shield:
            from uavtrack_env.wrappers import CBFShield

            env = CBFShield(env, expert)
        return env

    return make


def make_vec_env(args: Args):
    """SharedPolicyVecEnv -> AgentVecMonitor (-> VecNormalize), seeded."""
    from stable_baselines3.common.vec_env import VecNormalize

    from uavtrack_env.wrappers.sb3 import AgentVecMonitor, SharedPolicyVecEnv

    vec = AgentVecMonitor(SharedPolicyVecEnv(env_fn(args), n_copies=args.n_envs))
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


def safety_counter():
    """SB3 callback counting violation agent-steps (and shield interventions) during training;
    TensorBoard ``safety/*``; ``.totals`` for args.json."""
    from stable_baselines3.common.callbacks import BaseCallback

    class SafetyCounter(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.totals = dict.fromkeys(
                ("agent_steps", "collision", "disconnection", "occlusion", "shield_active"), 0
            )

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                v = info.get("violations")
                if v is None:  # absorbing row of a finished agent
                    continue
                self.totals["agent_steps"] += 1
                for k in ("collision", "disconnection", "occlusion"):
                    self.totals[k] += bool(v[k])
                self.totals["shield_active"] += bool(info.get("shield", {}).get("active", False))
            return True

        def _on_rollout_end(self) -> None:
            for k, v in self.totals.items():
                self.logger.record(f"safety/{k}", v)

    return SafetyCounter()


def save_checkpoint(model, vec, ckdir: Path) -> None:
    """Model and VecNormalize statistics under CheckpointCallback's names (for ``--resume``)."""
    from stable_baselines3.common.vec_env import VecNormalize

    model.save(ckdir / f"ppo_{model.num_timesteps}_steps.zip")
    if isinstance(vec, VecNormalize):
        vec.save(str(ckdir / f"ppo_vecnormalize_{model.num_timesteps}_steps.pkl"))


def _progress_callback(enabled: bool):
    """SB3's rich progress bar if rich is installed, else a tqdm callback (None if disabled)."""
    from stable_baselines3.common.callbacks import BaseCallback

    if not enabled:
        return None, False
    try:
        import rich  # noqa: F401

        return None, True
    except ImportError:
        pass
    from tqdm import tqdm

    class TqdmCallback(BaseCallback):
        def _on_training_start(self) -> None:
            total = self.locals["total_timesteps"]
            self.bar = tqdm(total=total, initial=self.model.num_timesteps, unit="step")

        def _on_step(self) -> bool:
            self.bar.update(self.model.num_timesteps - self.bar.n)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return TqdmCallback(), False


# ---------------------------------------------------------------------- train
def demonstrations(args: Args) -> tuple[np.ndarray, np.ndarray]:
    """The expert's (observations, actions) on unshielded training worlds, cached in a .npz."""
    from train import bc

    path = Path(args.bc_demos or args.out / "demos.npz")
    if path.exists():
        with np.load(path) as d:
            print(f"behaviour cloning: {len(d['obs'])} samples from {path}")
            return d["obs"], d["actions"]
    make = env_fn(dataclasses.replace(args, shield=False))
    obs, actions = bc.collect(
        make, args.bc_episodes, BC_SEED + args.seed, args.progress, expert_settings(args)
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, obs=obs, actions=actions)
    return obs, actions


def train(args: Args):
    """Train (or resume) and save; returns the model and its VecEnv."""
    import torch
    from stable_baselines3.common.callbacks import CheckpointCallback

    torch.set_num_threads(args.threads)
    out = args.out
    ckdir = out / "checkpoints"
    ckdir.mkdir(parents=True, exist_ok=True)
    model, vec = _model_and_env(args)
    bc_stats: dict = {}
    demos = demonstrations(args) if args.bc_episodes > 0 else None  # loaded once
    if args.resume is None and demos is not None:
        bc_stats = _clone_expert(args, model, vec, demos, ckdir)
    ckpt = CheckpointCallback(
        save_freq=max(1, args.checkpoint_freq // vec.num_envs),
        save_path=str(ckdir),
        name_prefix="ppo",
        save_vecnormalize=True,
    )
    bar, rich_bar = _progress_callback(args.progress)
    t0 = time.perf_counter()
    start = model.num_timesteps
    safety = safety_counter()
    callbacks = [c for c in (ckpt, bar, safety) if c is not None]
    if args.bc_anchor > 0:
        from train import bc

        callbacks.append(bc.anchor_callback(*demos, args.bc_anchor, seed=args.seed))
    _learn(args, model, callbacks, rich_bar, bool(bc_stats))
    elapsed = time.perf_counter() - t0
    _save_run(args, model, vec, ckdir)
    saved = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(args).items()}
    saved.update(
        num_timesteps=int(model.num_timesteps),
        this_call_timesteps=int(model.num_timesteps - start),
        train_seconds=elapsed,
        agent_steps_per_s=(model.num_timesteps - start) / elapsed,
        **bc_stats,
        training_violations=safety.totals,  # agent-steps of this call
    )
    (out / "args.json").write_text(json.dumps(saved, indent=2))
    (out / "config.json").write_text(json.dumps(run_record(args), indent=2))
    return model, vec


def _model_and_env(args: Args):
    """The VecEnv and the PPO model: the last checkpoint of ``--resume`` (with its VecNormalize
    statistics), else a new model with the command line's hyperparameters."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    out = args.out
    vec = make_vec_env(args)
    if args.resume is not None:
        path, norm = last_checkpoint(args.resume)
        if isinstance(vec, VecNormalize) and norm is not None:
            vec = VecNormalize.load(str(norm), vec.venv)
            vec.seed(args.seed)
        model = PPO.load(path, env=vec, device="cpu", tensorboard_log=str(out / "tb"))
        print(f"resuming {path} at {model.num_timesteps} agent-steps")
        return model, vec
    hidden = [int(h) for h in args.net_arch.split(",") if h]
    model = PPO(
        "MlpPolicy",
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
        seed=args.seed,
        progress=args.progress,
    )
    print("behaviour cloning: " + ", ".join(f"{k} {v:.4g}" for k, v in bc_stats.items()))
    save_checkpoint(model, vec, ckdir)  # the cloned policy, before any PPO step
    return bc_stats


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


def evaluate_model(model, vec, args: Args) -> list[dict]:
    """Deterministic policy on the paper's scenarios and seeded random worlds (shielded if
    trained shielded) -> one metrics dict per episode, also written to DIR/metrics.json."""
    from stable_baselines3.common.vec_env import VecNormalize

    normalizer = vec if isinstance(vec, VecNormalize) else None
    if normalizer is not None:
        normalizer.training = False
    policy = SB3Policy(model, normalizer)
    steps = max(1, round(args.eval_duration / DT))
    label = "PPO + shield" if args.shield else "PPO"
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
    (args.out / "metrics.json").write_text(json.dumps(runs, indent=2))
    return runs


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(argv)
    model, vec = train(args)
    runs = evaluate_model(model, vec, args)
    vec.close()
    print(f"trained to {model.num_timesteps} agent-steps; evaluation ({args.eval_duration:g} s):")
    print(table(runs))
    for m in runs:
        v = m["violations_per_1000_steps"]
        rate = m["shield_intervention_rate"]
        print(
            f"{m['scenario']}{m['init']} seed {m['seed']}: violations/1000 agent-steps "
            + ", ".join(f"{k} {x:.1f}" for k, x in v.items())
            + ("" if rate is None else f"; shield active {100 * rate:.1f} %")
        )
    print(f"\nwrote {args.out}/ (model.zip, checkpoints/, tb/, metrics.json)")
    return runs


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
