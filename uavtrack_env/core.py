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

from . import core_kernels
from .broadphase import CONTACT_MARGIN, Bodies
from .config import DT, EnvConfig
from .rewards import FEATURE_ERROR_CAP
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
            contacts={
                "ground": self.contacts["ground"][k],
                "obstacle": self.contacts["obstacle"][k],
                "target": self.contacts["target"][k],
            },
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
    dyn = cfg.dynamics
    position, yaw, velocity, yaw_rate, u = core_kernels.integrate(
        *state, alive, u, dyn.model == "lag", dyn.tau, dyn.a_max, min(1.0, DT / dyn.yaw_tau), DT
    )
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
    (pair, nearest_uav, clearance, nearest_obstacle, target_clearance, theta, in_noi, touch) = (
        core_kernels.sense_geometry(
            position, alive, centers, headings, CAR_HALF_EXTENTS, obstacles.centers,
            obstacles.half_extents, obstacles.present, cfg.uav_radius, CONTACT_MARGIN,
        )
    )  # fmt: skip
    bodies = None
    if cfg.skip_proven_queries:
        bodies = Bodies(alive, obstacles.centers, obstacles.half_extents, cfg.uav_radius)
    det = detector.detect_batch(
        list(worlds), position, yaw, centers, headings, headings, rngs, bodies=bodies
    )
    received = receive_batch(pair, alive, cfg.comms, list(rngs))
    none = np.zeros((3, K, n), bool)
    hits = {"ground": none[0], "obstacle": none[1], "target": none[2]}
    for k, world in enumerate(worlds):
        if bodies is not None and not touch[k]:
            continue  # no UAV near anything: PyBullet would report no contact
        for key, hit in world.contacts(n).items():
            hits[key][k] = hit
    return Measurements(
        detections=det,
        distances=pair,
        received=received,
        contacts=hits,
        nearest_uav=nearest_uav,
        obstacle_clearance=clearance,
        nearest_obstacle=nearest_obstacle,
        target_center=centers,
        target_heading=headings,
        target_clearance=target_clearance,
        occlusion_angles=theta,
        occlusion_candidates=in_noi,
    )


@dataclass(frozen=True)
class Constants:
    """An env config's numbers as the kernels take them (built once per env)."""

    score_settings: np.ndarray
    """lost penalty, R_s, R_c, collision penalty, tolerated blocked share, exp shape (0/1)."""
    q: np.ndarray
    """Feature weights of eq. (18) (Table III)."""
    r: np.ndarray
    """Input weights of eq. (18) (Table III)."""
    camera: np.ndarray
    """[fx, fy, cu, cv]."""
    box_point: bool
    """The reward scores the bounding box's centre (`RewardConfig.image_point`)."""

    @classmethod
    def of(cls, cfg: EnvConfig) -> Constants:
        rc, cam = cfg.reward, cfg.camera
        settings = np.array(
            [
                rc.lost_penalty, cfg.violations.r_s, cfg.comms.r_c, rc.collision_penalty,
                1.0 - cfg.detector.min_visible_fraction, float(rc.shape == "exp"),
            ]
        )  # fmt: skip
        return cls(
            settings,
            np.asarray(rc.q, float),
            np.asarray(rc.r, float),
            np.array([cam.fx, cam.fy, cam.cu, cam.cv]),
            rc.image_point == "box",
        )


def scored_features(const: Constants, det: Detections) -> np.ndarray:
    """The true features (K, n, 4) the reward scores: with ``const.box_point`` x1, x2 are the
    noise-free bounding box's centre, (u - c_u) / f_x and (v - c_v) / f_y."""
    if not const.box_point:
        return det.true_features
    features = det.true_features.copy()
    features[..., :2] = (det.box_center - const.camera[2:]) / const.camera[:2]
    return features


def score(
    const: Constants, m: Measurements, references: np.ndarray, alive: np.ndarray, u: np.ndarray
) -> Score:
    """Reward terms (from the true features and u (K, n, 4)) and the three violations: the
    terms of `rewards` (`tracking_term`, `effort_term`, `reward`, `connected`), in one kernel."""
    det, hits = m.detections, m.contacts
    values, flags, disconnected = core_kernels.score(
        scored_features(const, det), references, det.in_front, det.detected, u, hits["ground"],
        hits["obstacle"], hits["target"], m.nearest_uav, alive, m.distances,
        det.blocked_fraction, const.q, const.r, FEATURE_ERROR_CAP, const.score_settings,
    )  # fmt: skip
    return Score(
        tracking=values[0],
        effort=values[1],
        reward=values[2],
        collided=flags[0],
        uav_too_close=flags[1],
        disconnected=disconnected,
        occluded=flags[2],
    )


def observation(
    cfg: EnvConfig,
    const: Constants,
    m: Measurements,
    state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    references: np.ndarray,
    obstacles: Obstacles,
    bounds: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Every UAV's observation (K, n, n_obs) float32, clipped to ``bounds`` (rows of finished
    UAVs included)."""
    position, yaw, velocity, yaw_rate = state
    det = m.detections
    return core_kernels.observation(
        det.u, det.v, det.depth, det.psi, det.visible_fraction, det.detected, position, yaw,
        velocity, yaw_rate, references, m.received, m.distances, m.obstacle_clearance,
        obstacles.centers, obstacles.half_extents, obstacles.present,
        const.camera, cfg.n_neighbours, cfg.n_obstacles_obs,
        *bounds,
    )  # fmt: skip
