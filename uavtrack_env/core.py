"""One simulation step as arrays over K worlds of n UAVs: sense, score, observe.

The state of the UAVs has leading axes (K, n); the ParallelEnv calls these functions with K = 1,
``vector_env`` with its K worlds, so both run the same arithmetic. What stays a loop over the
worlds: the car's motion, PyBullet (poses, contacts and ray casts, one client per world) and each
world's random stream, drawn in a fixed order per world (the detector's noise and dropouts, then
the comms). Worlds with fewer obstacles than the most cluttered one are padded with absent
obstacles (`Obstacles.present`), which no distance, occlusion set or observation sees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .broadphase import Bodies, contacts_in_doubt
from .config import DT, EnvConfig
from .dynamics import integrate
from .geometry import occlusion_angle, point_box_distance, world_to_cam_vec
from .rewards import connected_batch, effort_term, reward, tracking_term
from .scenarios import Layout
from .sensors import Detections, Detector, receive_batch
from .target import CAR_HALF_EXTENTS, TargetMotion
from .world import World

NEIGHBOUR_FIELDS = 4
"""Observation entries per neighbour: relative position in the camera frame (3), mask (1)."""
OBSTACLE_FIELDS = 7
"""Observation entries per obstacle: relative centre (3), half extents (3), mask (1)."""

_FAR = 1.0e6
"""Where padded (absent) obstacles sit (m): beyond every world."""


@dataclass(frozen=True)
class Obstacles:
    """The obstacle boxes of K worlds, padded to the largest count M: (K, M, 3) arrays."""

    centers: np.ndarray
    half_extents: np.ndarray
    present: np.ndarray
    """(K, M) bool: a real obstacle (False: padding)."""
    counts: tuple[int, ...]
    """Real obstacles per world (they come first)."""

    @property
    def padded(self) -> bool:
        """Some world has padding (fewer obstacles than the most cluttered one)."""
        return min(self.counts) < self.present.shape[1]

    @classmethod
    def stack(cls, layouts: Sequence[Layout]) -> Obstacles:
        counts = tuple(len(lay.obstacle_centers) for lay in layouts)
        K, M = len(layouts), max(counts)
        centers = np.full((K, M, 3), _FAR)
        half = np.zeros((K, M, 3))
        present = np.zeros((K, M), bool)
        for k, (lay, m) in enumerate(zip(layouts, counts, strict=True)):
            centers[k, :m] = np.asarray(lay.obstacle_centers, float).reshape(m, 3)
            half[k, :m] = np.asarray(lay.obstacle_half_extents, float).reshape(m, 3)
            present[k, :m] = True
        return cls(centers, half, present, counts)


@dataclass
class Measurements:
    """What the sensors and the world's geometry report at one step.

    In a batch every array has a leading world axis (K, ...); `world` gives one world's view,
    with the shapes below and only its real obstacles.
    """

    detections: Detections
    distances: np.ndarray
    """(n, n) inter-UAV distances (m)."""
    received: np.ndarray
    """(n, n) bool: UAV i received UAV j's position this step."""
    contacts: dict[str, np.ndarray]
    """``ground``, ``obstacle``, ``target``: (n,) bool PyBullet contacts."""
    nearest_uav: np.ndarray
    """(n,) distance to the nearest other alive UAV (inf if none)."""
    obstacle_clearance: np.ndarray
    """(n, m) distance from each UAV's sphere to each obstacle box (m)."""
    nearest_obstacle: np.ndarray
    """(n,) smallest obstacle clearance (inf without obstacles)."""
    target_center: np.ndarray
    target_heading: float | np.ndarray
    target_clearance: np.ndarray
    """(n,) distance from each UAV's sphere to the car's oriented box (m)."""
    occlusion_angles: np.ndarray
    """(n, m) theta of eq. (38)."""
    occlusion_candidates: np.ndarray
    """(n, m) bool: obstacle in N_oi (39)."""

    def world(self, k: int, m: int) -> Measurements:
        """World k of a batch (views), with its ``m`` real obstacles."""
        return Measurements(
            detections=self.detections.world(k),
            distances=self.distances[k],
            received=self.received[k],
            contacts={key: hit[k] for key, hit in self.contacts.items()},
            nearest_uav=self.nearest_uav[k],
            obstacle_clearance=self.obstacle_clearance[k, :, :m],
            nearest_obstacle=self.nearest_obstacle[k],
            target_center=self.target_center[k],
            target_heading=float(self.target_heading[k]),
            target_clearance=self.target_clearance[k],
            occlusion_angles=self.occlusion_angles[k, :, :m],
            occlusion_candidates=self.occlusion_candidates[k, :, :m],
        )


@dataclass
class Score:
    """This step's reward terms and safety violations, (n,) per UAV ((K, n) in a batch)."""

    tracking: np.ndarray
    effort: np.ndarray
    reward: np.ndarray
    collided: np.ndarray
    uav_too_close: np.ndarray
    disconnected: bool | np.ndarray
    """Whether the alive UAVs' graph is split ((K,) in a batch)."""
    occluded: np.ndarray

    def world(self, k: int) -> Score:
        """World k of a batch (views)."""
        return Score(
            tracking=self.tracking[k],
            effort=self.effort[k],
            reward=self.reward[k],
            collided=self.collided[k],
            uav_too_close=self.uav_too_close[k],
            disconnected=bool(self.disconnected[k]),
            occluded=self.occluded[k],
        )


def simulate(
    cfg: EnvConfig,
    worlds: Sequence[World],
    targets: Sequence[TargetMotion],
    state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    alive: np.ndarray,
    u: np.ndarray,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """Apply u (K, n, 4) for one step (zero for finished UAVs), move the cars, pose the bodies.

    ``state`` = (position (K, n, 3), yaw (K, n), velocity (K, n, 3), yaw rate (K, n));
    returns the new state and the applied u."""
    u = np.where(alive[..., None], u, 0.0)
    position, yaw, velocity, yaw_rate = integrate(*state, u, cfg.dynamics, DT)
    for k, (world, target) in enumerate(zip(worlds, targets, strict=True)):
        target.step(DT)
        world.set_poses(position[k], yaw[k], alive[k], target.center(), target.heading, defer=True)
    return (position, yaw, velocity, yaw_rate), u


def sense(
    cfg: EnvConfig,
    detector: Detector,
    worlds: Sequence[World],
    targets: Sequence[TargetMotion],
    rngs: Sequence[np.random.Generator],
    obstacles: Obstacles,
    position: np.ndarray,
    yaw: np.ndarray,
    alive: np.ndarray,
) -> Measurements:
    """Detector, comms, contacts and distances of K worlds (position (K, n, 3), yaw and alive
    (K, n)); each world draws from its generator in a fixed order: the detector, then the
    comms."""
    K, n = alive.shape
    centers = np.empty((K, 3))  # filled row by row: np.array of a list of arrays is slow
    for k, target in enumerate(targets):
        centers[k] = target.center()
    headings = np.array([t.heading for t in targets], float)
    clearance = _box_distance(position, obstacles) - cfg.uav_radius
    target_clearance = _target_clearance(position, centers, headings) - cfg.uav_radius
    bodies = touch = None
    if cfg.skip_proven_queries:
        bodies = Bodies(alive, obstacles.centers, obstacles.half_extents, cfg.uav_radius)
        touch = contacts_in_doubt(
            clearance, target_clearance, position[..., 2], cfg.uav_radius, alive
        )
    det = detector.detect_batch(
        list(worlds), position, yaw, centers, headings, headings, rngs, bodies=bodies
    )
    pair = np.linalg.norm(position[:, :, None] - position[:, None], axis=-1)
    received = receive_batch(pair, alive, cfg.comms, list(rngs))
    hits = {key: np.zeros((K, n), bool) for key in ("ground", "obstacle", "target")}
    for k, world in enumerate(worlds):
        if touch is not None and not touch[k]:
            continue  # no UAV near anything: PyBullet would report no contact
        for key, hit in world.contacts(n).items():
            hits[key][k] = hit

    both = alive[:, :, None] & alive[:, None, :]
    both.reshape(K, n * n)[:, :: n + 1] = False  # the diagonals
    dist = np.where(both, pair, np.inf)
    theta, in_noi = _occlusion(position, centers, obstacles)
    M = clearance.shape[-1]
    return Measurements(
        detections=det,
        distances=pair,
        received=received,
        contacts=hits,
        nearest_uav=dist.min(axis=-1),
        obstacle_clearance=clearance,
        nearest_obstacle=clearance.min(axis=-1) if M else np.full((K, n), np.inf),
        target_center=centers,
        target_heading=headings,
        target_clearance=target_clearance,
        occlusion_angles=theta,
        occlusion_candidates=in_noi,
    )


def _box_distance(position: np.ndarray, obstacles: Obstacles) -> np.ndarray:
    """Distance from each UAV centre to each obstacle box (K, n, M); inf for padding."""
    d = (
        np.abs(position[:, :, None, :] - obstacles.centers[:, None])
        - obstacles.half_extents[:, None]
    )
    dist = np.linalg.norm(np.maximum(d, 0.0), axis=-1)
    return np.where(obstacles.present[:, None], dist, np.inf) if obstacles.padded else dist


def _occlusion(
    position: np.ndarray, target_centers: np.ndarray, obstacles: Obstacles
) -> tuple[np.ndarray, np.ndarray]:
    """theta (K, n, M) of eq. (38) with n^i = target - p^i (36), and membership of N_oi (39)."""
    centers = obstacles.centers
    n_vec = target_centers[:, None] - position  # (K, n, 3)
    theta = occlusion_angle(position[:, :, None], centers[:, None], n_vec[:, :, None])
    d_obs = np.linalg.norm(centers[:, None] - position[:, :, None], axis=-1)
    in_noi = d_obs <= np.linalg.norm(n_vec, axis=-1)[..., None]
    return theta, (in_noi & obstacles.present[:, None]) if obstacles.padded else in_noi


def _target_clearance(
    position: np.ndarray, centers: np.ndarray, headings: np.ndarray
) -> np.ndarray:
    """Distance from each UAV centre to its world's car box (K, n), in the car's frame."""
    K, n = position.shape[:2]
    local = (position - centers[:, None]).reshape(K * n, 3)
    h = np.repeat(headings, n)
    c, s = np.cos(h), np.sin(h)
    local = np.column_stack(
        [c * local[:, 0] + s * local[:, 1], -s * local[:, 0] + c * local[:, 1], local[:, 2]]
    )
    d = point_box_distance(local, np.zeros((1, 3)), CAR_HALF_EXTENTS[None])[:, 0]
    return d.reshape(K, n)


def score(
    cfg: EnvConfig, m: Measurements, references: np.ndarray, alive: np.ndarray, u: np.ndarray
) -> Score:
    """Reward terms (from the true features and u (K, n, 4)) and the three violations."""
    K, n = alive.shape
    det, hits = m.detections, m.contacts
    too_close = m.nearest_uav < cfg.violations.r_s
    collided = (hits["ground"] | hits["obstacle"] | hits["target"] | too_close) & alive
    tracking = tracking_term(
        det.true_features.reshape(K * n, 4),
        references.reshape(K * n, 4),
        det.in_front.reshape(K * n),
        det.detected.reshape(K * n),
        cfg.reward,
    ).reshape(K, n)
    effort = effort_term(u.reshape(K * n, 4), cfg.reward).reshape(K, n)
    return Score(
        tracking=tracking,
        effort=effort,
        reward=reward(tracking + effort, collided, cfg.reward),
        collided=collided,
        uav_too_close=too_close,
        disconnected=~connected_batch(m.distances, alive, cfg.comms.r_c),
        occluded=det.blocked_fraction > 1.0 - cfg.detector.min_visible_fraction,
    )


def observation(
    cfg: EnvConfig,
    m: Measurements,
    state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    references: np.ndarray,
    obstacles: Obstacles,
    bounds: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Every UAV's observation (K, n, n_obs) float32, clipped to ``bounds`` (rows of finished
    UAVs included)."""
    position, yaw = state[0], state[1]
    K, n = yaw.shape
    blocks = [_own_block(cfg, m.detections, state, references).reshape(K, n, -1)]
    if cfg.n_neighbours:
        blocks.append(_neighbour_block(cfg, m.received, m.distances, position, yaw))
    if cfg.n_obstacles_obs:
        blocks.append(_obstacle_block(cfg, m.obstacle_clearance, position, yaw, obstacles))
    obs = np.clip(np.concatenate(blocks, -1), *bounds)
    return obs.astype(np.float32)


def _own_block(
    cfg: EnvConfig,
    det: Detections,
    state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    references: np.ndarray,
) -> np.ndarray:
    """The own fields (K n, 19): measured features, detection, own motion, s*."""
    position, yaw, velocity, yaw_rate = (x.reshape(-1, *x.shape[2:]) for x in state)
    B, cam = len(yaw), cfg.camera
    detected = det.detected.reshape(B)
    psi = det.psi.reshape(B)
    with np.errstate(invalid="ignore", divide="ignore"):
        feats = np.column_stack(
            [
                (det.u.reshape(B) - cam.cu) / cam.fx,
                (det.v.reshape(B) - cam.cv) / cam.fy,
                1.0 / det.depth.reshape(B),
                np.sin(psi),
                np.cos(psi),
            ]
        )
    feats[~detected] = 0.0
    ref = references.reshape(B, 4)
    return np.column_stack(
        [
            feats,
            detected,
            det.visible_fraction.reshape(B),
            world_to_cam_vec(velocity, yaw),
            -yaw_rate,
            np.sin(yaw),
            np.cos(yaw),
            position[:, 2],
            ref[:, :3],
            np.sin(ref[:, 3]),
            np.cos(ref[:, 3]),
        ]
    )


def _neighbour_block(
    cfg: EnvConfig, received: np.ndarray, pair: np.ndarray, position: np.ndarray, yaw: np.ndarray
) -> np.ndarray:
    """The nearest received neighbours (K, n, n_neighbours * 4), camera frame, zero-padded."""
    K, n = yaw.shape
    k = cfg.n_neighbours
    d = np.where(received, pair, np.inf)
    order = np.argsort(d, axis=-1, kind="stable")[..., :k]
    world, me = np.arange(K)[:, None, None], np.arange(n)[None, :, None]
    rel = position[world, order] - position[:, :, None]
    mask = np.isfinite(d[world, me, order])
    rel = world_to_cam_vec(rel, yaw[..., None]) * mask[..., None]
    nb = np.concatenate([rel, mask[..., None]], -1)
    if nb.shape[2] < k:
        nb = np.concatenate([nb, np.zeros((K, n, k - nb.shape[2], NEIGHBOUR_FIELDS))], 2)
    return nb.reshape(K, n, -1)


def _obstacle_block(
    cfg: EnvConfig,
    clearance: np.ndarray,
    position: np.ndarray,
    yaw: np.ndarray,
    obstacles: Obstacles,
) -> np.ndarray:
    """The nearest obstacles (K, n, n_obstacles_obs * 7), camera frame, zero-padded."""
    K, n = yaw.shape
    k, M = cfg.n_obstacles_obs, clearance.shape[-1]
    order = np.argsort(clearance, axis=-1, kind="stable")[..., :k]
    world = np.arange(K)[:, None, None]
    rel = obstacles.centers[world, order] - position[:, :, None]
    ob = np.concatenate(
        [
            world_to_cam_vec(rel, yaw[..., None]),
            obstacles.half_extents[world, order],
            np.ones(order.shape + (1,)),
        ],
        -1,
    )
    if obstacles.padded:
        ob = np.where(obstacles.present[world, order][..., None], ob, 0.0)
    if M < k:
        ob = np.concatenate([ob, np.zeros((K, n, k - M, OBSTACLE_FIELDS))], 2)
    return ob.reshape(K, n, -1)
