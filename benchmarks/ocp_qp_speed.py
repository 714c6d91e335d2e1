"""Median time of one QP with the structure of the tuned NMPC's SQP subproblem: HPIPM vs qrqp.

    python benchmarks/ocp_qp_speed.py [--calls 30]

The QP has the NMPC's stage layout (N_p = 50, 4 features + 3 bound slacks + 4 safety-row
slacks carried as states so that every constraint couples one stage, 4 inputs + 3 slack inputs,
6 soft-bound rows per stage, 4 safety rows on the first 10 stages) with random dynamics near the
identity. HPIPM gets the stage structure (N, nx, nu, ng) explicitly; qrqp (the NMPC's default QP
inside `sqpmethod`) solves it cold and warm-started from its own solution, the best case of the
closed loop's shifted warm start. Prints medians and the largest difference of the solutions.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time

import casadi as ca
import numpy as np

N, NS, NU0, NR, K_ROWS = 50, 4, 4, 4, 10
NX, NU = NS + 3 + NR, NU0 + 3


def build(seed: int = 0) -> tuple[dict, list[int]]:
    """QP data (H, g, A, bounds) in the stage order x_0 u_0 x_1 ... x_N, and ng per stage."""
    rng = np.random.default_rng(seed)
    nv = (N + 1) * NX + N * NU

    def ix(k: int) -> int:
        return k * (NX + NU)

    def iu(k: int) -> int:
        return ix(k) + NX

    Ad = np.eye(NS) + 1e-3 * rng.normal(size=(NS, NS))
    Bd = 0.0125 * rng.normal(size=(NS, NU0))
    rows, lba, uba, ngs = [], [], [], []
    for k in range(N + 1):
        if k < N:  # dynamics x_{k+1} = [A s + B u, mu, rho]: first the gap rows of stage k
            for i in range(NX):
                r = np.zeros(nv)
                r[ix(k + 1) + i] = 1.0
                if i < NS:
                    r[ix(k) : ix(k) + NS] -= Ad[i]
                    r[iu(k) : iu(k) + NU0] -= Bd[i]
                elif i < NS + 3:
                    r[iu(k) + NU0 + i - NS] = -1.0
                else:
                    r[ix(k) + i] = -1.0
                rows.append(r)
                lba.append(0.0)
                uba.append(0.0)
        ng = 0
        if k >= 1:  # soft feature bounds lo - sig <= s <= hi + sig
            for i in range(3):
                for sign, lo, hi in ((1.0, -0.5, np.inf), (-1.0, -np.inf, 0.5)):
                    r = np.zeros(nv)
                    r[ix(k) + i], r[ix(k) + NS + i] = 1.0, sign
                    rows.append(r)
                    lba.append(lo)
                    uba.append(hi)
                    ng += 1
        if k < K_ROWS:  # the shield's half-spaces a v - rho <= b
            for j in range(NR):
                r = np.zeros(nv)
                r[iu(k) : iu(k) + 3] = rng.normal(size=3)
                r[ix(k) + NS + 3 + j] = -1.0
                rows.append(r)
                lba.append(-np.inf)
                uba.append(0.3)
                ng += 1
        ngs.append(ng)
    H, g = np.zeros((nv, nv)), np.zeros(nv)
    lbx, ubx = np.full(nv, -np.inf), np.full(nv, np.inf)
    for k in range(N + 1):
        s, sl = slice(ix(k), ix(k) + NS), slice(ix(k) + NS, ix(k) + NX)
        H[s, s] = 2.0 * np.diag([10.0, 10.0, 100.0, 1.0])
        H[sl, sl] = 1e-2 * np.eye(3 + NR)
        g[sl] = 1000.0  # L1 penalty on the slacks
        lbx[sl] = 0.0
        if k < N:
            u = slice(iu(k), iu(k) + NU)
            H[u, u] = 0.2 * np.eye(NU)
            lbx[iu(k) : iu(k) + NU0], ubx[iu(k) : iu(k) + NU0] = -2.0, 2.0
    lbx[ix(0) : ix(0) + NS] = ubx[ix(0) : ix(0) + NS] = [0.3, -0.2, 0.2, 1.0]
    data = {
        "h": ca.sparsify(ca.DM(H)),
        "g": g,
        "a": ca.sparsify(ca.DM(np.array(rows))),
        "lba": np.array(lba),
        "uba": np.array(uba),
        "lbx": lbx,
        "ubx": ubx,
    }
    return data, ngs


@contextlib.contextmanager
def _silenced_stdout():
    """CasADi's hpipm interface prints its stage dimensions on every call (C++ stdout)."""
    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def _median_ms(solver: ca.Function, args: dict, calls: int) -> tuple[float, dict]:
    with _silenced_stdout():
        sol = solver(**args)
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            sol = solver(**args)
            times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), sol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=30)
    calls = ap.parse_args().calls
    data, ngs = build()
    sp = {"h": data["h"].sparsity(), "a": data["a"].sparsity()}
    structure = {"N": N, "nx": [NX] * (N + 1), "nu": [NU] * N + [0], "ng": ngs}
    quiet = {"print_iter": False, "print_header": False, "print_info": False}
    with _silenced_stdout():
        solvers = {
            "hpipm (speed)": ca.conic("hp", "hpipm", sp, {**structure, "hpipm": {"mode": "speed"}}),
            "hpipm (robust)": ca.conic(
                "hr", "hpipm", sp, {**structure, "hpipm": {"mode": "robust"}}
            ),
            "qrqp, cold": ca.conic("qc", "qrqp", sp, {**quiet, "max_iter": 1000}),
        }
    results = {}
    print(f"OCP QP: N = {N}, nx = {NX}, nu = {NU}, {data['a'].shape[0]} rows; median of {calls}")
    for name, solver in solvers.items():
        ms, sol = _median_ms(solver, data, calls)
        results[name] = np.array(sol["x"]).ravel()
        print(f"{name:16s} {ms:9.3f} ms  iterations {solver.stats().get('iter_count')}")
    with _silenced_stdout():
        cold = solvers["qrqp, cold"](**data)
    warm = {**data, "x0": cold["x"], "lam_x0": cold["lam_x"], "lam_a0": cold["lam_a"]}
    ms, sol = _median_ms(solvers["qrqp, cold"], warm, calls)
    print(
        f"{'qrqp, warm':16s} {ms:9.3f} ms  iterations {solvers['qrqp, cold'].stats()['iter_count']}"
    )
    ref = results["qrqp, cold"]
    for name, x in results.items():
        print(f"max |x - x_qrqp| {name}: {np.abs(x - ref).max():.2e}")


if __name__ == "__main__":
    main()
