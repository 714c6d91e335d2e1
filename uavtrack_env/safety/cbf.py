"""Barrier functions h and their CBF constraint rows (paper section IV, eqs. 20-45).

Every row is a linear inequality on the UAV's *global-frame* translational velocity V = p-dot
(single integrator, eq. 3)::

    A V <= b,    b = gamma * h + drift - margin,

and it encodes ``h-dot >= -gamma * h + margin`` because along the dynamics
``h-dot = -A V + drift`` (``drift`` collects what the UAV does not control: the target's
estimated motion). Rows never involve the yaw rate: the A matrices of (25), (34) and (45) have
zeros in the omega block, so the angular part of the paper's 6-vector u^g is decoupled from
every barrier.

Row families (``KIND_NAMES``), all built from what one UAV knows (its `SafetyContext`):

* ``uav``       UAV-UAV collision (20)-(25), j in N_si (within D_s); each UAV takes half (23).
* ``obstacle``  UAV-obstacle collision: the paper's point model (centre, radius R_s) or an exact
                box-distance barrier ``dist(p, box)^2 - c^2`` (not in the paper; the default).
* ``target``    the target car as an oriented box moving with its estimated velocity.
* ``floor``     altitude floor ``h = z - z_min`` (not in the paper).
* ``connect``   connectivity (29)-(34), j in N_ci (within R_c); half each, with a discrete-time
                margin (see `connectivity_rows`).
* ``occlusion`` occlusion (37)-(45), j in N_oi (obstacle centres closer than the target); the
                paper's n-dot = 0 (43) or a 'moving-target' n-dot = V_q - V.

The first four are hard in the shield, the last two soft.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, NamedTuple

import numpy as np

from uavtrack_env.safety.barrier_rows import all_rows, box_sdists, make_way
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.occlusion import OVER_THE_TOP, POINT_MODES
from uavtrack_env.safety.second_order import second_order_rows

KIND_NAMES = ("uav", "obstacle", "target", "floor", "connect", "occlusion")
"""Row family names, indexed by `CBFRows.kind`."""
UAV, OBSTACLE, TARGET, FLOOR, CONNECT, OCCLUSION = range(6)
HARD_KINDS = (UAV, OBSTACLE, TARGET, FLOOR)
"""Row families that are never relaxed (collision and altitude)."""

DEFAULT_CAR_HALF_EXTENTS = (2.3, 0.9, 0.75)
"""Half size of the target car, 4.6 x 1.8 x 1.5 m (section VI-A)."""

_EMPTY3 = np.zeros((0, 3))
_ZEROS3 = np.zeros(3)
_NO_CAP = np.zeros(0)
"""`barrier_rows.first_order_rows`' ``cap_rho`` without a speed cap (second-order rows)."""


def _vec3(name: str, value, default=None) -> np.ndarray:
    if value is None:
        value = default
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


def _rows3(name: str, value) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.size == 0:
        return _EMPTY3
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (k, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite")
    return arr


@dataclass(frozen=True)
class SafetyContext:
    """Everything UAV i knows when it certifies an action (global frame, SI units).

    The filter is distributed: it uses nothing but this object.
    """

    position: np.ndarray
    """(3,) own position p^i (GPS), eq. (3)."""
    yaw: float
    """Own yaw = camera heading (rad); the camera-to-global rotation is `cam_to_world(yaw)`."""
    neighbours: np.ndarray = field(default_factory=lambda: _EMPTY3)
    """(k, 3) positions of the UAVs whose messages were received (within R_c)."""
    obstacle_centers: np.ndarray = field(default_factory=lambda: _EMPTY3)
    """(m, 3) centres p_o^j of the known axis-aligned box obstacles (section IV-C)."""
    obstacle_half_extents: np.ndarray = field(default_factory=lambda: _EMPTY3)
    """(m, 3) half sizes of the obstacle boxes."""
    target_position: np.ndarray | None = None
    """(3,) own estimate of the target centre r_q (global); None: no target rows."""
    target_velocity: np.ndarray | None = None
    """(3,) estimate of the target velocity V_q (global); default zero."""
    target_half_extents: np.ndarray | None = None
    """(3,) car half size; default (2.3, 0.9, 0.75) (section VI-A)."""
    target_heading: float | None = None
    """Car yaw (rad); None: from the velocity estimate (0 when it is below 0.1 m/s)."""
    target_growth: np.ndarray = field(default_factory=lambda: _ZEROS3)
    """(3,) speeds (m/s) at which the car box's faces move outwards along its axes (x, y in the
    car's frame, z): an undetected car's reachable set (`onboard.car_box`); a scalar: every
    axis alike."""
    target_frustum: bool = False
    """The car's row is the frustum over its box (`barrier_rows.target_row`), which climbing
    always keeps; for a stale car (`onboard.car_box`). False: the box barrier."""
    neighbour_ids: tuple[int, ...] | None = None
    """Optional agent ids of `neighbours`: they name the rows ("uav:<id>") and, with `own_id`,
    rank the team-mates in a fallback (`SafetyFilter.yield_by_rank`)."""
    own_id: int | None = None
    """Optional agent id of this UAV, among the ids of `neighbour_ids`
    (`SafetyFilter.yield_by_rank`)."""
    velocity: np.ndarray | None = None
    """(3,) own actual global velocity (IMU); needed only by second-order rows (``lag_tau``)."""
    neighbour_velocities: np.ndarray | None = None
    """(k, 3) velocities of `neighbours` (e.g. differenced messages); None: taken as zero."""
    neighbour_radius: np.ndarray | None = None
    """(k,) each neighbour is within this distance (m) of `neighbours` (a lost message's
    reachable set, `onboard.NeighbourTable`); None: exactly there."""
    neighbour_velocity_radius: np.ndarray | None = None
    """(k,) each neighbour's velocity is within this (m/s) of `neighbour_velocities`."""

    @classmethod
    def trusted(cls, **values: Any) -> SafetyContext:
        """A context from values the caller guarantees are valid: float arrays of the shapes
        above, finite, every optional one set or None; ``target_velocity``,
        ``target_half_extents`` and ``target_heading`` are then required with a target. No
        checks: the onboard stack builds one per UAV per step from the env's own data, where
        checking costs about as much as the rows it feeds."""
        unknown = values.keys() - _CONTEXT_DEFAULTS.keys()
        if unknown:
            raise TypeError(f"SafetyContext has no fields {sorted(unknown)}")
        ctx = object.__new__(cls)
        state = ctx.__dict__  # frozen dataclass: fields are set past __setattr__, as dataclasses do
        state.update(_CONTEXT_DEFAULTS)
        state.update(values)
        return ctx

    def __post_init__(self) -> None:
        put = object.__setattr__
        put(self, "position", _vec3("position", self.position))
        yaw = float(self.yaw)
        if not math.isfinite(yaw):
            raise ValueError(f"yaw must be a finite angle in radians, got {self.yaw}")
        put(self, "yaw", yaw)
        put(self, "neighbours", _rows3("neighbours", self.neighbours))
        centers = _rows3("obstacle_centers", self.obstacle_centers)
        half = _rows3("obstacle_half_extents", self.obstacle_half_extents)
        if centers.shape != half.shape:
            raise ValueError(
                f"obstacle_centers {centers.shape} and obstacle_half_extents {half.shape} "
                "must have the same shape (m, 3)"
            )
        if (half < 0).any():
            raise ValueError("obstacle_half_extents must be >= 0")
        put(self, "obstacle_centers", centers)
        put(self, "obstacle_half_extents", half)
        if self.target_position is not None:
            put(self, "target_position", _vec3("target_position", self.target_position))
        vq = _vec3("target_velocity", self.target_velocity, (0.0, 0.0, 0.0))
        put(self, "target_velocity", vq)
        th = _vec3("target_half_extents", self.target_half_extents, DEFAULT_CAR_HALF_EXTENTS)
        if (th < 0).any():
            raise ValueError("target_half_extents must be >= 0")
        put(self, "target_half_extents", th)
        if self.target_heading is None:
            speed = math.hypot(vq[0], vq[1])
            put(self, "target_heading", math.atan2(vq[1], vq[0]) if speed > 0.1 else 0.0)
        elif not math.isfinite(float(self.target_heading)):
            raise ValueError(f"target_heading must be finite, got {self.target_heading}")
        growth = np.asarray(self.target_growth, dtype=float)
        if growth.shape not in ((), (3,)):
            raise ValueError(f"target_growth must be a speed or shape (3,), got {growth.shape}")
        growth = np.broadcast_to(growth, (3,)).copy()
        if not (np.isfinite(growth).all() and (growth >= 0.0).all()):
            raise ValueError(f"target_growth must be finite speeds >= 0 (m/s), got {growth}")
        put(self, "target_growth", growth)
        if not isinstance(self.target_frustum, bool | np.bool_):
            raise ValueError(f"target_frustum must be a bool, got {self.target_frustum!r}")
        put(self, "target_frustum", bool(self.target_frustum))
        if self.velocity is not None:
            put(self, "velocity", _vec3("velocity", self.velocity))
        if self.neighbour_velocities is not None:
            nv = _rows3("neighbour_velocities", self.neighbour_velocities)
            if nv.shape != self.neighbours.shape:
                raise ValueError(
                    f"neighbour_velocities {nv.shape} must match neighbours {self.neighbours.shape}"
                )
            put(self, "neighbour_velocities", nv)
        k = len(self.neighbours)
        for name in ("neighbour_radius", "neighbour_velocity_radius"):
            value = getattr(self, name)
            if value is not None:
                arr = np.asarray(value, dtype=float).reshape(-1)
                if arr.shape != (k,) or not (np.isfinite(arr).all() and (arr >= 0).all()):
                    raise ValueError(
                        f"{name} must hold {k} finite distances >= 0 (one per neighbour), "
                        f"got {value!r}"
                    )
                put(self, name, arr)
        if self.neighbour_ids is not None and len(self.neighbour_ids) != len(self.neighbours):
            raise ValueError(
                f"neighbour_ids has {len(self.neighbour_ids)} entries for "
                f"{len(self.neighbours)} neighbours"
            )
        if self.own_id is not None:
            if not isinstance(self.own_id, int | np.integer) or isinstance(self.own_id, bool):
                raise ValueError(f"own_id must be an int agent id or None, got {self.own_id!r}")
            if self.neighbour_ids is not None and self.own_id in self.neighbour_ids:
                raise ValueError(
                    f"own_id {self.own_id} is also in neighbour_ids {self.neighbour_ids}: a UAV "
                    "is not its own team-mate"
                )
            put(self, "own_id", int(self.own_id))


_CONTEXT_DEFAULTS = {
    f.name: f.default if f.default_factory is MISSING else f.default_factory()
    for f in fields(SafetyContext)
}
"""`SafetyContext.trusted`'s values of the fields it is not given (shared arrays: read-only
use only, as everywhere in the shield)."""


class CBFRows(NamedTuple):
    """A stack of CBF rows ``A V <= b`` on the global velocity V, with their bookkeeping.

    Rows are ordered uav, obstacle, target, floor, connect, occlusion; only members of the
    paper's neighbour sets (N_si, N_ci, N_oi) are present.
    """

    A: np.ndarray
    """(k, 3) row coefficients on V^g (the omega block of (25)/(34)/(45) is zero and dropped)."""
    b: np.ndarray
    """(k,) right-hand sides, ``gamma * h + drift - margin`` (first-order rows; see
    `RowBuilder._second_order` for the rows of a lagged plant)."""
    h: np.ndarray
    """(k,) barrier values."""
    gamma: np.ndarray
    """(k,) effective class-K rate (e.g. gamma_s / 2 for (25), gamma_c / 2 for (34))."""
    drift: np.ndarray
    """(k,) part of h-dot not controlled by the UAV: ``h-dot = -A V + drift``."""
    margin: np.ndarray
    """(k,) discrete-time margin subtracted from b."""
    kind: np.ndarray
    """(k,) int family index into `KIND_NAMES`."""
    index: np.ndarray
    """(k,) index of the neighbour/obstacle the row refers to (0 for target and floor; -(j + 1)
    for the occlusion row of team-mate j)."""

    @property
    def hard(self) -> np.ndarray:
        """(k,) True for collision and altitude rows (never relaxed)."""
        return self.kind < CONNECT

    @property
    def size(self) -> int:
        """Number of rows."""
        return len(self.b)

    def name(self, r: int, neighbour_ids=None) -> str:
        """Name of row r, e.g. 'uav:2', 'obstacle:5', 'occlusion:5', 'occlusion:uav:2',
        'connect:1', 'target'."""
        return row_name(int(self.kind[r]), int(self.index[r]), neighbour_ids)

    def names(self, neighbour_ids=None) -> list[str]:
        """Names of all rows."""
        return [self.name(r, neighbour_ids) for r in range(len(self.b))]


def row_name(kind: int, index: int, neighbour_ids=None) -> str:
    """Name of a row of family ``kind`` for neighbour/obstacle ``index`` (`CBFRows.name`); the
    UAV and connectivity rows, and the occlusion rows of team-mates ('occlusion:uav:<id>'),
    name the team-mate's id in ``neighbour_ids``, if given."""
    if kind in (TARGET, FLOOR):
        return KIND_NAMES[kind]
    if kind == OCCLUSION and index < 0:
        mate = -index - 1
        return f"occlusion:uav:{mate if neighbour_ids is None else neighbour_ids[mate]}"
    if neighbour_ids is not None and kind in (UAV, CONNECT):
        index = neighbour_ids[index]
    return f"{KIND_NAMES[kind]}:{index}"


# --------------------------------------------------------------------------- barrier functions
def h_pair(p: np.ndarray, q: np.ndarray, radius: float) -> np.ndarray:
    """||p - q||^2 - radius^2: collision barrier (20) and the point-obstacle model."""
    d = np.asarray(p, float) - np.asarray(q, float)
    return np.einsum("...i,...i->...", d, d) - radius**2


def h_connect(p: np.ndarray, q: np.ndarray, r_c: float) -> np.ndarray:
    """R_c^2 - ||p - q||^2: connectivity barrier (29)."""
    return -h_pair(p, q, r_c)


def h_box(
    p: np.ndarray,
    centers: np.ndarray,
    half: np.ndarray,
    clearance: float,
    yaw: float = 0.0,
    grounded: bool = False,
) -> np.ndarray:
    """Box barrier ``sdist(p, box)^2 - clearance^2`` for boxes rotated by ``yaw`` about z.

    ``sdist^2`` is the squared distance outside and minus the squared penetration depth inside;
    inside a ``grounded`` box (the car's barrier, `barrier_rows.target_row`) `box_sdist`'s
    ``-e_xy (t + clearance)``.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(p, float)[None, :] - np.atleast_2d(np.asarray(centers, float))
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    half = np.ascontiguousarray(np.atleast_2d(np.asarray(half, float)))
    return box_sdists(local, half, grounded, float(clearance)) - clearance**2


def h_occlusion(p: np.ndarray, p_o: np.ndarray, n: np.ndarray, theta_star: float) -> np.ndarray:
    """theta - theta* of eqs. (37)-(39): angle between p_o - p and n = target - p."""
    d = np.atleast_2d(p_o) - np.asarray(p, float)
    x = (d @ n) / (np.linalg.norm(d, axis=1) * np.linalg.norm(n))
    return np.arccos(np.clip(x, -1.0, 1.0)) - theta_star


class RowBuilder:
    """Builds all rows of UAV i's QP (47) from its `SafetyContext` (one per filter).

    Rates per family: uav gamma_s/2 (23), obstacle and target gamma_obstacle, floor gamma_z,
    connect gamma_c/2 with `connectivity_margin` (32), occlusion gamma_o (40). The per-layout
    constants are cached and the rows built in one compiled call (`all_rows`): this runs at
    80 Hz per UAV.
    """

    def __init__(
        self,
        cbf: CBFConfig,
        *,
        obstacle_model: str = "box",
        connectivity_margin: float = 0.0,
        target_as_obstacle: bool = True,
        occlusion: bool = True,
        lag_tau: float = 0.0,
        accel_bound: float = 0.0,
        make_way: bool = False,
    ) -> None:
        if not (math.isfinite(accel_bound) and accel_bound >= 0.0):
            raise ValueError(f"accel_bound must be a finite number >= 0 (m/s^2), got {accel_bound}")
        if not (math.isfinite(lag_tau) and lag_tau >= 0.0):
            raise ValueError(f"lag_tau must be a finite time constant >= 0 (s), got {lag_tau}")
        if obstacle_model not in ("box", "point"):
            raise ValueError(f"obstacle_model must be 'box' or 'point', got {obstacle_model!r}")
        if cbf.occlusion_model not in ("paper", "moving-target"):
            raise ValueError(
                f"occlusion_model must be 'paper' or 'moving-target', got {cbf.occlusion_model!r}"
            )
        self.cbf = cbf = cbf if cbf.resolved else cbf.resolve()
        self.obstacle_model = obstacle_model
        self.margin = float(connectivity_margin)
        self.target_as_obstacle = target_as_obstacle
        self.occlusion = occlusion
        self.lag_tau = float(lag_tau)
        self.make_way = bool(make_way)
        # the deceleration a braking row may ask for: 80 % of what the per-axis command box of
        # `ShieldOptions.accel_bound` guarantees in any direction
        self.brake_decel = 0.8 * float(accel_bound) / math.sqrt(3.0)
        self._gammas = np.array(
            (
                0.5 * cbf.gamma_s,
                cbf.gamma_obstacle,
                cbf.gamma_obstacle,
                cbf.gamma_z,
                0.5 * cbf.gamma_c,
                cbf.gamma_o,
            )
        )
        self._margins = np.array((0.0, 0.0, 0.0, 0.0, self.margin, 0.0))
        self._point_mode = POINT_MODES.index(cbf.occlusion_point)
        self._theta_star = cbf.theta_star
        self._second_params = self.second_order_params()

    def __call__(
        self, ctx: SafetyContext, make_way: bool | None = None, over_the_top: bool = False
    ) -> CBFRows:
        """All member rows of the QP (47) for this context (``make_way``: overrides the
        builder's, `ShieldOptions.make_way`; ``over_the_top``: the 'edges' rows of boxes the
        sight line goes through lead out over the box's top,
        `SafetyFilter.climb_over_occluders`)."""
        cbf = self.cbf
        nb, oc = ctx.neighbours, ctx.obstacle_centers
        car = ctx.target_position is not None
        way = self.make_way if make_way is None else make_way
        rows_rho = self.pair_radii(ctx) if way else _radii(ctx)
        A, floats, ints, sizes = all_rows(
            ctx.position,
            nb,
            rows_rho,
            oc,
            ctx.obstacle_half_extents,
            self.obstacle_model == "box",
            car and self.target_as_obstacle,
            ctx.target_position if car else _ZEROS3,
            ctx.target_velocity if car else _ZEROS3,
            ctx.target_half_extents if car else _ZEROS3,
            ctx.target_heading if car else 0.0,
            ctx.target_growth,
            bool(ctx.target_frustum),
            cbf.d_s,
            cbf.r_s,
            cbf.r_c,
            cbf.alpha_v,
            cbf.obstacle_clearance,
            cbf.z_min,
            car and self.occlusion,  # the occlusion rows (45), `occlusion_family`
            self._theta_star,
            OVER_THE_TOP if over_the_top and self.climbs_over_occluders else self._point_mode,
            cbf.occlusion_model == "moving-target",
            cbf.occlusion_size_margin,
            self._gammas,
            self._margins,
            _radii(ctx) if self.lag_tau == 0.0 else _NO_CAP,
            np.zeros_like(nb) if ctx.neighbour_velocities is None else ctx.neighbour_velocities,
            cbf.team_mate_radius,
        )
        b, h, gamma, drift, margin = floats
        kind, index = ints
        if self.lag_tau > 0.0:
            b = self._second_order(ctx, A, h, b, margin, kind, index, sizes, rows_rho)
        return CBFRows(A, b, h, gamma, drift, margin, kind, index)

    @property
    def climbs_over_occluders(self) -> bool:
        """Its occlusion rows have a way out over a box's top (`over_the_top`): 'edges' only."""
        return self.occlusion and self._point_mode == POINT_MODES.index("edges")

    def pair_radii(self, ctx: SafetyContext) -> np.ndarray:
        """The team-mates' radii in the pair rows: the context's, grown for team-mates the
        car's box has caught (`barrier_rows.make_way`)."""
        rho = _radii(ctx)
        if ctx.target_position is None or not self.target_as_obstacle or not len(rho):
            return rho
        return make_way(
            ctx.position, ctx.neighbours, rho, ctx.target_position, ctx.target_half_extents,
            float(ctx.target_heading), self.cbf.obstacle_clearance, self.cbf.r_s,
        )  # fmt: skip

    def makes_way(self, ctx: SafetyContext) -> bool:
        """This context's rows grow a team-mate's radius (`pair_radii`)."""
        return self.make_way and not np.array_equal(self.pair_radii(ctx), _radii(ctx))

    def pass_params(self) -> tuple[np.ndarray, ...]:
        """`onboard_pass.observe_pass`'s ``row_p``, ``flags``, ``gammas``, ``margins`` and
        ``second_p``: the arguments `__call__` gives `all_rows` and the second-order rows that
        do not depend on the context."""
        cbf = self.cbf
        row_p = np.array(
            (cbf.d_s, cbf.r_s, cbf.r_c, cbf.alpha_v, cbf.obstacle_clearance, cbf.z_min,
             self._theta_star, self._point_mode, cbf.team_mate_radius)
        )  # fmt: skip
        flags = np.array(
            (self.obstacle_model == "box", self.target_as_obstacle, self.occlusion,
             cbf.occlusion_model == "moving-target", cbf.occlusion_size_margin, self.make_way)
        )  # fmt: skip
        return row_p, flags, self._gammas, self._margins, self._second_params

    def second_order_params(self) -> np.ndarray:
        """`second_order.second_order_rows`' ``params`` of this builder."""
        cbf = self.cbf
        standoff = cbf.obstacle_clearance if self.obstacle_model == "box" else cbf.r_s
        return np.array(
            (self.lag_tau, cbf.gamma_s, cbf.gamma_c, cbf.gamma_obstacle, cbf.gamma_z,
             cbf.obstacle_clearance, cbf.obstacle_clearance**2, standoff, standoff**2,
             self.obstacle_model == "box", cbf.r_s, cbf.r_c, cbf.alpha_v, self.brake_decel)
        )  # fmt: skip

    def _second_order(
        self,
        ctx: SafetyContext,
        A: np.ndarray,
        h: np.ndarray,
        b: np.ndarray,
        margin: np.ndarray,
        kind: np.ndarray,
        index: np.ndarray,
        sizes: np.ndarray,
        rho: np.ndarray,
    ) -> np.ndarray:
        """Right-hand sides of the collision, floor and connectivity rows as second-order CBFs
        for a first-order velocity lag ``v-dot = (u - v) / tau`` (not in the paper).

        With the actual velocity v, psi = h-dot + gamma1 h and psi-dot + psi / tau >= 0 give,
        for the row's own share s and A = -grad h,
        ``A u <= -grad h . v + s (tau dv' H dv + (tau gamma1 + 1) grad h . dv + gamma1 h)``,
        dv the velocity relative to the other body and H the Hessian of h. As tau -> 0 this is
        the first-order row; rows keep their A, only b changes. Occlusion rows stay first order.

        The share s is 1 for rows of one UAV. A pair row splits the pair's condition (the split
        of (23)): s = 1/2 while the bracket (the pair's need) is >= 0, so the halves sum to the
        condition; once it is < 0 the pair must brake and s = 1: each UAV brakes for the pair on
        its own, so the condition holds even if the team-mate cannot do its half (a UAV pinned
        by other hard rows gives its pair row up in a fallback) as long as the team-mate does
        not accelerate towards it. ``rho``: the team-mates' radii of the rows (`pair_radii`).
        Compiled: `second_order.second_order_rows`.
        """
        v = ctx.velocity
        if v is None:
            raise ValueError("second-order rows (lag_tau > 0) need SafetyContext.velocity")
        sigma = ctx.neighbour_velocity_radius
        return second_order_rows(
            A, h, b, margin, kind, index, sizes, v, _neighbour_velocities(ctx),
            ctx.target_velocity, float(ctx.target_heading), ctx.target_growth,
            bool(ctx.target_frustum), True, rho,
            sigma is not None, _ZEROS3 if sigma is None else sigma, self._second_params,
        )  # fmt: skip


def _radii(ctx: SafetyContext) -> np.ndarray:
    """The context's team-mate radii (zeros: known exactly)."""
    rho = ctx.neighbour_radius
    return np.zeros(len(ctx.neighbours)) if rho is None else rho


def _neighbour_velocities(ctx: SafetyContext) -> np.ndarray:
    """The neighbours' velocities (zeros without neighbours); the pair rows need them."""
    nb_v = ctx.neighbour_velocities
    if nb_v is None:
        if len(ctx.neighbours):
            raise ValueError(
                "second-order rows (lag_tau > 0) need SafetyContext.neighbour_velocities: "
                "each pair row is one UAV's half of a condition on the relative velocity"
            )
        nb_v = np.zeros_like(ctx.neighbours)
    return nb_v


def build_rows(ctx: SafetyContext, cbf: CBFConfig, **kwargs) -> CBFRows:
    """All rows of UAV i's QP (47) (convenience wrapper around `RowBuilder`)."""
    return RowBuilder(cbf, **kwargs)(ctx)
