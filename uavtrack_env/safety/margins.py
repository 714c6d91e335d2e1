"""Safety margins between the barriers and the env's violation thresholds (not in the paper).

The env counts ``d < R_s`` as a UAV-UAV collision and ``d > R_c`` as a broken link, while the
barriers keep ``h >= 0`` only up to round-off (and, with the velocity-lag model, up to the lag), so
the expert and the RL shield certify with ``R_s + r_s_margin`` and ``R_c - r_c_margin``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.validation import Fields as _Fields


@dataclass(frozen=True)
class ShieldMargins:
    """Safety margins of the expert's CBF-QP and the RL shield (not in the paper; see above)."""

    r_s_margin: float = 0.05
    """Added to R_s (eq. 20) when certifying, so round-off never lets d drop below the env's R_s."""
    r_c_margin: float = 0.05
    """Subtracted from R_c (eq. 29) when certifying (D_s is capped at the reduced R_c, eq. 27)."""
    target_margin: float = 0.25
    """Added (m) to the car's heading-free half extents: estimate error the shield tolerates."""
    target_sigmas: float = 3.0
    """Further inflation in standard deviations of the UKF's target-position estimate."""
    target_margin_max: float = 2.0
    """Cap (m) on the total inflation of the car box (long dropouts grow the covariance)."""
    surface_gap: float = 0.1
    """Required gap (m) between the UAV sphere and an obstacle/the ground at the barrier's edge:
    ``obstacle_clearance - uav_radius`` and ``z_min - uav_radius`` must be at least this."""
    target_stale_after: float = 0.25
    """For this long (s) without a detection the car's box follows the UKF's prediction (its
    pad covers the error); after it, the box is the car's reachable set (`onboard.car_box`)."""
    target_speed_max: float | None = None
    """Bound (m/s) on the car's speed: a stale car's box is its reachable set, growing at this
    speed from the last trusted estimate (`onboard.car_box`). None: the world's fastest car
    (the paper's 0.5 m/s, ``random_world.target_speed``)."""
    car_on_ground: bool = True
    """The car drives on the flat ground (section VI-A): its box spans the heights 0 to its
    height (plus ``target_margin``), whatever the UKF's height estimate; False: the estimated
    height with the same pads as the horizontal axes."""
    truncated_box_pad: bool = True
    """While the car's box is cut by the image border, its centre (u, v) is biased inwards and
    the UKF's position with it, by up to the part of the car outside the image: pad the car's
    box, growing at twice ``target_speed_max``, by up to the car's footprint half diagonal
    horizontally (a cut in u) and its half height vertically (a cut in v, unless
    ``car_on_ground``) until ``truncation_recovery`` s of uncut detections have passed."""
    truncation_recovery: float = 0.5
    """Uncut detection time (s) after which the UKF has shed a truncated box's bias."""
    message_timeout: float = 1.0
    """A team-mate not heard for this long (s) is forgotten (it collided, was parked or left
    R_c); until then its rows stay, on its last message and reachable set (`NeighbourTable`).
    At a drop probability p a team-mate in range stays silent this long with probability
    p^(80 t): at 1 s, 2e-4 for p = 0.9 (at 0.5 s, 1.5 %: often enough for a UAV to forget a
    team-mate within reach); a longer timeout costs a UAV near one that did leave a wait while
    its ball grows."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        for f_name in (
            "r_s_margin",
            "r_c_margin",
            "target_margin",
            "target_sigmas",
            "target_margin_max",
            "surface_gap",
            "target_stale_after",
            "truncation_recovery",
        ):
            f.number(f_name, lo=0)
        f.flag("truncated_box_pad")
        f.flag("car_on_ground")
        if self.target_speed_max is not None:
            f.number("target_speed_max", lo=0)
        f.number("message_timeout", lo=0, lo_open=True)
        if self.target_margin_max < self.target_margin:
            raise ValueError(
                f"ShieldMargins.target_margin_max must be >= target_margin = {self.target_margin}"
                f", got {self.target_margin_max}"
            )


def shield_cbf(base: CBFConfig, margins: ShieldMargins) -> CBFConfig:
    """The CBF config the shield certifies with: R_s + margin, R_c - margin, D_s <= R_c.

    Raises ValueError when the inflated R_s breaks eq. (28) or the ranges become inconsistent.
    """
    r_s = base.r_s + margins.r_s_margin
    r_c = base.r_c - margins.r_c_margin
    try:
        return dataclasses.replace(base, r_s=r_s, r_c=r_c, d_s=min(base.d_s, r_c))
    except ValueError as exc:
        raise ValueError(
            f"the shield certifies with R_s + {margins.r_s_margin} = {r_s} m and "
            f"R_c - {margins.r_c_margin} = {r_c} m, which the CBF config does not allow: {exc}"
        ) from exc
