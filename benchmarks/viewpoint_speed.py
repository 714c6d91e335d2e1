"""Cost of the expert's viewpoint layer per UAV-step (median microseconds).

The sight-line geometry runs every ``replan_period_s`` (10 Hz) and is skipped when no box is
taller than the car's visible part; x2* slews every step. Scenario A: 1 m cubes (skipped);
scenario C: 2.5 m boxes; a replan step alone is timed too.

Run: python benchmarks/viewpoint_speed.py [--n 4000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from ukf_speed import _median_us  # benchmarks/ is on sys.path when run as a script

from uavtrack_env.config import DT
from uavtrack_env.control.viewpoint import ViewpointConfig, ViewpointPlanner, required_x2
from uavtrack_env.scenarios import paper_layout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=4000, help="timed calls per measurement")
    n = ap.parse_args().n
    target, vel, uav = np.array([0.0, 0.0, 0.75]), np.array([0.5, 0.0, 0.0]), np.array([0, 7, 2.0])
    cfg = ViewpointConfig()
    shift = np.linspace(0.0, cfg.horizon_s, cfg.samples)[:, None] * vel
    print(f"{'median us':44s} {'A (1 m cubes)':>14s} {'C (2.5 m boxes)':>16s}")
    rows = {
        "ViewpointPlanner.update (mean over steps)": [],
        "required_x2 over the 3 s look-ahead": [],
    }
    for scenario in ("A", "C"):
        lay = paper_layout(scenario, 0)
        planner = ViewpointPlanner(0.188, lay.obstacle_centers, lay.obstacle_half_extents, cfg, DT)
        t0 = time.perf_counter()
        for _ in range(n):
            planner.update(target, vel, uav, 0.25, 7.0)
        rows["ViewpointPlanner.update (mean over steps)"].append(
            (time.perf_counter() - t0) / n * 1e6
        )
        rows["required_x2 over the 3 s look-ahead"].append(
            _median_us(
                lambda lay=lay: required_x2(
                    target + shift,
                    uav + shift,
                    lay.obstacle_centers,
                    lay.obstacle_half_extents,
                    cfg,
                ),
                n,
            )
        )
    for name, (a, c) in rows.items():
        print(f"{name:44s} {a:14.1f} {c:16.1f}")


if __name__ == "__main__":
    main()
