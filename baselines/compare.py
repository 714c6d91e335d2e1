"""Expert vs PPO vs PPO + shield on the paper's scenarios A-C and on seeded random worlds.

    python -m baselines.compare --ppo runs/ppo --ppo-shield runs/ppo-shield --seeds 20 \\
        --out runs/compare

Prints and writes DIR/compare.md (one row per policy and world group: RMS pixel errors,
collisions, disconnection and occluded steps, shield intervention rate), DIR/details.md (per UAV,
in the form of Table VI) and DIR/metrics.json (every episode in the schema of
``baselines/evaluate.py`` plus ``violations_per_1000_steps`` and ``shield_intervention_rate``).
The PPO runs are read from the output directories of ``python -m train.ppo``; a run trained with
``--shield`` is evaluated shielded. Episodes use evaluate's environment settings (detector noise
on; ``--dynamics`` defaults to the paper's single integrator, eq. (3), under which the shield's
guarantees hold).
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DT
from uavtrack_env.metrics import EpisodeRecorder

from . import evaluate

VIOLATIONS = ("collision", "disconnection", "occlusion")
Policy = Callable[[dict, dict], dict]


# ------------------------------------------------------------------ policies
class SB3Policy:
    """A trained SB3 model as ``policy(obs, infos) -> {agent: action}``, shared by all agents.

    Observations are normalised with the saved VecNormalize statistics when given; actions are
    the deterministic policy's (the distribution's mean).
    """

    def __init__(self, model: Any, obs_normalizer: Any | None = None) -> None:
        self.model = model
        self.obs_normalizer = obs_normalizer

    def __call__(self, obs: dict, infos: dict) -> dict[str, np.ndarray]:
        agents = list(obs)
        if not agents:
            return {}
        batch = np.stack([np.asarray(obs[a], np.float32) for a in agents])
        if self.obs_normalizer is not None:
            batch = self.obs_normalizer.normalize_obs(batch)
        actions, _ = self.model.predict(batch, deterministic=True)
        actions = np.clip(actions, -1.0, 1.0).astype(np.float32)
        return dict(zip(agents, actions, strict=True))


def load_run(run_dir: Path, cloned: bool = False) -> tuple[SB3Policy, dict]:
    """The final model of a ``train.ppo`` run directory and its saved arguments; with
    ``cloned``, its behaviour-cloned policy before any PPO step (checkpoint 0)."""
    from stable_baselines3 import PPO

    run_dir = Path(run_dir)
    model_path = run_dir / "model.zip"
    norm_path = run_dir / "vecnormalize.pkl"
    if cloned:
        model_path = run_dir / "checkpoints" / "ppo_0_steps.zip"
        norm_path = run_dir / "checkpoints" / "ppo_vecnormalize_0_steps.pkl"
    if not model_path.exists():
        raise ValueError(f"{model_path} not found: expected the output directory of train.ppo")
    args = json.loads((run_dir / "args.json").read_text())
    normalizer = None
    if norm_path.exists():
        with norm_path.open("rb") as f:  # a VecNormalize without its venv: normalize_obs only
            normalizer = pickle.load(f)
        normalizer.training = False
    return SB3Policy(PPO.load(model_path, device="cpu"), normalizer), args


# ------------------------------------------------------------------- episode
def _shield_flags(infos: dict, policy: Any) -> dict[str, bool] | None:
    """Whether the shield (wrapper) or the expert's own CBF-QP changed each agent's action."""
    flags = {a: bool(i["shield"]["active"]) for a, i in infos.items() if "shield" in i}
    if flags:
        return flags
    agents = getattr(policy, "agents", None)
    if isinstance(agents, dict) and getattr(policy, "use_cbf", False):
        return {
            a: bool(st.last_report is not None and st.last_report.active)
            for a, st in agents.items()
            if a in infos
        }
    return None


def run_policy_episode(
    env: Any,
    policy: Policy,
    *,
    seed: int,
    steps: int,
    label: str,
    dynamics: str,
    progress: bool = False,
) -> dict:
    """One episode of ``policy`` on ``env`` (a ParallelEnv, shielded or not) -> metrics dict.

    The dict has the keys of ``baselines/evaluate.py``'s metrics.json (``uavs`` from
    `EpisodeRecorder`, ``timing_ms``) plus ``violations_per_1000_steps`` (collision,
    disconnection and occlusion agent-steps per 1000 agent-steps), ``violation_steps`` (the raw
    counts) and ``shield_intervention_rate`` (fraction of agent-steps whose action the shield, or
    the expert's CBF-QP, changed; None without either). ``policy.reset()`` is called after the
    env's reset when it exists.
    """
    obs, infos = env.reset(seed=seed)
    if hasattr(policy, "reset"):
        policy.reset()
    raw = env.unwrapped
    rec = EpisodeRecorder(
        raw.possible_agents, DT, raw.config.cbf.theta_star, raw.layout.obstacle_centers
    )
    rec.record(infos)
    counts = dict.fromkeys(VIOLATIONS, 0)
    agent_steps, active, certified = 0, 0, 0
    env_time, policy_time = [], []
    slacks = getattr(policy, "slacks", None)
    for _ in tqdm(range(steps), desc=label, disable=not progress, leave=False):
        if not env.agents:
            break
        t0 = time.perf_counter()
        actions = policy(obs, infos)
        t1 = time.perf_counter()
        obs, _, _, _, infos = env.step(actions)
        env_time.append(time.perf_counter() - t1)
        policy_time.append(t1 - t0)
        rec.record(infos, slacks() if slacks else None)
        for info in infos.values():
            agent_steps += 1
            for k in VIOLATIONS:
                counts[k] += bool(info["violations"][k])
        flags = _shield_flags(infos, policy)
        if flags is not None:
            certified += len(flags)
            active += sum(flags.values())
    n = raw.config.n_uavs
    per_k = {k: 1000.0 * v / agent_steps if agent_steps else math.nan for k, v in counts.items()}
    return {
        "scenario": raw.config.scenario,
        "init": raw.config.init,
        "seed": seed,
        "duration_s": (rec.steps - 1) * DT,
        "policy": label,
        "dynamics": dynamics,
        "cbf": certified > 0 or bool(getattr(policy, "use_cbf", False)),
        "uavs": rec.summary(),
        "timing_ms": {
            "env": 1e3 * float(np.median(env_time)) / n if env_time else math.nan,
            "policy": 1e3 * float(np.median(policy_time)) / n if policy_time else math.nan,
        },
        "initial_conditions": {
            a: [*map(float, raw.layout.uav_positions[i][:2]), float(raw.layout.uav_yaws[i])]
            for i, a in enumerate(raw.possible_agents)
        },
        "violations_per_1000_steps": per_k,
        "violation_steps": counts,
        "agent_steps": agent_steps,
        "shield_intervention_rate": active / certified if certified else None,
    }


def eval_worlds(
    scenarios: list[str], seeds: int, first_seed: int = 0
) -> list[tuple[str, int, int]]:
    """(scenario, init, seed) of the evaluation set: both Table VI rows of each paper scenario
    (seed ``first_seed``), then ``seeds`` random worlds with seeds first_seed + 1000 + k (kept
    apart from training's small seeds)."""
    worlds = [(s, i, first_seed) for s in scenarios for i in (0, 1)]
    return worlds + [("random", 0, first_seed + 1000 + k) for k in range(seeds)]


def env_args(dynamics: str = "integrator", noiseless: bool = False) -> argparse.Namespace:
    """The argument namespace evaluate's helpers read (its defaults; given dynamics/noise).

    The occlusion rows stay the env's defaults (n-dot = 0, the boxes' vertical axes), under
    which the README's RL comparison was measured, for the expert and the shield alike.
    """
    args = evaluate.parse_args(
        ["--dynamics", dynamics, "--no-figures", "--no-progress"]
        + ["--occlusion-model", "paper", "--occlusion-point", "axis"]
    )
    args.no_noise = noiseless
    return args


def make_eval_env(
    scenario: str, init: int, steps: int, args: argparse.Namespace, shield: bool, **env_kw
) -> Any:
    """evaluate's environment for one world, wrapped in `CBFShield` when ``shield``."""
    kw = evaluate._env_kwargs(args, scenario, init, steps)
    kw["render_mode"] = None
    kw.update(env_kw)
    env = uavtrack_v0.parallel_env(**kw)
    if shield:
        import warnings

        from uavtrack_env.wrappers import CBFShield

        with warnings.catch_warnings():  # best-effort warning under 'lag' dynamics
            warnings.simplefilter("ignore")
            env = CBFShield(env)
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
    ap.add_argument("--duration", type=float, default=60.0, help="episode length in s")
    ap.add_argument("--dynamics", default="integrator", choices=["integrator", "lag"])
    ap.add_argument("--no-expert", action="store_true", help="skip the expert (slowest)")
    ap.add_argument(
        "--planner",
        default="paper",
        choices=["paper", "tuned"],
        help="the expert's NMPC: 'paper' (the expert train.bc clones; the README's comparisons) "
        "or 'tuned' (baselines.evaluate's default)",
    )
    ap.add_argument("--out", type=Path, default=Path("runs/compare"))
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    args = ap.parse_args(argv)
    if args.seeds < 0 or not math.isfinite(args.duration) or args.duration <= 0:
        ap.error("--seeds must be >= 0 and --duration > 0")
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
    eargs = env_args(args.dynamics)
    steps = max(1, round(args.duration / DT))
    entrants: list[tuple[str, bool, Callable[[Any], Policy]]] = []
    if not args.no_expert:
        eargs.policy, eargs.planner = "expert", args.planner
        entrants.append(("expert", False, lambda env: evaluate._make_policy(eargs, env)))
    for run_dir, label in ((args.ppo, "PPO"), (args.ppo_shield, "PPO + shield")):
        if run_dir is not None:
            policy, run_args = load_run(run_dir)
            entrants.append((label, bool(run_args["shield"]), lambda env, p=policy: p))
    if args.cloned is not None:
        policy, run_args = load_run(args.cloned, cloned=True)
        label = "cloned + shield" if run_args["shield"] else "cloned"
        entrants.append((label, bool(run_args["shield"]), lambda env, p=policy: p))
    if not entrants:
        raise SystemExit(
            "nothing to compare: give --ppo, --ppo-shield or --cloned (or drop --no-expert)"
        )
    worlds = eval_worlds(args.scenarios, args.seeds)
    runs = []
    bar = tqdm(total=len(worlds) * len(entrants), desc="compare", disable=args.no_progress)
    for label, shielded, make_policy in entrants:
        for scenario, init, seed in worlds:
            env = make_eval_env(scenario, init, steps, eargs, shielded)
            env.reset(seed=seed)  # the expert is built from a reset env (its obstacle map)
            policy = make_policy(env)
            runs.append(
                run_policy_episode(
                    env, policy, seed=seed, steps=steps, label=label, dynamics=args.dynamics
                )
            )
            env.close()
            bar.update()
    bar.close()
    md = comparison_table(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    budget = []
    for run_dir, label in ((args.ppo, "PPO"), (args.ppo_shield, "PPO + shield")):
        if run_dir is not None:
            info = json.loads((Path(run_dir) / "args.json").read_text())
            budget.append(f"{label}: {info.get('num_timesteps', '?')} agent-steps ({run_dir})")
    if args.cloned is not None:
        info = json.loads((Path(args.cloned) / "args.json").read_text())
        budget.append(
            f"cloned: {info.get('bc_samples', '?'):.0f} expert agent-steps "
            f"({info.get('bc_episodes')} episodes), no PPO step ({args.cloned})"
        )
    header = (
        f"Episodes of {args.duration:g} s, dynamics {args.dynamics}; random worlds: "
        f"{args.seeds} seeds.\n" + "".join(f"- {b}\n" for b in budget)
    )
    (args.out / "compare.md").write_text(header + "\n" + md + "\n")
    (args.out / "details.md").write_text(evaluate.table(runs) + "\n")
    (args.out / "metrics.json").write_text(json.dumps(runs, indent=2))
    print(header)
    print(md)
    print(f"\nwrote {args.out}/ (compare.md, details.md, metrics.json)")
    return runs


if __name__ == "__main__":
    main()
