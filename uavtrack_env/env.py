"""The PettingZoo ParallelEnv: n UAVs with fixed cameras track a car through box obstacles."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from . import render as rendering
from .config import DT, EnvConfig
from .dynamics import integrate
from .geometry import occlusion_angle, point_box_distance, world_to_cam_vec
from .rewards import connected, effort_term, reward, tracking_term
from .scenarios import Layout, make_layout
from .sensors import Detections, Detector, receive_positions
from .target import CAR_HALF_EXTENTS, TargetMotion
from .world import World

OWN_FIELDS = (
    (
        "features",
        5,
        "measured x1, x2, x3, sin psi, cos psi (zeros when not detected), eqs. (6), (8)",
    ),
    ("detection", 2, "detected flag, visible fraction of the target"),
    ("velocity", 3, "own velocity in the camera frame [v_cx, v_cy, v_cz] (m/s)"),
    ("yaw_rate", 1, "own omega_cy (rad/s)"),
    ("heading", 2, "sin yaw, cos yaw"),
    ("altitude", 1, "own z (m)"),
    ("reference", 5, "x1*, x2*, x3*, sin psi*, cos psi* of this agent's reference s*"),
)
WORLD_LIMIT = 1.0e4
"""Bound (m, m/s) of the state vector's entries."""
ALTITUDE_LIMIT = 100.0
"""Observed altitude is clipped to [0, ALTITUDE_LIMIT] m."""
OBSTACLE_RANGE = 100.0
"""Observed obstacle offsets and sizes are clipped to +-OBSTACLE_RANGE m."""
NEIGHBOUR_FIELDS = 4
"""Per neighbour: relative position in the camera frame (3, m) and a mask (1)."""
OBSTACLE_FIELDS = 7
"""Per obstacle: relative centre in the camera frame (3, m), half extents (3, m), mask (1)."""


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
    c = sum q_k e_k^2 + lost_penalty * not_detected + sum r_k u_k^2: r = -c by default, or
    r = exp(-c) with ``reward={"shape": "exp"}`` (for RL), minus ``reward.collision_penalty`` on a
    collision. Both parts of -c are in ``info`` (``reward_tracking``, ``reward_effort``).

    **Cost and violations** (``info[agent]``): ``violations = {collision, disconnection,
    occlusion}`` and ``cost`` = how many are true. Collision: touching an obstacle, the car or the
    ground (PyBullet contacts), or another UAV closer than R_s. Disconnection: the UAVs' graph with
    edges <= R_c is not connected. Occlusion: obstacles (or UAVs) block more of the car's sample
    points than the detector can tolerate.

    **Episode end**: terminated on collision (that agent or all, ``terminate_on_collision``);
    truncated after ``max_cycles`` steps (80 Hz).

    **Arguments**: the fields of :class:`uavtrack_env.config.EnvConfig`; unknown names raise.

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
        self._scale = cfg.limits.scale
        self.n_obs = (
            sum(f[1] for f in OWN_FIELDS)
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
        self._image_size = np.array([cfg.camera.width, cfg.camera.height], float)
        self.np_random: np.random.Generator | None = None
        self.layout: Layout | None = None
        self.last_detection: Detections | None = None
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

    def _observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite bounds per observation entry; values beyond them are clipped (documented)."""
        cfg = self.config
        v, w, r_c = 2.0 * cfg.limits.v_max, 2.0 * cfg.limits.omega_max, cfg.comms.r_c
        own_hi = [
            5,
            5,
            1 / cfg.camera.near,
            1,
            1,
            1,
            1,
            v,
            v,
            v,
            w,
            1,
            1,
            ALTITUDE_LIMIT,
            5,
            5,
            1 / cfg.camera.near,
            1,
            1,
        ]
        own_lo = [-5, -5, 0, -1, -1, 0, 0, -v, -v, -v, -w, -1, -1, 0, -5, -5, 0, -1, -1]
        nb_hi, nb_lo = (
            [r_c, r_c, r_c, 1] * cfg.n_neighbours,
            [-r_c, -r_c, -r_c, 0] * cfg.n_neighbours,
        )
        d = OBSTACLE_RANGE
        ob_hi = [d, d, d, d, d, d, 1] * cfg.n_obstacles_obs
        ob_lo = [-d, -d, -d, 0, 0, 0, 0] * cfg.n_obstacles_obs
        low = np.array(own_lo + nb_lo + ob_lo, np.float32)
        high = np.array(own_hi + nb_hi + ob_hi, np.float32)
        assert low.shape == (self.n_obs,)
        return low, high

    def observation_fields(self) -> list[tuple[str, int, str]]:
        """(name, size, meaning) of each block of the observation vector, in order."""
        cfg = self.config
        return [
            *OWN_FIELDS,
            *[
                (f"neighbour_{k}", NEIGHBOUR_FIELDS, "rel. position (camera frame), mask")
                for k in range(cfg.n_neighbours)
            ],
            *[
                (f"obstacle_{k}", OBSTACLE_FIELDS, "rel. centre (camera frame), half extents, mask")
                for k in range(cfg.n_obstacles_obs)
            ],
        ]

    # ------------------------------------------------------------------ reset
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
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
        self.agents = self.possible_agents[:]
        self.num_cycles = 0
        self._clip_count = np.zeros(n, int)
        self.last_action = np.zeros((n, 4))
        self.world.set_poses(self.position, self.yaw, self.alive, self.target.center(), 0.0)
        obs, _, _, infos = self._sense(np.zeros((n, 4)), np.zeros(n, bool))
        return obs, infos

    # ------------------------------------------------------------------- step
    def step(self, actions: dict[str, Any]):
        u, clipped = self._validate(actions)
        self._advance_world(u)
        obs, rewards, collided, infos = self._sense(u, clipped)
        return (obs, rewards, *self._episode_end(collided), infos)

    def _validate(self, actions: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """Check every action before anything changes; return u (n, 4) in SI units, clip flags."""
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
        n = self.config.n_uavs
        a = np.zeros((n, 4))
        for agent, act in actions.items():
            try:
                arr = np.asarray(act, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(
                    f"action for {agent!r} cannot be read as 4 floats: {act!r}"
                ) from exc
            if arr.shape != (4,):
                raise ValueError(
                    f"action for {agent!r} has shape {arr.shape}; expected (4,) = "
                    "[v_cx, v_cy, v_cz, omega_cy] normalised to [-1, 1]"
                )
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"action for {agent!r} is not finite: {arr.tolist()}")
            a[self._index[agent]] = arr
        clipped = np.any(np.abs(a) > 1.0, axis=1)
        return np.clip(a, -1.0, 1.0) * self._scale, clipped

    def _advance_world(self, u: np.ndarray) -> None:
        u = np.where(self.alive[:, None], u, 0.0)
        self.position, self.yaw, self.velocity, self.yaw_rate = integrate(
            self.position, self.yaw, self.velocity, self.yaw_rate, u, self.config.dynamics, DT
        )
        self.target.step(DT)
        self.world.set_poses(
            self.position, self.yaw, self.alive, self.target.center(), self.target.heading
        )
        self.last_action = u
        self.num_cycles += 1

    # ----------------------------------------------------------- sense & score
    def _sense(self, u: np.ndarray, clipped: np.ndarray):
        """Sensors -> observation, reward, cost and info for the live agents."""
        cfg, rng = self.config, self.np_random
        n = cfg.n_uavs
        tgt_c, heading = self.target.center(), self.target.heading
        det = self.detector.detect(
            self.world, self.position, self.yaw, tgt_c, heading, heading, rng
        )
        self.last_detection = det
        pair = np.linalg.norm(self.position[:, None] - self.position[None], axis=-1)
        received = receive_positions(pair, self.alive, cfg.comms, rng)
        hits = self.world.contacts(n)

        dist = pair.copy()
        dist[~self.alive, :] = np.inf
        dist[:, ~self.alive] = np.inf
        np.fill_diagonal(dist, np.inf)
        nearest_uav = dist.min(axis=1)
        clearance = (
            point_box_distance(
                self.position, self.layout.obstacle_centers, self.layout.obstacle_half_extents
            )
            - cfg.uav_radius
        )
        nearest_obstacle = clearance.min(axis=1) if clearance.shape[1] else np.full(n, np.inf)
        collided = (
            hits["ground"] | hits["obstacle"] | hits["target"] | (nearest_uav < cfg.cbf.r_s)
        ) & self.alive
        disconnected = not connected(pair, self.alive, cfg.cbf.r_c)
        occluded = det.blocked_fraction > 1.0 - cfg.detector.min_visible_fraction

        tracking = tracking_term(
            det.true_features, self.references, det.in_front, det.detected, cfg.reward
        )
        effort = effort_term(u, cfg.reward)
        rew = reward(tracking + effort, collided, cfg.reward)
        self._clip_count += clipped
        obs_all = self._observations(det, received, clearance, pair)
        theta, in_noi = self._occlusion_angles(tgt_c)
        target_clear = self._target_clearance(tgt_c, heading)

        obs, rewards, infos = {}, {}, {}
        for agent in self.agents:
            i = self._index[agent]
            violations = {
                "collision": bool(collided[i]),
                "disconnection": disconnected,
                "occlusion": bool(occluded[i]),
            }
            obs[agent] = obs_all[i]
            rewards[agent] = float(rew[i])
            infos[agent] = {
                "cost": float(sum(violations.values())),
                "violations": violations,
                "collision_with": {
                    "uav": bool(nearest_uav[i] < cfg.cbf.r_s),
                    **{k: bool(v[i]) for k, v in hits.items()},
                },
                "reward_tracking": -float(tracking[i]),
                "reward_effort": -float(effort[i]),
                "action_clipped": bool(clipped[i]),
                "n_clipped_actions": int(self._clip_count[i]),
                "measurement": self._measurement(det, i),
                "own": {
                    "position": self.position[i].copy(),
                    "yaw": float(self.yaw[i]),
                    "velocity": self.velocity[i].copy(),
                    "yaw_rate": float(self.yaw_rate[i]),
                    "applied_u": u[i].copy(),
                },
                "neighbours": {
                    self.possible_agents[j]: self.position[j].copy()
                    for j in np.flatnonzero(received[i])
                },
                "reference": self.references[i].copy(),
                "truth": self._truth(
                    i, det, nearest_uav, nearest_obstacle, target_clear, theta, in_noi
                ),
            }
        return obs, rewards, collided, infos

    @staticmethod
    def _measurement(det: Detections, i: int) -> dict:
        """The detector's report for UAV i; u, v, depth, psi are None when not detected."""
        ok = bool(det.detected[i])
        return {
            "detected": ok,
            "u": float(det.u[i]) if ok else None,
            "v": float(det.v[i]) if ok else None,
            "depth": float(det.depth[i]) if ok else None,
            "psi": float(det.psi[i]) if ok else None,
            "visible_fraction": float(det.visible_fraction[i]),
            "truncated_u": ok and bool(det.truncated[i, 0]),
            "truncated_v": ok and bool(det.truncated[i, 1]),
        }

    def _truth(
        self, i, det: Detections, nearest_uav, nearest_obstacle, target_clear, theta, in_noi
    ) -> dict:
        cam = self.config.camera
        s, ref = det.true_features[i], self.references[i]
        ref_px = np.array([cam.fx * ref[0] + cam.cu, cam.fy * ref[1] + cam.cv])
        center_error = np.array([cam.fx * s[0] + cam.cu, cam.fy * s[1] + cam.cv]) - ref_px
        return {
            "features": s.copy(),
            # Capped at the image size: a car behind the camera projects arbitrarily far.
            "pixel_error": np.clip(det.box_center[i] - ref_px, -self._image_size, self._image_size),
            "center_pixel_error": center_error,
            "depth_error": float(1.0 / s[2] - 1.0 / ref[2]) if det.in_front[i] else None,
            "target_position": self.target.center(),
            "target_velocity": self.target.velocity(),
            "target_acceleration": self.target.acceleration(),
            "nearest_uav_distance": float(nearest_uav[i]),
            "nearest_obstacle_clearance": float(nearest_obstacle[i]),
            "target_clearance": float(target_clear[i]),
            "occlusion_angles": theta[i].copy(),
            "occlusion_candidates": in_noi[i].copy(),
            "min_occlusion_angle": float(theta[i][in_noi[i]].min()) if in_noi[i].any() else np.pi,
            "blocked_fraction": float(det.blocked_fraction[i]),
        }

    def _occlusion_angles(self, target_center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """theta (n, m) of eq. (38) with n^i = target - p^i (36), and membership of N_oi (39)."""
        centers = self.layout.obstacle_centers
        n_vec = target_center - self.position  # (n, 3)
        theta = occlusion_angle(self.position[:, None], centers[None], n_vec[:, None])
        d_obs = np.linalg.norm(centers[None] - self.position[:, None], axis=-1)
        return theta, d_obs <= np.linalg.norm(n_vec, axis=-1)[:, None]

    def _target_clearance(self, center: np.ndarray, heading: float) -> np.ndarray:
        """Distance from each UAV's sphere to the car's oriented box (n,)."""
        local = self.position - center
        c, s = np.cos(heading), np.sin(heading)
        local = np.column_stack(
            [c * local[:, 0] + s * local[:, 1], -s * local[:, 0] + c * local[:, 1], local[:, 2]]
        )
        d = point_box_distance(local, np.zeros((1, 3)), CAR_HALF_EXTENTS[None])[:, 0]
        return d - self.config.uav_radius

    def _observations(
        self, det: Detections, received: np.ndarray, clearance: np.ndarray, pair: np.ndarray
    ) -> np.ndarray:
        """All agents' observation vectors (n, n_obs), float32."""
        cfg = self.config
        cam = cfg.camera
        n = cfg.n_uavs
        ok = det.detected
        with np.errstate(invalid="ignore", divide="ignore"):
            feats = np.column_stack(
                [
                    (det.u - cam.cu) / cam.fx,
                    (det.v - cam.cv) / cam.fy,
                    1.0 / det.depth,
                    np.sin(det.psi),
                    np.cos(det.psi),
                ]
            )
        feats[~ok] = 0.0
        ref = self.references
        own = np.column_stack(
            [
                feats,
                ok,
                det.visible_fraction,
                world_to_cam_vec(self.velocity, self.yaw),
                -self.yaw_rate,
                np.sin(self.yaw),
                np.cos(self.yaw),
                self.position[:, 2],
                ref[:, :3],
                np.sin(ref[:, 3]),
                np.cos(ref[:, 3]),
            ]
        )
        blocks = [own]
        k = cfg.n_neighbours
        if k:
            d = np.where(received, pair, np.inf)
            order = np.argsort(d, axis=1, kind="stable")[:, :k]
            rel = self.position[order] - self.position[:, None]
            mask = np.isfinite(np.take_along_axis(d, order, 1))
            rel = world_to_cam_vec(rel, self.yaw[:, None]) * mask[..., None]
            nb = np.concatenate([rel, mask[..., None]], -1)
            if nb.shape[1] < k:
                nb = np.concatenate([nb, np.zeros((n, k - nb.shape[1], NEIGHBOUR_FIELDS))], 1)
            blocks.append(nb.reshape(n, -1))
        k = cfg.n_obstacles_obs
        if k:
            m = clearance.shape[1]
            order = np.argsort(clearance, axis=1, kind="stable")[:, :k]
            rel = self.layout.obstacle_centers[order] - self.position[:, None]
            ob = np.concatenate(
                [
                    world_to_cam_vec(rel, self.yaw[:, None]),
                    self.layout.obstacle_half_extents[order],
                    np.ones(order.shape + (1,)),
                ],
                -1,
            )
            if m < k:
                ob = np.concatenate([ob, np.zeros((n, k - m, OBSTACLE_FIELDS))], 1)
            blocks.append(ob.reshape(n, -1))
        return np.clip(np.concatenate(blocks, 1), self._obs_low, self._obs_high).astype(np.float32)

    def _episode_end(self, collided: np.ndarray):
        cfg = self.config
        if cfg.terminate_on_collision == "all" and collided.any():
            collided = self.alive.copy()
        truncate = self.num_cycles >= self.max_cycles
        terminations = {a: bool(collided[self._index[a]]) for a in self.agents}
        truncations = {a: truncate for a in self.agents}
        self.alive &= ~collided
        self.agents = [a for a in self.agents if not (terminations[a] or truncate)]
        if self.agents and collided.any():  # park the UAVs that just left
            self.world.set_poses(
                self.position, self.yaw, self.alive, self.target.center(), self.target.heading
            )
        return terminations, truncations

    # ------------------------------------------------------------ extras
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
        if self.np_random is None:
            raise RuntimeError("render() called before reset()")
        if self.render_mode == "human":
            rendering.follow_target(self)
            return None
        return rendering.rgb_frame(self)

    def close(self) -> None:
        self.world.close()
