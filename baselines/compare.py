"""Expert vs PPO vs PPO + shield on the paper's scenarios A-C and on seeded random worlds.

    python -m baselines.compare --ppo runs/ppo --ppo-shield runs/ppo-shield --seeds 20 \\
        --out runs/compare

Prints and writes DIR/compare.md (one row per policy and world group: RMS pixel errors,
collisions, disconnection and occluded steps, shield intervention rate), DIR/details.md (per UAV,
in the form of Table VI), DIR/config.json and DIR/metrics.json (every episode in the schema of
`uavtrack_env.runner.run_episode`). The expert uses ``--preset`` (default 'tuned') with ``--set``
overrides. The learned policies are read from the output directories of ``python -m train.ppo``
(``--ppo``, ``--ppo-shield``, ``--run``) or ``python -m train.rllib_ppo`` (``--run``); a run
trained shielded is evaluated behind the shield it trained with (`run_shield`: its preset and
``--set``). ``--ensemble DIR DIR ...`` evaluates
several ``train.ppo`` runs (e.g. seeds) as one policy, the mean of their actions. Episodes use
evaluate's world (detector noise on; ``--dynamics`` defaults to the paper's single integrator,
eq. (3), under which the shield's guarantees hold).
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from train.frames import FrameHistory
from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DT
from uavtrack_env.presets import RL_PRESET, ExpertConfig, add_preset_arguments, expert_config_from
from uavtrack_env.provenance import cli_command, config_record
from uavtrack_env.runner import Policy, run_episode

from . import evaluate


# ------------------------------------------------------------------ policies
class SB3Policy:
    """A trained SB3 model as ``policy(obs, infos) -> {agent: action}``, shared by all agents.

    Observations are stacked over the last ``frames`` steps as in training (`train.frames`;
    `reset` starts a new episode), then normalised with the saved VecNormalize statistics when
    given; actions are the deterministic policy's (the distribution's mean).
    """

    def __init__(self, model: Any, obs_normalizer: Any | None = None, frames: int = 1) -> None:
        self.model = model
        self.obs_normalizer = obs_normalizer
        self.history = FrameHistory(frames)

    def reset(self, layout: Any = None) -> None:
        """A new episode: forget the observation history (`runner.run_episode` calls this)."""
        self.history.reset()

    def __call__(self, obs: dict, infos: dict) -> dict[str, np.ndarray]:
        agents = list(obs)
        if not agents:
            return {}
        stacked = self.history(obs)
        batch = np.stack([stacked[a] for a in agents])
        if self.obs_normalizer is not None:
            batch = self.obs_normalizer.normalize_obs(batch)
        actions, _ = self.model.predict(batch, deterministic=True)
        actions = np.clip(actions, -1.0, 1.0).astype(np.float32)
        return dict(zip(agents, actions, strict=True))


class EnsemblePolicy:
    """The mean of several policies' actions, each fed the same observations (deep-ensemble
    averaging: independently trained seeds err in different directions, their mean less).

    Members keep their own input history and normalisation; the mean of actions in [-1, 1]
    stays in [-1, 1].
    """

    def __init__(self, members: list[Policy]) -> None:
        if not members:
            raise ValueError("an ensemble needs at least one member policy")
        self.members = list(members)

    def reset(self, layout: Any = None) -> None:
        """A new episode: each member that keeps a history forgets it."""
        for member in self.members:
            if hasattr(member, "reset"):
                member.reset(layout)

    def __call__(self, obs: dict, infos: dict) -> dict[str, np.ndarray]:
        actions = [member(obs, infos) for member in self.members]
        return {
            a: np.mean([act[a] for act in actions], axis=0).astype(np.float32) for a in actions[0]
        }


def load_policy(model_path: Path, norm_path: Path | None = None, frames: int = 1) -> SB3Policy:
    """A saved SB3 model (.zip) as a deterministic `SB3Policy` over ``frames`` stacked
    observations, with its VecNormalize statistics (.pkl) when ``norm_path`` exists."""
    from stable_baselines3 import PPO

    normalizer = None
    if norm_path is not None and Path(norm_path).exists():
        with Path(norm_path).open("rb") as f:  # a VecNormalize without its venv: normalize_obs
            normalizer = pickle.load(f)
        normalizer.training = False
    return SB3Policy(PPO.load(model_path, device="cpu"), normalizer, frames)


def load_run(run_dir: Path, cloned: bool = False) -> tuple[SB3Policy, dict]:
    """The final model of a ``train.ppo`` run directory and its saved arguments; with
    ``cloned``, its behaviour-cloned policy before any PPO step (checkpoint 0)."""
    run_dir = Path(run_dir)
    model_path = run_dir / "model.zip"
    norm_path = run_dir / "vecnormalize.pkl"
    if cloned:
        model_path = run_dir / "checkpoints" / "ppo_0_steps.zip"
        norm_path = run_dir / "checkpoints" / "ppo_vecnormalize_0_steps.pkl"
    if not model_path.exists():
        raise ValueError(f"{model_path} not found: expected the output directory of train.ppo")
    args = json.loads((run_dir / "args.json").read_text())
    return load_policy(model_path, norm_path, args.get("frame_stack", 1)), args


def load_any_run(run_dir: Path) -> tuple[str, bool, Policy]:
    """(label, shielded, policy) of a ``train.ppo`` or ``train.rllib_ppo`` output directory."""
    run_dir = Path(run_dir)
    if (run_dir / "model.zip").exists():
        from train.ppo import policy_label

        policy, run_args = load_run(run_dir)
        shielded = bool(run_args["shield"])
        lagrangian = bool(run_args.get("lagrangian", False))
        label = policy_label(shielded, lagrangian)
        return label, shielded, policy
    if (run_dir / "checkpoint").is_dir():
        from train import rllib_ppo

        policy, record = rllib_ppo.load_run(run_dir)
        shielded = bool(record["rllib"]["shield"])
        return ("RLlib PPO + shield" if shielded else "RLlib PPO"), shielded, policy
    raise ValueError(
        f"{run_dir} is neither a train.ppo run (model.zip) nor a train.rllib_ppo run (checkpoint/)"
    )


def run_shield(run_dir: Path) -> ExpertConfig:
    """The shield a run trained with: its preset with its ``--set`` overrides (``args.json`` of a
    ``train.ppo`` run, ``config.json`` of a ``train.rllib_ppo`` run)."""
    from train.ppo import OLDER_RUNS

    run_dir = Path(run_dir)
    if (run_dir / "args.json").exists():
        record = json.loads((run_dir / "args.json").read_text())
        preset = record.get("preset", OLDER_RUNS["preset"])
    else:  # train.rllib_ppo.train records preset None unless told: RLlibPPOConfig's default
        record = json.loads((run_dir / "config.json").read_text())
        preset = record.get("preset") or RL_PRESET
    return expert_config_from(preset, list(record.get("set", [])))


def load_ensemble(run_dirs: list[Path]) -> tuple[str, bool, EnsemblePolicy]:
    """(label, shielded, policy) of the mean of several ``train.ppo`` runs' actions; the runs
    must agree on the shield (whether, and which) and on the Lagrangian."""
    if len(run_dirs) < 2:
        raise ValueError(f"--ensemble needs at least two run directories, got {len(run_dirs)}")
    loaded = [load_run(d) for d in run_dirs]
    kinds = {(bool(a["shield"]), bool(a.get("lagrangian", False))) for _, a in loaded}
    if len(kinds) > 1:
        raise ValueError(
            f"--ensemble runs must all be shielded or all unshielded, and all PPO or all "
            f"PPO-Lagrangian; got {sorted(kinds)} from {[str(d) for d in run_dirs]}"
        )
    shields = [run_shield(d) for d in run_dirs]
    if any(s != shields[0] for s in shields):
        presets = [(a.get("preset"), a.get("set", [])) for _, a in loaded]
        raise ValueError(
            f"--ensemble runs must share one shield (preset and --set), got {presets} "
            f"from {[str(d) for d in run_dirs]}"
        )
    from train.ppo import policy_label

    shielded, lagrangian = kinds.pop()
    name, _, shield = policy_label(shielded, lagrangian).partition(" + ")
    label = f"{name} ensemble of {len(loaded)}" + (f" + {shield}" if shield else "")
    return label, shielded, EnsemblePolicy([p for p, _ in loaded])


# ------------------------------------------------------------------- episode
def run_policy_episode(
    env: Any, policy: Policy, *, seed: int, steps: int, label: str, dynamics: str
) -> dict:
    """One episode of ``policy`` on ``env`` (a ParallelEnv, shielded or not) -> metrics dict
    (`uavtrack_env.runner.run_episode`'s, with the policy's label and the dynamics)."""
    metrics = run_episode(env, policy, seed=seed, steps=steps, label=label).metrics
    metrics.update(policy=label, dynamics=dynamics)
    metrics["cbf"] = metrics["shield_intervention_rate"] is not None
    return metrics


def eval_worlds(
    scenarios: list[str], seeds: int, first_seed: int = 0, paper_episodes: int = 1
) -> list[tuple[str, int, int]]:
    """(scenario, init, seed) of the evaluation set: both Table VI rows of each paper scenario
    (``paper_episodes`` episodes, seeds first_seed + e: the sensors' noise and the radio's
    drops), then ``seeds`` random worlds with seeds first_seed + 1000 + k (kept apart from
    training's small seeds)."""
    worlds = [
        (s, i, first_seed + e) for s in scenarios for i in (0, 1) for e in range(paper_episodes)
    ]
    return worlds + [("random", 0, first_seed + 1000 + k) for k in range(seeds)]


def make_eval_env(
    scenario: str,
    init: int,
    steps: int,
    *,
    dynamics: str,
    shield: ExpertConfig | None,
    noise: bool = True,
) -> Any:
    """evaluate's world (no rendering) for one scenario, wrapped in `CBFShield` configured by
    ``shield`` unless it is None."""
    kw = evaluate.world_kwargs(scenario, init, steps, dynamics=dynamics, noise=noise, render=False)
    env = uavtrack_v0.parallel_env(**kw)
    if shield is not None:
        from uavtrack_env.wrappers import CBFShield

        env = CBFShield(env, shield)
    return env


# --------------------------------------------------------------------- table
def summary_rows(runs: list[dict]) -> list[dict]:
    """Aggregate episodes per (policy, world group): paper scenarios one by one, random pooled."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for m in runs:
        world = f"{m['scenario']}{m['init']}" if m["scenario"] != "random" else "random"
        groups.setdefault((m["policy"], world), []).append(m)
    rows = []
    for (policy, world), ms in groups.items():
        uavs = [u for m in ms for u in m["uavs"].values()]
        rates_all = [m["shield_intervention_rate"] for m in ms]
        rows.append(
            {
                "policy": policy,
                "world": world,
                "episodes": len(ms),
                "rms_u_px": float(np.mean([u["rms_u_px"] for u in uavs])),
                "rms_v_px": float(np.mean([u["rms_v_px"] for u in uavs])),
                "collisions": sum(not u["collision_ok"] for u in uavs),
                "disconnection_steps": sum(m["violation_steps"]["disconnection"] for m in ms),
                "occluded_steps": sum(m["violation_steps"]["occlusion"] for m in ms),
                "mean_duration_s": float(np.mean([m["duration_s"] for m in ms])),
                "intervention_rate": (
                    None
                    if all(r is None for r in rates_all)
                    else float(np.mean([r or 0.0 for r in rates_all]))
                ),
            }
        )
    return rows


def comparison_table(runs: list[dict]) -> str:
    """Markdown: one row per policy and world group."""
    head = (
        "| Policy | World | Episodes | RMS U (px) | RMS V (px) | Collisions (UAVs) "
        "| Disconnected steps | Occluded steps | Mean length (s) | Intervention rate |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|---|---|"]
    for r in summary_rows(runs):
        rate = "-" if r["intervention_rate"] is None else f"{100 * r['intervention_rate']:.1f} %"
        lines.append(
            f"| {r['policy']} | {r['world']} | {r['episodes']} | {r['rms_u_px']:.1f} "
            f"| {r['rms_v_px']:.1f} | {r['collisions']} | {r['disconnection_steps']} "
            f"| {r['occluded_steps']} | {r['mean_duration_s']:.1f} | {rate} |"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------- CLI
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m baselines.compare",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--ppo", type=Path, help="train.ppo output directory (unshielded run)")
    ap.add_argument("--ppo-shield", type=Path, help="train.ppo output directory (shielded run)")
    ap.add_argument(
        "--run",
        type=Path,
        action="append",
        default=[],
        help="a train.ppo or train.rllib_ppo output directory (repeatable); evaluated shielded "
        "if it trained shielded, named by its settings (PPO, PPO-Lagrangian, RLlib PPO)",
    )
    ap.add_argument(
        "--ensemble",
        type=Path,
        nargs="+",
        action="append",
        default=[],
        metavar="DIR",
        help="train.ppo output directories evaluated as one policy, the mean of their actions "
        "(repeatable: one ensemble per flag)",
    )
    ap.add_argument(
        "--cloned", type=Path, help="a train.ppo run with --bc-episodes: its cloned policy"
    )
    ap.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        help="only merge the metrics.json of earlier compare runs (e.g. entrants run in parallel)",
    )
    ap.add_argument("--seeds", type=int, default=20, help="number of seeded random worlds")
    ap.add_argument("--scenarios", nargs="*", default=["A", "B", "C"], choices=["A", "B", "C"])
    ap.add_argument(
        "--paper-episodes",
        type=int,
        default=1,
        help="episodes per paper world, seeds 0, 1, ... (the sensors' noise, the radio's drops)",
    )
    ap.add_argument("--duration", type=float, default=60.0, help="episode length in s")
    ap.add_argument("--dynamics", default="integrator", choices=["integrator", "lag"])
    ap.add_argument("--no-expert", action="store_true", help="skip the expert (slowest)")
    add_preset_arguments(ap)
    ap.add_argument("--out", type=Path, default=Path("runs/compare"))
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    args = ap.parse_args(argv)
    if args.seeds < 0 or not math.isfinite(args.duration) or args.duration <= 0:
        ap.error("--seeds must be >= 0 and --duration > 0")
    if args.paper_episodes < 1:
        ap.error(f"--paper-episodes must be >= 1, got {args.paper_episodes}")
    return args


def merge(dirs: list[Path], out: Path) -> list[dict]:
    """One table from several compare output directories (their episodes and budget lines)."""
    runs, header = [], []
    for d in dirs:
        runs += json.loads((Path(d) / "metrics.json").read_text())
        lines = (Path(d) / "compare.md").read_text().split("\n\n")[0].splitlines()
        header += [ln for ln in lines if ln not in header]
    md = comparison_table(runs)
    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.md").write_text("\n".join(header) + "\n\n" + md + "\n")
    (out / "metrics.json").write_text(json.dumps(runs, indent=2))
    print("\n".join(header) + "\n\n" + md)
    return runs


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(argv)
    if args.merge:
        return merge(args.merge, args.out)
    expert = expert_config_from(args.preset, args.set)
    steps = max(1, round(args.duration / DT))
    entrants = _entrants(args, expert)
    runs = _run_entrants(args, entrants, steps)
    md = comparison_table(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    header = _header(args)
    command = cli_command("baselines.compare", argv)
    record = config_record(args.preset, None, expert, command, dynamics=args.dynamics)
    for m in runs:
        m["preset"], m["config"] = args.preset, record
    (args.out / "config.json").write_text(json.dumps(record, indent=2))
    (args.out / "compare.md").write_text(header + "\n" + md + "\n")
    (args.out / "details.md").write_text(evaluate.table(runs) + "\n")
    (args.out / "metrics.json").write_text(json.dumps(runs, indent=2))
    print(header)
    print(md)
    print(f"\nwrote {args.out}/ (compare.md, details.md, metrics.json)")
    return runs


Entrant = tuple[str, ExpertConfig | None, Callable[[Any], Policy]]
"""(label, the shield's `ExpertConfig` or None, policy factory) of one policy compared."""


def _entrants(args: argparse.Namespace, expert: ExpertConfig) -> list[Entrant]:
    """The expert and the given runs, each shielded run with its own shield; SystemExit if
    none."""
    entrants: list[Entrant] = []
    if not args.no_expert:
        entrants.append(("expert", None, lambda env: evaluate.make_policy("expert", env, expert)))
    for run_dir, label in ((args.ppo, "PPO"), (args.ppo_shield, "PPO + shield")):
        if run_dir is not None:
            policy, run_args = load_run(run_dir)
            entrants.append((label, _shield(run_dir, run_args["shield"]), lambda env, p=policy: p))
    for run_dir in args.run:
        label, shielded, policy = load_any_run(run_dir)
        entrants.append((label, _shield(run_dir, shielded), lambda env, p=policy: p))
    for run_dirs in args.ensemble:
        label, shielded, policy = load_ensemble(run_dirs)
        entrants.append((label, _shield(run_dirs[0], shielded), lambda env, p=policy: p))
    if args.cloned is not None:
        policy, run_args = load_run(args.cloned, cloned=True)
        label = "cloned + shield" if run_args["shield"] else "cloned"
        entrants.append((label, _shield(args.cloned, run_args["shield"]), lambda env, p=policy: p))
    if not entrants:
        raise SystemExit(
            "nothing to compare: give --ppo, --ppo-shield, --run, --ensemble or --cloned "
            "(or drop --no-expert)"
        )
    return entrants


def _shield(run_dir: Path, shielded: bool) -> ExpertConfig | None:
    """The shield a run is evaluated behind: the one it trained with, or None."""
    return run_shield(run_dir) if shielded else None


def _run_entrants(args: argparse.Namespace, entrants: list[Entrant], steps: int) -> list[dict]:
    """One episode per entrant and evaluation world."""
    worlds = eval_worlds(args.scenarios, args.seeds, paper_episodes=args.paper_episodes)
    runs = []
    bar = tqdm(total=len(worlds) * len(entrants), desc="compare", disable=args.no_progress)
    for label, shield, make_policy in entrants:
        for scenario, init, seed in worlds:
            env = make_eval_env(scenario, init, steps, dynamics=args.dynamics, shield=shield)
            policy = make_policy(env)
            runs.append(
                run_policy_episode(
                    env, policy, seed=seed, steps=steps, label=label, dynamics=args.dynamics
                )
            )
            env.close()
            bar.update()
    bar.close()
    return runs


def _header(args: argparse.Namespace) -> str:
    """compare.md's first lines: the episodes, and each learned entrant's training budget."""
    budget = []
    for run_dir, label in ((args.ppo, "PPO"), (args.ppo_shield, "PPO + shield")):
        if run_dir is not None:
            info = json.loads((Path(run_dir) / "args.json").read_text())
            budget.append(f"{label}: {info.get('num_timesteps', '?')} agent-steps ({run_dir})")
    for run_dir in args.run:
        budget.append(f"{_budget(Path(run_dir))} ({run_dir})")
    for run_dirs in args.ensemble:
        steps = [_budget(Path(d)) for d in run_dirs]
        budget.append(f"ensemble: {', '.join(steps)} ({', '.join(map(str, run_dirs))})")
    if args.cloned is not None:
        info = json.loads((Path(args.cloned) / "args.json").read_text())
        budget.append(
            f"cloned: {info.get('bc_samples', '?'):.0f} expert agent-steps "
            f"({info.get('bc_episodes')} episodes), no PPO step ({args.cloned})"
        )
    return (
        f"Episodes of {args.duration:g} s, dynamics {args.dynamics}; paper worlds: "
        f"{args.paper_episodes} seed(s) each; random worlds: {args.seeds} seeds.\n"
        + "".join(f"- {b}\n" for b in budget)
    )


def _budget(run_dir: Path) -> str:
    """A run's training budget for compare.md's header."""
    if (run_dir / "args.json").exists():
        info = json.loads((run_dir / "args.json").read_text())
        return f"{info.get('num_timesteps', '?')} agent-steps"
    record = json.loads((run_dir / "config.json").read_text())
    return f"RLlib, {record.get('iterations', '?')} iterations"


if __name__ == "__main__":
    main()
