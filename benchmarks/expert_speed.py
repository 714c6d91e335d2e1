"""Median time of each expert stage and of the whole 3-UAV expert step, scenario A.

    python benchmarks/expert_speed.py [--steps 800] [--presets tuned paper] [--solvers sqp ipopt]
        [--jit] [--interpreted] [--threads 1 3]

Runs the closed loop in `baselines.evaluate`'s world (lag dynamics, detector noise on) and prints
per-UAV medians of the UKF, NMPC and CBF-QP, the whole expert step for 3 UAVs, the env step, and
the real-time factor at 80 Hz of expert alone and of expert + env (from the medians, and from the
wall time of the whole episode after its first step), for each preset
(`uavtrack_env.presets.PRESETS`) and NMPC solver. Rows: the default (`NMPCConfig.jit` None: the
per-step solver compiled when a C compiler is found), ``+jit`` (every solver compiled) and
``+interp`` (nothing compiled); ``tN``: the expert's planning threads (`ExpertPolicy`; default
one per UAV, at most the CPUs).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

from baselines import evaluate
from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DT
from uavtrack_env.expert import ExpertPolicy, default_threads, usable_cpus
from uavtrack_env.presets import PRESETS, expert_config


def run(
    preset: str, solver: str, steps: int, jit: bool | None = None, threads: int | None = None
) -> dict[str, float]:
    env = uavtrack_v0.parallel_env(**evaluate.world_kwargs("A", 0, steps, render=False))
    obs, infos = env.reset(seed=0)
    config = expert_config(preset, nmpc={"solver": solver, "jit": jit})
    expert = ExpertPolicy.from_env(env, config, threads)
    whole, env_t = [], []
    start = None
    while env.agents:
        if len(whole) == 1:
            start = time.perf_counter()  # after the first step: builds and the cold solve
        t0 = time.perf_counter()
        actions = expert(obs, infos)
        t1 = time.perf_counter()
        obs, _, _, _, infos = env.step(actions)
        whole.append(t1 - t0)
        env_t.append(time.perf_counter() - t1)
    env.close()
    expert.close()
    med = {k: 1e3 * statistics.median(v) for k, v in expert.timings.items()}
    med["expert_step_3uav"] = 1e3 * statistics.median(whole)
    med["env_step"] = 1e3 * statistics.median(env_t)
    med["wall_rt"] = (len(whole) - 1) * DT / (time.perf_counter() - start)
    return med


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--presets", nargs="+", default=["tuned", "paper"], choices=list(PRESETS))
    ap.add_argument("--solvers", nargs="+", default=["sqp", "ipopt"])
    ap.add_argument(
        "--jit", action="store_true", help="also each solver with nmpc.jit=True (needs gcc)"
    )
    ap.add_argument(
        "--interpreted", action="store_true", help="also each solver with nmpc.jit=False"
    )
    ap.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=[None],
        help="the expert's planning threads, one row each (default: one per UAV, at most the CPUs)",
    )
    args = ap.parse_args()
    print(
        f"machine: {platform.machine()}, python {platform.python_version()}, {args.steps} steps, "
        f"{usable_cpus()} CPUs, default threads {default_threads(3)}"
    )
    period = 1e3 / 80.0
    rows = {}
    for p in args.presets:
        for s in args.solvers:
            for t in args.threads:
                name = f"{p}/{s}" + (f" t{t}" if t else "")
                rows[name] = run(p, s, args.steps, threads=t)
                if args.jit:
                    rows[f"{name}+jit"] = run(p, s, args.steps, jit=True, threads=t)
                if args.interpreted:
                    rows[f"{name}+interp"] = run(p, s, args.steps, jit=False, threads=t)
    cols = ["ukf", "nmpc", "qp", "expert_step_3uav", "env_step"]
    print(
        f"{'preset/solver':>16} " + " ".join(f"{c:>17}" for c in cols) + f" {'RT x (expert)':>14}"
        f" {'RT x (+env)':>12} {'RT x (wall)':>12}"
    )
    for s, m in rows.items():
        rt = period / m["expert_step_3uav"]
        rt_env = period / (m["expert_step_3uav"] + m["env_step"])
        print(
            f"{s:>16} " + " ".join(f"{m[c]:>14.3f} ms" for c in cols) + f" {rt:>14.2f}"
            f" {rt_env:>12.2f} {m['wall_rt']:>12.2f}"
        )
    for p in args.presets:
        ipopt = rows.get(f"{p}/ipopt")
        if ipopt is None:
            continue
        for s, m in rows.items():
            if s.startswith(f"{p}/") and s != f"{p}/ipopt":
                print(f"NMPC {p}/ipopt / {s}: {ipopt['nmpc'] / m['nmpc']:.1f}x")


if __name__ == "__main__":
    main()
