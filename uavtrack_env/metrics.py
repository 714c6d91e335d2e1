"""Episode recording and the metrics of Tables V-VI (RMS image errors, safety flags).

RMS pixel errors are taken over every step of the episode, as in Table V between the centre of the
bounding box and the reference pixel (c + f x*), on the noise-free box (so detector noise does not
inflate them); steps where the target is lost still count, capped at the image size per axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class AgentTrace:
    """Per-step history of one UAV (lists of floats/arrays, converted by `arrays()`)."""

    t: list[float] = field(default_factory=list)
    pixel_error: list[np.ndarray] = field(default_factory=list)
    depth_error: list[float] = field(default_factory=list)
    measured_uv: list[tuple[float, float]] = field(default_factory=list)
    position: list[np.ndarray] = field(default_factory=list)
    nearest_uav: list[float] = field(default_factory=list)
    obstacle_clearance: list[float] = field(default_factory=list)
    occlusion_angles: list[np.ndarray] = field(default_factory=list)
    occlusion_candidates: list[np.ndarray] = field(default_factory=list)
    detected: list[bool] = field(default_factory=list)
    collision: list[bool] = field(default_factory=list)
    disconnection: list[bool] = field(default_factory=list)
    occlusion: list[bool] = field(default_factory=list)
    blocked_fraction: list[float] = field(default_factory=list)
    slack: list[float] = field(default_factory=list)


class EpisodeRecorder:
    """Collects the env's infos step by step; `summary()` gives the metrics.json per-UAV block."""

    def __init__(
        self,
        agents: list[str],
        dt: float,
        theta_star: float,
        obstacle_centers: np.ndarray | None = None,
    ) -> None:
        self.agents = list(agents)
        self.obstacle_centers = (
            np.zeros((0, 3)) if obstacle_centers is None else np.asarray(obstacle_centers, float)
        )
        self.target_position: list[np.ndarray] = []
        self.dt = dt
        self.theta_star = theta_star
        self.traces = {a: AgentTrace() for a in agents}
        self.uav_distances: list[np.ndarray] = []
        self.steps = 0

    def record(self, infos: dict[str, dict], slacks: dict[str, float] | None = None) -> None:
        t = self.steps * self.dt
        positions = {}
        for agent, info in infos.items():
            tr, truth, meas = self.traces[agent], info["truth"], info["measurement"]
            tr.t.append(t)
            tr.pixel_error.append(truth["pixel_error"])
            tr.depth_error.append(
                truth["depth_error"] if truth["depth_error"] is not None else math.nan
            )
            tr.measured_uv.append(
                (meas["u"], meas["v"]) if meas["detected"] else (math.nan, math.nan)
            )
            tr.position.append(info["own"]["position"])
            tr.nearest_uav.append(truth["nearest_uav_distance"])
            tr.obstacle_clearance.append(truth["nearest_obstacle_clearance"])
            tr.occlusion_angles.append(truth["occlusion_angles"])
            tr.occlusion_candidates.append(truth["occlusion_candidates"])
            tr.detected.append(meas["detected"])
            tr.blocked_fraction.append(truth["blocked_fraction"])
            for k in ("collision", "disconnection", "occlusion"):
                getattr(tr, k).append(info["violations"][k])
            tr.slack.append(0.0 if slacks is None else float(slacks.get(agent, 0.0)))
            positions[agent] = info["own"]["position"]
        if infos:
            self.target_position.append(next(iter(infos.values()))["truth"]["target_position"])
        pts = np.array([positions.get(a, [np.nan] * 3) for a in self.agents])
        self.uav_distances.append(np.linalg.norm(pts[:, None] - pts[None], axis=-1))
        self.steps += 1

    def summary(self) -> dict[str, dict]:
        """Per-UAV metrics with the keys of metrics.json (see baselines/evaluate.py)."""
        out = {}
        dists = np.array(self.uav_distances)  # (T, n, n)
        for i, agent in enumerate(self.agents):
            tr = self.traces[agent]
            if not tr.t:
                continue
            pe = np.array(tr.pixel_error)
            others = np.delete(dists[:, i, :], i, axis=1)
            theta = [
                np.min(a[c])
                for a, c in zip(tr.occlusion_angles, tr.occlusion_candidates, strict=True)
                if np.any(c)
            ]
            max_blocked = float(np.max(tr.blocked_fraction))
            out[agent] = {
                "rms_u_px": float(np.sqrt(np.mean(pe[:, 0] ** 2))),
                "rms_v_px": float(np.sqrt(np.mean(pe[:, 1] ** 2))),
                "rms_depth_m": float(np.sqrt(np.nanmean(np.array(tr.depth_error) ** 2))),
                "collision_ok": not any(tr.collision),
                "connectivity_ok": not any(tr.disconnection),
                "occlusion_ok": max_blocked == 0.0,
                "detection_kept_ok": not any(tr.occlusion),
                "max_blocked_fraction": max_blocked,
                "theta_ok": bool(not theta or min(theta) >= self.theta_star - 1e-9),
                "min_uav_dist_m": float(np.nanmin(others)) if others.size else math.inf,
                "max_uav_dist_m": float(np.nanmax(others)) if others.size else 0.0,
                "min_obstacle_clearance_m": float(np.min(tr.obstacle_clearance)),
                "min_occlusion_angle_deg": float(np.degrees(min(theta))) if theta else 180.0,
                "detected_fraction": float(np.mean(tr.detected)),
                "steps": len(tr.t),
            }
        return out
