"""Speed of the target UKF: plain filterpy, the vectorised subclass, and the team's filters
stepped in one compiled call (`TrackerBank`), per UAV-step (median microseconds).

Run: python benchmarks/ukf_speed.py [--n 3000] [--team 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from uavtrack_env.config import DT, CameraConfig
from uavtrack_env.estimation import Measurement, TargetEstimator, UKFConfig, make_filter
from uavtrack_env.estimation.bank import TrackerBank
from uavtrack_env.estimation.ukf import measurement_model

CAM = CameraConfig()


def _median_us(fn, n: int) -> float:
    for _ in range(min(200, n)):  # warm-up
        fn()
    times = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1e6)


def _filter_bench(vectorized: bool, n: int) -> tuple[float, float]:
    f = make_filter(CAM, UKFConfig(), DT, vectorized=vectorized)
    x0 = np.array([0.05, 0.1, 0.12, 3.1, 5.0, 1.0, 0.75, 1.5, 0.5, 0.0])
    P0 = np.diag([1e-4, 1e-4, 1e-5, 1e-3, 0.05, 0.05, 0.05, 0.1, 0.1, 0.01])
    u, yaw, acc = np.array([1.0, -0.2, 1.4, 0.1]), 0.3, np.zeros(3)
    z = measurement_model(x0, yaw, CAM, 1e-3)

    def predict():
        f.x, f.P = x0.copy(), P0.copy()
        f.predict(dt=DT, u=u, yaw=yaw, accel=acc)

    def predict_update():
        predict()
        f.update(z, yaw=yaw)

    return _median_us(predict_update, n), _median_us(predict, n)


def _estimator_bench(vectorized: bool, n: int) -> tuple[float, float]:
    est = TargetEstimator(CAM, UKFConfig(vectorized=vectorized), DT)
    p, yaw = np.array([-8.0, 0.0, 4.0]), 0.0
    meas = Measurement(330.0, 300.0, 8.0, 3.1)
    u = np.zeros(4)  # hovering: consistent with the fixed pose and detection
    est.reset(meas, p, yaw)
    for _ in range(400):
        est.step(u, p, yaw, meas)
    detected = _median_us(lambda: est.step(u, p, yaw, meas), n)
    lost = _median_us(lambda: est.step(u, p, yaw, None), n)
    return detected, lost


def _team_bench(k: int, n: int) -> tuple[float, float]:
    """`TrackerBank.step` for k UAVs (a detection each, then all in a dropout), per UAV-step."""
    bank = TrackerBank(k, CAM, UKFConfig(), DT)
    state = [-8.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # hovering, as in `_estimator_bench`
    seen = np.array([[*state, 1.0, 330.0, 300.0, 8.0, 3.1, 0.0, 0.0]] * k)
    lost = np.array([[*state, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]] * k)
    slots = list(range(k))
    for _ in range(400):
        bank.step(slots, seen)
    detected = _median_us(lambda: bank.step(slots, seen), n) / k
    return detected, _median_us(lambda: bank.step(slots, lost), n) / k


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=3000, help="timed calls per measurement")
    ap.add_argument("--team", type=int, default=3, help="UAVs of the batched team step")
    args = ap.parse_args()
    n = args.n
    pu_plain, p_plain = _filter_bench(False, n)
    pu_fast, p_fast = _filter_bench(True, n)
    st_plain, lost_plain = _estimator_bench(False, n)
    st_fast, lost_fast = _estimator_bench(True, n)
    print(f"{'median us':34s} {'plain filterpy':>15s} {'vectorised':>11s} {'speed-up':>9s}")
    for name, a, b in (
        ("UKF predict + update", pu_plain, pu_fast),
        ("UKF predict only", p_plain, p_fast),
        ("TargetEstimator.step (detected)", st_plain, st_fast),
        ("TargetEstimator.step (dropout)", lost_plain, lost_fast),
    ):
        print(f"{name:34s} {a:15.1f} {b:11.1f} {a / b:8.2f}x")
    team_seen, team_lost = _team_bench(args.team, n)
    print(
        f"TrackerBank, {args.team} UAVs, per UAV-step (detected / dropout): "
        f"{team_seen:.1f} / {team_lost:.1f} us ({st_plain / team_seen:.1f}x / "
        f"{lost_plain / team_lost:.1f}x plain filterpy)"
    )


if __name__ == "__main__":
    main()
