"""Sensors: the geometric bounding-box detector (section II-D) and inter-UAV comms (section IV-B).

The detector stands in for the paper's YOLO network: it projects the car's box corners through
K (eq. 8) into a bounding box, measures its centre (u, v), the depth d (optical-axis depth Z of the
car's centre, so x3 = 1/d) and psi (eq. 4), and decides visibility by ray casts from the camera to a
grid of points inside the car and by the image bounds. Noise and dropouts come from the env's
generator. Everything is vectorised over the UAVs.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from . import broadphase, core_kernels
from .config import CameraConfig, CommsConfig, DetectorConfig
from .target import CAR_HALF_EXTENTS
from .world import World


@dataclass
class Detections:
    """One frame of the detector for all n UAVs (arrays with a leading UAV axis)."""

    detected: np.ndarray
    """(n,) bool: a bounding box was reported."""
    u: np.ndarray
    """(n,) measured bounding-box centre U (px); NaN when not detected."""
    v: np.ndarray
    """(n,) measured bounding-box centre V (px); NaN when not detected."""
    depth: np.ndarray
    """(n,) measured depth d (m); NaN when not detected."""
    psi: np.ndarray
    """(n,) measured relative angle (rad); NaN when not detected."""
    visible_fraction: np.ndarray
    """(n,) share of the target's sample points that are in the image and not blocked."""
    blocked_fraction: np.ndarray
    """(n,) share of the target's sample points whose line of sight is blocked."""
    true_features: np.ndarray
    """(n, 4) ground-truth s = [x1, x2, x3, psi] of the car's centre."""
    in_front: np.ndarray
    """(n,) bool: the car's centre lies in front of the camera."""
    box_center: np.ndarray
    """(n, 2) noise-free bounding-box centre (px), clipped to the image; the projection of the
    car's centre where a corner lies behind the camera."""
    truncated: np.ndarray
    """(n, 2) bool: the box is cut by the image's left/right (column 0) or top/bottom (column 1)
    border, so its centre is biased towards the image along that axis."""

    def copy(self) -> Detections:
        """A deep copy (every array copied)."""
        return Detections(*[getattr(self, name).copy() for name in _DETECTION_FIELDS])

    def world(self, k: int) -> Detections:
        """World k of a batch (`Detector.detect_batch`, arrays (K, n, ...)): views (n, ...)."""
        return Detections(
            self.detected[k], self.u[k], self.v[k], self.depth[k], self.psi[k],
            self.visible_fraction[k], self.blocked_fraction[k], self.true_features[k],
            self.in_front[k], self.box_center[k], self.truncated[k],
        )  # fmt: skip


_DETECTION_FIELDS = tuple(f.name for f in fields(Detections))


@dataclass(frozen=True)
class UAVSnapshot:
    """The true state of the UAVs and the car at one step, and the detector's last frame.

    Returned by ``UAVTrackEnv.snapshot()``: every array is a copy, never a view of the env's
    state. The layout (obstacles, references) is ``env.layout``.
    """

    positions: np.ndarray
    """(n, 3) UAV positions in the global frame (m)."""
    yaws: np.ndarray
    """(n,) UAV headings (rad); the camera looks along the heading."""
    velocities: np.ndarray
    """(n, 3) UAV velocities in the global frame (m/s)."""
    yaw_rates: np.ndarray
    """(n,) global yaw rates (rad/s), = -omega_cy."""
    alive: np.ndarray
    """(n,) bool: the UAV is still in the episode."""
    target_center: np.ndarray
    """(3,) centre of the car's box (m)."""
    target_heading: float
    """Heading of the car (rad)."""
    detection: Detections | None
    """The detector's frame at this step (None before the first reset)."""


def _unit_grid(counts: tuple[int, int, int]) -> np.ndarray:
    axes = [np.linspace(-0.8, 0.8, k) if k > 1 else np.zeros(1) for k in counts]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


_CORNER_SIGNS = np.array(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float
)


_CAR_RADIUS = float(np.linalg.norm(CAR_HALF_EXTENTS))
"""Half diagonal of the car's box (m)."""


def _to_world(local: np.ndarray, centers: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Points (P, 3) of a body frame in the global frame of K bodies: (K, P, 3)."""
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    x, y = local[:, 0], local[:, 1]
    out = np.empty((len(yaws), *local.shape))
    out[..., 0] = c * x - s * y
    out[..., 1] = s * x + c * y
    out[..., 2] = local[:, 2]
    out += centers[:, None]
    return out


class Detector:
    """Geometric bounding-box detector with configurable noise, dropouts and occlusion."""

    def __init__(self, camera: CameraConfig, cfg: DetectorConfig) -> None:
        self.camera = camera
        self.cfg = cfg
        samples = _unit_grid(cfg.samples_per_axis) * CAR_HALF_EXTENTS
        self._n_samples = len(samples)
        # One transform for all points: the centre, the ray-cast samples, the 8 box corners.
        self._local = np.vstack([np.zeros((1, 3)), samples, _CORNER_SIGNS * CAR_HALF_EXTENTS])
        self._sample_radius = float(np.linalg.norm(samples, axis=1).max())
        self._camera = np.array(
            [camera.fx, camera.fy, camera.cu, camera.cv, camera.width, camera.height, camera.near],
            float,
        )
        self._settings = np.array(
            [
                cfg.min_visible_fraction, cfg.dropout_prob, cfg.pixel_noise_std,
                cfg.depth_noise_std, cfg.psi_noise_std, camera.near,
            ],
            float,
        )  # fmt: skip

    def detect(
        self,
        world: World,
        positions: np.ndarray,
        yaws: np.ndarray,
        target_center: np.ndarray,
        target_yaw: float,
        target_heading: float,
        rng: np.random.Generator,
    ) -> Detections:
        """One frame for all UAVs of one world: project, ray-cast, box, then add noise and
        dropouts."""
        return self.detect_batch(
            [world],
            positions[None],
            yaws[None],
            np.asarray(target_center, float)[None],
            np.array([target_yaw], float),
            np.array([target_heading], float),
            [rng],
        ).world(0)

    def detect_batch(
        self,
        worlds: list[World],
        positions: np.ndarray,
        yaws: np.ndarray,
        target_centers: np.ndarray,
        target_yaws: np.ndarray,
        target_headings: np.ndarray,
        rngs: list[np.random.Generator],
        bodies: broadphase.Bodies | None = None,
    ) -> Detections:
        """`detect` for K worlds at once: positions (K, n, 3), yaws (K, n), the cars' centres
        (K, 3), yaws and headings (K,); each world casts its rays in its own PyBullet client
        and draws its noise from its own generator. With ``bodies`` (the env's record of what a ray
        may meet) only the rays whose answer `broadphase.known_answers` cannot prove go to
        PyBullet (None: all).
        Returns arrays (K, n, ...)."""
        K, n = yaws.shape
        rows, true, box_center, flags, truncated, in_image, samples = core_kernels.detector_frame(
            self._local, target_centers, target_yaws, target_headings, positions, yaws,
            self._camera, self._n_samples,
        )  # fmt: skip
        known = None
        if bodies is not None:
            known = broadphase.known_answers(
                positions, target_centers, samples, self._sample_radius, _CAR_RADIUS, bodies
            )
        reach = self._reach(worlds, positions, samples, known)
        # A fixed number of draws per frame keeps the random stream independent of outcomes;
        # each world draws its noise, then its dropouts.
        draws = [(rng.standard_normal((n, 4)), rng.random(n)) for rng in rngs]
        noise = draws[0][0] if K == 1 else np.concatenate([d[0] for d in draws])
        dropout = draws[0][1] if K == 1 else np.concatenate([d[1] for d in draws])
        values, detected = core_kernels.detector_measure(
            rows, flags[1], in_image, reach, noise, dropout, self._settings
        )
        values = values.reshape(len(values), K, n)
        return Detections(
            detected=detected.reshape(K, n),
            u=values[0],
            v=values[1],
            depth=values[2],
            psi=values[3],
            visible_fraction=values[4],
            blocked_fraction=values[5],
            truncated=truncated.reshape(K, n, 2),
            true_features=true.reshape(K, n, 4),
            in_front=flags[0].reshape(K, n),
            box_center=box_center.reshape(K, n, 2),
        )

    def _reach(
        self,
        worlds: list[World],
        positions: np.ndarray,
        samples: np.ndarray,
        known: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> np.ndarray:
        """Whether each UAV's ray to each sample point (K, s, 3) reaches the car: (K n, s) bool.
        The rays ``known`` (`broadphase.known_answers`) does not answer are cast in PyBullet."""
        K, n = positions.shape[:2]
        s = self._n_samples
        if known is None:
            reach, rays, in_doubt = np.zeros((K, n, s), bool), np.ones((K, n, s), bool), range(K)
        else:
            reach, rays, worlds_in_doubt = known
            in_doubt = worlds_in_doubt.tolist()
        for k in in_doubt:
            i, j = np.nonzero(rays[k])  # this world's rays that go to PyBullet
            reach[k, i, j] = worlds[k].rays_reach_target(positions[k, i], samples[k, j])
        return reach.reshape(K * n, s)


def receive_positions(
    dist: np.ndarray, alive: np.ndarray, cfg: CommsConfig, rng: np.random.Generator
) -> np.ndarray:
    """received[i, j]: UAV i got UAV j's position (within R_c, not dropped), (n, n).

    ``dist`` is the (n, n) matrix of inter-UAV distances.
    """
    return receive_batch(dist[None], alive[None], cfg, [rng])[0]


def receive_batch(
    dist: np.ndarray, alive: np.ndarray, cfg: CommsConfig, rngs: list[np.random.Generator]
) -> np.ndarray:
    """`receive_positions` for K worlds: dist (K, n, n), alive (K, n) -> (K, n, n)."""
    n = dist.shape[-1]
    draws = np.empty((len(rngs), n, n))
    for k, rng in enumerate(rngs):
        draws[k] = rng.random((n, n))
    return core_kernels.received(dist, alive, draws, cfg.drop_prob, cfg.r_c)
