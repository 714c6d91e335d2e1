"""Unscented Kalman filter on the paper's target model (sections II-C to II-E, eqs. 5-11, 14).

State (eq. 5), 10 entries::

    x = [x1, x2, x3, psi, r_q (3), V_q (3)]

* ``x1, x2, x3 = X/Z, Y/Z, 1/Z`` (eq. 6) of the target centre in the current camera frame.
* ``psi`` is the relative angle of eq. (4), wrapped to (-pi, pi].
* ``r_q`` and ``V_q`` are the target's position and velocity in the **global** frame (x forward,
  y left, z up): the car moves on the ground, so a constant-velocity model is natural there. The
  feature rows of (14) need V_q in the camera frame; it is rotated with the UAV's known yaw.

Process model: the continuous model (14) (feature rows = :func:`uavtrack_env.geometry.
feature_rates`, i.e. eq. (15) with omega_cx = omega_cz = 0; r_q-dot = V_q; V_q-dot = 0, or the
fitted target acceleration of Remark 2 during a dropout), discretised by forward Euler (10).
Measurement model (9)/(11): ``z = [u_px, v_px, d, psi, r_c]`` with ``d = Z`` the optical-axis depth
of the target centre (so ``x3 = 1/d``, eq. 8) and ``r_c = r_q - R_c^g(yaw) r_{q/c}`` the UAV's own
GPS position, which ties the image features to the global target position.

Angles: psi residuals are wrapped and sigma-point means of psi are circular means (filterpy's
``residual_x``/``residual_z``/``x_mean_fn``/``z_mean_fn``/``state_add`` hooks).

Covariance guard: sigma points use a square root that falls back from Cholesky to a clipped
eigen-decomposition (filterpy's ``sqrt_method`` hook), so filterpy never raises on an indefinite P;
after every predict/update P is symmetrised, repaired by eigenvalue clipping if Cholesky fails, and
capped per state (``UKFConfig.max_std``, a congruence scaling that keeps P positive definite) so
long dropouts cannot grow it without bound.

Speed: :class:`VectorizedUKF` subclasses filterpy's filter and pushes all sigma points through
fx and hx in one numpy call each; sigma points, weights, ``unscented_transform`` and the update
equations stay filterpy's. `uavtrack_env.estimation.bank.TrackerBank` runs the same equations and
bookkeeping for a whole team in one compiled call (see ``benchmarks/ukf_speed.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter, unscented_transform

from uavtrack_env.config import DT, CameraConfig
from uavtrack_env.estimation.motion_prediction import MotionFit, MotionHistory
from uavtrack_env.geometry import (
    cam_to_world_vec,
    feature_rates,
    world_to_cam_vec,
    wrap_angle,
    wrap_scalar,
)
from uavtrack_env.validation import Fields as _Fields

DIM_X = 10
"""State size, eq. (5)."""
DIM_Z = 7
"""Measurement size, eq. (11): [u_px, v_px, d, psi, r_c]."""
PSI = 3
"""Index of psi in both the state and the measurement."""


@dataclass(frozen=True)
class UKFConfig:
    """Tunables of the target UKF (section II-E) and the dropout motion fit (Remark 2)."""

    q_features: tuple[float, float, float, float] = (2.5e-4, 2.5e-4, 1e-5, 1e-3)
    """Process-noise densities of [x1, x2, x3, psi] per second, w_k of eq. (10): Q = q dt."""
    q_position: float = 1e-4
    """Process-noise density of r_q (m^2/s), w_k of eq. (10)."""
    q_velocity: tuple[float, float, float] = (0.05, 0.05, 0.002)
    """Target acceleration noise densities of global V_q (m^2/s^3), Remark 1's model mismatch."""
    pixel_std: float = 2.0
    """Std of the bounding-box centre (px), v_k of eq. (11)."""
    depth_std: float = 0.1
    """Std of the depth d = Z (m), v_k of eq. (11)."""
    psi_std: float = 0.03
    """Std of the measured relative angle psi (rad), v_k of eq. (11)."""
    truncated_variance_scale: float = 1.0
    """Multiplier of the pixel variance of a box coordinate cut by the image border (not in the
    paper; 1 = off; 1e6 all but ignores it). Off by default: ignoring v let x2 drift with the
    estimated car height in scenario C, and with the car filling the image (both axes cut) a
    collision-seeking policy reached the car through the RL shield."""
    gps_std: float = 0.05
    """Std of the UAV's own position r_c (m), v_k of eq. (11)."""
    init_position_std: float = 0.5
    """Initial std of r_q per axis (m) on reset."""
    init_velocity_std: tuple[float, float, float] = (3.0, 3.0, 0.3)
    """Initial std of global V_q per axis (m/s) on reset."""
    alpha: float = 0.5
    """Merwe sigma-point spread alpha (section II-E, ref. [30])."""
    beta: float = 2.0
    """Merwe prior-knowledge parameter beta (2 is optimal for Gaussians)."""
    kappa: float = 0.0
    """Merwe secondary scaling kappa."""
    x3_bounds: tuple[float, float] = (0.01, 10.0)
    """Clamp of the estimated x3 = 1/Z (depth between 0.1 m and 100 m); keeps 1/x3 finite."""
    x12_limit: float = 5.0
    """Clamp of |x1|, |x2| (79 deg off-axis, far outside the FOV): keeps the state finite when a
    dropout prediction runs the target past the image plane, where eq. (6) is singular."""
    max_std: tuple[float, ...] = (2.0, 2.0, 1.0, math.pi, 50.0, 50.0, 50.0, 10.0, 10.0, 10.0)
    """Ceiling on each state's std; bounds covariance growth in long dropouts."""
    fit_window: float = 3.0
    """Length (s) of the window of recent estimates fitted by the polynomial (Remark 2)."""
    fit_order: int = 2
    """Degree of the motion polynomial (Remark 2)."""
    fit_velocity_weight: float = 0.25
    """Weight (s^2) of the velocity residuals in the fit (Remark 2 fits position and velocity)."""
    fit_min_samples: int = 20
    """Fewer detected samples than this in the window: no fit, zero acceleration."""
    fit_settle_time: float = 0.0
    """Not in the paper: estimates of the first this-many seconds after reset are not fitted
    (Remark 2), since V_q converging from its initial 0 reads as an acceleration there."""
    fit_every: int = 4
    """Refit every this many detected steps (the fit costs ~30 us; 20 Hz is plenty)."""
    max_target_accel: float = 3.0
    """Norm clamp (m/s^2) of the fitted acceleration fed to the dropout prediction (Fig. 5)."""
    truncated_v_hold_height: bool = False
    """When the box is cut by the top or bottom border, replace its biased centre v by the value
    that the target's height estimated before the cut, the own altitude and the measured depth
    give, v = c_v + f_y (z_uav - z_q) / d (a pseudo-measurement, not in the paper: the car stays
    on the ground). The expert turns it on; a UAV looking down over a tall box otherwise sees the
    car rise as the bottom of its box leaves the image, or, with v ignored, lets x2 drift."""
    planar_target: bool = True
    """The target moves in the X-Y plane (section VI-A): the dropout prediction (Remark 2) keeps
    its height, with zero vertical velocity and acceleration."""
    dropout_use_fit_velocity: bool = True
    """At the start of a dropout, replace the mean of V_q by the fitted velocity (Fig. 5)."""
    vectorized: bool = True
    """Array code: a team's filters in one compiled call (`estimation.bank.TrackerBank`, the
    onboard stacks' path) and, for one UAV, the vectorised filterpy subclass (~5x); both equal plain
    filterpy to round-off. False: plain filterpy, one UAV at a time."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        positive = {"lo": 0, "lo_open": True}
        f.tuple("q_features", 4, **positive)
        f.number("q_position", **positive)
        f.tuple("q_velocity", 3, **positive)
        for name in ("pixel_std", "depth_std", "psi_std", "gps_std", "init_position_std"):
            f.number(name, **positive)
        f.number("truncated_variance_scale", lo=1)
        f.tuple("init_velocity_std", 3, **positive)
        f.number("alpha", **positive)
        f.number("beta")
        # Merwe's weights need n + kappa > 0 (lambda + n = alpha^2 (n + kappa)).
        f.number("kappa", lo=-DIM_X, lo_open=True)
        f.range_pair("x3_bounds", lo=0, lo_open=True, strict=True)
        f.number("x12_limit", **positive)
        f.tuple("max_std", DIM_X, **positive)
        f.number("fit_window", **positive)
        order = f.integer("fit_order", lo=0)
        f.number("fit_velocity_weight", lo=0)
        f.integer("fit_min_samples", lo=order + 1)  # a degree-k fit needs k + 1 samples
        f.number("fit_settle_time", lo=0)
        f.integer("fit_every", lo=1)
        f.number("max_target_accel", **positive)
        for name in (
            "truncated_v_hold_height",
            "planar_target",
            "dropout_use_fit_velocity",
            "vectorized",
        ):
            f.flag(name)


@dataclass(frozen=True)
class Measurement:
    """What the detector reports for one UAV in one frame (section II-D)."""

    u: float
    """Bounding-box centre along U (px)."""
    v: float
    """Bounding-box centre along V (px)."""
    depth: float
    """d = Z, optical-axis depth of the target centre (m), so x3 = 1/d (eq. 8)."""
    psi: float
    """Relative angle of eq. (4) (rad); wrapped by the filter."""
    truncated_u: bool = False
    """The box touches the left or right image border: its centre u is biased inwards."""
    truncated_v: bool = False
    """The box touches the top or bottom image border: its centre v is biased inwards."""

    @classmethod
    def trusted(
        cls, u: float, v: float, depth: float, psi: float, truncated_u: bool, truncated_v: bool
    ) -> Measurement:
        """A measurement from the env's own detector, already finite with depth > 0: built
        without the checks of the constructor."""
        meas = object.__new__(cls)
        meas.__dict__.update(
            u=u, v=v, depth=depth, psi=psi, truncated_u=truncated_u, truncated_v=truncated_v
        )
        return meas

    def __post_init__(self) -> None:
        vals = (self.u, self.v, self.depth, self.psi)
        if not all(isinstance(a, int | float | np.floating | np.integer) for a in vals):
            raise ValueError(f"Measurement fields must be real scalars, got {vals}")
        if not all(math.isfinite(float(a)) for a in vals):
            raise ValueError(f"Measurement fields must be finite, got {vals}")
        if not float(self.depth) > 0:
            raise ValueError(f"Measurement depth must be > 0 (target in front), got {self.depth}")


@dataclass
class Estimate:
    """The filter's output for one UAV and one step."""

    s: np.ndarray
    """Features [x1, x2, x3, psi] (psi wrapped), the NMPC's initial state s_k (eq. 19)."""
    target_position: np.ndarray
    """Global target position r_q (3,)."""
    target_velocity: np.ndarray
    """Global target velocity V_q (3,)."""
    target_acceleration: np.ndarray
    """Global target acceleration from the polynomial fit (Remark 2); zeros without enough data."""
    vq_cam: np.ndarray
    """Target velocity in the current camera frame (3,), for the NMPC model (15)."""
    detected: bool
    """Whether this step had a measurement update."""
    covariance: np.ndarray
    """State covariance P (10, 10)."""
    steps_since_detection: int = 0
    """Steps since the last measurement update (0 when detected)."""


class StepPlan(NamedTuple):
    """One estimator step's inputs, checked and prepared (`TargetEstimator.begin_step`)."""

    u: np.ndarray
    """Camera-frame command applied over the step, [v_cx, v_cy, v_cz, omega_cy]."""
    yaw_before: float
    """The UAV's yaw at the start of the step (the prediction's camera frame)."""
    yaw: float
    """The UAV's yaw now (after the step)."""
    z: np.ndarray | None
    """The measurement vector of eq. (11), None without a detection."""
    R: np.ndarray | None
    """Its noise covariance when it differs from the filter's R (a truncated box)."""
    accel: np.ndarray
    """Global target acceleration of the prediction (Remark 2 during a dropout, else 0)."""


# ---------------------------------------------------------------- models (numpy, batched)


def process_model(
    x: np.ndarray, dt: float, u: np.ndarray, yaw: float, accel: np.ndarray
) -> np.ndarray:
    """Forward-Euler step (10) of model (14) for states of shape (10,) or (..., N, 10).

    ``u`` is the camera-frame command [v_cx, v_cy, v_cz, omega_cy] applied over the step, ``yaw``
    the UAV yaw at the start of the step, ``accel`` the global target acceleration (zero in the
    paper's constant-velocity model; the fitted one during a dropout). With several filters,
    ``u`` (K, 1, 4), ``yaw`` (K, 1) and ``accel`` (K, 1, 3) broadcast against x (K, N, 10).
    """
    xt = np.moveaxis(x, -1, 0)
    vq_cam = np.moveaxis(world_to_cam_vec(x[..., 7:10], yaw), -1, 0)
    # eq. (15) rows of (14)
    sdot = np.stack(feature_rates(xt[0:4], np.moveaxis(u, -1, 0), vq_cam), -1)
    out = x.copy()
    out[..., 0:4] += dt * sdot
    out[..., PSI] = wrap_angle(out[..., PSI])
    out[..., 4:7] += dt * x[..., 7:10]  # r_q-dot = V_q
    out[..., 7:10] += dt * accel  # V_q-dot = 0 (eq. 14) or the fitted acceleration
    return out


def measurement_model(x: np.ndarray, yaw: float, camera: CameraConfig, x3_min: float) -> np.ndarray:
    """h(x) of eq. (9) for states (10,) or (..., N, 10): [u_px, v_px, d, psi, r_c].

    r_c = r_q - R_c^g(yaw) r_{q/c} with r_{q/c} = [x1, x2, 1] / x3 in the camera frame.
    x3 is floored at ``x3_min`` so wide sigma points cannot divide by zero. With several
    filters, ``yaw`` (K, 1) broadcasts against x (K, N, 10).
    """
    x1, x2 = x[..., 0], x[..., 1]
    x3 = np.maximum(x[..., 2], x3_min)
    depth = 1.0 / x3
    r_qc_cam = np.stack([x1 * depth, x2 * depth, depth], -1)
    r_c = x[..., 4:7] - cam_to_world_vec(r_qc_cam, yaw)
    img = np.stack([camera.fx * x1 + camera.cu, camera.fy * x2 + camera.cv, depth, x[..., PSI]], -1)
    return np.concatenate([img, r_c], -1)


def angle_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b with the psi entry wrapped; works on (n,) and (N, n) arrays."""
    d = np.subtract(a, b)
    d[..., PSI] = wrap_angle(d[..., PSI])
    return d


def circular_mean(sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
    """Weighted mean of sigma points with psi averaged on the circle."""
    m = Wm @ sigmas
    m[PSI] = math.atan2(Wm @ np.sin(sigmas[:, PSI]), Wm @ np.cos(sigmas[:, PSI]))
    return m


def angle_add(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """x + dx with psi wrapped (filterpy's state_add hook)."""
    y = np.add(x, dx)
    y[..., PSI] = wrap_angle(y[..., PSI])
    return y


def safe_sqrt(P: np.ndarray) -> np.ndarray:
    """Matrix square root S with S.T @ S = P for sigma points: Cholesky, else clipped eigen.

    filterpy uses the rows of the returned matrix as sigma offsets, so any S with S.T S = P works.
    """
    P = 0.5 * (P + P.T)
    try:
        return np.linalg.cholesky(P).T
    except np.linalg.LinAlgError:
        lam, V = np.linalg.eigh(P)
        floor = 1e-12 * max(float(np.max(np.abs(lam))), 1.0)
        return np.sqrt(np.maximum(lam, floor))[:, None] * V.T


def repair_covariance(
    P: np.ndarray, max_std: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symmetrise covariances (K, n, n), clip the spectrum of those whose Cholesky fails, cap
    their stds at ``max_std``: (P, repaired (K,), capped (K,))."""
    Ps = 0.5 * (P + np.swapaxes(P, -1, -2))
    repaired = np.zeros(len(Ps), bool)
    try:
        np.linalg.cholesky(Ps)
    except np.linalg.LinAlgError:
        for k, Pk in enumerate(Ps):
            try:
                np.linalg.cholesky(Pk)
            except np.linalg.LinAlgError:
                lam, V = np.linalg.eigh(Pk)
                floor = 1e-12 * max(float(np.max(np.abs(lam))), 1.0)
                Pk = (V * np.maximum(lam, floor)) @ V.T
                Ps[k] = 0.5 * (Pk + Pk.T)
                repaired[k] = True
    std = np.sqrt(np.maximum(np.diagonal(Ps, axis1=-2, axis2=-1), 0.0))
    scale = np.minimum(1.0, max_std / np.maximum(std, 1e-300))
    capped = np.any(scale < 1.0, axis=-1)
    if capped.any():  # a factor 1 is exact: uncapped matrices stay bit for bit
        Ps = scale[:, :, None] * Ps * scale[:, None, :]
    return Ps, repaired, capped


def tidy_states(
    x: np.ndarray, P: np.ndarray, cfg: UKFConfig, max_std: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Guard K filter states after a predict or update: wrap psi and clamp x1..x3 of ``x``
    (K, 10) in place; symmetrise, repair and cap ``P`` (K, 10, 10).

    Returns (P, changed beyond the wrap (K,), repaired (K,))."""
    x[:, PSI] = wrap_angle(x[:, PSI])
    lim, (lo, hi) = cfg.x12_limit, cfg.x3_bounds
    s = np.clip(x[:, 0:3], [-lim, -lim, lo], [lim, lim, hi])
    clamped = np.any(s != x[:, 0:3], axis=1)
    x[:, 0:3] = s
    P, repaired, capped = repair_covariance(P, max_std)
    return P, clamped | repaired | capped, repaired


# ---------------------------------------------------------------- filterpy filters


def _angle_safe_ut(
    sigmas: np.ndarray,
    Wm: np.ndarray,
    Wc: np.ndarray,
    noise_cov: np.ndarray | None = None,
    mean_fn: Callable | None = None,
    residual_fn: Callable | None = None,
):
    """filterpy's unscented_transform on its fast (vectorised) branch.

    psi of each sigma point is first moved by a multiple of 2 pi to lie within pi of the circular
    mean, so the plain subtraction inside filterpy equals the wrapped residual.
    """
    mean = circular_mean(sigmas, Wm)
    s = sigmas.copy()
    s[:, PSI] = mean[PSI] + wrap_angle(sigmas[:, PSI] - mean[PSI])
    return unscented_transform(s, Wm, Wc, noise_cov, circular_mean, None)


class VectorizedSigmaPoints(MerweScaledSigmaPoints):
    """filterpy's Merwe points with the 2n rows built in one array operation (the same numbers:
    filterpy's loop computes x - (-U_k) and x - U_k with plain subtraction)."""

    def sigma_points(self, x, P) -> np.ndarray:
        if self.n != np.size(x):
            raise ValueError(f"expected size(x) {self.n}, but size is {np.size(x)}")
        lambda_ = self.alpha**2 * (self.n + self.kappa) - self.n
        U = self.sqrt((lambda_ + self.n) * np.atleast_2d(P))
        x = np.asarray(x, dtype=float)
        return np.concatenate([x[None], x + U, x - U])


class VectorizedUKF(UnscentedKalmanFilter):
    """filterpy's UKF with fx and hx applied to all sigma points in one numpy call each.

    ``fx_batch(sigmas (N, n), dt, **fx_args) -> (N, n)`` and ``hx_batch(sigmas, **hx_args) ->
    (N, m)``. The residual functions must accept (N, n) arrays. Predict and update are filterpy's
    own methods; only the per-sigma-point Python loops (fx, hx, the residual loop of the unscented
    transform and of the cross covariance) are replaced by array operations.
    """

    def __init__(self, *args, fx_batch: Callable, hx_batch: Callable, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.fx_batch = fx_batch
        self.hx_batch = hx_batch

    def compute_process_sigmas(self, dt, fx=None, **fx_args) -> None:
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = self.fx_batch(sigmas, dt, **fx_args)

    def predict(self, dt=None, UT=None, fx=None, **fx_args) -> None:
        super().predict(dt, UT or _angle_safe_ut, fx, **fx_args)

    def update(self, z, R=None, UT=None, hx=None, **hx_args) -> None:
        if z is None:
            super().update(None)
            return
        rows = iter(self.hx_batch(self.sigmas_f, **hx_args))
        super().update(z, R, UT or _angle_safe_ut, lambda _s, **_kw: next(rows), **hx_args)

    def cross_variance(self, x, z, sigmas_f, sigmas_h) -> np.ndarray:
        dx = self.residual_x(sigmas_f, x)
        dz = self.residual_z(sigmas_h, z)
        return (dx * self.Wc[:, None]).T @ dz


def make_filter(
    camera: CameraConfig, cfg: UKFConfig, dt: float, vectorized: bool | None = None
) -> UnscentedKalmanFilter:
    """Build the filterpy UKF on models (10)-(11); plain filterpy if ``vectorized`` is False."""
    vectorized = cfg.vectorized if vectorized is None else vectorized
    x3_min = cfg.x3_bounds[0]
    # Sigma points use plain subtraction: psi of a sigma point may leave (-pi, pi] by a little,
    # which is harmless (fx wraps it, circular means and wrapped residuals absorb it) and saves
    # 20 Python calls per sigma-point set.
    kind = VectorizedSigmaPoints if vectorized else MerweScaledSigmaPoints
    points = kind(DIM_X, cfg.alpha, cfg.beta, cfg.kappa, sqrt_method=safe_sqrt)

    def hx(x: np.ndarray, yaw: float) -> np.ndarray:
        return measurement_model(x, yaw, camera, x3_min)

    kwargs = dict(
        dim_x=DIM_X,
        dim_z=DIM_Z,
        dt=dt,
        hx=hx,
        fx=process_model,
        points=points,
        x_mean_fn=circular_mean,
        z_mean_fn=circular_mean,
        residual_x=angle_residual,
        residual_z=angle_residual,
        state_add=angle_add,
    )
    ukf = (
        VectorizedUKF(fx_batch=process_model, hx_batch=hx, **kwargs)
        if vectorized
        else UnscentedKalmanFilter(**kwargs)
    )
    q = np.concatenate([cfg.q_features, [cfg.q_position] * 3, cfg.q_velocity])
    ukf.Q = np.diag(q * dt)
    ukf.R = np.diag(
        [cfg.pixel_std**2, cfg.pixel_std**2, cfg.depth_std**2, cfg.psi_std**2]
        + [cfg.gps_std**2] * 3
    )
    return ukf


# ---------------------------------------------------------------- the estimator


_DEFAULT_CAMERA = CameraConfig()
_DEFAULT_CFG = UKFConfig()


def _vec(name: str, value, n: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array of shape ({n},), got {value!r}") from exc
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {arr.shape}")
    if not all(map(math.isfinite, arr.tolist())):
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


def _scalar(name: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real scalar, got {value!r}") from exc
    if not math.isfinite(out):
        raise ValueError(f"{name} must be finite, got {value}")
    return out


class TargetEstimator:
    """Per-UAV target estimator: filterpy UKF (10)-(11) plus the dropout motion fit (Remark 2).

    Call :meth:`reset` with the first detection, then :meth:`step` once per control period with
    the command applied over that period, the UAV's own pose, and the detection (or None).
    """

    def __init__(
        self, camera: CameraConfig = _DEFAULT_CAMERA, cfg: UKFConfig = _DEFAULT_CFG, dt: float = DT
    ) -> None:
        if not isinstance(camera, CameraConfig):
            raise ValueError(f"camera must be a CameraConfig, got {type(camera).__name__}")
        if not isinstance(cfg, UKFConfig):
            raise ValueError(f"cfg must be a UKFConfig, got {type(cfg).__name__}")
        self.dt = _scalar("dt", dt)
        if self.dt <= 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self.camera = camera
        self.cfg = cfg
        self.ukf = make_filter(camera, cfg, self.dt)
        self.history = MotionHistory(
            window=cfg.fit_window,
            capacity=max(math.ceil(cfg.fit_window / self.dt) + 1, cfg.fit_min_samples),
            order=cfg.fit_order,
            velocity_weight=cfg.fit_velocity_weight,
            min_samples=cfg.fit_min_samples,
        )
        self._max_std = np.asarray(cfg.max_std, dtype=float)
        self._ready = False
        self.t = 0.0
        self.n_covariance_repairs = 0
        """How often P had to be repaired (indefinite after a predict/update)."""
        self._yaw = 0.0
        self._since = 0
        self._detected_steps = 0
        self._accel = np.zeros(3)
        self._held_height: float | None = None

    # -- helpers

    def _z(self, meas: Measurement, uav_position: np.ndarray) -> np.ndarray:
        x, y, z = uav_position.tolist()
        return np.array((meas.u, meas.v, meas.depth, wrap_scalar(meas.psi), x, y, z), dtype=float)

    def _clamp_accel(self, fit: MotionFit | None) -> np.ndarray:
        if fit is None:
            return np.zeros(3)
        a = fit.acceleration
        n = float(np.linalg.norm(a))
        return a * (self.cfg.max_target_accel / n) if n > self.cfg.max_target_accel else a.copy()

    def _tidy(self) -> bool:
        """Wrap psi, clamp x1..x3, guard P; True if x or P changed beyond the wrap."""
        P, changed, repaired = tidy_states(
            self.ukf.x[None], self.ukf.P[None], self.cfg, self._max_std
        )
        self.ukf.P = P[0]
        self.n_covariance_repairs += int(repaired[0])
        return bool(changed[0])

    def _estimate(self, yaw: float, detected: bool) -> Estimate:
        x = self.ukf.x.copy()
        return Estimate(
            s=x[0:4],
            target_position=x[4:7],
            target_velocity=x[7:10],
            target_acceleration=self._accel.copy(),
            vq_cam=world_to_cam_vec(x[7:10], yaw),
            detected=detected,
            covariance=self.ukf.P.copy(),
            steps_since_detection=self._since,
        )

    def _record(self) -> None:
        if self.t < self.cfg.fit_settle_time:
            return
        self.history.add(self.t, self.ukf.x[4:7], self.ukf.x[7:10])
        self._detected_steps += 1
        if self._detected_steps % self.cfg.fit_every == 0:
            self._accel = self._clamp_accel(self.history.fit(self.t))

    # -- public API

    def reset(self, meas: Measurement, uav_position: np.ndarray, uav_yaw: float) -> Estimate:
        """Initialise the state from one detection by inverting eq. (8)/(9); V_q starts at 0."""
        if meas is None:
            raise ValueError("reset needs a Measurement (the target must be detected at start)")
        if not isinstance(meas, Measurement):
            raise ValueError(f"meas must be a Measurement, got {type(meas).__name__}")
        p = _vec("uav_position", uav_position, 3)
        yaw = _scalar("uav_yaw", uav_yaw)
        z = self._z(meas, p)
        cam, cfg = self.camera, self.cfg
        x1, x2 = (z[0] - cam.cu) / cam.fx, (z[1] - cam.cv) / cam.fy
        d = z[2]
        r_q = p + cam_to_world_vec(np.array([x1 * d, x2 * d, d]), yaw)
        x3 = min(max(1.0 / d, cfg.x3_bounds[0]), cfg.x3_bounds[1])
        self.ukf.x = np.concatenate([[x1, x2, x3, z[PSI]], r_q, np.zeros(3)])
        var = [
            (cfg.pixel_std / cam.fx) ** 2,
            (cfg.pixel_std / cam.fy) ** 2,
            (cfg.depth_std * x3 * x3) ** 2,
            cfg.psi_std**2,
            *([cfg.init_position_std**2] * 3),
            *np.square(cfg.init_velocity_std),
        ]
        self.ukf.P = np.diag(var)
        self.history.clear()
        self.t = 0.0
        self._yaw = yaw
        self._since = 0
        self._detected_steps = 0
        self._accel = np.zeros(3)
        self._held_height = None
        self._ready = True
        self._record()
        return self._estimate(yaw, True)

    def step(
        self,
        u_applied: np.ndarray,
        uav_position: np.ndarray,
        uav_yaw: float,
        meas: Measurement | None,
    ) -> Estimate:
        """Predict over dt with the applied command (10); update with the detection if any (11).

        ``u_applied`` = [v_cx, v_cy, v_cz, omega_cy] in the camera frame held over the last dt,
        ``uav_position`` and ``uav_yaw`` the UAV pose now (after the step). Without a detection
        the filter only predicts, with the target acceleration (and, at the dropout's start, the
        velocity) from the polynomial fit of Remark 2. `TrackerBank` runs the same step for several
        UAVs at once.
        """
        plan = self.begin_step(u_applied, uav_position, uav_yaw, meas)
        self.ukf.predict(dt=self.dt, u=plan.u, yaw=plan.yaw_before, accel=plan.accel)
        if self._tidy():  # keep the update's sigma points consistent with the tidied prior
            self.ukf.sigmas_f = self.ukf.points_fn.sigma_points(self.ukf.x, self.ukf.P)
        if plan.z is not None:
            self.ukf.update(plan.z, R=plan.R, yaw=plan.yaw)
            self._tidy()
        return self.end_step(plan)

    def begin_step(
        self,
        u_applied: np.ndarray,
        uav_position: np.ndarray,
        uav_yaw: float,
        meas: Measurement | None,
    ) -> StepPlan:
        """Check the inputs of `step` and prepare its filter step: the measurement vector (with
        the held height), its noise, and the dropout start of Remark 2 (which edits V_q)."""
        if not self._ready:
            raise RuntimeError("call reset() with a first detection before step()")
        u = _vec("u_applied", u_applied, 4)
        p = _vec("uav_position", uav_position, 3)
        yaw = _scalar("uav_yaw", uav_yaw)
        if meas is not None and not isinstance(meas, Measurement):
            raise ValueError(f"meas must be a Measurement or None, got {type(meas).__name__}")
        return self.begin_step_trusted(u, p, yaw, meas)

    def begin_step_trusted(
        self, u: np.ndarray, p: np.ndarray, yaw: float, meas: Measurement | None
    ) -> StepPlan:
        """`begin_step` of inputs the caller guarantees: finite float64 arrays u (4,) and p
        (3,), a float yaw, a `Measurement` or None (the env's own data); no checks."""
        z = None if meas is None else self._z(meas, p)
        if z is not None and self.cfg.truncated_v_hold_height:
            if meas.truncated_v:
                if self._held_height is None:
                    self._held_height = float(self.ukf.x[6])
                z[1] = self.camera.cv + self.camera.fy * (p[2] - self._held_height) / meas.depth
            else:
                self._held_height = None

        if z is None and self._since == 0:  # dropout starts: freeze the fit (Fig. 5)
            fit = self.history.fit(self.t)
            self._accel = self._clamp_accel(fit)
            if fit is not None and self.cfg.dropout_use_fit_velocity:
                self.ukf.x[7:10] = fit.velocity
            if self.cfg.planar_target:
                self._accel[2] = 0.0
                self.ukf.x[9] = 0.0
        accel = self._accel if z is None else np.zeros(3)
        R = None
        if z is not None and (meas.truncated_u or meas.truncated_v):
            R = self.ukf.R.copy()
            for i, cut in enumerate((meas.truncated_u, meas.truncated_v)):
                if cut:
                    R[i, i] *= self.cfg.truncated_variance_scale
        return StepPlan(u, self._yaw, yaw, z, R, accel)

    def end_step(self, plan: StepPlan) -> Estimate:
        """Close a step after the filter's predict and update: clock, dropout count, history."""
        self.t += self.dt
        self._yaw = plan.yaw
        if plan.z is None:
            self._since += 1
        else:
            self._since = 0
            self._record()
        return self._estimate(plan.yaw, plan.z is not None)
