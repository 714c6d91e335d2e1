"""fatrop (CasADi's structure-exploiting interior-point plugin) on the NMPC's NLP against the
default SQP, in `nmpc_speed`'s closed loop.

    python benchmarks/nmpc_fatrop.py [--preset paper] [--steps 200] [--interpreted]

fatrop needs the NLP stage by stage: per stage k the rows of x_{k+1} = F(x_k, u_k), then the
stage's own rows on (x_k, u_k) (the initial condition, Table I's soft bounds). The NMPC's
variables already come stage-wise; its rows are permuted here, those of Table I and (19) only:
presets without plan rows (``paper``, ``paper-planner``) run. Rows: the default SQP, fatrop from
the shifted previous solution, and fatrop with mu_init 1e-4 and a warm-started interior point;
compiled like the default solver unless ``--interpreted``.
"""

from __future__ import annotations

import argparse

import casadi as ca
import nmpc_speed  # the sibling script: benchmarks/ is this script's sys.path[0]
import numpy as np

from uavtrack_env.control import jit_cache
from uavtrack_env.control import nmpc as nmpc_module
from uavtrack_env.presets import PRESETS


def stage_order(ctrl: nmpc_module.NMPC) -> np.ndarray:
    """The permutation of the NMPC's rows into fatrop's stage order."""
    N = ctrl.N
    soft = [4 + 10 * n + 4 + np.arange(6) for n in range(N)]  # Table I's rows of x_{n+1}
    order = []
    for n in range(N):
        order.append(4 + 10 * n + np.arange(4))  # x_{n+1} = F(x_n, u_n)
        order.append(np.arange(4) if n == 0 else soft[n - 1])  # stage n's own rows
    order.append(soft[N - 1])
    perm = np.concatenate(order)
    assert np.array_equal(np.sort(perm), np.arange(ctrl._ng))
    return perm


class _Permuted(nmpc_module._BufferedSolver):
    """A solver whose rows are ``perm`` of the NMPC's: bounds and multipliers mapped both ways."""

    def __init__(self, function: ca.Function, perm: np.ndarray) -> None:
        super().__init__(function)
        self.perm, self.inv = perm, np.argsort(perm)

    def call(self, args: dict) -> dict[str, np.ndarray]:
        mapped = {
            k: (v[self.perm] if k in ("lbg", "ubg", "lam_g0") else v) for k, v in args.items()
        }
        out = super().call(mapped)
        out["lam_g"] = out["lam_g"][self.inv]
        return out


def use_fatrop(compiled: bool, **options):
    """A `nmpc_speed.run` patch: the controller's per-step solver becomes fatrop."""

    def patch(ctrl: nmpc_module.NMPC) -> None:
        perm = stage_order(ctrl)
        nlp = {**ctrl._nlp, "g": ctrl._nlp["g"][perm.tolist()]}
        lbg, ubg = ctrl._lbg[perm], ctrl._ubg[perm]
        opts = {
            "structure_detection": "auto",
            "equality": [bool(lo == hi) for lo, hi in zip(lbg, ubg, strict=True)],
            "expand": True,
            "print_time": False,
            "error_on_fail": False,
            "fatrop.print_level": 0,
            **{f"fatrop.{k}": v for k, v in options.items()},
        }
        if compiled:
            with nmpc_module._jit_build_dir() as build:
                jit = {**nmpc_module._jit_options(build), "jit_name": "fatrop"}
                function = ca.nlpsol("fatrop", "fatrop", nlp, {**opts, **jit})
        else:
            function = ca.nlpsol("fatrop", "fatrop", nlp, opts)
        ctrl._solver = _Permuted(function, perm)
        ctrl._solver_plugin = "fatrop"

    return patch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    ap.add_argument("--steps", type=int, default=200, help="closed-loop steps per start")
    ap.add_argument("--interpreted", action="store_true", help="nothing compiled")
    args = ap.parse_args()
    if PRESETS[args.preset].nmpc.safety_rows:
        ap.error(f"preset {args.preset!r} has plan rows, which this script does not permute")
    compiled = not args.interpreted and jit_cache.auto_enabled()
    jit = {} if compiled else {"jit": False}
    variants = {
        "sqp (default)": dict(patch=None),
        "fatrop": dict(patch=use_fatrop(compiled)),
        "fatrop, warm mu 1e-4": dict(
            patch=use_fatrop(compiled, mu_init=1e-4, warm_start_init_point=True)
        ),
    }
    print(f"NMPC of preset {args.preset!r}, {'compiled' if compiled else 'interpreted'}, "
          f"{args.steps} steps x {len(nmpc_speed.STARTS)} starts")  # fmt: skip
    print(f"{'solver':<22}{'median ms':>10}{'p90 ms':>9}{'iters':>7}{'|du| max':>10}{'fails':>7}")
    for name, kw in variants.items():
        r = nmpc_speed.run(args.preset, "sqp", args.steps, **kw, **jit)
        print(
            f"{name:<22}{r['median_ms']:>10.2f}{r['p90_ms']:>9.2f}{r['iters']:>7.1f}"
            f"{r['du']:>10.1e}{r['fails'] + r['rescues']:>7.0f}"
        )


if __name__ == "__main__":
    main()
