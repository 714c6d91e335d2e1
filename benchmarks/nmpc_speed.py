"""Median time per NMPC solve for each solver in a warm-started closed loop.

Run: ``python benchmarks/nmpc_speed.py [--steps 400] [--repeats 2] [--jit]``. The plant is eq. (15)
integrated with 4 RK4 substeps per 1/80 s step; the target moves with a slowly varying velocity.
The first (cold, Ipopt) solve of every run is excluded from the median and reported apart.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from uavtrack_env.config import DT
from uavtrack_env.control import NMPC
from uavtrack_env.control import nmpc as nmpc_module
from uavtrack_env.control.config import NMPCConfig
from uavtrack_env.geometry import feature_rates

REF = np.array([0.0, 0.0, 0.1, math.pi / 2])
STARTS = ([0.3, -0.2, 0.2, 1.0], [-0.4, 0.25, 0.12, 2.3])


def _plant(s: np.ndarray, u: np.ndarray, vq: np.ndarray, sub: int = 4) -> np.ndarray:
    h = DT / sub
    for _ in range(sub):
        k1 = np.array(feature_rates(s, u, vq))
        k2 = np.array(feature_rates(s + h / 2 * k1, u, vq))
        k3 = np.array(feature_rates(s + h / 2 * k2, u, vq))
        k4 = np.array(feature_rates(s + h * k3, u, vq))
        s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


def run(solver: str, steps: int, **overrides) -> dict:
    """Closed loop from each start (``overrides``: `NMPCConfig` fields); returns per-solve times,
    iterations and failures."""
    nmpc_module._BUILT.clear()  # time a full build, not the shared one
    t0 = time.perf_counter()
    ctrl = NMPC(REF, NMPCConfig(solver=solver), **overrides)
    build = time.perf_counter() - t0
    times, iters, cold, fails, rescues = [], [], [], 0, 0
    for start in STARTS:
        ctrl.reset()
        s = np.array(start)
        for k in range(steps):
            vq = np.array([0.5 + 0.5 * math.sin(k / 40), 0.0, 1.0])
            res = ctrl.solve(s, vq)
            (cold if k == 0 else times).append(res.solve_time_s)
            iters.append(res.iterations)
            fails += not res.success
            rescues += "+ipopt" in res.solver_used
            s = _plant(s, res.u, vq)
    return {
        "build_s": build,
        "median_ms": 1e3 * float(np.median(times)),
        "p90_ms": 1e3 * float(np.percentile(times, 90)),
        "cold_ms": 1e3 * float(np.median(cold)),
        "iters": float(np.median(iters)),
        "fails": fails,
        "rescues": rescues,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400, help="closed-loop steps per start")
    parser.add_argument("--repeats", type=int, default=2, help="runs per solver (median taken)")
    parser.add_argument(
        "--jit", action="store_true", help="add sqp and rti with the NLP JIT-compiled (needs gcc)"
    )
    args = parser.parse_args()
    variants = {
        "ipopt": ("ipopt", {}),
        "sqp (default)": ("sqp", {}),
        "rti": ("rti", {}),
    }
    if args.jit:
        variants["sqp + jit"] = ("sqp", {"jit": True})
        variants["rti + jit"] = ("rti", {"jit": True})
    rows = {}
    for name, (solver, opts) in variants.items():
        runs = [run(solver, args.steps, **opts) for _ in range(args.repeats)]
        rows[name] = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
    base = rows["ipopt"]["median_ms"]
    print(f"NMPC N_p=50, {args.steps} steps x {len(STARTS)} starts, {args.repeats} repeats")
    head = f"{'solver':<15}{'median ms':>10}{'p90 ms':>9}{'vs ipopt':>9}{'iters':>7}"
    print(head + f"{'cold ms':>9}{'fails':>7}{'rescues':>9}{'build s':>9}")
    for name, r in rows.items():
        print(
            f"{name:<15}{r['median_ms']:>10.2f}{r['p90_ms']:>9.2f}{base / r['median_ms']:>8.1f}x"
            f"{r['iters']:>7.0f}{r['cold_ms']:>9.1f}{r['fails']:>7.0f}{r['rescues']:>9.0f}"
            f"{r['build_s']:>9.2f}"
        )


if __name__ == "__main__":
    main()
