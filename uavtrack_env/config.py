"""Typed, frozen configuration with the paper's defaults.

Every tunable of the project lives here. Field docstrings name the equation or table of
`seed-paper.md` ("Image-Based Multi-UAV Tracking System in a Cluttered Environment") each
value comes from. Angles are radians unless the field name ends in ``_deg``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

CONTROL_RATE_HZ = 80.0
"""Sampling rate of detection, estimation and control (section VI-A)."""

DT = 1.0 / CONTROL_RATE_HZ


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera fixed to the UAV body, looking along its heading (section VI-A)."""

    fx: float = 381.36
    """Focal length along U in pixels (K, section VI-A)."""
    fy: float = 381.36
    """Focal length along V in pixels (K, section VI-A)."""
    cu: float = 320.0
    """Principal point U in pixels (K, section VI-A)."""
    cv: float = 240.0
    """Principal point V in pixels (K, section VI-A)."""
    width: int = 640
    """Image width in pixels (section VI-A)."""
    height: int = 480
    """Image height in pixels (section VI-A)."""
    near: float = 0.1
    """Nearest depth (m) at which a point counts as in front of the camera."""

    def __post_init__(self) -> None:
        _require(
            self.fx > 0 and self.fy > 0, f"focal lengths must be > 0, got {self.fx}, {self.fy}"
        )
        _require(self.width > 0 and self.height > 0, "image size must be positive")
        _require(self.near > 0, f"near must be > 0, got {self.near}")

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K of section VI-A."""
        return np.array([[self.fx, 0.0, self.cu], [0.0, self.fy, self.cv], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ControlLimits:
    """Camera-frame velocity command bounds u = [v_cx, v_cy, v_cz, omega_cy] (Table II)."""

    v_max: float = 10.0
    """|v_cx|, |v_cy|, |v_cz| <= v_max in m/s (Table II)."""
    omega_max: float = 0.6
    """|omega_cy| <= omega_max in rad/s (Table II)."""

    def __post_init__(self) -> None:
        _require(self.v_max > 0 and self.omega_max > 0, "control limits must be > 0")

    @property
    def scale(self) -> np.ndarray:
        """Multiplier from the normalised action in [-1, 1]^4 to u in SI units."""
        return np.array([self.v_max, self.v_max, self.v_max, self.omega_max])


@dataclass(frozen=True)
class FeatureBounds:
    """State constraints on the feature vector s = [x1, x2, x3, psi] (Table I).

    Table I bounds psi to [0, 180 deg], which the paper's own references (psi* = -pi/2 for UAV3)
    violate; psi is therefore left unbounded here (see docs/conventions.md).
    """

    x1: tuple[float, float] = (-0.84, 0.84)
    """x1 = X/Z bounds (Table I); +-0.84 is the image's horizontal half-width 320/381.36."""
    x2: tuple[float, float] = (-0.63, 0.63)
    """x2 = Y/Z bounds (Table I); +-0.63 is the image's vertical half-height 240/381.36."""
    x3: tuple[float, float] = (0.07, 1.0)
    """x3 = 1/Z bounds (Table I): depth between 1 m and about 14.3 m."""


@dataclass(frozen=True)
class NMPCConfig:
    """Nonlinear MPC of eqs. (18)-(19) (Table III)."""

    horizon: int = 50
    """Prediction horizon N_p (Table III)."""
    dt: float = DT
    """Sampling time of the prediction model (section VI-A, 80 Hz)."""
    q_s: tuple[float, float, float, float] = (1.0, 1.0, 100.0, 1.0)
    """Diagonal of Q_s, stage feature weight (Table III; as printed it is indefinite)."""
    r_u: tuple[float, float, float, float] = (0.02, 0.03, 0.01, 0.3)
    """Diagonal of R_u, input weight (Table III; diagonal intent)."""
    w_s: tuple[float, float, float, float] = (1.0, 1.0, 100.0, 1.0)
    """Diagonal of the terminal weight W_s of eq. (18); the paper gives no value, Q_s is used."""
    terminal_weight: Literal["w_s", "lqr"] = "w_s"
    """W_s of eq. (18): 'w_s' = diag(w_s); 'lqr' = the solution P of the discrete Riccati equation
    for Q_s, R_u and the model (19) linearised at the NMPC's reference with the target still, i.e.
    the infinite-horizon cost-to-go. N_p = 50 steps is only 0.625 s, and with W_s = Q_s the loop
    is ~3x slower than the LQR with the same Q_s, R_u (not in the paper)."""
    solver: Literal["sqp", "ipopt", "rti"] = "sqp"
    """NLP solver: 'ipopt' as in the paper, 'sqp' (sqpmethod + qrqp, warm-started), 'rti'."""
    max_iter: int = 20
    """Iteration cap per solve."""
    yaw_rate_reference: Literal["zero", "target-turn"] = "zero"
    """omega_cy of the desired input u_d in (19): 'zero' (the paper) or 'target-turn', the
    target's turn rate from its estimated velocity and acceleration (not in the paper): R_u
    then stops pulling the yaw rate to 0 while the formation turns with the target."""
    turn_rate_min_speed: float = 0.2
    """Below this target speed (m/s) the turn rate is undefined and 0 is used."""
    safety_rows: int = 0
    """Not in the paper: how many of the shield's CBF half-spaces (47) the plan respects on its
    velocities (0 = the paper's NMPC, which does not know the CBF-QP exists). See
    `uavtrack_env.control.nmpc` and docs/conventions.md."""
    safety_row_stages: int | None = None
    """Plan stages 0..K-1 that respect those half-spaces (None: the whole horizon)."""

    def __post_init__(self) -> None:
        _require(self.horizon >= 1, f"horizon must be >= 1, got {self.horizon}")
        _require(self.safety_rows >= 0, f"safety_rows must be >= 0, got {self.safety_rows}")
        _require(
            self.yaw_rate_reference in ("zero", "target-turn"),
            f"yaw_rate_reference must be 'zero' or 'target-turn', got {self.yaw_rate_reference!r}",
        )
        _require(self.turn_rate_min_speed > 0, "turn_rate_min_speed must be > 0")
        _require(
            self.safety_row_stages is None or 1 <= self.safety_row_stages <= self.horizon,
            f"safety_row_stages must be None or in [1, horizon], got {self.safety_row_stages}",
        )
        _require(self.dt > 0, f"dt must be > 0, got {self.dt}")
        for name in ("q_s", "r_u", "w_s"):
            _require(all(w >= 0 for w in getattr(self, name)), f"{name} must be non-negative")
        _require(
            self.terminal_weight in ("w_s", "lqr"),
            f"terminal_weight must be 'w_s' or 'lqr', got {self.terminal_weight!r}",
        )
        _require(
            self.terminal_weight != "lqr" or min(self.r_u) > 0,
            "terminal_weight='lqr' needs every r_u > 0",
        )


@dataclass(frozen=True)
class CBFConfig:
    """Control barrier functions and the QP (47) (Table IV)."""

    r_s: float = 2.0
    """Minimum safety range R_s between UAVs, eq. (20) (Table IV)."""
    r_c: float = 20.0
    """Maximum connectivity range R_c, eq. (29) (Table IV)."""
    d_s: float = 20.0
    """Range D_s of the collision neighbour set N_si, eq. (27) (Table IV)."""
    theta_star_deg: float = 30.0
    """Occlusion-free half-angle theta* of eq. (37) in degrees (Table IV)."""
    gamma_s: float = 3.0
    """Collision CBF rate gamma_s, eq. (21) (Table IV); must satisfy eq. (28)."""
    gamma_c: float = 1.0
    """Connectivity CBF rate gamma_c, eq. (30) (Table IV)."""
    gamma_o: float = 0.1
    """Occlusion CBF rate gamma_o, eq. (40) (Table IV; Fig. 20 uses 0.5)."""
    alpha_v: float = 10.0
    """Speed bound ||V_c^g|| <= alpha_v in m/s, eq. (47) (Table IV)."""
    alpha_omega: float = 0.6
    """Angular speed bound ||omega_c^g|| <= alpha_omega in rad/s, eq. (47) (Table IV)."""
    obstacle_clearance: float = 0.75
    """Not in the paper: minimum distance (m) from a UAV's centre to an obstacle's surface."""
    gamma_obstacle: float = 3.0
    """Not in the paper: CBF rate for UAV-obstacle and UAV-target rows (like gamma_s)."""
    z_min: float = 0.5
    """Not in the paper: altitude floor (m) for the UAV centre."""
    gamma_z: float = 3.0
    """Not in the paper: CBF rate of the altitude floor."""
    occlusion_model: Literal["paper", "moving-target"] = "paper"
    """'paper': eq. (43), n-dot = 0; 'moving-target': n-dot from the estimated target velocity."""
    occlusion_point: Literal["centre", "axis", "edges"] = "axis"
    """Occluder point p_o of eq. (38): the box 'centre' (paper), or the point closest in angle to
    the line of sight on its vertical axis ('axis'; tall boxes are not points) or on its 12 edges
    ('edges'; wide boxes close to the UAV are not points either)."""
    occlusion_size_margin: bool = False
    """Not in the paper: widen theta* by the box's angular radius asin(r_xy / |p_o - p|)."""

    def __post_init__(self) -> None:
        _require(0 < self.r_s < self.d_s <= self.r_c, "need 0 < R_s < D_s <= R_c (eq. 27)")
        _require(0 < self.theta_star_deg < 90, "theta* must lie in (0, 90) degrees")
        _require(
            self.occlusion_point in ("centre", "axis", "edges"),
            f"occlusion_point must be 'centre', 'axis' or 'edges', got {self.occlusion_point!r}",
        )
        for name in ("gamma_s", "gamma_c", "gamma_o", "alpha_v", "alpha_omega", "gamma_z"):
            _require(getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")
        bound = 4.0 * self.alpha_v * self.r_s / (self.d_s**2 - self.r_s**2)
        _require(
            self.gamma_s >= bound,
            f"gamma_s = {self.gamma_s} violates eq. (28): the distributed collision CBF needs "
            f"gamma_s >= 4 alpha_v R_s / (D_s^2 - R_s^2) = {bound:.4f}",
        )

    @property
    def theta_star(self) -> float:
        """theta* in radians."""
        return math.radians(self.theta_star_deg)


@dataclass(frozen=True)
class DynamicsConfig:
    """UAV motion model."""

    model: Literal["integrator", "lag"] = "integrator"
    """'integrator': the paper's single integrator, eq. (3); 'lag': first-order velocity lag."""
    tau: float = 0.25
    """Velocity time constant (s) of the 'lag' model, a quadrotor's attitude-loop response."""
    a_max: float = 6.0
    """Acceleration limit (m/s^2) of the 'lag' model."""
    yaw_tau: float = 0.1
    """Yaw-rate time constant (s) of the 'lag' model."""

    def __post_init__(self) -> None:
        _require(self.model in ("integrator", "lag"), f"unknown dynamics model {self.model!r}")
        _require(self.tau > 0 and self.yaw_tau > 0 and self.a_max > 0, "lag params must be > 0")


@dataclass(frozen=True)
class DetectorConfig:
    """Geometric bounding-box detector (stands in for the paper's YOLO, section II-D)."""

    pixel_noise_std: float = 2.0
    """Std of the bounding-box centre noise (px)."""
    depth_noise_std: float = 0.1
    """Std of the depth noise (m)."""
    psi_noise_std: float = 0.03
    """Std of the relative-angle noise (rad)."""
    dropout_prob: float = 0.0
    """Probability that a visible target is not detected in a frame."""
    min_visible_fraction: float = 0.5
    """Detection needs at least this fraction of the target's sample points visible."""
    samples_per_axis: tuple[int, int, int] = (3, 2, 2)
    """Ray-cast sample grid on the target box (length, width, height); 12 rays per camera."""

    def __post_init__(self) -> None:
        for name in ("pixel_noise_std", "depth_noise_std", "psi_noise_std"):
            _require(getattr(self, name) >= 0, f"{name} must be >= 0")
        _require(0 <= self.dropout_prob <= 1, "dropout_prob must lie in [0, 1]")
        _require(0 < self.min_visible_fraction <= 1, "min_visible_fraction must lie in (0, 1]")
        _require(
            all(k >= 1 for k in self.samples_per_axis), "samples_per_axis entries must be >= 1"
        )

    @classmethod
    def noiseless(cls) -> DetectorConfig:
        """A detector without noise or dropouts (for tests and the ideal-sensor ablation)."""
        return cls(pixel_noise_std=0.0, depth_noise_std=0.0, psi_noise_std=0.0, dropout_prob=0.0)


@dataclass(frozen=True)
class CommsConfig:
    """Inter-UAV position messages (section IV-B: positions are known within R_c)."""

    r_c: float = 20.0
    """Communication range R_c (m) (Table IV)."""
    drop_prob: float = 0.0
    """Probability that one message is lost."""

    def __post_init__(self) -> None:
        _require(self.r_c > 0, "r_c must be > 0")
        _require(0 <= self.drop_prob <= 1, "drop_prob must lie in [0, 1]")


@dataclass(frozen=True)
class RewardConfig:
    """Reward from the stage cost c = e^T Q e + u^T R u of eq. (18) on true features."""

    q: tuple[float, float, float, float] = (1.0, 1.0, 100.0, 1.0)
    """Weights on [x1, x2, x3, psi] errors (Q_s diagonal, Table III)."""
    r: tuple[float, float, float, float] = (0.02, 0.03, 0.01, 0.3)
    """Weights on u = [v_cx, v_cy, v_cz, omega_cy] in SI units (R_u diagonal, Table III)."""
    lost_penalty: float = 1.0
    """Added to the tracking error when the target is not detected."""
    shape: str = "cost"
    """'cost': r = -c with c the stage cost of eq. (18) (the paper's objective). 'exp':
    r = exp(-c) in (0, 1], for RL: staying alive always pays, so a negative reward never makes
    ending the episode (by crashing) the best policy, and a lost target cannot dominate the
    scale."""
    collision_penalty: float = 0.0
    """Subtracted from the reward of a UAV on the step it collides (not in the paper)."""

    def __post_init__(self) -> None:
        _require(all(w >= 0 for w in (*self.q, *self.r)), "reward weights must be >= 0")
        _require(self.lost_penalty >= 0, "lost_penalty must be >= 0")
        _require(
            self.shape in ("cost", "exp"), f"shape must be 'cost' or 'exp', got {self.shape!r}"
        )
        _require(self.collision_penalty >= 0, "collision_penalty must be >= 0")


@dataclass(frozen=True)
class RandomWorldConfig:
    """Seeded cluttered-world generator for ``scenario="random"``."""

    n_obstacles: tuple[int, int] = (8, 16)
    """Inclusive range of the obstacle count."""
    size: tuple[float, float] = (0.6, 2.0)
    """Range of obstacle footprint edge lengths (m)."""
    height: tuple[float, float] = (0.8, 4.0)
    """Range of obstacle heights (m)."""
    extent: float = 40.0
    """Obstacles are placed within this distance ahead of the target's start (m)."""
    corridor: float = 2.5
    """Half-width (m) of the target's path kept free of obstacles."""
    target_speed: tuple[float, float] = (0.3, 1.0)
    """Range of the target's cruise speed (m/s)."""
    target_turn_rate: float = 0.25
    """Maximum target turn rate (rad/s)."""
    start_offset: float = 0.2
    """Each UAV starts within +-start_offset (m, per axis) of its formation pose; larger values
    (e.g. 3) give the off-formation starts of Table VI's second rows to learn from."""
    start_heading_offset: float = 0.0
    """Start heading within +-this (rad) of facing the car (0: facing it)."""

    def __post_init__(self) -> None:
        for name in ("n_obstacles", "size", "height", "target_speed"):
            lo, hi = getattr(self, name)
            _require(0 <= lo <= hi, f"{name} must be an ordered range (lo <= hi), got {(lo, hi)}")
        _require(self.extent > 0 and self.corridor > 0, "extent and corridor must be > 0")
        _require(self.target_turn_rate >= 0, "target_turn_rate must be >= 0")
        _require(0 <= self.start_offset <= 5.0, "start_offset must be in [0, 5] m")
        _require(
            0 <= self.start_heading_offset <= 1.0, "start_heading_offset must be in [0, 1] rad"
        )


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines one environment instance; `parallel_env(**kw)` fills it."""

    scenario: Literal["A", "B", "C", "random"] = "A"
    """Paper scenario (Table VI) or a seeded random world."""
    init: int = 0
    """Initial condition 0 or 1 of the scenario (the two rows per scenario of Table VI)."""
    n_uavs: int = 3
    """Number of UAVs; the paper's scenarios have 3."""
    max_cycles: int = 4800
    """Steps before truncation (4800 = 60 s at 80 Hz)."""
    render_mode: str | None = None
    """None, 'rgb_array' or 'human'."""
    terminate_on_collision: Literal["agent", "all"] = "all"
    """On a collision, end that agent only or the whole team."""
    n_neighbours: int = 4
    """K nearest neighbours in the observation."""
    n_obstacles_obs: int = 4
    """K nearest obstacles in the observation."""
    uav_radius: float = 0.25
    """Collision sphere radius of a UAV body (m)."""
    camera: CameraConfig = field(default_factory=CameraConfig)
    limits: ControlLimits = field(default_factory=ControlLimits)
    features: FeatureBounds = field(default_factory=FeatureBounds)
    cbf: CBFConfig = field(default_factory=CBFConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    comms: CommsConfig = field(default_factory=CommsConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    random_world: RandomWorldConfig = field(default_factory=RandomWorldConfig)

    def __post_init__(self) -> None:
        _require(
            self.scenario in ("A", "B", "C", "random"),
            f"scenario must be 'A', 'B', 'C' or 'random', got {self.scenario!r}",
        )
        _require(self.init in (0, 1), f"init must be 0 or 1 (Table VI rows), got {self.init!r}")
        _require(
            isinstance(self.n_uavs, int) and self.n_uavs >= 1,
            f"n_uavs must be >= 1, got {self.n_uavs}",
        )
        _require(
            self.scenario == "random" or self.n_uavs == 3,
            f"scenario {self.scenario!r} defines 3 UAVs (Table VI), got n_uavs={self.n_uavs}; "
            "use scenario='random' for other team sizes",
        )
        _require(
            isinstance(self.max_cycles, int) and self.max_cycles >= 1, "max_cycles must be >= 1"
        )
        _require(
            self.render_mode in (None, "rgb_array", "human"),
            f"render_mode must be None, 'rgb_array' or 'human', got {self.render_mode!r}",
        )
        _require(
            self.terminate_on_collision in ("agent", "all"),
            "terminate_on_collision must be 'agent' or 'all'",
        )
        _require(self.n_neighbours >= 0 and self.n_obstacles_obs >= 0, "K must be >= 0")
        _require(self.uav_radius > 0, "uav_radius must be > 0")

    @classmethod
    def from_kwargs(cls, **kwargs: Any) -> EnvConfig:
        """Build from keyword arguments; nested configs may be given as dicts.

        Unknown names raise TypeError listing the valid ones.
        """
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(kwargs) - set(fields))
        if unknown:
            raise TypeError(f"unknown argument(s) {unknown}; valid arguments are {sorted(fields)}")
        values = {}
        for name, value in kwargs.items():
            default = getattr(cls(), name) if name in _NESTED else None
            if name in _NESTED and isinstance(value, dict):
                valid = {f.name for f in dataclasses.fields(default)}
                bad = sorted(set(value) - valid)
                if bad:
                    raise TypeError(
                        f"unknown field(s) {bad} in {name}; valid fields are {sorted(valid)}"
                    )
                value = dataclasses.replace(default, **value)
            elif name in _NESTED and not isinstance(value, type(default)):
                raise TypeError(
                    f"{name} must be a {type(default).__name__} or a dict of its fields, "
                    f"got {type(value).__name__}"
                )
            values[name] = value
        return cls(**values)


_NESTED = {
    "camera",
    "limits",
    "features",
    "cbf",
    "dynamics",
    "detector",
    "comms",
    "reward",
    "random_world",
}
