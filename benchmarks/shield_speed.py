"""Median microseconds per SafetyFilter.certify() for a realistic context, per QP backend.

Context: 2 neighbours, 10 box obstacles, a moving target; half the calls need a correction
(the nominal violates a row or a bound), half are safe (fast path, no solver call). Also prints
the SafetyContext construction time, the row-building time per occluder point of (38), and the
bare QP solve through qpsolvers vs. daqp called directly (qpsolvers' own overhead) and vs. daqp's C
entry point from a numba kernel (`daqp_native.quadprog`, what the shield's compiled layers call).

Then the onboard stack's own path (`SafetyFilter.certify_trusted` with the rows built once, as
`CBFShield` calls it) on the contexts of a shielded episode (random world, n = 3, random actions):
medians of rows and of safe-nominal and corrected certifications, each call timed ``--live-repeats``
times and its fastest taken (the warm-cache cost: the VM's speed drifts within minutes).

Run: python benchmarks/shield_speed.py [--calls 4000] [--live-steps 300] [--live-repeats 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np
import qpsolvers

from uavtrack_env.safety import SOLVERS, SafetyContext, SafetyFilter
from uavtrack_env.safety.cbf import RowBuilder


def make_pool(rng: np.random.Generator, size: int) -> list[tuple[np.ndarray, dict]]:
    """(nominal, context kwargs) pairs; the UAV sits among obstacles near one neighbour."""
    pool = []
    for _ in range(size):
        p = np.array([0.0, 0.0, 3.0]) + rng.uniform(-1, 1, 3)
        ang = rng.uniform(0, 2 * np.pi, 2)
        rad = rng.uniform([2.5, 6.0], [4.0, 12.0])
        nb = p + np.c_[rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-1, 1, 2)]
        centers = p + np.c_[rng.uniform(-12, 12, (10, 2)), rng.uniform(-2, 0, 10)]
        kw = {
            "position": p,
            "yaw": rng.uniform(-np.pi, np.pi),
            "neighbours": nb,
            "obstacle_centers": centers,
            "obstacle_half_extents": rng.uniform(0.4, 1.2, (10, 3)),
            "target_position": p + [8.0, 0.0, -2.25] + rng.uniform(-1, 1, 3),
            "target_velocity": np.array([1.0, 0.2, 0.0]),
        }
        u = np.r_[rng.uniform(-9, 9, 3), rng.uniform(-0.5, 0.5)]
        pool.append((u, kw))
    return pool


def timed(fn, n: int) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out[i] = time.perf_counter() - t0
    return out * 1e6


def live_contexts(steps: int, seed: int) -> list[tuple]:
    """(filter, command, context, rows) of every certification in a seeded shielded episode."""
    from uavtrack_env import uavtrack_v0
    from uavtrack_env.wrappers import CBFShield

    env = CBFShield(uavtrack_v0.parallel_env(scenario="random", n_uavs=3, max_cycles=steps))
    env.reset(seed=seed)
    calls = []
    for agent in env.onboard.values():

        def record(u, agent=agent, certify=agent.certify_trusted):
            calls.append((agent.filter, u.copy(), agent.context(), agent.rows()))
            return certify(u)

        agent.certify_trusted = record
    rng = np.random.default_rng(seed)
    while env.agents:
        env.step({a: rng.uniform(-1.0, 1.0, 4) for a in env.agents})
    env.close()
    return calls


def live_section(steps: int, repeats: int, seed: int) -> None:
    """Rows and `certify_trusted` on an episode's own contexts, fastest of ``repeats`` each."""
    calls = live_contexts(steps, seed)

    def fastest(fn) -> float:
        fn()
        best = math.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t0)
        return best * 1e6

    rows = [fastest(lambda f=f, c=c: f.row_builder(c)) for f, _u, c, _r in calls]
    certify = [
        fastest(lambda f=f, u=u, c=c, r=r: f.certify_trusted(u, c, r)) for f, u, c, r in calls
    ]
    nominal = np.array([f.certify_trusted(u, c, r)[1].status == "nominal" for f, u, c, r in calls])
    certify = np.array(certify)
    print(
        f"live contexts ({len(calls)} certifications, {1 - nominal.mean():.0%} corrected): "
        f"rows median {np.median(rows):6.1f} us | certify_trusted nominal "
        f"{np.median(certify[nominal]):6.1f} us, corrected {np.median(certify[~nominal]):6.1f} us"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=4000, help="certify() calls per backend")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--live-steps", type=int, default=300, help="steps of the shielded episode")
    ap.add_argument("--live-repeats", type=int, default=5, help="timings per live call")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)

    ref = SafetyFilter()
    pool = make_pool(rng, 4 * args.calls)
    ctxs = [SafetyContext(**kw) for _, kw in pool]
    reports = [ref.certify(u, c)[1] for (u, _), c in zip(pool, ctxs, strict=True)]
    # Only contexts whose state is safe (an unsafe start is not a realistic steady state).
    status = [r.status if r.min_hard_h >= 0 else "unsafe-start" for r in reports]
    safe = [i for i, s in enumerate(status) if s == "nominal"]
    fix = [i for i, s in enumerate(status) if s not in ("nominal", "unsafe-start")]
    half = min(len(safe), len(fix), args.calls // 2)
    order = np.array(safe[:half] + fix[:half])
    rng.shuffle(order)
    us = [pool[i][0] for i in order]
    cs = [ctxs[i] for i in order]
    corrected = np.array([status[i] != "nominal" for i in order])
    n = len(order)
    print(f"{n} calls, {corrected.mean():.0%} need a correction "
          f"(statuses in pool: { {s: status.count(s) for s in set(status)} })")  # fmt: skip

    t_ctx = timed(lambda i: SafetyContext(**pool[order[i]][1]), n)
    print(f"SafetyContext(...) construction   median {np.median(t_ctx):7.1f} us")
    for point in ("axis", "centre", "edges"):  # the default first
        cbf = dataclasses.replace(ref.cbf, occlusion_point=point)
        rb = RowBuilder(cbf, connectivity_margin=ref.connectivity_margin)
        t_rows = timed(lambda i, rb=rb: rb(cs[i]), n)
        print(f"row building, occluder {point:6s}     median {np.median(t_rows):7.1f} us")

    results = {}
    for solver in SOLVERS:
        f = SafetyFilter(solver=solver)
        for i in range(200):  # warm-up
            f.certify(us[i % n], cs[i % n])
        t = timed(lambda i, f=f: f.certify(us[i], cs[i]), n)
        results[solver] = t
        print(
            f"certify [{solver:11s}] median all {np.median(t):7.1f} us | "
            f"fast path {np.median(t[~corrected]):7.1f} us | "
            f"corrected {np.median(t[corrected]):7.1f} us | p95 {np.percentile(t, 95):7.1f} us"
        )
    base = np.median(results["daqp"])
    for solver in SOLVERS:
        print(f"  ratio {solver:11s} / daqp(qpsolvers): {np.median(results[solver]) / base:5.2f}")

    # Bare QP: 3 variables, box bounds, 6 unit rows (a typical corrected call's size).
    G = rng.normal(size=(6, 3))
    G /= np.linalg.norm(G, axis=1, keepdims=True)
    h = rng.uniform(0.2, 2.0, 6)
    P, q = np.eye(3), -np.array([8.0, 5.0, -3.0])
    lb, ub = -10 * np.ones(3), 10 * np.ones(3)
    import daqp

    from uavtrack_env.safety import daqp_native

    settings = daqp_native.settings(1e-6)  # daqp.solve's default primal_tol
    bu, bl = np.r_[ub, h], np.r_[lb, -1e30 * np.ones(6)]
    sense = np.zeros(9, dtype=np.int32)

    def via_qpsolvers(solver):
        return lambda i: qpsolvers.solve_qp(P, q, G, h, lb=lb, ub=ub, solver=solver)

    for name, fn in (
        ("qpsolvers daqp  ", via_qpsolvers("daqp")),
        ("qpsolvers proxqp", via_qpsolvers("proxqp")),
        ("daqp.solve      ", lambda i: daqp.solve(P, q, G, bu, bl, sense)),
        ("daqp_quadprog   ", lambda i: daqp_native.quadprog(P, q, G, bu, bl, sense, settings)),
    ):
        fn(0)
        print(f"bare QP {name} median {np.median(timed(fn, 3000)):7.1f} us")
    live_section(args.live_steps, args.live_repeats, args.seed)


if __name__ == "__main__":
    main()
