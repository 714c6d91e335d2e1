"""The PettingZoo ParallelEnv: n UAVs with fixed cameras track a car through box obstacles."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from . import core, core_kernels
from . import render as rendering
from .config import EnvConfig
from .core import NEIGHBOUR_FIELDS, OBSTACLE_FIELDS, Measurements, Score
from .infos import PixelFrame, agent_infos
from .scenarios import Layout, make_layout
from .sensors import Detections, Detector, UAVSnapshot
from .target import TargetMotion
from .world import World

Bound = float | Callable[[EnvConfig], float]
"""An observation bound: a number, or a function of the env's config."""


@dataclass(frozen=True)
class ObsField:
    """One block of the observation vector: its name, meaning and per-entry (low, high) bounds.

    The bounds are finite; values beyond them are clipped (documented in the env's docstring).
    """

    name: str
    meaning: str
    bounds: tuple[tuple[Bound, Bound], ...]
    """(low, high) of each entry, in order; a callable is evaluated on the EnvConfig."""

    @property
    def size(self) -> int:
        return len(self.bounds)

    def low_high(self, cfg: EnvConfig) -> tuple[list[float], list[float]]:
        """The block's lower and upper bounds for ``cfg``."""
        value = [[b(cfg) if callable(b) else b for b in pair] for pair in self.bounds]
        return [lo for lo, _ in value], [hi for _, hi in value]


def _inv_near(cfg: EnvConfig) -> float:
    return 1 / cfg.camera.near


def _speed(sign: float) -> Callable[[EnvConfig], float]:
    """Bound of an observed speed: twice the command limit v_max."""
    return lambda cfg: sign * 2.0 * cfg.limits.v_max


def _turn(sign: float) -> Callable[[EnvConfig], float]:
    return lambda cfg: sign * 2.0 * cfg.limits.omega_max


def _comms(sign: float) -> Callable[[EnvConfig], float]:
    return lambda cfg: sign * cfg.comms.r_c


WORLD_LIMIT = 1.0e4
"""Bound (m, m/s) of the state vector's entries."""
ALTITUDE_LIMIT = 100.0
"""Observed altitude is clipped to [0, ALTITUDE_LIMIT] m."""
OBSTACLE_RANGE = 100.0
"""Observed obstacle offsets and sizes are clipped to +-OBSTACLE_RANGE m."""

_UNIT = (-1, 1)
_FEATURE_BOUNDS = ((-5, 5), (-5, 5), (0, _inv_near), _UNIT, _UNIT)
OWN_FIELDS = (
    ObsField(
        "features",
        "measured x1, x2, x3, sin psi, cos psi (zeros when not detected), eqs. (6), (8)",
        _FEATURE_BOUNDS,
    ),
    ObsField("detection", "detected flag, visible fraction of the target", ((0, 1), (0, 1))),
    ObsField(
        "velocity",
        "own velocity in the camera frame [v_cx, v_cy, v_cz] (m/s)",
        ((_speed(-1), _speed(1)),) * 3,
    ),
    ObsField("yaw_rate", "own omega_cy (rad/s)", ((_turn(-1), _turn(1)),)),
    ObsField("heading", "sin yaw, cos yaw", (_UNIT, _UNIT)),
    ObsField("altitude", "own z (m)", ((0, ALTITUDE_LIMIT),)),
    ObsField(
        "reference",
        "x1*, x2*, x3*, sin psi*, cos psi* of this agent's reference s*",
        _FEATURE_BOUNDS,
    ),
)
"""The agent's own blocks, in order, each with its bounds."""
NEIGHBOUR_FIELD = ObsField(
    "neighbour",
    "rel. position (camera frame), mask",
    ((_comms(-1), _comms(1)),) * 3 + ((0, 1),),
)
"""Per neighbour (one of the K nearest received): relative position in the camera frame (3, m),
mask (1)."""
OBSTACLE_FIELD = ObsField(
    "obstacle",
    "rel. centre (camera frame), half extents, mask",
    ((-OBSTACLE_RANGE, OBSTACLE_RANGE),) * 3 + ((0, OBSTACLE_RANGE),) * 3 + ((0, 1),),
)
"""Per obstacle (one of the K nearest): relative centre in the camera frame (3, m), half extents
(3, m), mask (1)."""


class UAVTrackEnv(ParallelEnv):
    """Cooperative visual tracking of a car by n UAVs in a cluttered PyBullet world.

    Implements the setting of "Image-Based Multi-UAV Tracking System in a Cluttered Environment"
    (Hung, Hsu, Cheng): each UAV carries a fixed pinhole camera (K of section VI-A, no gimbal) and
    must keep the car at its reference image features s* = [x1*, x2*, x3*, psi*] while avoiding
    collisions, staying connected within R_c and keeping obstacles from hiding the car.

    **Agents**: ``uav_0 ... uav_{n-1}`` (``n_uavs``, 3 in the paper's scenarios).

    **Action** (per agent): ``Box(-1, 1, (4,), float32)``, scaled by Table II to the camera-frame
    velocity command u = [v_cx, v_cy, v_cz, omega_cy] = a * [10, 10, 10, 0.6] (m/s, rad/s); camera
    frame X right, Y down, Z forward. Finite values outside [-1, 1] are clipped and counted in
    ``info["n_clipped_actions"]``; NaN/inf, wrong shapes, unknown or finished agents raise.

    **Observation** (per agent): a float32 vector; see ``observation_fields()``: measured features,
    detection, own velocity/yaw rate/heading/altitude, the reference, then K nearest received
    neighbours and K nearest obstacles (camera frame, with masks).

    **Reward**: from the NMPC stage cost (18) on the true features (weights Table III),
    c = sum q_k e_k^2 + lost_penalty * not_detected + sum r_k u_k^2: r = exp(-c) in (0, 1] by
    default (for RL: crashing never pays), minus ``reward.collision_penalty`` (10) on each step in
    collision, with x1, x2 at the bounding box's centre (the point of the RMS errors); the
    paper's r = -c on the car's centre with ``defaults="paper"``. Both parts of -c are in
    ``info`` (``reward_tracking``, ``reward_effort``).

    **Cost and violations** (``info[agent]``): ``violations = {collision, disconnection,
    occlusion}`` (bools), ``costs`` the same keys as floats (1.0 when violated this step, else
    0.0) and ``cost`` their sum (`SafeRLParallelEnv` returns it from ``step``). Collision:
    touching an obstacle, the car or the ground (PyBullet contacts), or another UAV closer than
    R_s. Disconnection: the UAVs' graph with edges <= R_c is not connected. Occlusion: obstacles
    (or UAVs) block more of the car's sample points than the detector can tolerate. Every info
    value is finite: a nearest distance to nothing (a UAV alone, a world without obstacles) is
    `infos.NOTHING_NEAR` (1e4 m).

    **Episode end**: ``terminate_on_collision`` = 'agent' (default) terminates a UAV that
    collides and the team flies on; 'all' terminates every UAV (``defaults="paper"``); 'never'
    terminates none and charges each step in collision as cost (Safety-Gymnasium's convention).
    Truncated after ``max_cycles`` steps (80 Hz).

    **Arguments**: the fields of :class:`uavtrack_env.config.EnvConfig`, over ``defaults``
    ('rl', or 'paper': r = -c on the car's centre and a collision ends the episode for all, as
    in the paper's evaluation; `uavtrack_env.config.ENV_DEFAULTS`); unknown names raise.

    **Seams**: ``validate_actions(actions)`` runs step()'s checks and scaling without stepping
    (u in SI units, clip flags); ``snapshot()`` returns the true state as a
    :class:`~uavtrack_env.sensors.UAVSnapshot` (copies); ``layout`` holds the episode's obstacles
    and references; ``world`` the PyBullet bodies. ``step`` runs simulate -> sense -> score ->
    observe, each its own method; the random stream is drawn by the detector, then the comms.

    **Version history**: v0: initial release.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": ["rgb_array", "human"],
        "name": "uavtrack_v0",
        "is_parallelizable": True,
        "render_fps": 80,
    }

    def __init__(self, **kwargs: Any) -> None:
        self.config = cfg = EnvConfig.from_kwargs(**kwargs)
        self.render_mode = cfg.render_mode
        self.max_cycles = cfg.max_cycles
        self.possible_agents = [f"uav_{i}" for i in range(cfg.n_uavs)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._every_row = list(range(cfg.n_uavs))
        self._scale = cfg.limits.scale
        self._constants = core.Constants.of(cfg)
        self.n_obs = (
            sum(f.size for f in OWN_FIELDS)
            + cfg.n_neighbours * NEIGHBOUR_FIELDS
            + cfg.n_obstacles_obs * OBSTACLE_FIELDS
        )
        self._obs_low, self._obs_high = self._observation_bounds()
        obs_space = gymnasium.spaces.Box(self._obs_low, self._obs_high, dtype=np.float32)
        self._obs_spaces = {a: obs_space for a in self.possible_agents}
        self._act_spaces = {
            a: gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32) for a in self.possible_agents
        }
        self.state_space = gymnasium.spaces.Box(
            -WORLD_LIMIT, WORLD_LIMIT, (9 * cfg.n_uavs + 8,), np.float32
        )
        self.world = World(gui=self.render_mode == "human")
        self.detector = Detector(cfg.camera, cfg.detector)
        self.np_random: np.random.Generator | None = None
        self.layout: Layout | None = None
        self.last_detection: Detections | None = None
        self.last_received: np.ndarray | None = None
        """(n, n) bool: UAV i heard UAV j's message at the latest step or reset."""
        self.num_cycles = 0

    # ----------------------------------------------------------------- spaces
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._obs_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._act_spaces[self._check_agent(agent)]

    def _check_agent(self, agent: str) -> str:
        if agent not in self._index:
            raise KeyError(f"unknown agent {agent!r}; agents are {self.possible_agents}")
        return agent

    def _observation_fields(self) -> list[ObsField]:
        cfg = self.config
        return [
            *OWN_FIELDS,
            *[NEIGHBOUR_FIELD] * cfg.n_neighbours,
            *[OBSTACLE_FIELD] * cfg.n_obstacles_obs,
        ]

    def _observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite bounds per observation entry, from the field table; values beyond them are
        clipped (documented)."""
        low: list[float] = []
        high: list[float] = []
        for f in self._observation_fields():
            lo, hi = f.low_high(self.config)
            low += lo
            high += hi
        assert len(low) == self.n_obs
        return np.array(low, np.float32), np.array(high, np.float32)

    def observation_fields(self) -> list[tuple[str, int, str]]:
        """(name, size, meaning) of each block of the observation vector, in order."""
        cfg = self.config
        own = [(f.name, f.size, f.meaning) for f in OWN_FIELDS]
        nb, ob = NEIGHBOUR_FIELD, OBSTACLE_FIELD
        return [
            *own,
            *[(f"{nb.name}_{k}", nb.size, nb.meaning) for k in range(cfg.n_neighbours)],
            *[(f"{ob.name}_{k}", ob.size, ob.meaning) for k in range(cfg.n_obstacles_obs)],
        ]

    # ------------------------------------------------------------------ reset
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start an episode: seed (an int >= 0, or None to go on with the env's generator) ->
        (observations, infos). ``options`` are ignored, as PettingZoo's API test expects (the env
        is configured through ``uavtrack_v0.parallel_env(**config)``)."""
        self._check_open("reset")
        if seed is not None or self.np_random is None:
            self.np_random, _ = seeding.np_random(seed)
        cfg = self.config
        self.layout = layout = make_layout(cfg, self.np_random)
        self.world.build(layout, cfg.uav_radius)
        n = cfg.n_uavs
        self.position = layout.uav_positions.astype(float).copy()
        self.yaw = layout.uav_yaws.astype(float).copy()
        self.velocity = np.zeros((n, 3))
        self.yaw_rate = np.zeros(n)
        self.alive = np.ones(n, bool)
        self.target = TargetMotion(layout.target_program, *layout.target_start)
        self.references = layout.references
        self._pixels = PixelFrame.of(cfg.camera, layout.references)
        self.agents = self.possible_agents[:]
        self.num_cycles = 0
        self._clip_count = np.zeros(n, int)
        self.last_action = np.zeros((n, 4))
        self.world.set_poses(self.position, self.yaw, self.alive, self.target.center(), 0.0)
        self._obstacles = core.Obstacles.stack([layout])
        u, clipped = np.zeros((n, 4)), np.zeros(n, bool)
        batch = self._sense()
        m, score = self._view(batch, self._score(batch, u))
        return self._observe(batch), self._infos(m, score, u, clipped)

    # ------------------------------------------------------------------- step
    def step(self, actions: dict[str, Any]):
        """simulate -> sense -> score -> observe; then the episode's end."""
        return self._step_checked(*self.validate_actions(actions))

    def _step_checked(self, u: np.ndarray, clipped: np.ndarray):
        """`step` of actions `validate_actions` has checked and scaled (u, clipped)."""
        batch, batch_score = self._advance(u, clipped)
        obs = self._observe(batch)
        m, score = self._view(batch, batch_score)
        reward = score.reward.tolist()
        rewards = {a: reward[self._index[a]] for a in self.agents}
        infos = self._infos(m, score, u, clipped)
        terminations, truncations = self._episode_end(score.collided)
        return obs, rewards, terminations, truncations, infos

    def _advance(self, u: np.ndarray, clipped: np.ndarray) -> tuple[Measurements, Score]:
        """simulate -> sense -> score: the step's state change and its measurements (a batch
        of one world; `_view` gives the world's own)."""
        self._simulate(u, clipped)
        m = self._sense()
        return m, self._score(m, u)

    def _view(self, m: Measurements, score: Score) -> tuple[Measurements, Score]:
        """This world's measurements and score from its batch of one (and its detections and
        messages as ``last_detection``, ``last_received``)."""
        view = m.world(0, self._obstacles.counts[0])
        self.last_detection, self.last_received = view.detections, view.received
        return view, score.world(0)

    def validate_actions(self, actions: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """Check a step's actions without changing anything.

        Returns u (n, 4) float64 in SI units (clipped to Table II; zero rows for finished
        agents) and clipped (n,) bool (the agent's action left [-1, 1]). Raises RuntimeError
        before reset or after the episode's end; KeyError for unknown, finished or missing
        agents; ValueError for a non-dict, wrong shapes or non-finite values.
        """
        self._check_can_act(actions)
        try:  # every action at once; the first bad one is named below
            stacked = np.array(list(actions.values()), dtype=np.float64)
        except (TypeError, ValueError):
            stacked = None
        # A sum is finite only if every term is (an overflow just takes the slow path).
        if (
            stacked is None
            or stacked.shape != (len(actions), 4)
            or not math.isfinite(stacked.sum())
        ):
            stacked = [self.check_action(agent, act) for agent, act in actions.items()]
        return self._scaled([self._index[agent] for agent in actions], stacked)

    def _scaled(self, rows: list[int], actions: Any) -> tuple[np.ndarray, np.ndarray]:
        """`validate_actions`' (u, clipped) of checked float64 actions (len(rows), 4) of the
        live agents in ``rows``."""
        if rows == self._every_row and isinstance(actions, np.ndarray):
            a = actions  # a new array, in the UAVs' order
        else:
            a = np.zeros((self.config.n_uavs, 4))
            a[rows] = actions
        return core_kernels.scaled_actions(a, self._scale)

    @staticmethod
    def check_action(agent: str, act: Any) -> np.ndarray:
        """One agent's action as 4 finite float64s (not yet clipped); ValueError otherwise."""
        try:
            arr = np.asarray(act, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"action for {agent!r} cannot be read as 4 floats: {act!r}") from exc
        if arr.shape != (4,):
            raise ValueError(
                f"action for {agent!r} has shape {arr.shape}; expected (4,) = "
                "[v_cx, v_cy, v_cz, omega_cy] normalised to [-1, 1]"
            )
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"action for {agent!r} is not finite: {arr.tolist()}")
        return arr

    def _check_can_act(self, actions: Any) -> None:
        """The episode is running and ``actions`` names exactly the live agents."""
        self._check_open("step")
        if self.np_random is None:
            raise RuntimeError("step() called before reset(); call env.reset(seed=...) first")
        if not self.agents:
            raise RuntimeError("the episode is over (no live agents); call env.reset()")
        if not isinstance(actions, dict):
            raise ValueError(
                f"actions must be a dict agent -> action, got {type(actions).__name__}"
            )
        for agent in actions:
            if agent not in self._index:
                raise KeyError(f"action for unknown agent {agent!r}; agents are {self.agents}")
            if agent not in self.agents:
                raise KeyError(
                    f"action for finished agent {agent!r}; live agents are {self.agents}"
                )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise KeyError(f"no action for live agent(s) {missing}; every live agent must act")

    # --------------------------------------------------------------- simulate
    def _simulate(self, u: np.ndarray, clipped: np.ndarray) -> None:
        """Apply u (zero for finished UAVs) for one step; move the car; pose the bodies."""
        self._clip_count += clipped
        state = (self.position[None], self.yaw[None], self.velocity[None], self.yaw_rate[None])
        new, u = core.simulate(
            self.config, [self.world], [self.target], state, self.alive[None], u[None]
        )
        self.position, self.yaw, self.velocity, self.yaw_rate = (x[0] for x in new)
        self.last_action = u[0]
        self.num_cycles += 1

    # ------------------------------------------------------------------ sense
    def _sense(self) -> Measurements:
        """Detector, comms, contacts and distances for this step (a batch of one world, the
        arithmetic of `vector_env`; `uavtrack_env.core`).

        The random stream is drawn in a fixed order: the detector, then the comms.
        """
        m = core.sense(
            self.config, self.detector, [self.world], [self.target], [self.np_random],
            self._obstacles, self.position[None], self.yaw[None], self.alive[None],
        )  # fmt: skip
        return m

    # ------------------------------------------------------------------ score
    def _score(self, m: Measurements, u: np.ndarray) -> Score:
        """Reward terms (from the true features and u) and the three violations (a batch of one
        world)."""
        return core.score(self._constants, m, self.references[None], self.alive[None], u[None])

    # ---------------------------------------------------------------- observe
    def _observe(self, m: Measurements) -> dict[str, np.ndarray]:
        """Each live agent's observation vector (float32, clipped to the observation space)."""
        obs = self._observation_array(m)
        return {a: obs[self._index[a]] for a in self.agents}

    def _observation_array(self, m: Measurements) -> np.ndarray:
        """Every UAV's observation (n, n_obs) float32, clipped to the observation space (rows
        of finished UAVs included), from the batch of one world ``m``."""
        state = (self.position[None], self.yaw[None], self.velocity[None], self.yaw_rate[None])
        bounds = (self._obs_low, self._obs_high)
        return core.observation(
            self.config, self._constants, m, state, self.references[None], self._obstacles, bounds
        )[0]

    # ------------------------------------------------------------------ infos
    def _infos(
        self, m: Measurements, score: Score, u: np.ndarray, clipped: np.ndarray
    ) -> dict[str, dict]:
        """Each live agent's info dict: cost, violations, reward terms, measurement, truth."""
        rows = [self._index[a] for a in self.agents]
        state = (self.position, self.yaw, self.velocity, self.yaw_rate)
        infos = agent_infos(
            rows, self.possible_agents, m, score, u, clipped, self._clip_count, self.references,
            self._pixels, self.target, state,
        )  # fmt: skip
        return dict(zip(self.agents, infos, strict=True))

    # ------------------------------------------------------------ episode end
    def _episode_end(self, collided: np.ndarray):
        live = self.agents
        terminated, truncate = self._end_arrays(collided)
        ended = terminated.tolist()
        terminations = {a: ended[self._index[a]] for a in live}
        truncations = {a: truncate for a in live}
        return terminations, truncations

    def _end_arrays(self, collided: np.ndarray) -> tuple[np.ndarray, bool]:
        """Which UAVs this step terminates (n,) and whether it truncates; updates ``alive`` and
        ``agents`` and parks the UAVs that left."""
        mode, hit = self.config.terminate_on_collision, bool(collided.any())
        if mode == "never":
            collided, hit = np.zeros_like(collided), False  # charged as cost only
        elif mode == "all" and hit:
            collided = self.alive.copy()
        truncate = self.num_cycles >= self.max_cycles
        if hit:
            self.alive &= ~collided
        alive = self.alive.tolist()
        self.agents = [] if truncate else [a for a in self.agents if alive[self._index[a]]]
        if self.agents and hit:  # park the UAVs that just left
            self.world.set_poses(
                self.position, self.yaw, self.alive, self.target.center(), self.target.heading
            )
        return collided, truncate

    # ------------------------------------------------------------ extras
    def snapshot(self) -> UAVSnapshot:
        """The true state of the UAVs and the car, and the last detection (copies, not views)."""
        if self.np_random is None:
            raise RuntimeError("snapshot() called before reset()")
        det = self.last_detection
        return UAVSnapshot(
            positions=self.position.copy(),
            yaws=self.yaw.copy(),
            velocities=self.velocity.copy(),
            yaw_rates=self.yaw_rate.copy(),
            alive=self.alive.copy(),
            target_center=self.target.center().copy(),
            target_heading=float(self.target.heading),
            detection=None if det is None else det.copy(),
        )

    def state(self) -> np.ndarray:
        """Global state for centralised critics: per UAV [p (3), sin/cos yaw, v (3), alive], then
        the target [p (3), sin/cos heading, v (3)]."""
        if self.np_random is None:
            raise RuntimeError("state() called before reset()")
        alive = self.alive.astype(float)[:, None]
        uavs = np.column_stack(
            [self.position, np.sin(self.yaw), np.cos(self.yaw), self.velocity, alive]
        )
        h = self.target.heading
        tgt = np.concatenate([self.target.center(), [np.sin(h), np.cos(h)], self.target.velocity()])
        state = np.concatenate([uavs.ravel(), tgt])
        return np.clip(state, -WORLD_LIMIT, WORLD_LIMIT).astype(np.float32)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() called with render_mode=None; nothing to render")
            return None
        self._check_open("render")
        if self.np_random is None:
            raise RuntimeError("render() called before reset()")
        snap = self.snapshot()
        if self.render_mode == "human":
            rendering.follow_target(self.world, snap)
            return None
        return rendering.rgb_frame(self.world, self.config, self.layout, snap)

    def close(self) -> None:
        """Release the PyBullet client (idempotent); the env cannot step or reset after it."""
        self.world.close()

    def _check_open(self, call: str) -> None:
        self.world.require_open(call, "uavtrack_v0.parallel_env(**config)")

    def __reduce_ex__(self, protocol):
        return self.world.__reduce_ex__(protocol)  # refuses: the world owns a live client
