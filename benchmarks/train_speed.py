"""Training throughput of shared-parameter PPO, with and without the CBF shield.

    PYTHONPATH=. python benchmarks/train_speed.py [--timesteps 36864] [--repeats 3] [--n-envs K]
        [--n-epochs E] [--batch-size B] [--net-arch 128,128] [--frame-stack K]
        [--target-kl 0.01 --learning-rate 5e-5 --log-std-init -3.5]

Per configuration, the median over repeats of: agent-steps/s of ``PPO.learn`` (rollouts + updates
of the model `train.ppo` builds, with its defaults unless given) and of stepping train.ppo's
VecEnv alone with random actions (collection only: `VectorSharedPolicyVecEnv`, shielded by
`VectorCBFShield`), plus the shield's slowdown ratio. One torch thread; random worlds,
integrator dynamics, 1200-step episodes (as train.ppo).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
import warnings
from typing import Any

import numpy as np

from train.ppo import Args, make_args, make_vec_env, model_and_env


def ppo_args(shield: bool, seed: int, **given: Any) -> Args:
    """train.ppo's arguments: its defaults but for the ones ``given`` (None: the default)."""
    out = tempfile.mkdtemp(prefix="uavtrack-bench-")
    chosen = {k: v for k, v in given.items() if v is not None}
    return make_args(out=out, shield=shield, seed=seed, **chosen)


def vec_rate(shield: bool, steps: int, seed: int, **given: Any) -> float:
    """Agent-steps/s of the VecEnv alone (random actions)."""
    vec = make_vec_env(ppo_args(shield, seed, normalize=False, **given))
    vec.reset()
    rng = np.random.default_rng(seed)
    vector_steps = max(1, steps // vec.num_envs)
    t0 = time.perf_counter()
    for _ in range(vector_steps):
        vec.step(rng.uniform(-0.3, 0.3, (vec.num_envs, 4)).astype(np.float32))
    rate = vector_steps * vec.num_envs / (time.perf_counter() - t0)
    vec.close()
    return rate


def learn_rate(shield: bool, steps: int, seed: int, **given: Any) -> tuple[float, float]:
    """Agent-steps/s of PPO.learn (collection and updates), and the share of its time spent in
    the updates (`PPO.train`)."""
    import torch

    torch.set_num_threads(1)
    model, vec = model_and_env(ppo_args(shield, seed, **given))
    updates = 0.0
    train = model.train

    def timed_train() -> None:
        nonlocal updates
        t = time.perf_counter()
        train()
        updates += time.perf_counter() - t

    model.train = timed_train
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps)
    elapsed = time.perf_counter() - t0
    vec.close()
    return model.num_timesteps / elapsed, updates / elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--timesteps", type=int, default=36_864, help="agent-steps per repeat")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--n-envs", type=int, help="worlds (rows = worlds x 3; train.ppo's default)")
    ap.add_argument("--n-epochs", type=int, help="PPO epochs per rollout (train.ppo's default)")
    ap.add_argument("--batch-size", type=int, help="PPO minibatch (train.ppo's default)")
    ap.add_argument("--net-arch", help="hidden sizes of pi and vf (train.ppo's default)")
    ap.add_argument("--frame-stack", type=int, help="observations per input (train.ppo's default)")
    ap.add_argument("--target-kl", type=float, help="early stop of an update's epochs")
    ap.add_argument("--learning-rate", type=float, help="Adam step (train.ppo's default)")
    ap.add_argument("--log-std-init", type=float, help="initial log std (train.ppo's default)")
    args = ap.parse_args()
    names = ("n_envs", "n_epochs", "batch_size", "net_arch", "frame_stack", "target_kl",
             "learning_rate", "log_std_init")  # fmt: skip
    given = {k: getattr(args, k) for k in names}
    chosen = ppo_args(False, 0, **given)
    warnings.simplefilter("ignore")
    print(
        f"machine: {platform.processor() or platform.machine()}, python "
        f"{platform.python_version()}; {chosen.n_envs} worlds x 3 UAVs, PPO minibatch "
        f"{chosen.batch_size}, {chosen.n_epochs} epochs, net {chosen.net_arch}, "
        f"{chosen.frame_stack} frame(s), target KL {chosen.target_kl or 'off'}, learning rate "
        f"{chosen.learning_rate:g}, log std {chosen.log_std_init:g}; "
        f"{args.timesteps} agent-steps, median of {args.repeats}"
    )
    res, shares = {}, {}
    for shield in (False, True):
        learned = [learn_rate(shield, args.timesteps, s, **given) for s in range(args.repeats)]
        res[shield] = (
            statistics.median(
                vec_rate(shield, args.timesteps, s, **given) for s in range(args.repeats)
            ),
            statistics.median(rate for rate, _ in learned),
        )
        shares[shield] = statistics.median(share for _, share in learned)
    print(
        f"{'config':<14} {'VecEnv agent-steps/s':>21} {'PPO.learn agent-steps/s':>24} "
        f"{'updates share':>14} {'ceiling':>9}"
    )
    for shield, (v, lr) in res.items():
        share = shares[shield]
        print(
            f"{'PPO + shield' if shield else 'PPO':<14} {v:>21.0f} {lr:>24.0f} "
            f"{share:>14.2f} {lr / share:>9.0f}"
        )
    print(
        "ceiling: PPO.learn agent-steps/s if collecting cost nothing (the updates alone, "
        f"{chosen.n_epochs} epochs, one torch thread)"
    )
    (v0, l0), (v1, l1) = res[False], res[True]
    print(f"{'shield cost':<14} {v0 / v1:>20.2f}x {l0 / l1:>23.2f}x  (slowdown)")
    us = 1e6 * (1 / v1 - 1 / v0)
    print(
        f"shielded minus unshielded VecEnv time per agent-step: {us:.0f} us (the onboard stacks "
        "of `VectorCBFShield`)"
    )


if __name__ == "__main__":
    main()
