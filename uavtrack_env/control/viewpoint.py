"""Anticipatory viewpoint altitude: raise x2* before a tall box can cut the line of sight.

Not in the paper. With a camera fixed to the body, looking horizontally, a UAV flying beside the
car cannot keep a box between the road and its own track out of the horizontal line of sight
(the sight line sweeps across the box's footprint); it can only look over it. The paper's UAVs
do so in scenario C ("larger tracking errors are observed in V-axis ... due to the higher
obstacles", section VI-C), but its occlusion CBF (45), a rate condition with gamma_o = 0.1 that
models the target as static (43), reacts too late to climb a 2.5 m box in time.

Geometry (camera level, x1 ~ 0): a target point at height z_p and the UAV at horizontal range D
and height z_u. The sight line clears a box top z_b (plus margin) whose footprint it enters at
horizontal distance d from the target when (z_u - z_p) / D >= (z_b - z_p) / d. With
x2 = (z_u - z_q) / D for the target's centre z_q this is

    x2 >= (z_p - z_q) / D + (z_b - z_p) / d,

independent of how far the UAV stands off. ``required_x2`` evaluates it over boxes and
predicted poses; `ViewpointPlanner` raises the reference x2* to it, rate-limited, and lowers it
again when the way is clear.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uavtrack_env.validation import Fields as _Fields


@dataclass(frozen=True)
class ViewpointConfig:
    """Tunables of the viewpoint layer (not in the paper)."""

    enabled: bool = True
    """Raise x2* for tall boxes; False leaves the paper's constant reference."""
    horizon_s: float = 3.0
    """Look-ahead over which target and UAV are extrapolated at the target's velocity (s)."""
    samples: int = 7
    """Poses sampled over [0, horizon_s]."""
    target_height_m: float = 0.75
    """Height of the car's centre above the flat ground (the paper's car is 1.5 m tall); used
    instead of the estimate's z, which the bounding-box centre biases when seen from above."""
    visible_height_m: float = 0.6
    """Height above the target's centre of the part that must stay in sight (upper half of the
    paper's 1.5 m car: the detector needs half of it)."""
    top_margin_m: float = 0.2
    """Clearance of the sight line above a box top (m)."""
    footprint_margin_m: float = 0.2
    """Box footprints are inflated by this much in x and y (m)."""
    x2_max: float = 0.6
    """Upper limit of the raised x2* (Table I allows 0.63; most of the car must stay in the
    image for the detector)."""
    max_box_offset: float = 0.15
    """Clip of the measured offset between the box centre's and the car centre's x2."""
    rate: float = 0.15
    """Largest change of x2* per second, up or down."""
    replan_period_s: float = 0.1
    """How often the sight-line geometry is re-evaluated (s); x2* itself moves every step."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.flag("enabled")
        f.number("horizon_s", lo=0)
        f.integer("samples", lo=1)
        for name in (
            "target_height_m",
            "visible_height_m",
            "top_margin_m",
            "footprint_margin_m",
            "max_box_offset",
        ):
            f.number(name, lo=0)
        f.number("x2_max", lo=0, hi=1, lo_open=True, hi_open=True)
        f.number("rate", lo=0, lo_open=True)
        f.number("replan_period_s", lo=0, lo_open=True)


def entry_fraction(
    start: np.ndarray, end: np.ndarray, box_min: np.ndarray, box_max: np.ndarray
) -> np.ndarray:
    """Where horizontal segments start -> end first enter box footprints (slab method).

    start, end: (..., 2); box_min, box_max: (m, 2). Returns (..., m) fractions in [0, 1] along
    each segment, NaN for boxes it misses; 0 when its start lies inside.
    """
    start, end = start[..., None, :], end[..., None, :]
    d = end - start
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (box_min - start) / d
        t2 = (box_max - start) / d
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    # A zero direction component: inside the slab for all t, or never.
    inside = (start >= box_min) & (start <= box_max)
    lo = np.where(d == 0, np.where(inside, -np.inf, np.inf), lo)
    hi = np.where(d == 0, np.where(inside, np.inf, -np.inf), hi)
    t_in = np.maximum(lo.max(axis=-1), 0.0)
    t_out = np.minimum(hi.min(axis=-1), 1.0)
    return np.where(t_in <= t_out, t_in, np.nan)


def required_x2(
    target: np.ndarray,
    uav: np.ndarray,
    box_centers: np.ndarray,
    box_half_extents: np.ndarray,
    cfg: ViewpointConfig,
) -> np.ndarray:
    """The least x2 for which every box top stays below the sight line (0 if none in the way).

    target, uav: (..., 3) positions (target = the car's centre); returns (...,).
    """
    target, uav = np.asarray(target, float), np.asarray(uav, float)
    z_p = target[..., 2:3] + cfg.visible_height_m  # (..., 1)
    tops = box_centers[:, 2] + box_half_extents[:, 2] + cfg.top_margin_m  # (m,)
    half = box_half_extents[:, :2] + cfg.footprint_margin_m
    t = entry_fraction(
        target[..., :2], uav[..., :2], box_centers[:, :2] - half, box_centers[:, :2] + half
    )
    reach = np.maximum(np.linalg.norm(uav[..., :2] - target[..., :2], axis=-1), 1e-3)[..., None]
    need = cfg.visible_height_m / reach + (tops - z_p) / np.maximum(t * reach, 1e-3)
    need = np.where(np.isfinite(t) & (tops > z_p), need, 0.0)
    return need.max(axis=-1, initial=0.0)


class ViewpointPlanner:
    """Per-UAV x2* schedule: the paper's x2* unless a tall box ahead needs a higher sight line.

    The box map is the known, static obstacle map. The geometry is re-evaluated every
    ``replan_period_s``; x2* moves towards its goal every step at most ``rate * dt``.
    """

    def __init__(
        self,
        x2_reference: float,
        box_centers: np.ndarray,
        box_half_extents: np.ndarray,
        cfg: ViewpointConfig,
        dt: float,
    ) -> None:
        self.x2_ref = float(x2_reference)
        self.cfg = cfg
        self.dt = dt
        self.centers = np.asarray(box_centers, float).reshape(-1, 3)
        self.half_extents = np.asarray(box_half_extents, float).reshape(-1, 3)
        self._highest = float(np.max(self.centers[:, 2] + self.half_extents[:, 2], initial=-np.inf))
        self._taus = np.linspace(0.0, cfg.horizon_s, cfg.samples)[:, None]
        self._period = max(1, round(cfg.replan_period_s / dt))
        self.reset()

    def reset(self) -> None:
        self.x2 = self.x2_ref
        self.goal = self.x2_ref
        self._steps = 0

    def update(
        self,
        target: np.ndarray,
        target_velocity: np.ndarray,
        uav: np.ndarray,
        x2_now: float | None = None,
        depth: float | None = None,
    ) -> float:
        """Advance one step; returns the x2* to track now.

        target, target_velocity: the target estimate (global); uav: own position. ``x2_now`` and
        ``depth`` (the estimated feature x2 and depth 1/x3) convert the requirement, which is
        for the car's centre, to the tracked box centre: seen from above, the box centre sits
        lower in the image than the centre's projection, by ``x2_now - (z_u - z_q) / depth``.
        """
        cfg = self.cfg
        target = np.array([target[0], target[1], cfg.target_height_m])
        if self._steps % self._period == 0:
            self.goal = self.x2_ref
            if cfg.enabled and self._highest + cfg.top_margin_m > target[2] + cfg.visible_height_m:
                shift = self._taus * np.array([target_velocity[0], target_velocity[1], 0.0])
                need = float(
                    required_x2(
                        target + shift, uav + shift, self.centers, self.half_extents, cfg
                    ).max()
                )
                if need > 0 and x2_now is not None and depth is not None and depth > 0:
                    offset = x2_now - (uav[2] - target[2]) / depth
                    need += float(np.clip(offset, 0.0, cfg.max_box_offset))
                self.goal = min(max(self.x2_ref, need), max(cfg.x2_max, self.x2_ref))
        self._steps += 1
        step = cfg.rate * self.dt
        self.x2 += float(np.clip(self.goal - self.x2, -step, step))
        return self.x2


__all__ = ["ViewpointConfig", "ViewpointPlanner", "entry_fraction", "required_x2"]
