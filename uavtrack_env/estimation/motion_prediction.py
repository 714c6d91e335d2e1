"""Polynomial target-motion fit used to bridge detection dropouts (Remark 2, Fig. 5).

The paper fits a high-order polynomial to the target's recent position and velocity data with a
QP (cf. (27) of its ref. [6]) and feeds the fitted velocity and acceleration (Gamma-dot,
Gamma-ddot) into the UKF while the target is not detected. The QP there is an unconstrained
weighted least-squares problem, so it is solved here in closed form (normal equations, compiled
with numba: it runs every few steps for every UAV):

    min_c  sum_k ||P(t_k) c - p_k||^2 + w * sum_k ||P'(t_k) c - v_k||^2

with one polynomial per axis in a normalised time tau = (t - t_last) / (t_last - t_first) in
[-1, 0] (for conditioning).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np


@dataclass(frozen=True)
class MotionFit:
    """Fitted position, velocity and acceleration (each (3,), global frame) at ``t``."""

    t: float
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


_NO_SAMPLES = np.zeros((0, 3))


def _check_series(name: str, values: np.ndarray, n: int) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 2 or arr.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3) to match t, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def fit_polynomial(
    t: np.ndarray,
    positions: np.ndarray,
    velocities: np.ndarray | None = None,
    *,
    order: int = 2,
    velocity_weight: float = 0.0,
    t_eval: float | None = None,
) -> MotionFit:
    """Least-squares polynomial fit of a 3-D trajectory (Remark 2); evaluated at ``t_eval``.

    ``t`` (N,) sample times, ``positions`` (N, 3), optional ``velocities`` (N, 3) entering with
    weight ``velocity_weight`` (s^2: a 1 m/s velocity residual costs like a sqrt(w) m position
    residual). ``t_eval`` defaults to the latest sample time. Needs at least ``order + 1``
    samples at distinct times.
    """
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t must be a non-empty 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("t contains NaN or inf")
    if not isinstance(order, int | np.integer) or order < 0:
        raise ValueError(f"order must be a non-negative int, got {order!r}")
    if not (np.isfinite(velocity_weight) and velocity_weight >= 0):
        raise ValueError(f"velocity_weight must be finite and >= 0, got {velocity_weight}")
    n = t.size
    p = _check_series("positions", positions, n)
    if np.unique(t).size < order + 1:
        raise ValueError(
            f"a degree-{order} fit needs at least {order + 1} distinct sample times, got "
            f"{np.unique(t).size}"
        )
    if velocities is not None and velocity_weight > 0:
        velocities = _check_series("velocities", velocities, n)
    else:
        velocities = None
    te = float(t.max()) if t_eval is None else float(t_eval)
    if not np.isfinite(te):
        raise ValueError(f"t_eval must be finite, got {t_eval}")
    v = _NO_SAMPLES if velocities is None else velocities
    _n, pos, vel, acc = _fit(t, p, v, -np.inf, int(order), float(velocity_weight), te, 0)
    return MotionFit(te, pos, vel, acc)


@numba.njit(cache=True)
def _fit(t, p, v, lo, order, velocity_weight, te, min_samples):  # pragma: no cover (compiled)
    """The fit of the samples with ``t >= lo`` (``v`` empty: positions only), by the normal
    equations (tau in [-1, 0] keeps them well conditioned for the low orders used): (samples,
    position, velocity, acceleration at ``te``); not fitted (zeros) below ``min_samples``."""
    nb = order + 1
    t_last, t_first, count = -np.inf, np.inf, 0
    for i in range(t.shape[0]):
        if t[i] >= lo:
            t_last, t_first, count = max(t_last, t[i]), min(t_first, t[i]), count + 1
    N = np.zeros((nb, nb))
    r = np.zeros((nb, 3))
    if count == 0 or count < min_samples:
        return count, np.zeros(3), np.zeros(3), np.zeros(3)
    span = max(t_last - t_first, 1e-9)
    basis = np.empty(nb)
    dbasis = np.zeros(nb)
    use_v = v.shape[0] > 0 and velocity_weight > 0.0
    for i in range(t.shape[0]):
        if t[i] < lo:
            continue
        tau = (t[i] - t_last) / span
        basis[0] = 1.0
        for k in range(1, nb):
            basis[k] = basis[k - 1] * tau
            dbasis[k] = k * basis[k - 1] / span
        for a in range(nb):
            for b in range(nb):
                N[a, b] += basis[a] * basis[b]
                if use_v:
                    N[a, b] += velocity_weight * dbasis[a] * dbasis[b]
            for j in range(3):
                r[a, j] += basis[a] * p[i, j]
                if use_v:
                    r[a, j] += velocity_weight * dbasis[a] * v[i, j]
    coef = np.linalg.solve(N, r)  # (order + 1, 3)
    x = (te - t_last) / span
    b0 = np.zeros(nb)
    b1 = np.zeros(nb)
    b2 = np.zeros(nb)
    for k in range(nb):
        b0[k] = x**k
        if k >= 1:
            b1[k] = k * x ** (k - 1) / span
        if k >= 2:
            b2[k] = k * (k - 1) * x ** (k - 2) / span**2
    return count, b0 @ coef, b1 @ coef, b2 @ coef


class MotionHistory:
    """Ring buffer of recent (t, position, velocity) target estimates with a sliding-window fit.

    Only samples within ``window`` seconds of the newest one enter the fit, so the stale
    samples from before a long dropout are ignored.
    """

    def __init__(
        self,
        window: float = 1.5,
        capacity: int = 256,
        order: int = 2,
        velocity_weight: float = 0.25,
        min_samples: int = 10,
    ) -> None:
        if not (window > 0 and capacity >= 1 and min_samples >= order + 1):
            raise ValueError(
                f"need window > 0, capacity >= 1, min_samples >= order + 1; got window={window}, "
                f"capacity={capacity}, min_samples={min_samples}, order={order}"
            )
        self.window = float(window)
        self.order = int(order)
        self.velocity_weight = float(velocity_weight)
        self.min_samples = int(min_samples)
        self._t = np.full(capacity, -np.inf)
        self._p = np.zeros((capacity, 3))
        self._v = np.zeros((capacity, 3))
        self._next = 0
        self._count = 0

    def clear(self) -> None:
        """Forget all samples."""
        self._t[:] = -np.inf
        self._next = 0
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def add(self, t: float, position: np.ndarray, velocity: np.ndarray) -> None:
        """Append one sample (overwrites the oldest when full)."""
        i = self._next
        self._t[i] = t
        self._p[i] = position
        self._v[i] = velocity
        self._next = (i + 1) % self._t.size
        self._count = min(self._count + 1, self._t.size)

    def fit(self, t_eval: float | None = None) -> MotionFit | None:
        """Fit the samples in the window and evaluate at ``t_eval``; None if too few samples."""
        if self._count == 0:
            return None
        t_new = float(self._t.max())
        te = t_new if t_eval is None else float(t_eval)
        # the samples are finite and one control period apart: no checks needed
        n, pos, vel, acc = _fit(
            self._t,
            self._p,
            self._v,
            t_new - self.window,
            self.order,
            self.velocity_weight,
            te,
            self.min_samples,
        )
        return None if n < self.min_samples else MotionFit(te, pos, vel, acc)
