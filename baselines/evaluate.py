"""Run one episode and report the metrics of Tables V-VI.

    python -m baselines.evaluate --scenario A --init 0 --out runs/A0

Writes DIR/metrics.json, DIR/table.md and DIR/frame.png (the last rendered frame).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DT
from uavtrack_env.metrics import EpisodeRecorder
from uavtrack_env.policies import HoverPolicy, RandomPolicy, VisualServoPolicy

POLICIES = {"servo": VisualServoPolicy, "hover": HoverPolicy, "random": RandomPolicy}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenario", default="A", choices=["A", "B", "C", "random"])
    ap.add_argument("--init", type=int, default=0, choices=[0, 1], help="Table VI row")
    ap.add_argument("--seed", type=int, default=0, help="env seed (noise, random world)")
    ap.add_argument("--duration", type=float, default=60.0, help="episode length (s)")
    ap.add_argument("--policy", default="servo", choices=sorted(POLICIES))
    ap.add_argument("--dynamics", default="integrator", choices=["integrator", "lag"])
    ap.add_argument("--out", type=Path, default=Path("runs/latest"))
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap.parse_args(argv)


def run_episode(args: argparse.Namespace) -> dict:
    steps = max(1, round(args.duration / DT))
    env = uavtrack_v0.parallel_env(
        scenario=args.scenario,
        init=args.init,
        max_cycles=steps,
        render_mode="rgb_array",
        dynamics={"model": args.dynamics},
    )
    policy = POLICIES[args.policy]()
    obs, infos = env.reset(seed=args.seed)
    rec = EpisodeRecorder(env.possible_agents, DT, env.config.cbf.theta_star)
    rec.record(infos)
    env_time = []
    for _ in tqdm(range(steps), desc=f"{args.scenario}{args.init}", disable=args.no_progress):
        if not env.agents:
            break
        actions = {a: policy(a, obs[a]) for a in env.agents}
        t0 = time.perf_counter()
        obs, _, _, _, infos = env.step(actions)
        env_time.append(time.perf_counter() - t0)
        rec.record(infos)
    args.out.mkdir(parents=True, exist_ok=True)
    frame = env.render()
    import matplotlib.pyplot as plt

    plt.imsave(args.out / "frame.png", frame)
    n = env.config.n_uavs
    metrics = {
        "scenario": args.scenario,
        "init": args.init,
        "seed": args.seed,
        "duration_s": rec.steps * DT,
        "policy": args.policy,
        "dynamics": args.dynamics,
        "uavs": rec.summary(),
        "timing_ms": {"env": 1e3 * float(np.median(env_time)) / n if env_time else math.nan},
        "initial_conditions": {
            a: [*map(float, env.layout.uav_positions[i][:2]), float(env.layout.uav_yaws[i])]
            for i, a in enumerate(env.possible_agents)
        },
    }
    env.close()
    return metrics


def table(metrics: dict) -> str:
    """A markdown table in the form of Table VI."""
    yn = {True: "Y", False: "N"}
    lines = [
        "| Scenario | UAV | Initial (x, y, heading) | Occlusion | Connectivity | Collision "
        "| RMS U (px) | RMS V (px) | RMS depth (m) | detected |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, (agent, m) in enumerate(metrics["uavs"].items()):
        x, y, h = metrics["initial_conditions"][agent]
        lines.append(
            f"| {metrics['scenario']}{metrics['init']} | {i + 1} | ({x:g}, {y:g}, {h:g}) "
            f"| {yn[m['occlusion_ok']]} | {yn[m['connectivity_ok']]} | {yn[m['collision_ok']]} "
            f"| {m['rms_u_px']:.2f} | {m['rms_v_px']:.2f} | {m['rms_depth_m']:.2f} "
            f"| {m['detected_fraction']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    metrics = run_episode(args)
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    md = table(metrics)
    (args.out / "table.md").write_text(md + "\n")
    print(md)
    print(f"\nwrote {args.out}/metrics.json, table.md, frame.png")


if __name__ == "__main__":
    main()
