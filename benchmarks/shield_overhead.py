"""Env steps/s with and without `CBFShield`, and the shield's cost per agent-step (medians).

Setting: n = 3 UAVs, seeded random worlds, uniform random actions in [-1, 1]^4 (the shield is
active on most steps) and small actions (|a| <= 0.05, it almost never is). Pinned to one core with
single-threaded BLAS. The shield's cost per agent-step is split into

* certify: one agent's share of the team's certification = the CBF-QP (47) on each agent's
  rows, all agents in one compiled call (`onboard.certify_team`; the rows are built when the
  agents observe their infos, which ``observe`` includes);
* observe: the input rows, the team's UKF step (its target estimates), the team-mates'
  messages, the car's box and the rows, in one compiled call for all agents
  (`onboard.observe_frame`), per agent-step;
* own: the wrapper's own time per agent-step (its step minus the env's step inside it, i.e.
  the env's action validation and its checked step, both of which a bare ``env.step`` runs):
  the shield's cost, estimator included, amortised over a step of all agents;
* total: shielded minus bare time per agent-step, everything the wrapper adds (own, plus the
  env's step costing more when the shield keeps UAVs alive that random actions would crash).

Steps/s and agent-steps/s are throughputs (total step time over steps, or over the agents that
acted); component costs are medians. Unshielded random actions crash UAVs, which then stop
acting (``terminate_on_collision="agent"``): a bare step then has fewer agents than a shielded
one, so the per-agent-step figures are the fair comparison.

Then the same for ``VectorCBFShield`` over ``vector_env(--vector)``: bare and shielded
agent-steps/s, and its own time per agent-step (its step minus the vector env's step inside).

``--count-calls``: instead of timing, count the Python-level calls (Python functions and
builtins, as a profiler sees them) the shield makes per agent-step, outside the env's step: a
deterministic measure of its interpreter work for comparing commits on a VM whose speed drifts
within minutes.

Run: python benchmarks/shield_overhead.py [--steps 2000] [--repeats 3] [--vector 16]
[--dynamics lag] [--count-calls] (lag: second-order rows, `lag_aware`)
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from uavtrack_env import uavtrack_v0  # noqa: E402
from uavtrack_env.wrappers import CBFShield, VectorCBFShield  # noqa: E402
from uavtrack_env.wrappers import shield as shield_module  # noqa: E402

N_UAVS = 3
WORLD: dict = {
    "scenario": "random",
    "n_uavs": N_UAVS,
    "max_cycles": 500,
    "terminate_on_collision": "agent",
}
"""The worlds of every run (``--dynamics`` sets their motion model)."""


def _timed(fn, sink: list[float]):
    """``fn`` recording its wall time (s) into ``sink`` (benchmark-only instrumentation)."""

    @functools.wraps(fn)
    def run(*args, **kwargs):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        sink.append(time.perf_counter() - t0)
        return out

    return run


def _timed_share(fn, sink: list[float]):
    """``fn(agents, ...)`` recording its wall time (s) per agent into ``sink``."""

    @functools.wraps(fn)
    def run(agents, *args, **kwargs):
        t0 = time.perf_counter()
        out = fn(agents, *args, **kwargs)
        sink.append((time.perf_counter() - t0) / len(agents))
        return out

    return run


def run(shield: bool, amplitude: float, steps: int, seed: int) -> dict[str, np.ndarray]:
    """Step times (s) over ``steps`` steps of fresh seeded episodes, plus component times (the
    observation's per team step)."""
    times: dict[str, list[float]] = {
        "step": [],
        "certify": [],
        "observe": [],
        "env": [],
        "validate": [],
        "active": [],
        "agents": [],
    }
    rng = np.random.default_rng(seed)
    done, episode = 0, 0
    certify_team = shield_module.certify_team
    shield_module.certify_team = _timed_share(certify_team, times["certify"])
    while done < steps:
        raw = uavtrack_v0.parallel_env(**WORLD)
        env = CBFShield(raw) if shield else raw
        env.reset(seed=seed + episode)
        if shield:  # instance-level wrappers: the class itself has no timing code
            env._observe = _timed(env._observe, times["observe"])
            raw._step_checked = _timed(raw._step_checked, times["env"])
            raw.validate_actions = _timed(raw.validate_actions, times["validate"])
        while env.agents and done < steps:
            actions = {a: amplitude * rng.uniform(-1.0, 1.0, 4) for a in env.agents}
            times["agents"].append(len(actions))
            t0 = time.perf_counter()
            _o, _r, _t, _tr, infos = env.step(actions)
            times["step"].append(time.perf_counter() - t0)
            if shield:
                times["active"] += [float(i["shield"]["active"]) for i in infos.values()]
            done += 1
        env.close()
        episode += 1
    shield_module.certify_team = certify_team
    return {k: np.asarray(v) for k, v in times.items()}


def count_calls(amplitude: float, steps: int, seed: int) -> float:
    """Python-level calls per agent-step the shield makes outside the env's checked step and
    its action validation, over ``steps`` steps of seeded episodes."""
    counts = {"calls": 0, "agents": 0}
    inside = [0]

    def hook(_frame, event, _arg) -> None:
        if event in ("call", "c_call") and not inside[0]:
            counts["calls"] += 1

    def outside_count(fn):
        @functools.wraps(fn)
        def run(*args, **kwargs):
            inside[0] += 1
            try:
                return fn(*args, **kwargs)
            finally:
                inside[0] -= 1

        return run

    rng = np.random.default_rng(seed)
    done, episode = 0, 0
    while done < steps:
        raw = uavtrack_v0.parallel_env(**WORLD)
        env = CBFShield(raw)
        env.reset(seed=seed + episode)
        raw._step_checked = outside_count(raw._step_checked)
        raw.validate_actions = outside_count(raw.validate_actions)
        while env.agents and done < steps:
            actions = {a: amplitude * rng.uniform(-1.0, 1.0, 4) for a in env.agents}
            counts["agents"] += len(actions)
            sys.setprofile(hook)
            env.step(actions)
            sys.setprofile(None)
            done += 1
        env.close()
        episode += 1
    return counts["calls"] / counts["agents"]


def run_vector(shield: bool, amplitude: float, steps: int, seed: int, k: int) -> dict:
    """Total and inner (the vector env's own step) times (s) and agent-steps of ``steps`` steps
    of ``vector_env(k)``, bare or under `VectorCBFShield`."""
    venv = uavtrack_v0.vector_env(k, **WORLD)
    env = VectorCBFShield(venv) if shield else venv
    inner: list[float] = []
    venv.step = _timed(venv.step, inner)  # instance-level: the class has no timing code
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    total, rows = 0.0, 0
    for _ in range(steps):
        actions = amplitude * rng.uniform(-1.0, 1.0, (k, N_UAVS, 4))
        rows += int(venv._active.sum())
        t0 = time.perf_counter()
        env.step(actions)
        total += time.perf_counter() - t0
    env.close()
    return {"total": total, "inner": float(np.sum(inner)), "rows": rows}


def vector_section(args: argparse.Namespace, label: str, amp: float) -> None:
    """Bare vs shielded ``vector_env``, and `VectorCBFShield`'s own time per agent-step."""
    k = args.vector
    steps = max(1, args.steps // k * N_UAVS)
    bare_a, shield_a, own = [], [], []
    for r in range(args.repeats):
        bare = run_vector(False, amp, steps, args.seed + 1000 * r, k)
        shielded = run_vector(True, amp, steps, args.seed + 1000 * r, k)
        bare_a.append(bare["total"] / bare["rows"])
        shield_a.append(shielded["total"] / shielded["rows"])
        own.append((shielded["total"] - shielded["inner"]) / shielded["rows"])
    ba, sa = np.median(bare_a), np.median(shield_a)
    print(f"== VectorCBFShield(vector_env({k})), n={N_UAVS}, {label} ({args.repeats} x {steps})")
    print(f"  agent-steps/s bare {1 / ba:8.0f}   shielded {1 / sa:8.0f}   ratio {ba / sa:.2f}")
    print(f"  shield's own time per agent-step (mean) {np.median(own) * 1e6:6.1f} us (goal 100)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000, help="env steps per configuration")
    ap.add_argument("--repeats", type=int, default=3, help="repeat each configuration")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--all-cores", action="store_true", help="do not pin to one core")
    ap.add_argument("--vector", type=int, default=16, help="worlds of the vector_env (0: skip)")
    ap.add_argument(
        "--dynamics", default="integrator", choices=("integrator", "lag"), help="UAV motion model"
    )
    ap.add_argument(
        "--count-calls", action="store_true", help="count the shield's Python calls, no timing"
    )
    args = ap.parse_args()
    WORLD["dynamics"] = {"model": args.dynamics}
    if args.count_calls:
        run(True, 1.0, 50, args.seed + 10**6)  # loads the compiled kernels outside the count
        for label, amp in (("random actions", 1.0), ("small actions", 0.05)):
            per = count_calls(amp, args.steps, args.seed)
            print(f"== n={N_UAVS}, {args.dynamics} dynamics, {label} ({args.steps} steps)")
            print(f"  the shield's Python calls per agent-step: {per:.1f}")
        return
    if not args.all_cores and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    run(True, 1.0, 50, args.seed + 10**6)  # warm-up: loads the compiled kernels (numba's cache)
    for label, amp in (("random actions", 1.0), ("small actions", 0.05)):
        bare_t, shield_t, bare_a, shield_a, cert, obs, act, own = ([] for _ in range(8))
        for r in range(args.repeats):
            bare = run(False, amp, args.steps, args.seed + 1000 * r)
            shielded = run(True, amp, args.steps, args.seed + 1000 * r)
            bare_t.append(bare["step"].mean())  # throughput: total time / steps
            shield_t.append(shielded["step"].mean())
            bare_a.append(bare["step"].sum() / bare["agents"].sum())  # per agent-step
            shield_a.append(shielded["step"].sum() / shielded["agents"].sum())
            cert.append(np.median(shielded["certify"]))
            obs.append(np.median(shielded["observe"]) / N_UAVS)
            act.append(shielded["active"].mean())
            env_time = shielded["env"].sum() + shielded["validate"].sum()
            own_time = shielded["step"].sum() - env_time
            own.append(own_time / shielded["agents"].sum())
        b, s = np.median(bare_t), np.median(shield_t)
        ba, sa = np.median(bare_a), np.median(shield_a)
        print(
            f"== n={N_UAVS}, random world, {args.dynamics} dynamics, {label} "
            f"({args.repeats} x {args.steps} steps)"
        )
        print(f"  env steps/s   bare {1 / b:8.0f}   shielded {1 / s:8.0f}   ratio {b / s:.2f}")
        print(f"  agent-steps/s bare {1 / ba:8.0f}   shielded {1 / sa:8.0f}   ratio {ba / sa:.2f}")
        print(f"  shield active on {np.median(act):.0%} of agent-steps")
        print(
            "  per agent-step (us): "
            f"certify median {np.median(cert) * 1e6:6.1f}   "
            f"observe median {np.median(obs) * 1e6:6.1f}"
        )
        print(
            f"  shield's own time per agent-step (mean) {np.median(own) * 1e6:6.1f} us (goal 100)"
            f"   total overhead vs bare (mean) {(sa - ba) * 1e6:6.1f} us"
        )
        print(f"  certify median per repeat (us): {', '.join(f'{c * 1e6:.1f}' for c in cert)}")
        if args.vector:
            vector_section(args, label, amp)


if __name__ == "__main__":
    main()
