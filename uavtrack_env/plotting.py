"""The paper's figures (Figs. 12-20) from an `EpisodeRecorder`, written as PNG files."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from .metrics import EpisodeRecorder


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def image_trajectories(rec: EpisodeRecorder, references: np.ndarray, cam, path: Path) -> Path:
    """Fig. 12: the car's centre in each UAV's image (measured bounding-box centres)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for i, agent in enumerate(rec.agents):
        uv = np.array(rec.traces[agent].measured_uv, float)
        ax.plot(uv[:, 0], uv[:, 1], lw=0.8, label=f"UAV{i + 1}")
        ru, rv = cam.cu + cam.fx * references[i][0], cam.cv + cam.fy * references[i][1]
        ax.plot(ru, rv, "k+", ms=12)
    ax.set(xlim=(0, cam.width), ylim=(cam.height, 0), xlabel="U (px)", ylabel="V (px)")
    ax.set_title("Target in the image (+: reference)")
    ax.legend()
    return _save(fig, path)


def depth_errors(rec: EpisodeRecorder, path: Path) -> Path:
    """Fig. 13: depth error d - 1/x3* over time."""
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for i, agent in enumerate(rec.agents):
        tr = rec.traces[agent]
        ax.plot(tr.t, tr.depth_error, lw=0.8, label=f"UAV{i + 1}")
    ax.axhline(0, color="k", lw=0.5)
    ax.set(xlabel="time (s)", ylabel="depth error (m)")
    ax.legend()
    return _save(fig, path)


def uav_distances(rec: EpisodeRecorder, r_s: float, r_c: float, path: Path) -> Path:
    """Fig. 14: pairwise UAV distances with the R_s and R_c lines."""
    d = np.array(rec.uav_distances)
    t = np.arange(len(d)) * rec.dt
    fig, ax = plt.subplots(figsize=(7, 3.2))
    n = len(rec.agents)
    for i in range(n):
        for j in range(i + 1, n):
            ax.plot(t, d[:, i, j], lw=0.8, label=f"UAV{i + 1}-UAV{j + 1}")
    ax.axhline(r_s, color="r", ls="--", lw=0.8, label="R_s")
    ax.axhline(r_c, color="g", ls="--", lw=0.8, label="R_c")
    ax.set(xlabel="time (s)", ylabel="distance (m)")
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def obstacle_distances(rec: EpisodeRecorder, agent: str, r_s: float, path: Path) -> Path:
    """Figs. 15-16: distances from one UAV to each obstacle's centre, and the true clearance."""
    tr = rec.traces[agent]
    pos = np.array(tr.position)
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for k, c in enumerate(rec.obstacle_centers):
        ax.plot(tr.t, np.linalg.norm(pos - c, axis=1), lw=0.7, label=f"obst. {k + 1}")
    ax.plot(tr.t, tr.obstacle_clearance, "k", lw=1.2, label="clearance (surface)")
    ax.axhline(r_s, color="r", ls="--", lw=0.8, label="R_s")
    ax.set(xlabel="time (s)", ylabel="distance (m)", ylim=(0, 20))
    ax.set_title(f"{agent}: distance to obstacles")
    ax.legend(fontsize=6, ncol=3)
    return _save(fig, path)


def trajectories(rec: EpisodeRecorder, half_extents: np.ndarray, path: Path) -> Path:
    """Fig. 17: XY and XZ trajectories of the UAVs and the target, with the obstacles."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    tgt = np.array(rec.target_position)
    for ax, (i, j, lab) in ((a, (0, 1, "Y")), (b, (0, 2, "Z"))):
        for c, h in zip(rec.obstacle_centers, half_extents, strict=True):
            ax.add_patch(plt.Rectangle((c[i] - h[i], c[j] - h[j]), 2 * h[i], 2 * h[j], color="0.6"))
        for k, agent in enumerate(rec.agents):
            pos = np.array(rec.traces[agent].position)
            ax.plot(pos[:, i], pos[:, j], lw=0.9, label=f"UAV{k + 1}")
            ax.plot(pos[0, i], pos[0, j], "ko", ms=3)
        if len(tgt):
            ax.plot(tgt[:, i], tgt[:, j], "r--", lw=1.0, label="target")
        ax.set(xlabel="X (m)", ylabel=f"{lab} (m)")
        ax.set_aspect("equal", adjustable="datalim")
    a.legend(fontsize=7)
    return _save(fig, path)


def occlusion_angles(rec: EpisodeRecorder, agent: str, theta_star: float, path: Path) -> Path:
    """Figs. 18-20: occlusion angles theta (38) of the obstacles in N_oi, and the QP slack."""
    tr = rec.traces[agent]
    ang = np.degrees(np.array(tr.occlusion_angles, float))
    ang[~np.array(tr.occlusion_candidates, bool)] = np.nan
    fig, (a, b) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for k in range(ang.shape[1]):
        if np.isfinite(ang[:, k]).any():
            a.plot(tr.t, ang[:, k], lw=0.8, label=f"obst. {k + 1}")
    a.axhline(np.degrees(theta_star), color="r", ls="--", lw=0.8, label="theta*")
    a.set(ylabel="theta (deg)", ylim=(0, 180))
    a.set_title(f"{agent}: occlusion angles")
    a.legend(fontsize=6, ncol=4)
    b.plot(tr.t, tr.slack, "k", lw=0.8)
    b.set(xlabel="time (s)", ylabel="slack (m/s)")
    return _save(fig, path)


def all_figures(
    rec: EpisodeRecorder,
    env_config,
    cbf,
    references,
    half_extents,
    out: Path,
    suffix: str = "",
) -> list[Path]:
    """Write every figure into ``out``; ``cbf`` is the resolved `CBFConfig` the expert
    certified with (its R_s, R_c and theta* are drawn). Returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [
        image_trajectories(rec, references, env_config.camera, out / f"fig12_image{suffix}.png"),
        depth_errors(rec, out / f"fig13_depth{suffix}.png"),
        uav_distances(rec, cbf.r_s, cbf.r_c, out / f"fig14_uav_distances{suffix}.png"),
        trajectories(rec, half_extents, out / f"fig17_trajectories{suffix}.png"),
    ]
    for k, agent in enumerate(rec.agents):
        paths.append(
            obstacle_distances(
                rec, agent, cbf.r_s, out / f"fig15_16_obstacles_uav{k + 1}{suffix}.png"
            )
        )
        paths.append(
            occlusion_angles(
                rec, agent, cbf.theta_star, out / f"fig18_19_occlusion_uav{k + 1}{suffix}.png"
            )
        )
    return paths
