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
def _points(x, P, lam, M, L, out):  # pragma: no cover (compiled)
    """Merwe's 2n + 1 points into ``out``: x, x + U_i, x - U_i with U^T U = (lam + n) P
    (`ukf.safe_sqrt`: Cholesky, else the clipped spectrum); M, L: (n, n) work arrays."""
    n = x.shape[0]
    c = lam + n
    for i in range(n):
        for j in range(n):
            M[i, j] = 0.5 * (c * P[i, j] + c * P[j, i])
    out[0] = x
    if _cholesky(M, L):
        for i in range(n):
            for j in range(n):
                out[1 + i, j] = x[j] + L[j, i]
                out[1 + n + i, j] = x[j] - L[j, i]
        return
    ev, V = _clipped_spectrum(M)
    for i in range(n):
        r = math.sqrt(ev[i])
        for j in range(n):
            out[1 + i, j] = x[j] + r * V[j, i]
            out[1 + n + i, j] = x[j] - r * V[j, i]


@numba.njit(cache=True)
def _sigma_points(x, P, lam):  # pragma: no cover (compiled)
    """`_points` into a new array."""
    n = x.shape[0]
    out = np.empty((2 * n + 1, n))
    _points(x, P, lam, np.empty((n, n)), np.empty((n, n)), out)
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
def _measure(sig, yaw, fx, fy, cu, cv, x3_min, out):  # pragma: no cover (compiled)
    """`ukf.measurement_model` (9) of each sigma point into ``out``: [u_px, v_px, d, psi, r_c]."""
    c, s = math.cos(yaw), math.sin(yaw)
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


@numba.njit(cache=True)
def _moments(sig, Wm, Wc, noise, x, P, y):  # pragma: no cover (compiled)
    """The unscented transform (`ukf._angle_safe_ut`) of sigma points plus ``noise`` into x,
    P; ``y`` gets the residuals. psi is averaged on the circle and every point's psi residual
    wrapped to within pi of that mean (moving a point by 2 pi leaves the circular mean as is,
    so one pass gives it)."""
    m, n = sig.shape
    sn, cs = 0.0, 0.0
    for i in range(m):
        sn += Wm[i] * math.sin(sig[i, PSI])
        cs += Wm[i] * math.cos(sig[i, PSI])
    for j in range(n):
        acc = 0.0
        for i in range(m):
            acc += Wm[i] * sig[i, j]
        x[j] = acc
    x[PSI] = math.atan2(sn, cs)
    for i in range(m):
        for j in range(n):
            y[i, j] = sig[i, j] - x[j]
        y[i, PSI] = _wrap(sig[i, PSI] - x[PSI])
    for a in range(n):
        for b in range(a, n):
            acc = 0.0
            for i in range(m):
                acc += Wc[i] * y[i, a] * y[i, b]
            P[a, b] = acc + noise[a, b]
            P[b, a] = acc + noise[b, a]


@numba.njit(cache=True)
def _guard(x, P, L, lim, x3_lo, x3_hi, max_std):  # pragma: no cover (compiled)
    """`ukf.tidy_states` of one filter in place: wrap psi, clamp x1..x3; symmetrise P, repair
    it by eigenvalue clipping if Cholesky fails, cap its stds. L: (n, n) work array. Returns
    whether P was repaired."""
    x[PSI] = _wrap(x[PSI])
    x[0] = min(max(x[0], -lim), lim)
    x[1] = min(max(x[1], -lim), lim)
    x[2] = min(max(x[2], x3_lo), x3_hi)
    n = P.shape[0]
    for a in range(n):
        for b in range(a + 1, n):
            P[a, b] = P[b, a] = 0.5 * (P[a, b] + P[b, a])
    repaired = not _cholesky(P, L)
    if repaired:
        ev, V = _clipped_spectrum(P)
        R = (V * ev) @ V.T
        for a in range(n):
            for b in range(n):
                P[a, b] = 0.5 * (R[a, b] + R[b, a])
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
    return repaired


@numba.njit(cache=True)
def _kalman_update(x, P, z, zp, S, Pxz, L, K):  # pragma: no cover (compiled)
    """filterpy's Kalman update from the unscented moments, in place: K = Pxz S^-1 (Cholesky
    solve; S is a covariance plus R), x += K (z - zp) with psi wrapped, P -= K Pxz^T
    (= K S K^T)."""
    n, q = Pxz.shape
    if _cholesky(S, L):
        for a in range(n):  # solve S K[a]^T = Pxz[a]^T
            for c in range(q):
                t = Pxz[a, c]
                for k in range(c):
                    t -= L[c, k] * K[a, k]
                K[a, c] = t / L[c, c]
            for c in range(q - 1, -1, -1):
                t = K[a, c]
                for k in range(c + 1, q):
                    t -= L[k, c] * K[a, k]
                K[a, c] = t / L[c, c]
    else:
        K[:] = Pxz @ np.linalg.inv(S)
    innovation = z - zp
    innovation[PSI] = _wrap(innovation[PSI])
    for a in range(n):
        t = 0.0
        for c in range(q):
            t += K[a, c] * innovation[c]
        x[a] += t
    x[PSI] = _wrap(x[PSI])
    for a in range(n):
        for b in range(n):
            t = 0.0
            for c in range(q):
                t += K[a, c] * Pxz[b, c]
            P[a, b] -= t


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
    K, n = x.shape
    m, q = 2 * n + 1, z.shape[1]
    sig, y = np.empty((m, n)), np.empty((m, n))
    sig_h, dz = np.empty((m, q)), np.empty((m, q))
    M, L = np.empty((n, n)), np.empty((n, n))
    zp, S, Ls = np.empty(q), np.empty((q, q)), np.empty((q, q))
    Pxz, gain = np.empty((n, q)), np.empty((n, q))
    repairs = np.zeros(K, np.int64)
    for k in range(K):
        xk, Pk = x[k], P[k]
        _points(xk, Pk, lam, M, L, sig)
        _process(sig, dt, u[k], yaw_before[k], accel[k])
        _moments(sig, Wm, Wc, Q, xk, Pk, y)
        repairs[k] += _guard(xk, Pk, L, x12_limit, lo, hi, max_std)
        if not seen[k]:
            continue
        _points(xk, Pk, lam, M, L, sig)
        _measure(sig, yaw[k], fx, fy, cu, cv, lo, sig_h)
        _moments(sig_h, Wm, Wc, R[k], zp, S, dz)
        for i in range(m):  # the state residuals
            for a in range(n):
                y[i, a] = sig[i, a] - xk[a]
            y[i, PSI] = _wrap(y[i, PSI])
        for a in range(n):
            for c in range(q):
                t = 0.0
                for i in range(m):
                    t += Wc[i] * y[i, a] * dz[i, c]
                Pxz[a, c] = t
        _kalman_update(xk, Pk, z[k], zp, S, Pxz, Ls, gain)
        repairs[k] += _guard(xk, Pk, L, x12_limit, lo, hi, max_std)
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
