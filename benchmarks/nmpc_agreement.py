"""The expert's NMPC against a cold Ipopt on the problems of a closed-loop episode.

    python benchmarks/nmpc_agreement.py [--scenario C] [--steps 1600] [--every 20]
        [--set tol=1e-4 ...]

Runs the expert (default preset, `baselines.evaluate`'s world: lag dynamics, noise on) and, on
every ``--every``-th solve and on every solve slower than 30 ms, solves the same problem (state,
error signal, safety rows) once more from a cold start with Ipopt (tol `NMPCConfig.ipopt_tol`).
Prints the largest difference of the first inputs |u - u_ipopt| (m/s, rad/s) over the checks, how
many exceed 1e-3, and the solve-time distribution of the expert's NMPC. ``--set`` overrides
`NMPCConfig` fields (numbers or names).
"""

from __future__ import annotations

import argparse
import copy
import time
from dataclasses import replace

import numpy as np

from baselines import evaluate
from uavtrack_env import uavtrack_v0
from uavtrack_env.control import NMPC
from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.presets import DEFAULT_PRESET, expert_config

SLOW_S = 0.03


def _parse(value: str):
    try:
        return int(value)
    except ValueError:
        try:
            return float(value)
        except ValueError:
            return value


def _checked(nmpc: NMPC, every: int, regular: list, slow: list, times: list):
    """``nmpc.solve`` that also re-solves every ``every``-th and every slow problem cold."""
    reference = NMPC(nmpc.reference.copy(), replace(nmpc.cfg, solver="ipopt", jit=False),
                     nmpc.limits, nmpc.bounds)  # fmt: skip
    solve = nmpc.solve

    def checked(s, vq, aq=None, u_applied=None, safety_rows=None):
        state = copy.deepcopy(nmpc._last)
        t0 = time.perf_counter()
        res = solve(s, vq, aq, u_applied, safety_rows)
        dt = time.perf_counter() - t0
        times.append(dt)
        if len(times) % every == 0 or dt > SLOW_S:
            reference.reference[:] = nmpc.reference
            reference.reset()
            reference._last = state
            ref = reference.solve(s, vq, aq, u_applied, safety_rows)
            if res.success and ref.success:
                (slow if dt > SLOW_S else regular).append(float(np.abs(res.u - ref.u).max()))
        return res

    return checked


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="C", choices=["A", "B", "C"])
    ap.add_argument("--steps", type=int, default=1600)
    ap.add_argument("--every", type=int, default=20)
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE")
    args = ap.parse_args()
    overrides = {k: _parse(v) for k, v in (a.split("=", 1) for a in args.set)}
    config = expert_config(DEFAULT_PRESET)
    config = replace(config, nmpc=replace(config.nmpc, **overrides))
    world = evaluate.world_kwargs(args.scenario, 0, args.steps, render=False)
    env = uavtrack_v0.parallel_env(**world)
    obs, infos = env.reset(seed=0)
    expert = ExpertPolicy.from_env(env, config, threads=1)  # the checks in a fixed order
    regular, slow, times = [], [], []
    for st in expert.planners.values():
        st.nmpc.solve = _checked(st.nmpc, args.every, regular, slow, times)
    while env.agents:
        obs, _, _, _, infos = env.step(expert(obs, infos))
    env.close()
    ms = 1e3 * np.array(times[len(expert.planners) :])  # without the cold first solves
    print(f"scenario {args.scenario}0, {args.steps} steps, preset {DEFAULT_PRESET!r} {overrides}")
    print(
        f"NMPC solves: median {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.1f} ms, "
        f"max {ms.max():.1f} ms, {np.mean(ms > 1e3 * SLOW_S):.1%} slower than {1e3 * SLOW_S:.0f} ms"
    )
    for name, d in (("every-k", regular), ("slow", slow)):
        d = np.array(d or [0.0])
        print(
            f"|u - u_ipopt| on {len(d)} {name} checks: max {d.max():.1e}, p99 "
            f"{np.percentile(d, 99):.1e}, median {np.median(d):.1e}, > 1e-3 in {(d > 1e-3).sum()}"
        )


if __name__ == "__main__":
    main()
