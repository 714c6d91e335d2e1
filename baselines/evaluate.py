"""Evaluate the expert (UKF -> NMPC -> CBF-QP) or a baseline policy; reproduce Tables V-VI.

    python -m baselines.evaluate --scenario A --init 0 --out runs/A0       # one Table VI row
    python -m baselines.evaluate --all --out runs/table6                    # all six rows
                                                   # (in parallel: --workers, default all CPUs)
    python -m baselines.evaluate --scenario random --seed 3 --out runs/r3   # a random world
    python -m baselines.evaluate --scenario A --no-cbf --out runs/A0-nocbf  # ablation
    python -m baselines.evaluate --all --preset paper --out runs/paper      # the paper's equations
    python -m baselines.evaluate --scenario A --set cbf.gamma_o=0.5         # Fig. 20

Writes DIR/config.json (the resolved env and expert settings, preset, command, commit,
versions), DIR/metrics.json, DIR/table.md, DIR/frame.png and the figures of Figs. 12-20.
The world: 60 s at 80 Hz, velocity-lag dynamics and detector noise on (the paper's figures come
from a simulated quadrotor and a real detector). The expert: ``--preset`` (default 'tuned';
`uavtrack_env.presets`) with ``--set`` overrides.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from tqdm import tqdm

from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DT, DetectorConfig
from uavtrack_env.expert import ExpertPolicy, usable_cpus
from uavtrack_env.policies import HoverPolicy, RandomPolicy, VisualServoPolicy
from uavtrack_env.presets import (
    ExpertConfig,
    add_preset_arguments,
    expert_config,
    expert_config_from,
)
from uavtrack_env.provenance import cli_command, config_record
from uavtrack_env.runner import Policy, run_episode
from uavtrack_env.wrappers.video import RecordVideo

from .paper_results import TABLE_VI

POLICIES = ("expert", "servo", "hover", "random")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m baselines.evaluate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--scenario", default="A", choices=["A", "B", "C", "random"])
    ap.add_argument("--init", type=int, default=0, choices=[0, 1], help="Table VI row (0 or 1)")
    ap.add_argument("--all", action="store_true", help="run the six rows of Table VI")
    ap.add_argument("--seed", type=int, default=0, help="env seed (noise; the random world)")
    ap.add_argument("--duration", type=float, default=60.0, help="episode length in s")
    ap.add_argument("--policy", default="expert", choices=POLICIES)
    ap.add_argument("--dynamics", default="lag", choices=["integrator", "lag"])
    ap.add_argument("--no-noise", action="store_true", help="noiseless detector")
    add_preset_arguments(ap)
    ap.add_argument("--no-cbf", action="store_true", help="expert without the CBF-QP (use_cbf)")
    ap.add_argument(
        "--jit",
        action="store_true",
        help="JIT-compile every NMPC solver, the cold-start and rescue Ipopt too (nmpc.jit=True; "
        "by default only the per-step solver is compiled, when a C compiler is found; the first "
        "build on a machine takes 30-80 s, later ones reuse the cached objects)",
    )
    ap.add_argument("--out", type=Path, default=Path("runs/latest"))
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument(
        "--video",
        action="store_true",
        help="also write the episode as OUT/video-episode-0.mp4 (overview and cameras, 20 fps; "
        "the video extra)",
    )
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    ap.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes for --all's six rows (default: the CPUs this process may use, at most "
        "6); the results do not depend on it, the timings do",
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="UAVs the expert plans at once, their NMPC solves in parallel (default: one per UAV, "
        "at most the CPUs per process); the results do not depend on it, the timings do",
    )
    args = ap.parse_args(argv)
    if not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.workers is None:
        args.workers = min(6, usable_cpus())
    elif args.workers < 1:
        ap.error(f"--workers must be an integer >= 1, got {args.workers}")
    if args.threads is not None and args.threads < 1:
        ap.error(f"--threads must be an integer >= 1, got {args.threads}")
    return args


def world_kwargs(
    scenario: str,
    init: int,
    steps: int,
    *,
    dynamics: str = "lag",
    noise: bool = True,
    render: bool = True,
) -> dict[str, Any]:
    """The env keyword arguments of an evaluation world: the paper's settings (r = -c, a
    collision ends the episode) with these fields."""
    kw: dict[str, Any] = {
        "defaults": "paper",
        "scenario": scenario,
        "init": init,
        "max_cycles": steps,
        "render_mode": "rgb_array" if render else None,
        "dynamics": {"model": dynamics},
    }
    if not noise:
        kw["detector"] = DetectorConfig.noiseless()
    return kw


def expert_settings(preset: str, assignments: list[str], no_cbf: bool, jit: bool) -> ExpertConfig:
    """The CLI's expert: the preset, ``--set`` overrides, then ``--no-cbf`` and ``--jit``."""
    cfg = expert_config_from(preset, assignments)
    extra: dict[str, Any] = {}
    if no_cbf:
        extra["use_cbf"] = False
    if jit:
        extra["nmpc"] = {"jit": True}
    return expert_config(cfg, **extra)


def make_policy(name: str, env: Any, expert: ExpertConfig, threads: int | None = None) -> Policy:
    """The policy ``name`` (one of `POLICIES`) for ``env``'s agents (``threads``: the expert's,
    `ExpertPolicy`)."""
    if name == "expert":
        return ExpertPolicy(env.possible_agents, env.unwrapped.config, expert, threads)
    base = {"servo": VisualServoPolicy, "hover": HoverPolicy, "random": RandomPolicy}[name]()
    return lambda obs, infos: {a: base(a, obs[a]) for a in obs}


def evaluate_world(
    scenario: str,
    init: int,
    out: Path,
    *,
    seed: int = 0,
    duration: float = 60.0,
    dynamics: str = "lag",
    noise: bool = True,
    policy: str = "expert",
    expert: ExpertConfig | None = None,
    preset: str | None = None,
    figures: bool = True,
    video: bool = False,
    progress: bool = False,
    command: str | None = None,
    threads: int | None = None,
) -> dict:
    """One episode; writes config.json, metrics.json, table.md, frame.png and figures to ``out``
    (and with ``video``, the episode as ``out/video-episode-0.mp4``: `RecordVideo`)."""
    expert = expert or expert_config(preset)
    steps = max(1, round(duration / DT))
    render = figures or video
    env = uavtrack_v0.parallel_env(
        **world_kwargs(scenario, init, steps, dynamics=dynamics, noise=noise, render=render)
    )
    if video:
        env = RecordVideo(env, out, name_prefix="video")
    agent = make_policy(policy, env, expert, threads)
    label = f"{scenario}{init}" if scenario != "random" else f"seed {seed}"
    result = run_episode(
        env,
        agent,
        seed=seed,
        steps=steps,
        theta_star=expert.cbf.theta_star,
        label=label,
        progress=progress,
    )
    record = config_record(preset, env.config, expert, command, policy=policy)
    metrics = {**result.metrics, "policy": policy, "preset": preset, "config": record}
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(record, indent=2))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "table.md").write_text(table([metrics]) + "\n")
    if figures:
        import matplotlib.pyplot as plt

        from uavtrack_env.plotting import all_figures

        plt.imsave(out / "frame.png", env.render())
        cbf = expert.cbf.resolve(
            env.config.violations.r_s, env.config.comms.r_c, env.config.uav_radius
        )
        all_figures(
            result.recorder,
            env.config,
            cbf,
            env.layout.references,
            env.layout.obstacle_half_extents,
            out,
        )
    env.close()
    return metrics


def evaluate_rows(
    rows: list[tuple[str, int]], out: Path, workers: int, common: dict[str, Any]
) -> list[dict]:
    """`evaluate_world` of each (scenario, init) into OUT/<row>, in ``workers`` processes; the
    metrics in the order of ``rows`` (each row is seeded on its own: the same in any process)."""
    progress = common["progress"]
    if workers <= 1 or len(rows) <= 1:
        return [
            evaluate_world(s, i, out / f"{s}{i}", **common)
            for s, i in tqdm(rows, desc="Table VI", disable=not progress)
        ]
    procs = min(workers, len(rows))
    # one bar for the rows, not one per episode; the processes share the CPUs
    quiet = {**common, "progress": False}
    if quiet.get("threads") is None:
        quiet["threads"] = max(1, usable_cpus() // procs)
    spawn = multiprocessing.get_context("spawn")  # no PyBullet or solver state is inherited
    with ProcessPoolExecutor(procs, mp_context=spawn) as pool:
        futures = [pool.submit(evaluate_world, s, i, out / f"{s}{i}", **quiet) for s, i in rows]
        for _ in tqdm(
            as_completed(futures), total=len(rows), desc="Table VI", disable=not progress
        ):
            pass
        return [f.result() for f in futures]


def table(runs: list[dict], paper: bool = False) -> str:
    """A markdown table in the form of Table VI (with the paper's RMS errors if ``paper``).

    Occlusion is Y when no obstacle ever hid any of the car's 12 ray-cast points from that UAV
    (an occlusion-free image; the env's violation, detection lost, needs more than half hidden).
    Beside the paper's columns: the least occlusion angle theta of (38) over N_oi (theta* = 30
    deg, obstacle centres) and the largest share of the car's points hidden.
    """
    yn = {True: "Y", False: "N"}
    head = (
        "| Scenario | UAV | Initial (x, y, heading) | Occlusion | Connectivity | Collision "
        "| RMS U (px) | RMS V (px) |"
    )
    sep = "|---|---|---|---|---|---|---|---|"
    if paper:
        head += " paper U | paper V |"
        sep += "---|---|"
    head += " min theta (deg) | max hidden |"
    sep += "---|---|"
    lines = [head, sep]
    for m in runs:
        for i, (agent, r) in enumerate(m["uavs"].items()):
            x, y, h = m["initial_conditions"][agent]
            row = (
                f"| {m['scenario']}{m['init'] if m['scenario'] != 'random' else ''} | {i + 1} "
                f"| ({x:g}, {y:g}, {h:g}) | {yn[r['occlusion_ok']]} | {yn[r['connectivity_ok']]} "
                f"| {yn[r['collision_ok']]} | {r['rms_u_px']:.2f} | {r['rms_v_px']:.2f} |"
            )
            if paper:
                pu, pv = TABLE_VI[(m["scenario"], m["init"])][i]
                row += f" {pu:.2f} | {pv:.2f} |"
            hidden = 100 * r["max_blocked_fraction"]
            row += f" {r['min_occlusion_angle_deg']:.1f} | {hidden:.0f} % |"
            lines.append(row)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    expert = expert_settings(args.preset, args.set, args.no_cbf, args.jit)
    common = {
        "seed": args.seed,
        "duration": args.duration,
        "dynamics": args.dynamics,
        "noise": not args.no_noise,
        "policy": args.policy,
        "expert": expert,
        "preset": args.preset,
        "figures": not args.no_figures,
        "video": args.video,
        "progress": not args.no_progress,
        "command": cli_command("baselines.evaluate", argv),
        "threads": args.threads,
    }
    if args.all:
        rows = [(s, i) for s in ("A", "B", "C") for i in (0, 1)]
        runs = evaluate_rows(rows, args.out, args.workers, common)
        md = table(runs, paper=True)
        (args.out / "table.md").write_text(md + "\n")
        (args.out / "metrics.json").write_text(json.dumps(runs, indent=2))
        (args.out / "config.json").write_text(json.dumps(runs[0]["config"], indent=2))
    else:
        m = evaluate_world(args.scenario, args.init, args.out, **common)
        md = table([m], paper=args.scenario != "random")
        print(
            f"real time x{m['real_time_factor']:.2f} after a {m['startup_s']:.1f} s first step; "
            "timing (ms, median per UAV-step): "
            + ", ".join(f"{k} {v:.3f}" for k, v in m["timing_ms"].items())
        )
    print(md)
    print(f"\nwrote {args.out}/ (config.json, metrics.json, table.md, figures)")


if __name__ == "__main__":
    main()
