"""The target estimators of many UAVs as stacked arrays, stepped by one compiled call.

`TrackerBank` holds every state a `TargetEstimator` keeps (the UKF's x and P, the clock, the
dropout count, the held height, the motion history of Remark 2 and its fitted acceleration) for
``size`` UAVs in arrays, and steps any subset of them from the env's own data in one numba
kernel: the first detection initialises a filter (`TargetEstimator.reset`), later steps run
`TargetEstimator.begin_step_trusted`, the filter step of `team._step_filters` (the same
compiled code) and `TargetEstimator.end_step`. The arithmetic is that of those methods,
operation for operation, so both paths give the same estimates (tests/test_tracker_bank.py);
what the bank saves is the per-UAV Python around the kernel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from uavtrack_env.config import DT, CameraConfig
from uavtrack_env.estimation.motion_prediction import _fit
from uavtrack_env.estimation.team import _step_filters, _wrap, filter_constants
from uavtrack_env.estimation.ukf import DIM_X, DIM_Z, PSI, Estimate, TargetEstimator, UKFConfig

INPUT_COLUMNS = (
    "x", "y", "z", "yaw", "vx", "vy", "vz", "yaw_rate",
    "detected", "u", "v", "depth", "psi", "truncated_u", "truncated_v",
)  # fmt: skip
"""The columns of `TrackerBank.step`'s input rows: the UAV's own state after the step (GPS/IMU:
position, yaw, velocity, yaw rate) and the detector's report (flags as 0/1)."""

_OUT = DIM_X + 3 + 3 + 2
"""Output row: x (10), fitted acceleration (3), V_q in the camera frame (3), detected, steps
since the last detection."""


@numba.njit(cache=True)
def _clamped(acc, n_fit, min_samples, max_accel, out):  # pragma: no cover (compiled)
    """`TargetEstimator._clamp_accel` of a fit (none below ``min_samples``) into ``out``."""
    if n_fit < min_samples:
        out[:] = 0.0
        return
    n = math.sqrt(np.dot(acc, acc))
    if n > max_accel:
        for a in range(3):
            out[a] = acc[a] * (max_accel / n)
    else:
        out[:] = acc


@numba.njit(cache=True)
def _history_fit(i, t_eval, ht, hp, hv, hist, fit_p, fit_i):  # pragma: no cover (compiled)
    """`MotionHistory.fit` of slot i: (samples, velocity, acceleration); samples 0 when empty."""
    if hist[i, 1] == 0:
        return 0, np.zeros(3), np.zeros(3)
    t_new = np.max(ht[i])
    n, _pos, vel, acc = _fit(ht[i], hp[i], hv[i], t_new - fit_p[0], fit_i[0], fit_p[1], t_eval,
                             fit_i[1])  # fmt: skip
    return n, vel, acc


@numba.njit(cache=True)
def _record(i, x, clock, counts, accel, ht, hp, hv, hist, fit_p, fit_i):  # pragma: no cover
    """`TargetEstimator._record` of slot i: the history takes the estimate; refit every
    ``fit_every`` detected steps."""
    t = clock[i, 0]
    if t < fit_p[2]:
        return
    k = hist[i, 0]
    cap = ht.shape[1]
    ht[i, k] = t
    for a in range(3):
        hp[i, k, a] = x[i, 4 + a]
        hv[i, k, a] = x[i, 7 + a]
    hist[i, 0] = (k + 1) % cap
    hist[i, 1] = min(hist[i, 1] + 1, cap)
    counts[i, 1] += 1
    if counts[i, 1] % fit_i[2] == 0:
        n, _vel, acc = _history_fit(i, t, ht, hp, hv, hist, fit_p, fit_i)
        _clamped(acc, n, fit_i[1], fit_p[3], accel[i])


@numba.njit(cache=True)
def _output(i, j, x, P, accel, counts, yaw, detected, out_x, out_P):  # pragma: no cover
    """`TargetEstimator._estimate` of slot i into row j of the outputs."""
    for a in range(DIM_X):
        out_x[j, a] = x[i, a]
    for a in range(3):
        out_x[j, DIM_X + a] = accel[i, a]
    c, s = math.cos(yaw), math.sin(yaw)
    vx, vy, vz = x[i, 7], x[i, 8], x[i, 9]
    out_x[j, 13] = s * vx - c * vy  # `world_to_cam_vec`
    out_x[j, 14] = -vz
    out_x[j, 15] = c * vx + s * vy
    out_x[j, 16] = 1.0 if detected else 0.0
    out_x[j, 17] = counts[i, 0]
    out_P[j] = P[i]


@numba.njit(cache=True)
def _bank_step(
    slots, data, x, P, ready, clock, counts, accel, held, ht, hp, hv, hist, repairs,
    fit_p, fit_i, init_p, flags, lam, Wm, Wc, Q, R0, camera, x3_bounds, x12_limit, max_std,
    dt, out_x, out_P,
):  # fmt: skip  # pragma: no cover (compiled)
    """One step of the UAVs ``slots`` from their input rows (`INPUT_COLUMNS`), in place; row j
    of ``out_x``/``out_P`` gets slot j's estimate (when it has one: ``ready``)."""
    fx, fy, cu, cv = camera[0], camera[1], camera[2], camera[3]
    lo, hi = x3_bounds[0], x3_bounds[1]
    hold_height, planar, fit_velocity = flags[0], flags[1], flags[2]
    m = slots.shape[0]
    run = np.empty(m, np.int64)
    r = 0
    u = np.empty((m, 4))
    yaw_before = np.empty(m)
    acc_used = np.zeros((m, 3))
    seen = np.zeros(m, np.bool_)
    yaw_now = np.empty(m)
    z = np.zeros((m, DIM_Z))
    R = np.empty((m, DIM_Z, DIM_Z))
    for j in range(m):
        i = slots[j]
        row = data[j]
        detected = row[8] > 0.5
        yaw = row[3]
        if not ready[i]:
            if detected:  # `TargetEstimator.reset`: invert eq. (8)/(9), V_q = 0
                x1, x2 = (row[9] - cu) / fx, (row[10] - cv) / fy
                d = row[11]
                X, Y, Z = x1 * d, x2 * d, d
                c, s = math.cos(yaw), math.sin(yaw)
                x3 = min(max(1.0 / d, lo), hi)
                x[i, 0], x[i, 1], x[i, 2], x[i, PSI] = x1, x2, x3, _wrap(row[12])
                x[i, 4] = row[0] + (s * X + c * Z)  # `cam_to_world_vec`
                x[i, 5] = row[1] + (-c * X + s * Z)
                x[i, 6] = row[2] + -Y
                x[i, 7:] = 0.0
                P[i] = 0.0
                P[i, 0, 0] = (init_p[0] / fx) ** 2
                P[i, 1, 1] = (init_p[0] / fy) ** 2
                P[i, 2, 2] = (init_p[1] * x3 * x3) ** 2
                P[i, 3, 3] = init_p[2] ** 2
                for a in range(3):
                    P[i, 4 + a, 4 + a] = init_p[3] ** 2
                    P[i, 7 + a, 7 + a] = init_p[4 + a] ** 2
                ht[i] = -np.inf
                hist[i, 0], hist[i, 1] = 0, 0
                clock[i, 0], clock[i, 1] = 0.0, yaw
                counts[i, 0], counts[i, 1] = 0, 0
                accel[i] = 0.0
                held[i] = np.nan
                ready[i] = True
                _record(i, x, clock, counts, accel, ht, hp, hv, hist, fit_p, fit_i)
                _output(i, j, x, P, accel, counts, yaw, True, out_x, out_P)
            continue
        # `TargetEstimator.begin_step_trusted`
        c, s = math.cos(yaw), math.sin(yaw)
        vx, vy, vz = row[4], row[5], row[6]
        u[r, 0], u[r, 1], u[r, 2] = s * vx - c * vy, -vz, c * vx + s * vy  # `world_to_cam_vec`
        u[r, 3] = -row[7]
        R[r] = R0
        if detected:
            z[r, 0], z[r, 1], z[r, 2], z[r, 3] = row[9], row[10], row[11], _wrap(row[12])
            z[r, 4], z[r, 5], z[r, 6] = row[0], row[1], row[2]
            if hold_height:
                if row[14] > 0.5:
                    if math.isnan(held[i]):
                        held[i] = x[i, 6]
                    z[r, 1] = cv + fy * (row[2] - held[i]) / row[11]
                else:
                    held[i] = np.nan
            for a in range(2):
                if row[13 + a] > 0.5:
                    R[r, a, a] *= fit_p[4]
            seen[r] = True
        else:
            if counts[i, 0] == 0:  # dropout starts: freeze the fit (Fig. 5)
                n, vel, acc = _history_fit(i, clock[i, 0], ht, hp, hv, hist, fit_p, fit_i)
                _clamped(acc, n, fit_i[1], fit_p[3], accel[i])
                if n >= fit_i[1] and fit_velocity:
                    x[i, 7:10] = vel
                if planar:
                    accel[i, 2] = 0.0
                    x[i, 9] = 0.0
            acc_used[r] = accel[i]
        yaw_before[r] = clock[i, 1]
        yaw_now[r] = yaw
        run[r] = j
        r += 1
    if r == 0:
        return
    xr = np.empty((r, DIM_X))
    Pr = np.empty((r, DIM_X, DIM_X))
    for k in range(r):
        i = slots[run[k]]
        xr[k] = x[i]
        Pr[k] = P[i]
    rep = _step_filters(  # rows [0, r) of the inputs: the running filters
        xr, Pr, u, yaw_before, acc_used, seen, yaw_now, z, R, dt, lam, Wm, Wc, Q, camera,
        x3_bounds, x12_limit, max_std,
    )  # fmt: skip
    for k in range(r):  # `TargetEstimator.end_step`
        j = run[k]
        i = slots[j]
        x[i] = xr[k]
        P[i] = Pr[k]
        repairs[i] += rep[k]
        clock[i, 0] += dt
        clock[i, 1] = yaw_now[k]
        if seen[k]:
            counts[i, 0] = 0
            _record(i, x, clock, counts, accel, ht, hp, hv, hist, fit_p, fit_i)
        else:
            counts[i, 0] += 1
        _output(i, j, x, P, accel, counts, yaw_now[k], seen[k], out_x, out_P)


class TrackerBank:
    """The target estimators of ``size`` UAVs (one camera, `UKFConfig` and dt), as arrays.

    `step` advances any of them from their input rows (`INPUT_COLUMNS`); ``estimates[i]`` is
    slot i's latest `Estimate` (None until its first detection). `forget` starts slots over
    (a new episode). ``n_covariance_repairs[i]`` counts slot i's covariance repairs."""

    def __init__(
        self, size: int, camera: CameraConfig, cfg: UKFConfig | None = None, dt: float = DT
    ) -> None:
        cfg = cfg or UKFConfig()
        if not cfg.vectorized:
            raise ValueError("TrackerBank runs the array code: UKFConfig.vectorized must be True")
        template = TargetEstimator(camera, cfg, dt)  # the filter's constants, computed once
        lam, cam, x3_bounds, x12 = filter_constants(template)
        ukf = template.ukf
        self._consts = (
            np.array((cfg.fit_window, cfg.fit_velocity_weight, cfg.fit_settle_time,
                      cfg.max_target_accel, cfg.truncated_variance_scale)),
            np.array((cfg.fit_order, cfg.fit_min_samples, cfg.fit_every), np.int64),
            np.array((cfg.pixel_std, cfg.depth_std, cfg.psi_std, cfg.init_position_std,
                      *cfg.init_velocity_std)),
            np.array((cfg.truncated_v_hold_height, cfg.planar_target,
                      cfg.dropout_use_fit_velocity)),
            lam, ukf.Wm, ukf.Wc, ukf.Q, ukf.R, cam, x3_bounds, x12, template._max_std,
            float(template.dt),
        )  # fmt: skip
        cap = template.history._t.size
        self.size = size = int(size)
        self._x = np.zeros((size, DIM_X))
        self._P = np.zeros((size, DIM_X, DIM_X))
        self._ready = np.zeros(size, bool)
        self._clock = np.zeros((size, 2))  # t, the yaw of the last step
        self._counts = np.zeros((size, 2), np.int64)  # steps since detection, detected steps
        self._accel = np.zeros((size, 3))
        self._held = np.full(size, np.nan)  # the held height (NaN: none)
        self._ht = np.full((size, cap), -np.inf)
        self._hp = np.zeros((size, cap, 3))
        self._hv = np.zeros((size, cap, 3))
        self._hist = np.zeros((size, 2), np.int64)  # next index, samples
        self.n_covariance_repairs = np.zeros(size, np.int64)
        self._state = (
            self._x, self._P, self._ready, self._clock, self._counts, self._accel, self._held,
            self._ht, self._hp, self._hv, self._hist, self.n_covariance_repairs,
        )  # fmt: skip
        self.estimates = Estimates(size)
        """Slot i's latest `Estimate` (None until its first detection)."""

    def forget(self, slot: int) -> None:
        """Slot ``slot`` waits for a first detection again (its next one initialises it)."""
        self._ready[slot] = False
        self.estimates.clear(slot)

    def has_estimate(self, slot: int) -> bool:
        """Slot ``slot`` has had its first detection."""
        return bool(self._ready[slot])

    def step(self, slots: Sequence[int], data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step the UAVs ``slots`` (distinct) with their input rows ``data`` (len(slots), 15):
        the env's own data (finite, depth > 0 where detected), taken without further checks.
        Returns the step's outputs: row j of ``(out_x, out_P)`` is slot ``slots[j]``'s estimate
        (`Estimates.from_outputs`) where it has one."""
        idx, outputs = self.prepare(slots, data)
        _bank_step(idx, data, *self.kernel_args, *outputs)
        self.estimates.set(idx.tolist(), outputs, self._ready)
        return outputs

    def prepare(self, slots: Sequence[int], data: np.ndarray) -> tuple[np.ndarray, tuple]:
        """`step`'s checks of ``data`` and its output arrays: (slot indices, (out_x, out_P)).
        A caller that runs `_bank_step` inside a kernel of its own passes it ``kernel_args``
        and then gives `estimates` the outputs, as `step` does."""
        m = len(slots)
        if data.shape != (m, len(INPUT_COLUMNS)) or data.dtype != np.float64:
            raise ValueError(
                f"data must be a float64 array of shape ({m}, {len(INPUT_COLUMNS)}) (one row of "
                f"INPUT_COLUMNS per slot), got {data.dtype} {data.shape}"
            )
        return np.asarray(slots, np.int64), (np.empty((m, _OUT)), np.empty((m, DIM_X, DIM_X)))

    @property
    def kernel_args(self) -> tuple:
        """`_bank_step`'s arguments after (slots, data) and before the outputs: the state
        arrays (x, P, ready, clock, counts, ...) then the constants."""
        return (*self._state, *self._consts)


class Estimates(Sequence):
    """`TrackerBank.estimates`: each slot's latest `Estimate` (None before its first
    detection), made from its step's output rows when first read."""

    def __init__(self, size: int) -> None:
        self._made: list[Estimate | None] = [None] * size
        """Each slot's `Estimate`, once made."""
        self._outputs: list[tuple | None] = [None] * size
        """Each slot's latest step outputs (out_x, out_P)."""
        self._row = [0] * size
        """Each slot's row in them."""

    def set(self, slots: list[int], outputs: tuple[np.ndarray, np.ndarray], ready: np.ndarray):
        """Slot ``slots[j]``'s estimate is row j of `TrackerBank.step`'s ``outputs`` where
        ``ready[slots[j]]`` (it has had its first detection)."""
        for j, i in enumerate(slots):
            if ready[i]:
                self._made[i], self._outputs[i], self._row[i] = None, outputs, j

    def clear(self, slot: int) -> None:
        """Slot ``slot`` has no estimate."""
        self._made[slot] = self._outputs[slot] = None

    def __len__(self) -> int:
        return len(self._made)

    def __getitem__(self, slot):
        if isinstance(slot, slice):
            return [self[i] for i in range(*slot.indices(len(self)))]
        est = self._made[slot]
        if est is None and self._outputs[slot] is not None:
            (out_x, out_P), j = self._outputs[slot], self._row[slot]
            est = self._made[slot] = self.from_outputs(out_x[j], out_P[j])
        return est

    @staticmethod
    def from_outputs(row: np.ndarray, P: np.ndarray) -> Estimate:
        """The `Estimate` of one output row (x, acceleration, V_q in the camera frame,
        detected, steps since detection) and its covariance."""
        est = object.__new__(Estimate)  # fields set as the dataclass does
        est.__dict__.update(
            s=row[0:4], target_position=row[4:7], target_velocity=row[7:10],
            target_acceleration=row[10:13], vq_cam=row[13:16], detected=bool(row[16] > 0.5),
            covariance=P, steps_since_detection=int(row[17]),
        )  # fmt: skip
        return est
