"""The UKF step of several filters in one compiled kernel (section II-E, eqs. 10-11).

`TargetEstimator.step` runs one UAV's filter through filterpy. `_step_filters` runs the same
equations (Merwe's scaled sigma points, the process and measurement models (10)-(11), the
unscented transform with circular psi means, filterpy's Kalman update and the estimator's
covariance guard) for K filters in one numba kernel (`cache=True`: compiled once per machine,
then loaded); `bank.TrackerBank` wraps it with the estimator's bookkeeping. The two paths agree
to round-off (tests/test_tracker_bank.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from uavtrack_env.estimation.ukf import PSI, TargetEstimator

_TWO_PI = 2.0 * math.pi


@numba.njit(cache=True)
def _wrap(a):  # pragma: no cover (compiled)
    """`geometry.wrap_angle` of one angle: (-pi, pi]."""
    return math.pi - (math.pi - a) % _TWO_PI


@numba.njit(cache=True)
def _cholesky(M, L):  # pragma: no cover (compiled)
    """Lower Cholesky factor of M into L; False when M is not positive definite."""
    n = M.shape[0]
    L[:] = 0.0
    for j in range(n):
        d = M[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, n):
            t = M[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    return True


@numba.njit(cache=True)
def _clipped_spectrum(M):  # pragma: no cover (compiled)
    """Eigen-decomposition of symmetric M with eigenvalues floored at 1e-12 max(|lam|, 1) (the
    fallback of `ukf.safe_sqrt` and `ukf.repair_covariance`): (lam, V)."""
    lam, V = np.linalg.eigh(M)
    floor = 1e-12 * max(np.max(np.abs(lam)), 1.0)
    return np.maximum(lam, floor), V


@numba.njit(cache=True)
def _sigma_points(x, P, lam):  # pragma: no cover (compiled)
    """Merwe's 2n + 1 points: x, x + U_i, x - U_i with U^T U = (lam + n) P (`ukf.safe_sqrt`)."""
    n = x.shape[0]
    M = (lam + n) * P
    M = 0.5 * (M + M.T)
    L = np.empty((n, n))
    U = np.empty((n, n))
    if _cholesky(M, L):
        U[:] = L.T
    else:
        ev, V = _clipped_spectrum(M)
        for i in range(n):
            U[i] = math.sqrt(ev[i]) * V[:, i]
    out = np.empty((2 * n + 1, n))
    out[0] = x
    for i in range(n):
        out[1 + i] = x + U[i]
        out[1 + n + i] = x - U[i]
    return out


@numba.njit(cache=True)
def _process(sig, dt, u, yaw, accel):  # pragma: no cover (compiled)
    """`ukf.process_model` (10), (14)-(15) applied to each sigma point in place."""
    c, s = math.cos(yaw), math.sin(yaw)
    for i in range(sig.shape[0]):
        x1, x2, x3, psi = sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3]
        vx, vy, vz = sig[i, 7], sig[i, 8], sig[i, 9]
        dvx = u[0] - (s * vx - c * vy)  # V_q in the camera frame (`world_to_cam_vec`)
        dvy = u[1] + vz
        dvz = u[2] - (c * vx + s * vy)
        w = u[3]
        sig[i, 0] = x1 + dt * (-x3 * dvx + x1 * x3 * dvz - (1 + x1 * x1) * w)
        sig[i, 1] = x2 + dt * (-x3 * dvy + x2 * x3 * dvz - w * x1 * x2)
        sig[i, 2] = x3 + dt * (x3 * x3 * dvz - w * x1 * x3)
        sig[i, 3] = _wrap(psi + dt * (dvx * x3 / (1 + x1 * x1 + x2 * x2) ** 0.5))
        for j in range(3):
            sig[i, 4 + j] += dt * sig[i, 7 + j]
            sig[i, 7 + j] += dt * accel[j]


@numba.njit(cache=True)
def _measure(sig, yaw, fx, fy, cu, cv, x3_min):  # pragma: no cover (compiled)
    """`ukf.measurement_model` (9) of each sigma point: [u_px, v_px, d, psi, r_c]."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.empty((sig.shape[0], 7))
    for i in range(sig.shape[0]):
        x1, x2 = sig[i, 0], sig[i, 1]
        depth = 1.0 / max(sig[i, 2], x3_min)
        X, Y, Z = x1 * depth, x2 * depth, depth
        out[i, 0] = fx * x1 + cu
        out[i, 1] = fy * x2 + cv
        out[i, 2] = depth
        out[i, 3] = sig[i, 3]
        out[i, 4] = sig[i, 4] - (s * X + c * Z)  # r_q - R_c^g r_{q/c} (`cam_to_world_vec`)
        out[i, 5] = sig[i, 5] - (-c * X + s * Z)
        out[i, 6] = sig[i, 6] + Y
    return out


@numba.njit(cache=True)
def _circular_mean(sig, Wm):  # pragma: no cover (compiled)
    m = Wm @ sig
    sn, cs = 0.0, 0.0
    for i in range(sig.shape[0]):
        sn += Wm[i] * math.sin(sig[i, PSI])
        cs += Wm[i] * math.cos(sig[i, PSI])
    m[PSI] = math.atan2(sn, cs)
    return m


@numba.njit(cache=True)
def _unscented(sig, Wm, Wc, noise):  # pragma: no cover (compiled)
    """Mean and covariance of sigma points plus ``noise``, psi averaged on the circle: psi of
    every point is first moved within pi of the circular mean (`ukf._angle_safe_ut`)."""
    mean = _circular_mean(sig, Wm)
    s = sig.copy()
    for i in range(s.shape[0]):
        s[i, PSI] = mean[PSI] + _wrap(sig[i, PSI] - mean[PSI])
    x = _circular_mean(s, Wm)
    y = s - x
    return x, (y.T * Wc) @ y + noise


@numba.njit(cache=True)
def _guard(x, P, lim, x3_lo, x3_hi, max_std):  # pragma: no cover (compiled)
    """`ukf.tidy_states` of one filter: wrap psi, clamp x1..x3 (in place); symmetrise P, repair
    it by eigenvalue clipping if Cholesky fails, cap its stds. Returns (P, repaired)."""
    x[PSI] = _wrap(x[PSI])
    x[0] = min(max(x[0], -lim), lim)
    x[1] = min(max(x[1], -lim), lim)
    x[2] = min(max(x[2], x3_lo), x3_hi)
    n = P.shape[0]
    P = 0.5 * (P + P.T)
    repaired = not _cholesky(P, np.empty((n, n)))
    if repaired:
        ev, V = _clipped_spectrum(P)
        P = (V * ev) @ V.T
        P = 0.5 * (P + P.T)
    scale = np.empty(n)
    capped = False
    for i in range(n):
        std = math.sqrt(max(P[i, i], 0.0))
        scale[i] = min(1.0, max_std[i] / max(std, 1e-300))
        capped |= scale[i] < 1.0
    if capped:
        for i in range(n):
            for j in range(n):
                P[i, j] *= scale[i] * scale[j]
    return P, repaired


@numba.njit(cache=True)
def _residual(a, b):  # pragma: no cover (compiled)
    d = a - b
    for i in range(d.shape[0]):
        d[i, PSI] = _wrap(d[i, PSI])
    return d


@numba.njit(cache=True)
def _step_filters(
    x,
    P,
    u,
    yaw_before,
    accel,
    seen,
    yaw,
    z,
    R,
    dt,
    lam,
    Wm,
    Wc,
    Q,
    camera,
    x3_bounds,
    x12_limit,
    max_std,
):  # pragma: no cover (compiled)
    """Predict (10) and, where ``seen``, update (11) K filters in place; repairs per filter."""
    fx, fy, cu, cv = camera[0], camera[1], camera[2], camera[3]
    lo, hi = x3_bounds[0], x3_bounds[1]
    repairs = np.zeros(x.shape[0], np.int64)
    for k in range(x.shape[0]):
        sig = _sigma_points(x[k], P[k], lam)
        _process(sig, dt, u[k], yaw_before[k], accel[k])
        xk, Pk = _unscented(sig, Wm, Wc, Q)
        Pk, rep = _guard(xk, Pk, x12_limit, lo, hi, max_std)
        repairs[k] += rep
        if seen[k]:
            sig = _sigma_points(xk, Pk, lam)
            sig_h = _measure(sig, yaw[k], fx, fy, cu, cv, lo)
            zp, S = _unscented(sig_h, Wm, Wc, R[k])
            dx = _residual(sig, xk)
            dz = _residual(sig_h, zp)
            gain = ((dx.T * Wc) @ dz) @ np.linalg.inv(S)
            innovation = z[k] - zp
            innovation[PSI] = _wrap(innovation[PSI])
            xk = xk + gain @ innovation
            xk[PSI] = _wrap(xk[PSI])
            Pk = Pk - gain @ (S @ gain.T)
            Pk, rep = _guard(xk, Pk, x12_limit, lo, hi, max_std)
            repairs[k] += rep
        x[k] = xk
        P[k] = Pk
    return repairs


def sigma_points(x: np.ndarray, P: np.ndarray, lam: float) -> np.ndarray:
    """Merwe's 2n + 1 sigma points of K filters: x (K, n), P (K, n, n) -> (K, 2n + 1, n).

    The same points as filterpy's `MerweScaledSigmaPoints` with the `safe_sqrt` square root."""
    return np.stack([_sigma_points(xk, Pk, float(lam)) for xk, Pk in zip(x, P, strict=True)])


def filter_constants(est: TargetEstimator) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Merwe's lambda, the camera's (fx, fy, cu, cv), the x3 bounds and the x1/x2 limit of an
    estimator, as `_step_filters` takes them."""
    cam, cfg, points = est.camera, est.cfg, est.ukf.points_fn
    lam = points.alpha**2 * (points.n + points.kappa) - points.n
    cam_arr = np.array((cam.fx, cam.fy, cam.cu, cam.cv), float)
    return float(lam), cam_arr, np.asarray(cfg.x3_bounds, float), float(cfg.x12_limit)
