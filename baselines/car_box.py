"""Does the shield's exclusion box hold the true car? The assumption behind the car's row, measured.

    python -m baselines.car_box --worlds 12 --families random-held seek-car bang-bang-8

The shield keeps each UAV out of a box around its UKF estimate of the car (`uavtrack_env.onboard.
car_box`); the car's row is safe only while the true car lies inside that box. This runs hostile
policy families (`baselines.shield_adversary`) under `CBFShield` on seeded random worlds (n = 3,
lag dynamics, detector dropouts) and, at every agent-step with an estimate, checks the eight
corners of the true car (its true heading) against the box. It prints, per family, the share of
agent-steps with a corner outside, the worst excess (m), the same share for the box the car's own
footprint would give if it were oriented along the estimated velocity (same pads), and the UKF's
horizontal position error (median, 99th percentile, max) with its ratio to the filter's own
standard deviation.
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import dataclass, field

import numpy as np

from baselines.shield_adversary import FAMILIES, WorldSpec, make_env
from uavtrack_env.presets import ExpertConfig, add_preset_arguments, expert_config_from
from uavtrack_env.target import CAR_HALF_EXTENTS

_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) * CAR_HALF_EXTENTS


@dataclass
class Containment:
    """Tallies of one family: agent-steps with an estimate, those with the car outside the box,
    the worst excess (m), those with the car outside an oriented footprint box, and the UKF's
    horizontal errors (m) and error / std ratios."""

    steps: int = 0
    outside: int = 0
    worst: float = 0.0
    oriented_outside: int = 0
    errors: list[float] = field(default_factory=list)
    ratios: list[float] = field(default_factory=list)


def car_excess(truth: dict, centre: np.ndarray, heading: float, half: np.ndarray) -> float:
    """How far (m) the true car's farthest corner lies outside the box (<= 0: inside)."""
    vx, vy = truth["target_velocity"][:2]
    yaw = float(np.arctan2(vy, vx))
    c, s = np.cos(yaw), np.sin(yaw)
    corners = _CORNERS @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    rel = corners + truth["target_position"] - centre
    cb, sb = np.cos(heading), np.sin(heading)
    local = np.column_stack([cb * rel[:, 0] + sb * rel[:, 1], -sb * rel[:, 0] + cb * rel[:, 1]])
    return float(np.max(np.abs(np.column_stack([local, rel[:, 2]])) - half))


def measure(
    family: str, seeds: list[int], steps: int, config: ExpertConfig, n: int = 3
) -> Containment:
    """Run ``family`` shielded on the seeded worlds and tally the car box's containment."""
    out = Containment()
    for seed in seeds:
        env = make_env(WorldSpec(0, n, "lag", 0.0, seed), steps, config)
        policy = FAMILIES[family](env, np.random.default_rng(seed))
        obs, infos = env.reset(seed=seed)
        try:
            while env.agents:
                obs, _r, _te, _tr, infos = env.step(policy(obs, infos))
                for agent, info in infos.items():
                    onboard = env.onboard[agent]
                    est = onboard.estimate
                    if est is None:
                        continue
                    ctx = onboard.context()
                    excess = car_excess(
                        info["truth"],
                        ctx.target_position,
                        ctx.target_heading,
                        ctx.target_half_extents,
                    )
                    # the car's footprint along the estimated velocity, with the same pads
                    half = ctx.target_half_extents.copy()
                    half[:2] += CAR_HALF_EXTENTS[:2] - np.hypot(*CAR_HALF_EXTENTS[:2])
                    vx, vy = est.target_velocity[:2]
                    oriented = car_excess(
                        info["truth"], ctx.target_position, float(np.arctan2(vy, vx)), half
                    )
                    out.oriented_outside += oriented > 0.0
                    out.steps += 1
                    out.outside += excess > 0.0
                    out.worst = max(out.worst, excess)
                    err = float(
                        np.linalg.norm((info["truth"]["target_position"] - est.target_position)[:2])
                    )
                    sigma = float(np.sqrt(np.max(np.diag(est.covariance)[4:6])))
                    out.errors.append(err)
                    out.ratios.append(err / max(sigma, 1e-9))
        finally:
            env.close()
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", type=int, default=12, help="seeded random worlds per family")
    ap.add_argument("--steps", type=int, default=200, help="steps per episode (80 Hz)")
    ap.add_argument("--seed", type=int, default=1000, help="world k has seed SEED + k")
    ap.add_argument(
        "--families",
        nargs="+",
        default=["random-held", "seek-car", "bang-bang-8", "spin-dive"],
        choices=sorted(FAMILIES),
    )
    add_preset_arguments(ap)
    args = ap.parse_args(argv)
    config = expert_config_from(args.preset, args.set)
    seeds = [args.seed + k for k in range(args.worlds)]
    print(
        "| family | agent-steps | car outside the box | worst excess (m) | outside an oriented "
        "footprint | UKF horizontal error median / p99 / max (m) | error / std median / p99 |"
    )
    print("|---|---|---|---|---|---|---|")
    for family in args.families:
        m = measure(family, seeds, args.steps, config)
        e, r = np.asarray(m.errors), np.asarray(m.ratios)
        print(
            f"| {family} | {m.steps} | {m.outside / max(m.steps, 1):.2%} | {m.worst:.3f} | "
            f"{m.oriented_outside / max(m.steps, 1):.2%} | "
            f"{np.median(e):.2f} / {np.percentile(e, 99):.2f} / {e.max():.2f} | "
            f"{np.median(r):.1f} / {np.percentile(r, 99):.1f} |"
        )


if __name__ == "__main__":
    main()
