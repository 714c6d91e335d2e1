"""Soak: many resets and steps in one process, every value finite, memory flat, clients freed.

Phase 1 steps one ParallelEnv (random world, n = 3, random actions) for ``--steps`` steps over
``--resets`` episodes, checking that every observation, reward and info value is finite, and
prints the process's resident memory (RSS) after the first episode and at the end. Phase 2 does
the same for ``vector_env(num_envs=16)`` (random actions in [-1.2, 1.2], 200-step episodes, so
its worlds reset themselves many times) for ``--vector-steps`` agent-steps. Phase 3 creates and
closes ``--envs`` envs (and drops as many unclosed ones for the garbage collector) and counts the
PyBullet clients still connected.

Run: python benchmarks/soak.py [--steps 1000000] [--resets 1000] [--vector-steps 1000000]
[--envs 500]
"""

from __future__ import annotations

import argparse
import gc
import math
import resource
import time

import numpy as np
import pybullet as p
from tqdm import tqdm

from uavtrack_env import uavtrack_v0


def _rss_mb() -> float:
    """Resident set size of this process (MB), from /proc (Linux)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def _finite(tree) -> bool:
    """Every float in a nest of dicts, tuples and arrays is finite."""
    if isinstance(tree, dict):
        return all(_finite(v) for v in tree.values())
    if isinstance(tree, tuple):
        return all(_finite(v) for v in tree)
    if isinstance(tree, float | np.floating):
        return math.isfinite(tree)
    if isinstance(tree, np.ndarray) and tree.dtype.kind == "f":
        return bool(np.isfinite(tree).all())
    return True


def soak_steps(steps: int, resets: int, seed: int) -> None:
    env = uavtrack_v0.parallel_env(scenario="random", terminate_on_collision="agent")
    per_episode = max(1, steps // resets)
    rng = np.random.default_rng(seed)
    rss0, done, episodes, t0 = None, 0, 0, time.perf_counter()
    with tqdm(total=steps, unit="step") as bar:
        while done < steps:
            if not _finite(env.reset(seed=seed + episodes)):
                raise RuntimeError(f"a non-finite value at the reset of episode {episodes}")
            for _ in range(per_episode):
                if not env.agents or done >= steps:
                    break
                acts = {a: rng.uniform(-1, 1, 4).astype(np.float32) for a in env.agents}
                if not _finite(env.step(acts)):
                    raise RuntimeError(f"a non-finite value at episode {episodes}, step {done}")
                done += 1
                bar.update()
            episodes += 1
            if rss0 is None:
                rss0 = _rss_mb()
    env.close()
    wall = time.perf_counter() - t0
    print(
        f"{done} steps over {episodes} resets in {wall:.0f} s ({done / wall:.0f} steps/s); "
        f"RSS after the first episode {rss0:.1f} MB, at the end {_rss_mb():.1f} MB "
        f"(growth {_rss_mb() - rss0:+.1f} MB)"
    )


def soak_vector(agent_steps: int, seed: int, worlds: int = 16) -> None:
    env = uavtrack_v0.vector_env(
        worlds, scenario="random", max_cycles=200, terminate_on_collision="agent"
    )
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    rss0, done, resets, t0 = None, 0, 0, time.perf_counter()
    with tqdm(total=agent_steps, unit="agent-step") as bar:
        while done < agent_steps:
            a = rng.uniform(-1.2, 1.2, env.action_space.shape)
            out = env.step(a)
            if not _finite(out):
                raise RuntimeError(f"a non-finite value after {done} agent-steps")
            infos = out[-1]
            rows = int(infos["active"].sum())
            done += rows
            resets += int(infos.get("_final_obs", np.zeros(1, bool)).sum())
            bar.update(rows)
            if rss0 is None and resets:
                rss0 = _rss_mb()
    env.close()
    wall = time.perf_counter() - t0
    if rss0 is None:
        raise SystemExit(f"no world reset in {done} agent-steps: pass more --vector-steps")
    print(
        f"vector_env({worlds}): {done} agent-steps, {resets} world resets in {wall:.0f} s "
        f"({done / wall:.0f} agent-steps/s); RSS after the first reset {rss0:.1f} MB, at the "
        f"end {_rss_mb():.1f} MB (growth {_rss_mb() - rss0:+.1f} MB)"
    )


def soak_clients(envs: int) -> None:
    cids = []
    for k in range(envs):
        env = uavtrack_v0.parallel_env(scenario="random")
        env.reset(seed=k)
        cids.append(env.unwrapped.world.cid)
        env.close()
        dropped = uavtrack_v0.parallel_env(scenario="random")  # never closed
        cids.append(dropped.unwrapped.world.cid)
        del dropped
    gc.collect()
    still = sum(p.getConnectionInfo(physicsClientId=c)["isConnected"] for c in cids)
    print(f"{envs} envs closed and {envs} dropped: {still} PyBullet clients still connected")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--resets", type=int, default=1000)
    ap.add_argument("--vector-steps", type=int, default=1_000_000)
    ap.add_argument("--envs", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    soak_steps(args.steps, args.resets, args.seed)
    soak_vector(args.vector_steps, args.seed)
    soak_clients(args.envs)


if __name__ == "__main__":
    main()
