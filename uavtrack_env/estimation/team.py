"""The target UKFs of a whole team stepped at once (section II-E, eqs. 10-11).

`TargetEstimator.step` runs one UAV's filter through filterpy. `step_team` advances the filters of
several UAVs with the same equations (Merwe's scaled sigma points, the unscented transform with
circular psi means, filterpy's Kalman update) on arrays shaped (K, ...): one numpy call per
operation for the whole team instead of a dozen per UAV. Each estimator's own bookkeeping (the
dropout fit of Remark 2, the held height, the clock) is shared with the single-UAV path through
`TargetEstimator.begin_step`/`end_step`. The two paths agree to round-off
(tests/test_ukf_team.py); ``UKFConfig.vectorized = False`` steps each UAV through plain filterpy.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from uavtrack_env.estimation.ukf import (
    PSI,
    Estimate,
    Measurement,
    TargetEstimator,
    angle_add,
    angle_residual,
    measurement_model,
    process_model,
    safe_sqrt,
    tidy_states,
)
from uavtrack_env.geometry import wrap_angle

StepInput = tuple[np.ndarray, np.ndarray, float, Measurement | None]
"""`TargetEstimator.step`'s arguments: (u_applied, uav_position, uav_yaw, meas)."""


def _swap(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


def sigma_points(x: np.ndarray, P: np.ndarray, lam: float) -> np.ndarray:
    """Merwe's 2n + 1 sigma points of K filters: x (K, n), P (K, n, n) -> (K, 2n + 1, n).

    The same points as filterpy's `MerweScaledSigmaPoints` with the `safe_sqrt` square root."""
    n = x.shape[-1]
    M = (lam + n) * P
    M = 0.5 * (M + _swap(M))
    try:
        U = _swap(np.linalg.cholesky(M))
    except np.linalg.LinAlgError:  # an indefinite P: safe_sqrt's eigen fallback where needed
        U = np.stack([safe_sqrt(m) for m in M])
    xs = x[:, None, :]
    return np.concatenate([xs, xs + U, xs - U], axis=1)


def circular_means(sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
    """Weighted means of K sets of sigma points (K, N, n), psi averaged on the circle."""
    m = Wm @ sigmas
    m[:, PSI] = np.arctan2(np.sin(sigmas[..., PSI]) @ Wm, np.cos(sigmas[..., PSI]) @ Wm)
    return m


def unscented_transforms(
    sigmas: np.ndarray, Wm: np.ndarray, Wc: np.ndarray, noise: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean (K, n) and covariance (K, n, n) of K sets of sigma points plus ``noise``.

    As `uavtrack_env.estimation.ukf._angle_safe_ut`: psi of every point is first moved within pi
    of the circular mean, so plain differences are wrapped residuals."""
    mean = circular_means(sigmas, Wm)
    s = sigmas.copy()
    s[..., PSI] = mean[:, None, PSI] + wrap_angle(sigmas[..., PSI] - mean[:, None, PSI])
    x = circular_means(s, Wm)
    y = s - x[:, None, :]
    return x, _swap(y) @ (Wc[:, None] * y) + noise


def step_team(estimators: Sequence[TargetEstimator], inputs: Sequence[StepInput]) -> list[Estimate]:
    """`TargetEstimator.step` for every estimator with its input, in one batched pass.

    The estimators must share camera, `UKFConfig` and dt. Estimators whose config has
    ``vectorized = False`` step one by one through plain filterpy."""
    if len(estimators) != len(inputs):
        raise ValueError(f"{len(estimators)} estimators but {len(inputs)} inputs")
    if not estimators:
        return []
    first = estimators[0]
    for est in estimators[1:]:
        if (est.camera, est.cfg, est.dt) != (first.camera, first.cfg, first.dt):
            raise ValueError("step_team needs estimators with one camera, UKFConfig and dt")
    if not first.cfg.vectorized:
        return [est.step(*inp) for est, inp in zip(estimators, inputs, strict=True)]
    plans = [est.begin_step(*inp) for est, inp in zip(estimators, inputs, strict=True)]
    ukf, cfg = first.ukf, first.cfg
    points = ukf.points_fn
    lam = points.alpha**2 * (points.n + points.kappa) - points.n
    Wm, Wc = ukf.Wm, ukf.Wc
    max_std = first._max_std

    # predict (10): sigma points through fx, unscented transform with Q
    x = np.stack([est.ukf.x for est in estimators])
    P = np.stack([est.ukf.P for est in estimators])
    u = np.stack([p.u for p in plans])[:, None, :]
    yaw_before = np.array([p.yaw_before for p in plans])[:, None]
    accel = np.stack([p.accel for p in plans])[:, None, :]
    sigmas = process_model(sigma_points(x, P, lam), first.dt, u, yaw_before, accel)
    x, P = unscented_transforms(sigmas, Wm, Wc, ukf.Q)
    P, _, repaired = tidy_states(x, P, cfg, max_std)
    repairs = repaired.astype(int)

    # update (11) of the UAVs with a detection
    seen = [k for k, p in enumerate(plans) if p.z is not None]
    if seen:
        xs, Ps = x[seen], P[seen]
        sig_f = sigma_points(xs, Ps, lam)
        yaw = np.array([plans[k].yaw for k in seen])[:, None]
        sig_h = measurement_model(sig_f, yaw, first.camera, cfg.x3_bounds[0])
        R = np.stack([ukf.R if plans[k].R is None else plans[k].R for k in seen])
        zp, S = unscented_transforms(sig_h, Wm, Wc, R)
        dx = angle_residual(sig_f, xs[:, None, :])
        dz = angle_residual(sig_h, zp[:, None, :])
        gain = (_swap(dx * Wc[:, None]) @ dz) @ np.linalg.inv(S)
        innovation = angle_residual(np.stack([plans[k].z for k in seen]), zp)
        xs = angle_add(xs, (gain @ innovation[:, :, None])[:, :, 0])
        Ps = Ps - gain @ (S @ _swap(gain))
        Ps, _, repaired = tidy_states(xs, Ps, cfg, max_std)
        x[seen], P[seen] = xs, Ps
        repairs[seen] += repaired

    out = []
    for k, (est, plan) in enumerate(zip(estimators, plans, strict=True)):
        est.ukf.x, est.ukf.P = x[k].copy(), P[k].copy()
        est.n_covariance_repairs += int(repairs[k])
        out.append(est.end_step(plan))
    return out
