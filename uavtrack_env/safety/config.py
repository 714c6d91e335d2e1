"""Settings of the CBF rows (25), (34), (45) and their gains (Table IV): part of `ExpertConfig`."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

from uavtrack_env.safety.occlusion import POINT_MODES
from uavtrack_env.validation import Fields as _Fields
from uavtrack_env.validation import require as _require


@dataclass(frozen=True)
class CBFConfig:
    """Control barrier functions and the QP (47) (Table IV)."""

    r_s: float | None = None
    """Minimum safety range R_s between UAVs, eq. (20). None: the world's collision range
    (`EnvConfig.violations.r_s`, 2 m in Table IV); a value may only be larger (`resolve`)."""
    r_c: float | None = None
    """Maximum connectivity range R_c, eq. (29). None: the world's link range
    (`EnvConfig.comms.r_c`, 20 m in Table IV); a value may only be smaller (`resolve`)."""
    d_s: float | None = None
    """Range D_s of the collision neighbour set N_si, eq. (27); None: R_c (Table IV)."""
    theta_star_deg: float = 30.0
    """Occlusion-free half-angle theta* of eq. (37) in degrees (Table IV)."""
    gamma_s: float = 3.0
    """Collision CBF rate gamma_s, eq. (21) (Table IV); must satisfy eq. (28)."""
    gamma_c: float = 1.0
    """Connectivity CBF rate gamma_c, eq. (30) (Table IV)."""
    gamma_o: float = 0.1
    """Occlusion CBF rate gamma_o, eq. (40) (Table IV; Fig. 20 uses 0.5)."""
    alpha_v: float = 10.0
    """Speed bound ||V_c^g|| <= alpha_v in m/s, eq. (47) (Table IV)."""
    alpha_omega: float = 0.6
    """Angular speed bound ||omega_c^g|| <= alpha_omega in rad/s, eq. (47) (Table IV)."""
    obstacle_clearance: float = 0.75
    """Not in the paper: minimum distance (m) from a UAV's centre to an obstacle's surface."""
    gamma_obstacle: float = 3.0
    """Not in the paper: CBF rate for UAV-obstacle and UAV-target rows (like gamma_s)."""
    z_min: float = 0.5
    """Not in the paper: altitude floor (m) for the UAV centre."""
    gamma_z: float = 3.0
    """Not in the paper: CBF rate of the altitude floor."""
    occlusion_model: Literal["paper", "moving-target"] = "paper"
    """'paper': eq. (43), n-dot = 0; 'moving-target': n-dot from the estimated target velocity."""
    occlusion_point: Literal["centre", "axis", "edges"] = "axis"
    """Occluder point p_o of eq. (38): the box 'centre' (paper), or the point closest in angle to
    the line of sight on its vertical axis ('axis'; tall boxes are not points) or on its 12 edges
    ('edges'; wide boxes close to the UAV are not points either)."""
    occlusion_size_margin: bool = False
    """Not in the paper: widen theta* by the box's angular radius asin(r_xy / |p_o - p|)."""
    team_mate_radius: float | None = 0.0
    """Not in the paper: the team-mates occlude the car too, in the occlusion rows (45) each a
    box of this half size (m) around its believed position, grown by its message ball and
    moving at its believed velocity (`barrier_rows.all_rows`). 0 (every preset): they do not, as
    in the paper, whose rows cover the obstacles only; None: the world's UAV radius
    (`resolve`). Opt-in: docs/safety.md measures what it costs in crowds."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.number("r_s", lo=0, lo_open=True, none_means="the world's collision range")
        f.number("r_c", lo=0, lo_open=True, none_means="the world's link range")
        f.number("d_s", lo=0, lo_open=True, none_means="R_c")
        f.number("theta_star_deg", lo=0, hi=90, lo_open=True, hi_open=True)
        for name in (
            "gamma_s",
            "gamma_c",
            "gamma_o",
            "alpha_v",
            "alpha_omega",
            "obstacle_clearance",
            "gamma_obstacle",
            "gamma_z",
        ):
            f.number(name, lo=0, lo_open=True)
        f.number("z_min", lo=0)
        f.choice("occlusion_model", ("paper", "moving-target"))
        f.choice("occlusion_point", POINT_MODES)
        f.flag("occlusion_size_margin")
        f.number("team_mate_radius", lo=0, none_means="the world's UAV radius")
        if self.resolved:
            self._check_ranges()

    @property
    def resolved(self) -> bool:
        """R_s, R_c, D_s and the team-mates' radius are all set (`resolve` fills them from the
        world)."""
        return None not in (self.r_s, self.r_c, self.d_s, self.team_mate_radius)

    def resolve(self, r_s: float = 2.0, r_c: float = 20.0, uav_radius: float = 0.25) -> CBFConfig:
        """This config with R_s, R_c (and D_s) and the team-mates' radius set: the world's
        collision range ``r_s``, link range ``r_c`` and UAV radius where unset (the defaults are
        Table IV's and `EnvConfig.uav_radius`'s). A set R_s below the world's or a set R_c above
        it raises: the controller may be stricter than the world, never looser."""
        if self.r_s is not None and self.r_s < r_s:
            raise ValueError(f"cbf.r_s = {self.r_s} m is below the world's collision range {r_s} m")
        if self.r_c is not None and self.r_c > r_c:
            raise ValueError(f"cbf.r_c = {self.r_c} m is above the world's link range {r_c} m")
        r_s = r_s if self.r_s is None else self.r_s
        r_c = r_c if self.r_c is None else self.r_c
        d_s = r_c if self.d_s is None else self.d_s
        radius = uav_radius if self.team_mate_radius is None else self.team_mate_radius
        return dataclasses.replace(self, r_s=r_s, r_c=r_c, d_s=d_s, team_mate_radius=radius)

    def _check_ranges(self) -> None:
        _require(
            0 < self.r_s < self.d_s <= self.r_c,
            f"need 0 < R_s < D_s <= R_c (eq. 27), got R_s = {self.r_s}, D_s = {self.d_s}, "
            f"R_c = {self.r_c}",
        )
        bound = 4.0 * self.alpha_v * self.r_s / (self.d_s**2 - self.r_s**2)
        _require(
            self.gamma_s >= bound,
            f"gamma_s = {self.gamma_s} violates eq. (28): the distributed collision CBF needs "
            f"gamma_s >= 4 alpha_v R_s / (D_s^2 - R_s^2) = {bound:.4f}",
        )

    @property
    def theta_star(self) -> float:
        """theta* in radians."""
        return math.radians(self.theta_star_deg)
