"""Env steps per second with random actions, random world, detector on, rendering off.

    python benchmarks/env_speed.py [--steps 2000] [--repeats 5] [--n 3 10 30] [--vector 64]

Prints, per team size, the median over repeats of steps/s, agent-steps/s and us per agent-step,
the real-time factor at 80 Hz and the per-agent cost relative to n = 3; then the same for
``vector_env(num_envs=K)`` at each ``--vector-n`` (array infos, autoreset) beside the ParallelEnv,
and ``VectorCBFShield`` over it (n = 3) beside the bare vector env; with ``--exact``, both envs at
n = 3 with and without the skipped PyBullet queries (`uavtrack_env.broadphase`).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np

from uavtrack_env import uavtrack_v0
from uavtrack_env.config import MAX_EPISODE_STEPS
from uavtrack_env.wrappers import VectorCBFShield


def steps_per_second(n: int, steps: int, seed: int, skip: bool = True) -> float:
    env = uavtrack_v0.parallel_env(
        scenario="random",
        n_uavs=n,
        max_cycles=MAX_EPISODE_STEPS,
        terminate_on_collision="agent",
        skip_proven_queries=skip,
    )
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    elapsed, done = 0.0, 0
    while done < steps:
        if not env.agents:
            env.reset()
        actions = {a: rng.uniform(-0.3, 0.3, 4).astype(np.float32) for a in env.agents}
        t0 = time.perf_counter()
        env.step(actions)
        elapsed += time.perf_counter() - t0
        done += 1
    env.close()
    return steps / elapsed


def vector_agent_steps_per_second(
    k: int, steps: int, seed: int, n: int = 3, shield: bool = False, skip: bool = True
) -> float:
    """Agent-steps/s of ``vector_env(num_envs=k)`` with n UAVs (rows that took part in a step),
    wrapped in `VectorCBFShield` (preset ``tuned``) with ``shield``; ``skip``:
    `EnvConfig.skip_proven_queries`."""
    env = uavtrack_v0.vector_env(
        k,
        scenario="random",
        n_uavs=n,
        max_cycles=MAX_EPISODE_STEPS,
        terminate_on_collision="agent",
        skip_proven_queries=skip,
    )
    if shield:
        env = VectorCBFShield(env)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    # One untimed step: a process's first shielded step loads the onboard kernels from numba's
    # cache (~0.2 s, `kernels.onboard_kernels`), which would weigh on a short run.
    env.step(np.zeros(env.action_space.shape, np.float32))
    elapsed, rows = 0.0, 0
    for _ in range(steps):
        actions = rng.uniform(-0.3, 0.3, env.action_space.shape).astype(np.float32)
        t0 = time.perf_counter()
        infos = env.step(actions)[-1]
        elapsed += time.perf_counter() - t0
        rows += int(infos["active"].sum())
    env.close()
    return rows / elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--n", type=int, nargs="+", default=[3, 10, 30])
    ap.add_argument("--vector", type=int, default=64, help="worlds of the vector_env (0: skip)")
    ap.add_argument(
        "--vector-n", type=int, nargs="+", default=[3, 30], help="UAVs per vector_env world"
    )
    ap.add_argument(
        "--exact",
        action="store_true",
        help="also n = 3 with every ray and contact query sent to PyBullet "
        "(skip_proven_queries=False), beside the default",
    )
    args = ap.parse_args()
    print(
        f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}"
    )
    print(
        f"{'n':>4} {'steps/s':>9} {'agent-steps/s':>14} {'us/agent-step':>14} {'x real time':>12} "
        f"{'per-agent vs n=3':>17}"
    )
    base = None
    for n in args.n:
        rates = [steps_per_second(n, args.steps, seed) for seed in range(args.repeats)]
        sps = statistics.median(rates)
        per_agent = 1e6 / (sps * n)
        base = base or per_agent
        print(
            f"{n:>4} {sps:>9.0f} {sps * n:>14.0f} {per_agent:>14.1f} {sps / 80:>12.1f} "
            f"{per_agent / base:>17.2f}"
        )
    if args.vector:
        k = args.vector
        par = statistics.median(3 * steps_per_second(3, args.steps, s) for s in range(args.repeats))
        base = None
        for n in args.vector_n:
            vec = statistics.median(
                vector_agent_steps_per_second(k, max(1, 3 * args.steps // (k * n)), seed, n)
                for seed in range(args.repeats)
            )
            base = base or 1e6 / vec
            print(
                f"vector_env(num_envs={k}), n = {n}: {vec:.0f} agent-steps/s ({1e6 / vec:.1f} us "
                f"per agent-step, {1e6 / vec / base:.2f} x n = {args.vector_n[0]}'s); "
                f"ParallelEnv n = 3: {par:.0f}, ratio {vec / par:.2f}"
            )
        steps = max(1, args.steps // k)
        bare = statistics.median(
            vector_agent_steps_per_second(k, steps, s) for s in range(args.repeats)
        )
        shielded = statistics.median(
            vector_agent_steps_per_second(k, steps, s, shield=True) for s in range(args.repeats)
        )
        print(
            f"VectorCBFShield(vector_env(num_envs={k})), n = 3: {shielded:.0f} agent-steps/s "
            f"({1e6 / shielded:.1f} us per agent-step); bare {bare:.0f}, "
            f"ratio {shielded / bare:.2f}"
        )
    if args.exact and args.vector:
        for skip in (True, False):
            par = statistics.median(
                3 * steps_per_second(3, args.steps, s, skip) for s in range(args.repeats)
            )
            vec = statistics.median(
                vector_agent_steps_per_second(k, max(1, args.steps // k), s, 3, skip=skip)
                for s in range(args.repeats)
            )
            print(
                f"skip_proven_queries={skip}, n = 3: ParallelEnv {par:.0f}, "
                f"vector_env({k}) {vec:.0f} agent-steps/s"
            )


if __name__ == "__main__":
    main()
