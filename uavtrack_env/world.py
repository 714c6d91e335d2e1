"""The PyBullet world: one client per env; ground, box obstacles, the car, UAV spheres.

Bodies are kinematic: poses are set each step, never simulated by `stepSimulation`; PyBullet
provides contact detection on the real shapes and ray casts for the camera's line of sight. The
obstacles stay where the layout puts them: the env skips the queries its own record of the
bodies answers (`uavtrack_env.broadphase`), so a body moved in the client directly is not seen
by those.
Every call names this world's client, so envs in one process never share state.
"""

from __future__ import annotations

import math
import os
import weakref

import numpy as np
import pybullet as p

from .scenarios import Layout
from .target import CAR_HALF_EXTENTS

_PARK = np.array([1.0e4, 1.0e4, 1.0e3])
"""Where a UAV that left the episode is put, far from everything."""
UAV_COLOURS = [
    (0.12, 0.47, 0.71, 1),
    (0.17, 0.63, 0.17, 1),
    (0.58, 0.40, 0.74, 1),
    (1.00, 0.50, 0.05, 1),
    (0.09, 0.75, 0.81, 1),
    (0.55, 0.34, 0.29, 1),
]


def _quat(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


class World:
    """Owns a PyBullet client and the bodies of one episode."""

    def __init__(self, gui: bool = False) -> None:
        if gui and not os.environ.get("DISPLAY"):
            raise RuntimeError(
                "render_mode='human' opens the PyBullet GUI and needs a display (DISPLAY is not "
                "set); use render_mode='rgb_array' on a headless machine"
            )
        self.cid = p.connect(p.GUI if gui else p.DIRECT)
        if self.cid < 0:
            raise RuntimeError("could not connect to PyBullet")
        # an env dropped without close() still frees its client when it is collected
        self._release = weakref.finalize(self, _disconnect, self.cid)
        self.gui = gui
        self.uav_ids: list[int] = []
        self.obstacle_ids: list[int] = []
        self._pending: tuple | None = None

    def build(self, layout: Layout, uav_radius: float) -> None:
        """(Re)create every body for a new episode."""
        self._pending = None
        c = self.cid
        p.resetSimulation(physicsClientId=c)
        if self.gui:
            p.configureDebugVisualizer(p.COV_ENABLE_GUI, 0, physicsClientId=c)
        plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=c)
        plane_vis = p.createVisualShape(
            p.GEOM_BOX,
            halfExtents=[200, 200, 0.001],
            rgbaColor=[0.82, 0.85, 0.80, 1],
            physicsClientId=c,
        )
        self.ground_id = p.createMultiBody(0, plane, plane_vis, physicsClientId=c)
        self.obstacle_ids = [
            self._box(center, half, (0.55, 0.45, 0.35, 1))
            for center, half in zip(
                layout.obstacle_centers, layout.obstacle_half_extents, strict=True
            )
        ]
        self.target_id = self._box(
            np.array([0, 0, CAR_HALF_EXTENTS[2]]), CAR_HALF_EXTENTS, (0.85, 0.1, 0.1, 1)
        )
        col = p.createCollisionShape(p.GEOM_SPHERE, radius=uav_radius, physicsClientId=c)
        self.uav_ids = []
        for i, pos in enumerate(layout.uav_positions):
            vis = p.createVisualShape(
                p.GEOM_SPHERE,
                radius=uav_radius,
                rgbaColor=UAV_COLOURS[i % len(UAV_COLOURS)],
                physicsClientId=c,
            )
            # Mass > 0: Bullet skips static-static pairs, and UAV contacts must be found.
            uid = p.createMultiBody(1.0, col, vis, basePosition=pos.tolist(), physicsClientId=c)
            p.changeDynamics(
                uid, -1, activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=c
            )
            self.uav_ids.append(uid)
        self._kind = {self.ground_id: "ground", self.target_id: "target"}
        self._kind.update({oid: "obstacle" for oid in self.obstacle_ids})
        self._uav_index = {uid: i for i, uid in enumerate(self.uav_ids)}

    def _box(self, center: np.ndarray, half: np.ndarray, rgba) -> int:
        c = self.cid
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half), physicsClientId=c)
        vis = p.createVisualShape(
            p.GEOM_BOX, halfExtents=list(half), rgbaColor=rgba, physicsClientId=c
        )
        return p.createMultiBody(0, col, vis, basePosition=list(center), physicsClientId=c)

    def set_poses(
        self,
        positions: np.ndarray,
        yaws: np.ndarray,
        alive: np.ndarray,
        target_center: np.ndarray,
        target_yaw: float,
        defer: bool = False,
    ) -> None:
        """Pose the UAVs (those not ``alive`` parked far away) and the car. With ``defer`` the
        poses reach PyBullet only before the next query that reads them (ray casts, contacts,
        images), so a step whose queries are all skipped (`uavtrack_env.broadphase`) never
        sends them; a GUI world poses at once."""
        self._pending = (
            np.array(positions, float),
            np.array(yaws, float),
            np.array(alive, bool),
            np.array(target_center, float),
            float(target_yaw),
        )
        if not defer or self.gui:
            self.sync()

    def sync(self) -> None:
        """Send the latest poses of `set_poses` to PyBullet (nothing if they are there)."""
        if self._pending is None:
            return
        positions, yaws, alive, target_center, target_yaw = self._pending
        self._pending = None
        c = self.cid
        for uid, pos, yaw, ok in zip(
            self.uav_ids, positions.tolist(), yaws.tolist(), alive.tolist(), strict=True
        ):
            where = pos if ok else (_PARK + [0.0, 0.0, 10.0 * uid]).tolist()
            p.resetBasePositionAndOrientation(uid, where, _quat(yaw), physicsClientId=c)
        p.resetBasePositionAndOrientation(
            self.target_id, target_center.tolist(), _quat(target_yaw), physicsClientId=c
        )

    def contacts(self, n: int) -> dict[str, np.ndarray]:
        """Which UAVs touch the ground, an obstacle or the target: bool arrays (n,)."""
        self.sync()
        p.performCollisionDetection(physicsClientId=self.cid)
        hits = {k: np.zeros(n, bool) for k in ("ground", "obstacle", "target")}
        for cp in p.getContactPoints(physicsClientId=self.cid):
            if cp[8] > 0.0:  # contactDistance: positive means only within the margin
                continue
            for me, other in ((cp[1], cp[2]), (cp[2], cp[1])):
                if me in self._uav_index and other in self._kind:
                    hits[self._kind[other]][self._uav_index[me]] = True
        return hits

    def rays_reach_target(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """For each ray, whether the first body it hits is the target: bool (R,)."""
        if len(starts) == 0:
            return np.zeros(0, bool)
        self.sync()
        # float64 (R, 3) arrays go to PyBullet as they are (faster than lists of lists)
        starts = np.ascontiguousarray(starts, dtype=np.float64)
        ends = np.ascontiguousarray(ends, dtype=np.float64)
        out = p.rayTestBatch(starts, ends, numThreads=1, physicsClientId=self.cid)
        return np.array([r[0] for r in out]) == self.target_id

    def camera_image(
        self,
        eye: np.ndarray,
        target: np.ndarray,
        up: np.ndarray,
        fov_deg: float,
        width: int,
        height: int,
        far: float = 200.0,
    ) -> np.ndarray:
        """An RGB image (h, w, 3) uint8 rendered with TinyRenderer (headless)."""
        self.sync()
        view = p.computeViewMatrix(
            eye.tolist(), target.tolist(), up.tolist(), physicsClientId=self.cid
        )
        proj = p.computeProjectionMatrixFOV(
            fov_deg, width / height, 0.05, far, physicsClientId=self.cid
        )
        img = p.getCameraImage(
            width,
            height,
            view,
            proj,
            renderer=p.ER_TINY_RENDERER,
            shadow=0,
            physicsClientId=self.cid,
        )
        return np.asarray(img[2], np.uint8).reshape(height, width, 4)[:, :, :3].copy()

    def point_gui_camera(
        self, target: np.ndarray, distance: float, yaw_deg: float, pitch_deg: float
    ) -> None:
        """Aim the GUI's debug camera at ``target`` (only meaningful with ``gui=True``)."""
        self.sync()
        p.resetDebugVisualizerCamera(
            cameraDistance=distance,
            cameraYaw=yaw_deg,
            cameraPitch=pitch_deg,
            cameraTargetPosition=np.asarray(target, float).tolist(),
            physicsClientId=self.cid,
        )

    def close(self) -> None:
        self._release()
        self.cid = -1

    def require_open(self, call: str, build: str) -> None:
        """Raise if `close` released the client: ``call`` is the caller's method, ``build``
        the constructor to use instead."""
        if self.cid < 0:
            raise RuntimeError(
                f"{call}() called after close(): its PyBullet client is released; build a new "
                f"one with {build}"
            )

    def __reduce_ex__(self, protocol):
        raise TypeError(
            "a uavtrack env owns a live PyBullet client, which cannot be copied or pickled; build "
            "a new env from the same arguments instead (uavtrack_v0.parallel_env(**kwargs), or a "
            "functools.partial of it, which pickles)"
        )


def _disconnect(cid: int) -> None:
    """Disconnect PyBullet client ``cid`` (a `World`'s finalizer; runs at most once)."""
    try:
        p.disconnect(physicsClientId=cid)
    except p.error:
        pass
