"""Median time per NMPC solve for each solver in a warm-started closed loop, and its agreement
with Ipopt.

Run: ``python benchmarks/nmpc_speed.py [--preset tuned] [--steps 400] [--repeats 2]``. The plant is
eq. (15) integrated with 4 RK4 substeps per 1/80 s step; the target moves with a slowly varying
velocity; the preset's NMPC (`uavtrack_env.presets`) runs without the error signal (16), so that
every 10th step a cold Ipopt (tol `NMPCConfig.ipopt_tol`) solves the same problem and the largest
difference of the first inputs, |du|, is reported. With the tuned preset two half-spaces stand in
for the shield's rows. The first (cold, Ipopt) solve of every run is excluded from the median and
reported apart. Rows: the default (the per-step solver compiled when a C compiler is found,
`NMPCConfig.jit`), and ``interpreted`` (``jit=False``).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from uavtrack_env.config import DT
from uavtrack_env.control import NMPC
from uavtrack_env.control import nmpc as nmpc_module
from uavtrack_env.geometry import feature_rates
from uavtrack_env.presets import PRESETS

REF = np.array([0.0, 0.0, 0.1, math.pi / 2])
STARTS = ([0.3, -0.2, 0.2, 1.0], [-0.4, 0.25, 0.12, 2.3])
ROWS = (np.array([[0.3, 0.1, 1.0], [-1.0, 0.2, 0.1]]), np.array([1.2, 0.8]))


def _plant(s: np.ndarray, u: np.ndarray, vq: np.ndarray, sub: int = 4) -> np.ndarray:
    h = DT / sub
    for _ in range(sub):
        k1 = np.array(feature_rates(s, u, vq))
        k2 = np.array(feature_rates(s + h / 2 * k1, u, vq))
        k3 = np.array(feature_rates(s + h / 2 * k2, u, vq))
        k4 = np.array(feature_rates(s + h * k3, u, vq))
        s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


def run(preset: str, solver: str, steps: int, patch=None, **overrides) -> dict:
    """Closed loop from each start (``overrides``: `NMPCConfig` fields; ``patch(ctrl)``: swaps
    the built controller's per-step solver, for routes outside `NMPCConfig`); returns per-solve
    times, iterations, failures and the largest |du| against Ipopt."""
    cfg = PRESETS[preset].nmpc
    rows = ROWS if cfg.safety_rows else None
    nmpc_module._BUILT.clear()  # time a full build, not the shared one
    t0 = time.perf_counter()
    ctrl = NMPC(REF, cfg, solver=solver, error_signal=False, **overrides)
    if patch is not None:
        patch(ctrl)
    build = time.perf_counter() - t0
    ipopt = NMPC(REF, cfg, solver="ipopt", error_signal=False, jit=False)
    times, iters, cold, fails, rescues, du = [], [], [], 0, 0, [0.0]
    for start in STARTS:
        ctrl.reset()
        s = np.array(start)
        for k in range(steps):
            vq = np.array([0.5 + 0.5 * math.sin(k / 40), 0.0, 1.0])
            res = ctrl.solve(s, vq, safety_rows=rows)
            if k % 10 == 5 and solver != "ipopt":
                ipopt.reset()
                du.append(float(np.abs(ipopt.solve(s, vq, safety_rows=rows).u - res.u).max()))
            (cold if k == 0 else times).append(res.solve_time_s)
            iters.append(ctrl.last_stats()["iter_count"] if res.iterations < 0 else res.iterations)
            fails += not res.success
            rescues += "+ipopt" in res.solver_used
            s = _plant(s, res.u, vq)
    return {
        "build_s": build,
        "median_ms": 1e3 * float(np.median(times)),
        "p90_ms": 1e3 * float(np.percentile(times, 90)),
        "cold_ms": 1e3 * float(np.median(cold)),
        "iters": float(np.mean(iters)),
        "fails": fails,
        "rescues": rescues,
        "du": max(du),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tuned", choices=sorted(PRESETS))
    parser.add_argument("--steps", type=int, default=400, help="closed-loop steps per start")
    parser.add_argument("--repeats", type=int, default=2, help="runs per solver (median taken)")
    args = parser.parse_args()
    variants = {
        "ipopt": ("ipopt", {"jit": False}),
        "sqp (default)": ("sqp", {}),
        "sqp, interpreted": ("sqp", {"jit": False}),
        "rti": ("rti", {}),
        "rti, interpreted": ("rti", {"jit": False}),
    }
    rows = {}
    for name, (solver, opts) in variants.items():
        runs = [run(args.preset, solver, args.steps, **opts) for _ in range(args.repeats)]
        rows[name] = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
    base = rows["ipopt"]["median_ms"]
    print(
        f"NMPC of preset {args.preset!r}, N_p=50, {args.steps} steps x {len(STARTS)} starts, "
        f"{args.repeats} repeats"
    )
    head = f"{'solver':<18}{'median ms':>10}{'p90 ms':>9}{'vs ipopt':>9}{'iters':>7}"
    print(head + f"{'|du| max':>10}{'cold ms':>9}{'fails':>7}{'rescues':>9}{'build s':>9}")
    for name, r in rows.items():
        print(
            f"{name:<18}{r['median_ms']:>10.2f}{r['p90_ms']:>9.2f}{base / r['median_ms']:>8.1f}x"
            f"{r['iters']:>7.1f}{r['du']:>10.1e}{r['cold_ms']:>9.1f}{r['fails']:>7.0f}"
            f"{r['rescues']:>9.0f}{r['build_s']:>9.2f}"
        )


if __name__ == "__main__":
    main()
