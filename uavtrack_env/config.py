"""Typed, frozen configuration with the paper's defaults.

Every tunable of the project lives here. Field docstrings name the equation or table of
`seed-paper.md` ("Image-Based Multi-UAV Tracking System in a Cluttered Environment") each
value comes from. Angles are radians unless the field name ends in ``_deg``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from .validation import Fields as _Fields
from .validation import require as _require

CONTROL_RATE_HZ = 80.0
"""Sampling rate of detection, estimation and control (section VI-A)."""

DT = 1.0 / CONTROL_RATE_HZ


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
        f = _Fields(self)
        for name in ("fx", "fy", "near"):
            f.number(name, lo=0, lo_open=True)
        # The principal point lies in the image (any pixel of it, edges included).
        f.number("cu", lo=0, hi=f.integer("width", lo=1))
        f.number("cv", lo=0, hi=f.integer("height", lo=1))

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
        f = _Fields(self)
        f.number("v_max", lo=0, lo_open=True)
        f.number("omega_max", lo=0, lo_open=True)

    @property
    def scale(self) -> np.ndarray:
        """Multiplier from the normalised action in [-1, 1]^4 to u in SI units."""
        return np.array([self.v_max, self.v_max, self.v_max, self.omega_max])


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
        f = _Fields(self)
        f.choice("model", ("integrator", "lag"))
        for name in ("tau", "a_max", "yaw_tau"):
            f.number(name, lo=0, lo_open=True)


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
        f = _Fields(self)
        for name in ("pixel_noise_std", "depth_noise_std", "psi_noise_std"):
            f.number(name, lo=0)
        f.number("dropout_prob", lo=0, hi=1)
        f.number("min_visible_fraction", lo=0, hi=1, lo_open=True)
        counts = f.tuple("samples_per_axis", 3, integer=True, lo=1)
        rays = int(np.prod(counts))
        _require(
            rays <= MAX_RAYS_PER_STEP,
            f"DetectorConfig.samples_per_axis = {counts} casts {rays} rays per UAV and step; "
            f"PyBullet's ray batch takes at most {MAX_RAYS_PER_STEP} (MAX_RAYS_PER_STEP)",
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
        f = _Fields(self)
        f.number("r_c", lo=0, lo_open=True)
        f.number("drop_prob", lo=0, hi=1)


@dataclass(frozen=True)
class ViolationConfig:
    """Where the env counts a violation (the link range is ``comms.r_c``, the one R_c)."""

    r_s: float = 2.0
    """Two UAVs closer than R_s collide, eq. (20) (Table IV)."""

    def __post_init__(self) -> None:
        _Fields(self).number("r_s", lo=0, lo_open=True)


@dataclass(frozen=True)
class RewardConfig:
    """Reward from the stage cost c = e^T Q e + u^T R u of eq. (18) on true features."""

    q: tuple[float, float, float, float] = (1.0, 1.0, 100.0, 1.0)
    """Weights on [x1, x2, x3, psi] errors (Q_s diagonal, Table III)."""
    r: tuple[float, float, float, float] = (0.02, 0.03, 0.01, 0.3)
    """Weights on u = [v_cx, v_cy, v_cz, omega_cy] in SI units (R_u diagonal, Table III)."""
    lost_penalty: float = 1.0
    """Added to the tracking error when the target is not detected."""
    shape: str = "exp"
    """'exp' (for RL): r = exp(-c) in (0, 1] with c the stage cost of eq. (18): staying alive
    always pays, so ending the episode by crashing is never the best policy, and a lost target
    cannot dominate the scale. 'cost': r = -c, the paper's objective (``defaults="paper"``)."""
    collision_penalty: float = 10.0
    """Subtracted from the reward of a UAV on each step it is in collision (not in the paper;
    0 with ``defaults="paper"``)."""
    image_point: str = "box"
    """Which image point the x1, x2 errors score: 'box' (for RL), the noise-free bounding box's
    centre, the point Table V's RMS errors measure and the expert's detections give; 'center',
    the projection of the car's centre (the feature s of eq. (18); ``defaults="paper"``). The
    two differ by perspective, most for a car seen end-on."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.tuple("q", 4, lo=0)
        f.tuple("r", 4, lo=0)
        f.number("lost_penalty", lo=0)
        f.choice("shape", ("cost", "exp"))
        f.number("collision_penalty", lo=0)
        f.choice("image_point", ("center", "box"))


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
    min_start_altitude: float = 0.9
    """A random start is feasible only with every UAV at least this high (m)."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.range_pair("n_obstacles", lo=0, hi=MAX_RANDOM_OBSTACLES, integer=True)
        f.range_pair("size", lo=0, lo_open=True)
        f.range_pair("height", lo=0, lo_open=True)
        f.range_pair("target_speed", lo=0)
        f.number("extent", lo=0, lo_open=True)
        f.number("corridor", lo=0, lo_open=True)
        f.number("target_turn_rate", lo=0)
        f.number("start_offset", lo=0, hi=5.0)
        f.number("start_heading_offset", lo=0, hi=1.0)
        f.number("min_start_altitude", lo=0)


MAX_EPISODE_STEPS = 1_000_000
"""Upper limit of `EnvConfig.max_cycles` (3.5 h at 80 Hz). The random scenario precomputes the
car's program for the whole episode at reset (`scenarios.random_layout` draws one 2-6 s segment
at a time for ``max_cycles * DT`` seconds), so an unbounded episode length could hang reset."""

MAX_RAYS_PER_STEP = 16383
"""Most detector rays per step (``n_uavs * prod(detector.samples_per_axis)``): the detector casts
them in one ``pybullet.rayTestBatch`` (`World.rays_reach_target`). PyBullet's
MAX_RAY_INTERSECTION_BATCH_SIZE is 16384, and pybullet 3.2.7 raises "Number of rays exceed the
maximum batch size" above it and silently returns only 16383 results for exactly 16384 rays."""

MAX_RANDOM_OBSTACLES = 1000
"""Upper limit of `RandomWorldConfig.n_obstacles`: each obstacle is placed by rejection sampling
against the earlier ones at reset and becomes a PyBullet body."""


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
    terminate_on_collision: Literal["agent", "all", "never"] = "agent"
    """What a collision ends: 'agent' (that UAV leaves the episode, the team flies on), 'all'
    (the whole team; the paper's evaluation, ``defaults="paper"``) or 'never' (Safety-
    Gymnasium's convention: every UAV flies on and each step in collision is charged as cost)."""
    n_neighbours: int = 4
    """K nearest neighbours in the observation."""
    n_obstacles_obs: int = 4
    """K nearest obstacles in the observation."""
    uav_radius: float = 0.25
    """Collision sphere radius of a UAV body (m)."""
    skip_proven_queries: bool = True
    """Skip the PyBullet ray casts and contact queries whose answer the geometry proves (a ray
    to the car with nothing near its path, a UAV far from everything;
    `uavtrack_env.broadphase`); the results equal PyBullet's. False sends every query."""
    camera: CameraConfig = field(default_factory=CameraConfig)
    limits: ControlLimits = field(default_factory=ControlLimits)
    violations: ViolationConfig = field(default_factory=ViolationConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    comms: CommsConfig = field(default_factory=CommsConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    random_world: RandomWorldConfig = field(default_factory=RandomWorldConfig)

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.choice("scenario", ("A", "B", "C", "random"))
        f.integer("init", lo=0, hi=1)  # the two rows per scenario of Table VI
        f.integer("n_uavs", lo=1)
        _require(
            self.scenario == "random" or self.n_uavs == 3,
            f"EnvConfig.n_uavs must be 3 for scenario {self.scenario!r} (Table VI defines 3 "
            f"UAVs), got {self.n_uavs}; use scenario='random' for other team sizes",
        )
        f.integer("max_cycles", lo=1, hi=MAX_EPISODE_STEPS)
        f.choice("render_mode", (None, "rgb_array", "human"))
        f.choice("terminate_on_collision", ("agent", "all", "never"))
        f.integer("n_neighbours", lo=0)
        f.integer("n_obstacles_obs", lo=0)
        f.number("uav_radius", lo=0, lo_open=True)
        f.flag("skip_proven_queries")
        for name, kind in _NESTED_TYPES.items():
            f.instance(name, kind)
        rays = self.n_uavs * int(np.prod(self.detector.samples_per_axis))
        _require(
            rays <= MAX_RAYS_PER_STEP,
            f"EnvConfig.n_uavs = {self.n_uavs} UAVs x detector.samples_per_axis = "
            f"{self.detector.samples_per_axis} cast {rays} rays per step in one PyBullet "
            f"rayTestBatch, which takes at most {MAX_RAYS_PER_STEP} (MAX_RAYS_PER_STEP); "
            "use fewer UAVs or fewer samples",
        )
        _require(
            self.violations.r_s < self.comms.r_c,
            f"EnvConfig.violations.r_s = {self.violations.r_s} m must be < comms.r_c = "
            f"{self.comms.r_c} m: no pair could be both collision-free and linked",
        )

    @classmethod
    def from_kwargs(cls, defaults: str = "rl", **kwargs: Any) -> EnvConfig:
        """Build from keyword arguments over the named ``defaults`` (`ENV_DEFAULTS`: 'rl', the
        dataclass defaults, or 'paper'); nested configs may be given as dicts, which update the
        named defaults field by field.

        Unknown names raise TypeError listing the valid ones.
        """
        if defaults not in ENV_DEFAULTS:
            raise ValueError(f"unknown defaults {defaults!r}; choose one of {sorted(ENV_DEFAULTS)}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(kwargs) - set(fields))
        if unknown:
            valid = sorted([*fields, "defaults"])
            raise TypeError(f"unknown argument(s) {unknown}; valid arguments are {valid}")
        for name, base in ENV_DEFAULTS[defaults].items():
            given = kwargs.get(name)
            if name not in kwargs:
                kwargs[name] = base
            elif isinstance(given, dict) and isinstance(base, dict):
                kwargs[name] = {**base, **given}
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


ENV_DEFAULTS: dict[str, dict[str, Any]] = {
    "rl": {},
    "paper": {
        "terminate_on_collision": "all",
        "reward": {"shape": "cost", "collision_penalty": 0.0, "image_point": "center"},
    },
}
"""Named starting points of `EnvConfig.from_kwargs` (``parallel_env(defaults=...)``), as the
fields they change from the dataclass defaults. 'rl' (default): r = exp(-c) minus a collision
penalty on the bounding box's centre, a collision ends that UAV only. 'paper': r = -c of eq.
(18) on the car's centre, a collision ends the episode for all (``baselines.evaluate``'s
setting)."""

_NESTED = {
    "camera",
    "limits",
    "violations",
    "dynamics",
    "detector",
    "comms",
    "reward",
    "random_world",
}

_NESTED_TYPES = {
    "camera": CameraConfig,
    "limits": ControlLimits,
    "violations": ViolationConfig,
    "dynamics": DynamicsConfig,
    "detector": DetectorConfig,
    "comms": CommsConfig,
    "reward": RewardConfig,
    "random_world": RandomWorldConfig,
}
