"""The distributed CBF-QP (47): certify(nominal action, context) -> (safe action, report).

Problem (47) is posed over the paper's 6-vector ``u^g = [V^g, omega^g]`` with
``omega_x = omega_y = 0`` (the UAV only yaws) and ``omega_z^g = -omega_cy``. Its cost
``||u^g - u_hat||^2`` (u_hat = the nominal action rotated to the global frame) splits into a
velocity part and a yaw-rate part, and no CBF row touches the yaw rate (zero omega blocks in (25),
(34), (45)), so:

* the yaw rate is the nominal clipped to ``|omega| <= min(alpha_omega, Table II omega_max)``;
* the velocity solves ``min ||V - V_hat||^2`` s.t. the CBF rows, Table II and ``||V|| <= alpha_v``.

The velocity QP is solved in camera coordinates ``v_c = R^T V^g`` (R = `cam_to_world(yaw)`): an
orthogonal change of variables, so the cost and the feasible set are those of (47), but Table II
(``|v_cx|, |v_cy|, |v_cz| <= v_max``; note v_cy = -V_z) becomes plain variable bounds. Rows are
normalised to unit normals, so slacks and tolerances are in m/s.

Layers, each tried only if the previous one cannot give an answer:

1. fast path: the nominal action satisfies every row and bound -> returned unchanged ("nominal");
   if only a bound is violated, its closed-form projection is returned when it is feasible.
2. hard QP: every row hard ("optimal").
3. relaxed QPs ("relaxed"): first every row hard but the occlusion rows, which take slack under
   an L1 penalty, weighted the more the nearer a row's sight line is to its occluder and priced
   in the rate of its angle (`SafetyFilter.slack_factors`), so that of two conflicting occlusion
   rows the one about to occlude is kept, and a row no velocity can answer does not take the
   command from one it can (`ShieldOptions.occlusion_price` caps each weight in proportion to
   how far the command is from the rows); if that is infeasible too, the connectivity rows take
   slack as well, weighted at least 10 times the occlusion rows (100 / `occlusion_urgency`).
   Connectivity is therefore given up only where it conflicts with the collision and altitude
   rows, never for occlusion. Each runs only after the layer before it was infeasible, so a
   family's slack is zero whenever a solution without it exists (up to the exactness of the L1
   penalty, `soft_penalty` far above the rows' multipliers). With
   `ShieldOptions.climb_over_occluders`, a relaxed certificate that slacks the row of a box its
   sight line goes through is made again with that row leading out over the box's top
   (`SafetyFilter.climb_over_occluders`): the least-angle way out is often sideways, along a
   vertical edge whose gradient is level, and a box beside a UAV flying low can block it where
   climbing would clear the line.
4. fallbacks by priority: the rows whose geometry is known are never traded for rows built on
   an estimate. The car's row (a UKF estimate) is slacked first (weight `hard_penalty` / 100),
   then the other UAVs' rows (`hard_penalty`) with the floor and obstacle rows still hard, then
   those too (`hard_penalty` * 100): a best-effort separating velocity, e.g. when the state is
   already unsafe. If even that fails (solver error), brake: V = 0 with the clipped yaw rate.
   All report status "fallback" and list the hard rows they violate in ``gave_up``. A fallback
   that gave the car's box row up is certified again with the car's frustum
   (`SafetyFilter.climb_over_car`): beside the box the box row's gradient is horizontal, so it
   and an obstacle's row can leave no command, while climbing always raises the frustum. In that
   certificate the rows of team-mates known only within a reachable ball (lost messages) share
   the car's priority. A fallback that gave up a pair row its UAV answers for (of two UAVs, the
   one closing the gap faster; `pairs_answered`) is certified again with the pair rows it does
   not answer for given up first (`SafetyFilter.yield_by_rank`), so that two UAVs pinned by
   others do not both give up the row between them. certify never raises on a valid input and
   never returns NaN.

Speed bound ``||V|| <= alpha_v`` (a norm, not linear): after each QP, if ``||V|| > alpha_v`` a
tangent cut ``(V/||V||)^T v <= alpha_v`` (valid for the ball) is added and the QP re-solved, at most
`norm_cuts` times; a remaining excess is removed by scaling V towards 0. Scaling is sound for every
hard row: in a safe state each hard row has ``b >= 0`` (b = gamma h with h >= 0, static
obstacles), so V = 0 satisfies it, and for any V* that satisfies ``a^T V* <= b`` and t in [0, 1],
``a^T (t V*) = t a^T V* <= t b <= b``; Table II's box also contains the segment [0, V*]. Rows with
``b < 0`` (connectivity inside its discrete-time margin, recovery from an unsafe state) can lose at
most ``(1 - t) |b|``; the cuts make ``1 - t`` tiny (< 1e-6 typically) and the connectivity margin
carries 5 % headroom for it. (`tests/test_safety_shield.py` checks this numerically.)

Rows that cannot be active at any ``||V|| <= alpha_v`` (``b >= alpha_v ||a||``) are pruned from the
QP; they are implied by the ball, so the solution is unchanged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import Literal

import daqp
import numpy as np
import qpsolvers

from uavtrack_env.config import DT, ControlLimits
from uavtrack_env.geometry import cam_to_world_vec
from uavtrack_env.safety import daqp_native
from uavtrack_env.safety.cbf import (
    CONNECT,
    FLOOR,
    KIND_NAMES,
    OBSTACLE,
    OCCLUSION,
    TARGET,
    UAV,
    CBFRows,
    RowBuilder,
    SafetyContext,
    row_name,
)
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.qp_arrays import (
    INF,
    family_lows,
    meets,
    nearest_camera_rows,
    nominal_holds,
    outcome,
    qp_problem,
    triage,
    with_cut,
)
from uavtrack_env.safety.qp_layers import (
    LAYER_STATUS,
    OUT_HEAD,
    certify_changed,
    certify_many,
    occlusion_factors,
    occlusion_weight_cap,
)
from uavtrack_env.validation import Fields as _Fields

SOLVERS = ("daqp", "proxqp", "daqp-direct")
"""QP backends: 'daqp' and 'proxqp' through `qpsolvers.solve_qp`; 'daqp-direct' (the default)
calls daqp without qpsolvers' problem conversions and checks: all the QP layers of a call in one
compiled call to daqp's C entry point (`qp_layers`; `daqp.solve` per QP where that entry point
is unavailable, `daqp_native.AVAILABLE`). All are tested to give the same answers."""

_PRIMAL_TOL = 1e-10
"""Solver feasibility tolerance (m/s on unit rows). daqp's default 1e-6 lets h creep ~1e-6
below 0 over many steps at an active barrier; 1e-10 keeps the closed loop at ~1e-10."""


@dataclass(frozen=True)
class ShieldOptions:
    """Tunables of the shield that are not in the paper's Table IV."""

    obstacle_model: Literal["box", "point"] = "box"
    """'box': ``dist(p, box)^2 - clearance^2``; 'point': the paper's centre + R_s model (IV-A)."""
    target_as_obstacle: bool = True
    """Add a hard row keeping the UAV out of the (moving, oriented) target car box."""
    occlusion: bool = True
    """Include the soft occlusion rows (45)."""
    connectivity_margin: float | None = None
    """Per-UAV margin on (34) in h-dot units; None: 2.1 dt alpha_v^2 (5 % over the Euler loss)."""
    soft_penalty: float = 1e3
    """L1 weight on each soft row's slack (m/s) in the relaxed QP."""
    hard_penalty: float = 1e6
    """L1 weight on hard rows' slack in the fallback QP."""
    slack_regularization: float = 1e-6
    """Tiny quadratic weight on slacks (keeps the QP Hessian positive definite)."""
    norm_cuts: int = 4
    """Maximum tangent cuts for ||V|| <= alpha_v before scaling."""
    prune: bool = True
    """Drop rows implied by ||V|| <= alpha_v before the QP."""
    tol: float = 1e-9
    """Feasibility tolerance (m/s on unit rows) of the fast path and of active-row detection."""
    verify_tol: float = 1e-6
    """A solver's answer is rejected if it violates its QP's rows by more than this."""
    lag_tau: float = 0.0
    """Not in the paper: velocity time constant (s) of a first-order-lag plant; > 0 makes the
    collision, floor and connectivity rows second-order CBFs on the actual velocity
    (`SafetyContext.velocity` required). 0: the paper's integrator (3)."""
    accel_bound: float = 0.0
    """Not in the paper: the lag plant's acceleration limit a_max (m/s^2). With ``lag_tau`` > 0
    every command stays within ``accel_bound lag_tau / sqrt(3)`` of the actual velocity on each
    camera axis, so the plant never clips its acceleration and the second-order rows hold as
    written; the rows that keep the UAV from obstacles, the floor and the other UAVs also keep
    its braking distance (`RowBuilder`). 0: no bound."""
    occlusion_urgency: float = 10.0
    """Not in the paper: an occlusion row's slack weight in the relaxed QPs grows linearly from
    ``soft_penalty`` at h = 0 to this multiple of it at h = -theta* (the sight line touching
    the occluder, eq. (37)), so that of occlusion rows that conflict the one nearest to an
    actual occlusion is kept (`SafetyFilter.slack_factors`). 1: every row alike. Below 100, so that
    connectivity still outweighs occlusion."""
    occlusion_leverage: float | None = 1.0
    """Not in the paper: a length L (m). An occlusion row's slack weight is also multiplied by
    ``L |grad h|`` clipped to [1e-3, 1], |grad h| the row's gradient before the rows are
    normalised (rad/s of its angle per m/s): its slack is priced in the rate of the angle, so a
    row whose angle a velocity barely turns (its occluder near the car, both far from the UAV)
    cannot take the command away from rows it can keep (`SafetyFilter.slack_factors`). None: priced
    in m/s like the other rows."""
    make_way: bool = True
    """Not in the paper: a team-mate within the clearance of the car's box counts as anywhere
    within its reachable ball grown by the climb it needs to leave the box
    (`barrier_rows.make_way`), so that the other UAVs back off and let it out over the car
    instead of pinning it there with their half of the pair row. A courtesy: a fallback keeps
    it only where it costs no hard row (`SafetyFilter.settle`)."""
    occlusion_price: float | None = None
    """Not in the paper: a scale c (per m/s). Each occlusion row's slack weight in the relaxed
    QPs (`soft_penalty` times its factors, `SafetyFilter.slack_factors`) is capped at
    ``c max(D, 0.1)``, D the command's largest violation of the unit rows (m/s): the price
    follows how far the command is from the rows. A row kept against the command still wins
    (with one row, an exact penalty needs a weight above D), while a row that cannot be kept
    pushes each direction it barely touches (a component a_k of its unit normal) by at most
    ``c D a_k`` m/s, not by ``soft_penalty`` times its factors times a_k. None: no cap."""
    climb_over_occluders: bool = False
    """Not in the paper: a relaxed certificate that slacks the row of a box its sight line goes
    through is made again with that row's way out over the box's top, and kept where its line
    leaves the box sooner and it keeps every other row (`SafetyFilter.climb_over_occluders`).
    Occlusion point 'edges' only. Off by default: it frees a UAV pinned low beside a box, but on
    the adversary harness's dense worlds the car was occluded more often with it
    (docs/safety.md)."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.choice("obstacle_model", ("box", "point"))
        flags = ("target_as_obstacle", "occlusion", "prune", "make_way", "climb_over_occluders")
        for name in flags:
            f.flag(name)
        f.number("connectivity_margin", lo=0, none_means="2.1 dt alpha_v^2")
        f.number("soft_penalty", lo=0, lo_open=True)
        f.number("occlusion_price", lo=0, lo_open=True, none_means="no cap")
        f.number("hard_penalty", lo=0, lo_open=True)
        f.number("slack_regularization", lo=0)
        f.integer("norm_cuts", lo=0)
        f.number("tol", lo=0)
        f.number("verify_tol", lo=0)
        f.number("lag_tau", lo=0)
        f.number("accel_bound", lo=0)
        f.number("occlusion_urgency", lo=1, hi=100, hi_open=True)
        f.number("occlusion_leverage", lo=0, lo_open=True, none_means="priced in m/s")


@dataclass
class ShieldReport:
    """What `SafetyFilter.certify` did."""

    status: str
    """'nominal' (unchanged), 'optimal' (hard QP or bound projection), 'relaxed', 'fallback'."""
    active: bool
    """The action was changed."""
    correction_norm: float
    """||u_safe - u_nominal|| on the camera-frame command (SI units)."""
    slack: float
    """Total violation (m/s, unit rows) of the soft rows at the returned action."""
    active_rows: list[str]
    """Rows and bounds active at the solution: 'uav:2', 'obstacle:5', 'speed', 'box', ..."""
    solver: str = "none"
    """Backend that produced the answer ('none', 'closed-form', a `SOLVERS` name, 'brake')."""
    solver_calls: int = 0
    """QP solves in this call (cuts and phases included)."""
    time_us: float = 0.0
    """Wall time of certify() in microseconds."""
    hard_violation: float = 0.0
    """Total violation (m/s) of hard rows at the returned action (nonzero only in fallback)."""
    gave_up: list[str] = field(default_factory=list)
    """The hard rows the returned action violates (a fallback gave them up, lowest priority
    first: the car's row before other UAVs' before obstacles and the floor)."""
    slack_per_row: dict[str, float] = field(default_factory=dict)
    """Violation of each violated soft row (m/s)."""
    rows: CBFRows | None = field(default=None, repr=False)
    """The rows of this call (global frame), for logging."""
    neighbour_ids: tuple[int, ...] | None = field(default=None, repr=False)
    lows: list[float] | None = field(default=None, repr=False)
    """`qp_arrays.family_lows` of ``rows`` if the caller has it (`family_minima` reads it)."""

    @property
    def gave_car_up(self) -> bool:
        """A fallback that gave the car's row up (`SafetyFilter.climb_over_car` retries it)."""
        return self.status == "fallback" and "target" in self.gave_up

    @property
    def min_hard_h(self) -> float:
        """Smallest barrier value of the hard rows (< 0: the state is already unsafe)."""
        lows = self._lows()
        return math.inf if lows is None else lows[-1]

    @property
    def min_h_by_family(self) -> dict[str, float]:
        """The least barrier value h of each row family present (`KIND_NAMES`)."""
        return self.family_minima()[0]

    def family_minima(self) -> tuple[dict[str, float], float]:
        """(`min_h_by_family`, `min_hard_h`) in one pass over the rows."""
        lows = self._lows()
        if lows is None:
            return {}, math.inf
        *family, hard = lows
        return {name: low for name, low in zip(KIND_NAMES, family, strict=True) if low == low}, hard

    def _lows(self) -> list[float] | None:
        """`qp_arrays.family_lows` of the rows (NaN: no such family), None without rows."""
        if self.rows is None or not len(self.rows.h):
            return None
        if self.lows is None:
            self.lows = family_lows(self.rows.kind, self.rows.h, _N_KINDS, CONNECT).tolist()
        return self.lows

    @property
    def h(self) -> dict[str, float]:
        """Barrier values of all rows by name (for logging and figures)."""
        if self.rows is None:
            return {}
        names = self.rows.names(self.neighbour_ids)
        return dict(zip(names, self.rows.h.tolist(), strict=True))


def check_eq28(cbf: CBFConfig) -> None:
    """Raise ValueError unless gamma_s >= 4 alpha_v R_s / (D_s^2 - R_s^2), eq. (28)."""
    bound = 4.0 * cbf.alpha_v * cbf.r_s / (cbf.d_s**2 - cbf.r_s**2)
    if cbf.gamma_s < bound:
        raise ValueError(f"gamma_s = {cbf.gamma_s} violates eq. (28): need >= {bound:.4f}")


class SafetyFilter:
    """Distributed CBF-QP safety filter of eq. (47), one instance per UAV (or shared).

    Used as the last stage of the expert (NMPC action -> safe action) and as a shield around a
    learned policy. Stateless between calls.
    """

    def __init__(
        self,
        cbf: CBFConfig = CBFConfig(),  # noqa: B008 (frozen, immutable default)
        limits: ControlLimits = ControlLimits(),  # noqa: B008
        solver: str = "daqp-direct",
        **options,
    ) -> None:
        if not isinstance(cbf, CBFConfig):
            raise ValueError(f"cbf must be a CBFConfig, got {type(cbf).__name__}")
        if not isinstance(limits, ControlLimits):
            raise ValueError(f"limits must be a ControlLimits, got {type(limits).__name__}")
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        cbf = cbf if cbf.resolved else cbf.resolve()
        check_eq28(cbf)
        self.cbf, self.limits, self.solver = cbf, limits, solver
        self.options = ShieldOptions(**options)
        dt = DT
        for name, rate in (
            ("gamma_s / 2", 0.5 * cbf.gamma_s),
            ("gamma_c / 2", 0.5 * cbf.gamma_c),
            ("gamma_obstacle", cbf.gamma_obstacle),
            ("gamma_z", cbf.gamma_z),
        ):
            if rate * dt > 1.0:
                raise ValueError(
                    f"{name} * dt = {rate * dt:.3f} > 1: the discrete-time CBF condition "
                    "h(k+1) >= (1 - gamma dt) h(k) no longer keeps h >= 0"
                )
        self.alpha_v = float(cbf.alpha_v)
        self.v_max = float(limits.v_max)
        self.w_max = float(min(cbf.alpha_omega, limits.omega_max))
        m = self.options.connectivity_margin
        self.connectivity_margin = 2.1 * dt * self.alpha_v**2 if m is None else float(m)
        # Closed-form projection onto {box} n {ball} exists when one contains the other.
        if self.alpha_v <= self.v_max:
            self._bounds_code = 0  # the ball inside the box (`qp_arrays.triage`)
        elif self.alpha_v >= math.sqrt(3.0) * self.v_max:
            self._bounds_code = 1  # the box inside the ball
        else:
            self._bounds_code = 2
        self.row_builder = RowBuilder(
            cbf,
            obstacle_model=self.options.obstacle_model,
            connectivity_margin=self.connectivity_margin,
            target_as_obstacle=self.options.target_as_obstacle,
            occlusion=self.options.occlusion,
            lag_tau=self.options.lag_tau,
            accel_bound=self.options.accel_bound if self.options.lag_tau > 0.0 else 0.0,
            make_way=self.options.make_way,
        )
        self.climbs_over_occluders = (
            self.options.climb_over_occluders and self.row_builder.climbs_over_occluders
        )
        """`climb_over_occluders` is on (`ShieldOptions.climb_over_occluders`, 'edges' rows)."""
        self._lb3 = np.full(3, -self.v_max)
        self._ub3 = np.full(3, self.v_max)
        opt = self.options
        # per camera axis: ||u - v|| <= accel_bound * lag_tau, the lag plant is never clipped
        self._accel_step = opt.accel_bound * opt.lag_tau / math.sqrt(3.0)
        self._native: tuple[np.ndarray, np.ndarray] | None = None
        """`qp_layers.certify_changed`'s params and daqp settings ('daqp-direct' only)."""
        if solver == "daqp-direct" and daqp_native.AVAILABLE:
            params = (
                opt.soft_penalty,
                opt.hard_penalty,
                self.alpha_v,
                opt.slack_regularization,
                opt.verify_tol,
                opt.norm_cuts,
                self.v_max,
                self.w_max,
                opt.tol,
                self._accel_step,
                max(opt.tol, 1e-7),
                opt.prune,
                self._bounds_code,
                opt.occlusion_price or 0.0,
            )  # the order of `qp_layers.certify_changed`'s params
            self._native = (np.array(params), daqp_native.settings(_PRIMAL_TOL))

    # ----------------------------------------------------------------- public
    def rows(self, ctx: SafetyContext) -> CBFRows:
        """The CBF rows ``A V^g <= b`` of this context (global frame), as `certify` uses them."""
        if not isinstance(ctx, SafetyContext):
            raise ValueError(f"ctx must be a SafetyContext, got {type(ctx).__name__}")
        return self.row_builder(ctx)

    def camera_rows(self, rows: CBFRows, yaw: float, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``k`` rows as unit half-spaces ``a_c v_c <= b`` on the camera-frame velocity,
        those closest to active first (smallest b); rows the speed bound implies are dropped."""
        return nearest_camera_rows(rows.A, rows.b, yaw, self.alpha_v, k)

    def slack_factors(self, kind: np.ndarray, h: np.ndarray, A: np.ndarray) -> np.ndarray:
        """Each row's factor on its slack weight in the relaxed QPs: 1, and for an occlusion row
        from 1 at h = 0 up to `ShieldOptions.occlusion_urgency` at h = -theta* (37), where the
        sight line touches the occluder and beyond, times its leverage ``L |A|`` clipped to
        [1e-3, 1] (`ShieldOptions.occlusion_leverage`; ``A`` the rows' gradients)."""
        length = self.options.occlusion_leverage
        return occlusion_factors(
            np.asarray(kind), np.asarray(h, float), np.asarray(A, float), self.cbf.theta_star,
            self.options.occlusion_urgency, 0.0 if length is None else length,
        )  # fmt: skip

    def certify(
        self, u_nominal: np.ndarray, ctx: SafetyContext, rows: CBFRows | None = None
    ) -> tuple[np.ndarray, ShieldReport]:
        """Return the safe camera-frame action u = [v_cx, v_cy, v_cz, omega_cy] and a report.

        ``u_nominal`` is the camera-frame command in SI units (it may exceed Table II; it is then
        projected). ``rows``: `rows(ctx)` if the caller has already built them. Raises ValueError
        only for malformed input.
        """
        t0 = time.perf_counter()
        u = _checked_nominal(u_nominal, ctx)
        rows = self.row_builder(ctx) if rows is None else rows
        done = self._certify(u, ctx.yaw, ctx.velocity, rows, ctx.neighbour_ids, t0)
        return self.settle(u, ctx, done)

    def settle(
        self, u: np.ndarray, ctx: SafetyContext, done: tuple[np.ndarray, ShieldReport]
    ) -> tuple[np.ndarray, ShieldReport]:
        """``done`` = certify's (action, report) of ``u`` on ``rows(ctx)``; if it is relaxed,
        `climb_over_occluders`; if it is a fallback, `climb_over_car`. Where the rows grew a
        team-mate's radius (`ShieldOptions.make_way`) that growth is a courtesy: a fallback keeps
        it only if its action breaks no hard row of the plain rows more than the plain rows' own
        certificate does."""
        if done[1].status == "relaxed":
            return self.climb_over_occluders(u, ctx, done)
        if done[1].status != "fallback":
            return done
        if self.row_builder.makes_way(ctx):
            rows = self.row_builder(ctx, make_way=False)
            plain = self._certify(
                u, ctx.yaw, ctx.velocity, rows, ctx.neighbour_ids, time.perf_counter()
            )
            own, alone = _excess(rows, done[0], ctx.yaw), _excess(rows, plain[0], ctx.yaw)
            if (own > np.maximum(alone, 0.0) + self.options.verify_tol).any():
                done = plain
        return self.climb_over_car(u, ctx, self.yield_by_rank(u, ctx, done))

    def yield_by_rank(
        self,
        u: np.ndarray,
        ctx: SafetyContext,
        done: tuple[np.ndarray, ShieldReport],
        layer_kind: np.ndarray | None = None,
    ) -> tuple[np.ndarray, ShieldReport]:
        """``done`` = a fallback certificate of ``u`` on ``done[1].rows`` (layers by
        ``layer_kind``, default the rows' kinds). If it gives up a pair row this UAV answers
        for (`pairs_answered`), the certificate again with those rows at the team-mates'
        priority and the other pair rows given up with the car's row, before them. It replaces
        ``done`` where it gives up less of the rows this UAV answers for and breaks no obstacle
        or floor row more.

        The tie-break for crowds: the fallback QP slacks every pair row at one weight, so two
        UAVs each pinned by others can both give up the row between them, and that pair is
        then covered by neither. Ranked, one UAV of each pair keeps the row, or gives up as
        little of it as its other hard rows allow."""
        rows = done[1].rows
        if done[1].status != "fallback" or rows is None:
            return done
        kind = rows.kind if layer_kind is None else layer_kind
        pair = np.flatnonzero(rows.kind == UAV)
        answers = pairs_answered(ctx, rows.index[pair])
        if answers is None or answers.all():
            return done
        mine, theirs = pair[answers], pair[~answers]
        tol = self.options.verify_tol
        excess = _excess(rows, done[0], ctx.yaw)
        if not (excess[mine] > tol).any():
            return done
        ranked = kind.copy()
        ranked[mine], ranked[theirs] = UAV, TARGET
        again = self._certify(
            u, ctx.yaw, ctx.velocity, rows, ctx.neighbour_ids, time.perf_counter(), ranked
        )
        after = _excess(rows, again[0], ctx.yaw)
        fixed = (rows.kind == OBSTACLE) | (rows.kind == FLOOR)
        if (
            np.maximum(after[mine], 0.0).sum() >= np.maximum(excess[mine], 0.0).sum()
            or (after[fixed] > np.maximum(excess[fixed], 0.0) + tol).any()
        ):
            return done
        return again

    def may_climb_over_occluders(self, report: ShieldReport) -> bool:
        """A relaxed certificate whose rows hold an occlusion row at or below -theta*, where a
        sight line through its box has it (`climb_over_occluders` may then change it)."""
        rows = report.rows
        if report.status != "relaxed" or rows is None or not self.climbs_over_occluders:
            return False
        return bool((rows.h[rows.kind == OCCLUSION] <= -self.cbf.theta_star).any())

    def climb_over_occluders(
        self, u: np.ndarray, ctx: SafetyContext, done: tuple[np.ndarray, ShieldReport]
    ) -> tuple[np.ndarray, ShieldReport]:
        """``done`` = a relaxed certificate of ``u`` on ``rows(ctx)``; if it slacks an occlusion
        row whose sight line goes through its box, the certificate again with such rows leading
        out over their box's top (`RowBuilder` ``over_the_top``). It replaces ``done`` where
        its sight line leaves those boxes sooner (`_exit_time`) and it breaks no other row
        more.

        Through a box, a row's point is the least-angle point of the box's outline, often a
        vertical edge: its gradient then has no vertical part, and a UAV low among boxes whose
        sideways way out another box blocks keeps its car hidden, where climbing would clear
        the line. Where the sideways way out is open, or the box is tall, the row's own
        certificate leaves sooner and is kept."""
        rows = done[1].rows
        if not self.may_climb_over_occluders(done[1]):
            return done
        occluded = rows.kind == OCCLUSION
        tol = self.options.verify_tol
        excess = _row_excess(rows, done[0], ctx.yaw)
        if not (excess[occluded] > tol).any():
            return done
        over = self.row_builder(ctx, over_the_top=True)
        if not (np.array_equal(over.kind, rows.kind) and np.array_equal(over.index, rows.index)):
            return done  # a row left N_oi (36): not a way out of the same occlusion
        through = (over.A != rows.A).any(axis=1) & occluded
        if not through.any():
            return done
        t0 = time.perf_counter()
        again = self._certify(u, ctx.yaw, ctx.velocity, over, ctx.neighbour_ids, t0)
        after = _row_excess(over, again[0], ctx.yaw)
        if (
            again[1].status == "fallback"
            or (after[~occluded] > np.maximum(excess[~occluded], 0.0) + tol).any()
        ):
            return done
        theta_star = self.cbf.theta_star
        sooner = _exit_time(over, through, again[0], ctx.yaw, theta_star)
        return again if sooner < _exit_time(rows, through, done[0], ctx.yaw, theta_star) else done

    def climb_over_car(
        self, u: np.ndarray, ctx: SafetyContext, done: tuple[np.ndarray, ShieldReport]
    ) -> tuple[np.ndarray, ShieldReport]:
        """``done`` = certify's (action, report) of ``u``; if it is a fallback that gave the
        car's box row up, the certificate again with the car's frustum (`barrier_rows.target_row`).

        Beside the car's box its barrier's gradient is horizontal: a UAV between the car and an
        obstacle (whose row is horizontal too) has no command that keeps both, and giving the
        car's row up leaves it in the car's path. The frustum's zero set is at least the
        clearance from the box and climbing always raises it, so it and the obstacles' rows
        leave a way out: over the car. In this certificate the rows of team-mates known only
        within a reachable ball (a lost message: the worst case over the ball) are given up
        together with the car's frustum, not before it: a team-mate pressing from such a ball
        would otherwise push the UAV into the car (`baselines.shield_adversary`'s
        block-and-press), then ranked as `yield_by_rank` ranks them."""
        if not done[1].gave_car_up or ctx.target_frustum:
            return done
        ctx = replace(ctx, target_frustum=True)
        rows = self.row_builder(ctx, make_way=False)
        kind = _stale_team_mates_with_car(rows, ctx.neighbour_radius)
        done = self._certify(
            u, ctx.yaw, ctx.velocity, rows, ctx.neighbour_ids, time.perf_counter(), kind
        )
        return self.yield_by_rank(u, ctx, done, kind)

    def certify_trusted(
        self, u: np.ndarray, ctx: SafetyContext, rows: CBFRows
    ) -> tuple[np.ndarray, ShieldReport]:
        """`certify` of a command the caller guarantees is a finite float64 (4,) array, with
        ``rows(ctx)``: no checks (the shield's commands are the env's validated actions)."""
        return self.certify_pose(u, ctx.yaw, ctx.velocity, rows, ctx.neighbour_ids)

    def certify_pose(
        self,
        u: np.ndarray,
        yaw: float,
        velocity: np.ndarray | None,
        rows: CBFRows,
        neighbour_ids: tuple[int, ...] | None = None,
    ) -> tuple[np.ndarray, ShieldReport]:
        """`certify_trusted` given only what the QP reads of a context: the yaw, the actual
        velocity (``SafetyContext.velocity``) and the ids that name the rows."""
        return self._certify(u, yaw, velocity, rows, neighbour_ids, time.perf_counter())

    def certify_many(
        self,
        u: np.ndarray,
        yaws: np.ndarray,
        velocities: np.ndarray,
        rows: list[CBFRows] | Callable[[int], CBFRows],
        neighbour_ids: list[tuple[int, ...] | None],
        packed: tuple | None = None,
    ) -> Certificates:
        """`certify_pose` of m UAVs' commands ``u`` (m, 4) with their yaws (m,), actual
        velocities (m, 3), rows (a list, or UAV j's by ``rows(j)``) and row-naming ids: on
        'daqp-direct' one compiled call (`qp_layers.certify_many`). ``packed``: (A, b, kind,
        h, begin, end), arrays in which UAV j's rows are ``[begin[j]:end[j]]`` (required when
        ``rows`` is a callable)."""
        m = len(neighbour_ids)
        row = rows if callable(rows) else rows.__getitem__
        if self._native is None:
            done = [
                self.certify_pose(u[j], float(yaws[j]), velocities[j], row(j), neighbour_ids[j])
                for j in range(m)
            ]
            return Certificates.of_reports(np.array([d[0] for d in done]).reshape(m, 4),
                                           [d[1] for d in done])  # fmt: skip
        t0 = time.perf_counter()
        if packed is None:
            ends = [0]
            for r in rows:
                ends.append(ends[-1] + len(r.b))
            packed = (
                np.concatenate([r.A for r in rows]), np.concatenate([r.b for r in rows]),
                np.concatenate([r.kind for r in rows]), np.concatenate([r.h for r in rows]),
                np.array(ends[:-1], np.int64), np.array(ends[1:], np.int64),
            )  # fmt: skip
        A, b, kind, h, begin, end = packed
        changed, outs = certify_many(
            u, yaws, velocities, A, b, kind, self.slack_factors(kind, h, A), begin, end, self._lb3,
            self._ub3, *self._native,
        )  # fmt: skip
        share = (time.perf_counter() - t0) * 1e6 / max(m, 1)
        return Certificates(self, u, changed, outs, row, neighbour_ids, share)

    def _certify(
        self,
        u: np.ndarray,
        yaw: float,
        velocity: np.ndarray | None,
        rows: CBFRows,
        ids: tuple[int, ...] | None,
        t0: float,
        layer_kind: np.ndarray | None = None,
    ) -> tuple[np.ndarray, ShieldReport]:
        """The certificate of ``u`` (module docstring); ``layer_kind``: the family each row's
        layers treat it as (default ``rows.kind``; the report names rows by ``rows.kind``)."""
        kind = rows.kind if layer_kind is None else layer_kind
        has_velocity, velocity = velocity is not None, _ZEROS3 if velocity is None else velocity
        if nominal_holds(
            u, yaw, velocity, has_velocity, rows.A, rows.b, self.alpha_v, self.v_max,
            self.w_max, self.options.tol, self._accel_step, self._lb3, self._ub3,
        ):  # fmt: skip
            return u, ShieldReport(
                "nominal", False, 0.0, 0.0, [], time_us=(time.perf_counter() - t0) * 1e6,
                rows=rows, neighbour_ids=ids,
            )  # fmt: skip
        slack_factors = self.slack_factors(kind, rows.h, rows.A)
        if self._native is not None:
            out = certify_changed(
                u, yaw, velocity, has_velocity, rows.A, rows.b, kind, slack_factors, self._lb3,
                self._ub3, *self._native,
            )  # fmt: skip
            return out[:4], self._changed_report(out.tolist(), u, rows, ids, t0)
        stage, v, w, An, bn, (kinds, kept), (lb, ub) = triage(
            u, yaw, velocity, has_velocity, rows.A, rows.b, kind, self.alpha_v,
            self.v_max, self.w_max, self.options.tol, self._accel_step, self._lb3, self._ub3,
            self.options.prune, self._bounds_code,
        )  # fmt: skip
        status, solver, calls = "optimal", "closed-form", 0
        if stage == 2:
            try:
                v, status, solver, calls = self._solve_layers(
                    v, An, bn, kinds, lb, ub, slack_factors[kept]
                )
            except Exception:  # never let a numerical failure take the UAV down: brake
                v, status, solver, calls = np.zeros(3), "fallback", "brake", 0
        v0, v1, v2 = v.tolist()
        if math.isfinite(v0 + v1 + v2 + w):
            u_safe = np.array((v0, v1, v2, w))
        else:  # defensive: never hand out NaN
            u_safe = np.array((0.0, 0.0, 0.0, w))
            status, solver = "fallback", "brake"
        return u_safe, self._report(
            status, u, u_safe, rows, ids, t0, solver, calls, An, bn, kinds, kept
        )

    # ----------------------------------------------------------------- layers
    def _solve_layers(self, v_hat, An, bn, kinds, lb3, ub3, slack_factors=None):
        """Hard QP, relaxed QP, then the fallbacks by row priority, then brake (module
        docstring): each fallback keeps the rows of the known geometry hard while it can.
        ``slack_factors``: the rows' factors on their occlusion slack weights
        (`slack_factors`; None: 1)."""
        calls = 0
        slack_factors = np.ones(len(kinds)) if slack_factors is None else slack_factors
        cap = occlusion_weight_cap(v_hat, An, bn, self.options.occlusion_price or 0.0)
        for status, weights in self._layers(kinds, slack_factors, cap):
            v, n = self._solve(v_hat, An, bn, weights, lb3, ub3)
            calls += n
            if v is not None:
                return v, status, self.solver, calls
        return np.zeros(3), "fallback", "brake", calls

    def _layers(self, kinds: np.ndarray, slack_factors: np.ndarray, cap: float):
        """(status, slack weight per row; 0 = hard) of each QP layer, in the order tried;
        ``cap``: the most an occlusion row's weight may be (`qp_layers.occlusion_weight_cap`).

        Priorities: the floor and the static obstacles (exact geometry) > the other UAVs
        (messages, with their reachable sets) > the car (an estimate) > connectivity > occlusion.
        The first relaxation slacks the occlusion rows only, each weighted by its factor in
        ``slack_factors``; connectivity is slacked only when it conflicts with the collision and
        altitude rows, and from then on outweighs occlusion at least 100:``occlusion_urgency``.
        A fallback gives up the lowest-priority hard family that is left.
        """
        yield "optimal", np.zeros(len(kinds))
        opt = self.options
        occlusion, connect = kinds == OCCLUSION, kinds == CONNECT
        if occlusion.any():
            yield (
                "relaxed",
                np.where(occlusion, np.minimum(opt.soft_penalty * slack_factors, cap), 0.0),
            )
        base = np.where(
            connect,
            opt.soft_penalty,
            np.where(occlusion, np.minimum(1e-2 * opt.soft_penalty * slack_factors, cap), 0.0),
        )
        if connect.any():
            yield "relaxed", base
        target = kinds == TARGET
        if target.any():
            base = np.where(target, opt.hard_penalty * 1e-2, base)
            yield "fallback", base
        uav = kinds == UAV
        if uav.any():
            base = np.where(uav, opt.hard_penalty, base)
            yield "fallback", base
        yield "fallback", np.where(base > 0.0, base, opt.hard_penalty * 1e2)

    def _solve(self, v_hat, An, bn, weights, lb3, ub3) -> tuple[np.ndarray | None, int]:
        """min 1/2||v - v_hat||^2 + sum w_j s_j  s.t.  An v - s <= bn, box, s >= 0, with cuts."""
        H, f, G, (bu, bl), sense = qp_problem(
            v_hat, An, bn, weights, lb3, ub3, self.options.slack_regularization
        )
        calls = 0
        v, speed = None, 0.0
        for it in range(self.options.norm_cuts + 1):
            x = self._backend(H, f, G, bu, bl, sense)
            calls += 1
            if x is None:
                if v is None:
                    return None, calls
                # A cut made the QP degenerate for this backend: keep the previous solution
                # (feasible for every row) and scale it into the ball (sound, module docstring).
                return v * (self.alpha_v / speed), calls
            v = x[:3]
            speed = math.sqrt(v @ v)
            if speed <= self.alpha_v * (1.0 + 1e-9):
                return v, calls
            if it == self.options.norm_cuts:
                return v * (self.alpha_v / speed), calls
            G, (bu, bl), sense = with_cut(G, bu, bl, sense, v, speed, self.alpha_v)
        return None, calls  # pragma: no cover (loop always returns)

    def _backend(self, H, f, G, bu, bl, sense) -> np.ndarray | None:
        """One QP solve of a `qp_problem`; None on infeasibility, solver error or an inaccurate
        answer."""
        try:
            if self.solver == "daqp-direct":
                x, _, flag, _ = daqp.solve(H, f, G, bu, bl, sense, primal_tol=_PRIMAL_TOL)
                if flag < 1:
                    return None
            else:
                if self.solver == "proxqp":
                    kwargs = {"eps_abs": _PRIMAL_TOL, "eps_rel": 0.0}
                else:
                    kwargs = {"primal_tol": _PRIMAL_TOL}
                nv = len(f)
                h, ub = bu[nv:], bu[:nv]
                x = qpsolvers.solve_qp(
                    H,
                    f,
                    G if len(h) else None,
                    h if len(h) else None,
                    lb=bl[:nv],
                    ub=np.where(ub >= INF, np.inf, ub),
                    solver=self.solver,
                    **kwargs,
                )
                if x is None:
                    return None
        except Exception:  # a solver crash must not take the UAV down: the caller falls back
            return None
        x = np.asarray(x, dtype=float)
        return x if meets(x, G, bu, bl, self.options.verify_tol) else None

    # ----------------------------------------------------------------- report
    def _changed_report(self, out: list, u, rows, ids, t0) -> ShieldReport:
        """`_report` from `qp_layers.certify_changed`'s packed output (as a list)."""
        active_rows, slack_rows, gave_up = _changed_names(out, u[3], lambda r: rows.name(r, ids))
        return ShieldReport(
            status=LAYER_STATUS[int(out[4])],
            active=True,
            correction_norm=out[11],
            slack=out[7],
            active_rows=active_rows,
            solver=("closed-form", self.solver, "brake")[int(out[5])],
            solver_calls=int(out[6]),
            time_us=(time.perf_counter() - t0) * 1e6,
            hard_violation=out[8],
            gave_up=gave_up,
            slack_per_row=slack_rows,
            rows=rows,
            neighbour_ids=ids,
        )

    def _report(self, status, u, u_safe, rows, ids, t0, solver, calls, An, bn, kinds, kept):
        """Report for a changed action; slack and violations are measured at the returned action."""
        active, over_soft, over_hard, viol, slack_total, hard_violation, speed, box, norm = (
            outcome(An, bn, kinds, CONNECT, max(self.options.tol, 1e-7), u, u_safe,
                    self.alpha_v, self.v_max)
        )  # fmt: skip
        active_rows = [rows.name(kept[j], ids) for j in active.tolist()]
        slack_rows = {rows.name(kept[j], ids): float(viol[j]) for j in over_soft.tolist()}
        gave_up = [rows.name(kept[j], ids) for j in over_hard.tolist()]
        if speed:
            active_rows.append("speed")
        if box:
            active_rows.append("box")
        if u_safe[3] != u[3]:
            active_rows.append("yaw_rate")
        return ShieldReport(
            status=status,
            active=True,
            correction_norm=norm,
            slack=float(slack_total),
            active_rows=active_rows,
            solver=solver,
            solver_calls=calls,
            time_us=(time.perf_counter() - t0) * 1e6,
            hard_violation=float(hard_violation),
            gave_up=gave_up,
            slack_per_row=slack_rows,
            rows=rows,
            neighbour_ids=ids,
        )


def _row_excess(rows: CBFRows, u: np.ndarray, yaw: float) -> np.ndarray:
    """How far (m/s on unit rows) the camera-frame command ``u`` breaks each row of ``rows``;
    negative where it keeps it."""
    V = cam_to_world_vec(np.asarray(u[:3], float), yaw)
    return (rows.A @ V - rows.b) / np.maximum(np.linalg.norm(rows.A, axis=1), 1e-12)


def _exit_time(
    rows: CBFRows, through: np.ndarray, u: np.ndarray, yaw: float, theta_star: float
) -> float:
    """First-order time (s) until the sight line leaves every box of the occlusion rows
    ``through`` (boxes it goes through) at the camera-frame command ``u``: the longest of the
    rows' angles to their outline points, ``-h - theta*``, over their rates ``-A V + drift``
    (inf where a rate is not positive)."""
    V = cam_to_world_vec(np.asarray(u[:3], float), yaw)
    rate = rows.drift[through] - rows.A[through] @ V
    angle = np.maximum(-rows.h[through] - theta_star, 0.0)
    if (rate <= 0.0).any():
        return math.inf
    return float((angle / rate).max())


def _excess(rows: CBFRows, u: np.ndarray, yaw: float) -> np.ndarray:
    """`_row_excess` of each hard row (uav, obstacle, car, floor), -inf for soft rows."""
    return np.where(rows.kind < CONNECT, _row_excess(rows, u, yaw), -np.inf)


def pairs_answered(ctx: SafetyContext, mates: np.ndarray) -> np.ndarray | None:
    """Of the pairs with team-mates ``mates`` (indices into ``ctx.neighbours``), those this
    UAV answers for in a fallback (`SafetyFilter.yield_by_rank`); None without the ids.

    The UAV that closes the gap faster (its velocity towards the other; the team-mate's from
    ``ctx.neighbour_velocities``) answers for the pair: its braking opens the gap, while the
    one ahead can only run and may itself be pinned ahead. Without velocities, or within
    1 mm/s, the lower id answers. Both UAVs of a pair compute the same split from what they
    know of each other."""
    if ctx.own_id is None or ctx.neighbour_ids is None:
        return None
    answers = np.asarray(ctx.neighbour_ids, dtype=np.int64)[mates] > ctx.own_id
    if ctx.velocity is None or ctx.neighbour_velocities is None:
        return answers
    e = ctx.neighbours[mates] - ctx.position
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)
    own = e @ ctx.velocity
    their = -np.einsum("ij,ij->i", e, ctx.neighbour_velocities[mates])
    return np.where(np.abs(own - their) > _CLOSING_TIE, own > their, answers)


_CLOSING_TIE = 1e-3
"""Closing speeds (m/s) of the two UAVs of a pair this close are a tie (`pairs_answered`)."""


def _stale_team_mates_with_car(rows: CBFRows, radius: np.ndarray | None) -> np.ndarray | None:
    """The rows' kinds with the uav rows of team-mates known only within a ball (``radius``
    > 0, `SafetyContext.neighbour_radius`) given the car's priority (`SafetyFilter._layers`);
    None if there are none."""
    if radius is None:
        return None
    uav = np.flatnonzero(rows.kind == UAV)
    stale = uav[np.asarray(radius)[rows.index[uav]] > 0.0]
    if not len(stale):
        return None
    kind = rows.kind.copy()
    kind[stale] = TARGET
    return kind


_ZEROS3 = np.zeros(3)
_N_KINDS = len(KIND_NAMES)
_NOMINAL = {
    f.name: f.default if f.default_factory is MISSING else None for f in fields(ShieldReport)
}


def _changed_names(
    out: list, u_yaw_rate: float, name: Callable[[int], str]
) -> tuple[list[str], dict[str, float], list[str]]:
    """(active rows and bounds, violated soft rows with their violations, violated hard rows)
    of `qp_layers.certify_changed`'s packed output (as a list), rows named by ``name(r)``."""
    na, ns, nh = int(out[12]), int(out[13]), int(out[14])
    j = OUT_HEAD
    active_rows = [name(int(r)) for r in out[j : j + na]]
    j += na
    slack_rows = {
        name(int(r)): viol
        for r, viol in zip(out[j : j + ns], out[j + ns : j + 2 * ns], strict=True)
    }
    j += 2 * ns
    gave_up = [name(int(r)) for r in out[j : j + nh]]
    if out[9]:
        active_rows.append("speed")
    if out[10]:
        active_rows.append("box")
    if out[3] != u_yaw_rate:
        active_rows.append("yaw_rate")
    return active_rows, slack_rows, gave_up


class Certificates:
    """`SafetyFilter.certify_many`'s outcome for m UAVs: the certified commands and what each
    report says as arrays (m,), the `ShieldReport`s themselves made when first read
    (`report`, `reports`)."""

    def __init__(
        self,
        shield: SafetyFilter,
        u: np.ndarray,
        changed: np.ndarray,
        outs: np.ndarray,
        rows: Callable[[int], CBFRows],
        neighbour_ids: list[tuple[int, ...] | None],
        share: float,
    ) -> None:
        self.action = outs[:, :4].copy()
        """(m, 4) the certified commands."""
        self.changed = changed
        """(m,) the command was changed (``ShieldReport.active``)."""
        self.lows: np.ndarray | None = None
        """(m, 7) `qp_arrays.family_lows` of each UAV's rows, if the caller set them."""
        self._made: list[ShieldReport | None] = [None] * len(changed)
        self._args = (shield, u, outs, rows, neighbour_ids, share)
        self.rows_at: tuple | None = None
        """(kind, index, begin): UAV j's rows' kinds and indices from ``begin[j]`` on, if the
        caller set them (with ``lows``, `summary` then reads no report)."""

    @classmethod
    def of_reports(cls, action: np.ndarray, reports: list[ShieldReport]) -> Certificates:
        """The certificates of reports already made (the qpsolvers backends)."""
        self = object.__new__(cls)
        self.action, self._made, self._args = action, list(reports), None
        self.changed = np.array([r.active for r in reports], bool)
        self.lows = self.rows_at = None
        return self

    @property
    def correction_norm(self) -> np.ndarray:
        """(m,) ``ShieldReport.correction_norm`` of each UAV."""
        return self._column(11, "correction_norm")

    @property
    def hard_violation(self) -> np.ndarray:
        """(m,) ``ShieldReport.hard_violation`` of each UAV."""
        return self._column(8, "hard_violation")

    @property
    def fallback(self) -> np.ndarray:
        """(m,) the status is 'fallback' (braking included)."""
        if self._args is None:
            return np.array([r.status == "fallback" for r in self._made], bool)
        return self.changed & (self._args[2][:, 4] == LAYER_STATUS.index("fallback"))

    @property
    def relaxed(self) -> np.ndarray:
        """(m,) the status is 'relaxed' (a soft row took slack)."""
        if self._args is None:
            return np.array([r.status == "relaxed" for r in self._made], bool)
        return self.changed & (self._args[2][:, 4] == LAYER_STATUS.index("relaxed"))

    def _column(self, c: int, name: str) -> np.ndarray:
        if self._args is None:
            return np.array([getattr(r, name) for r in self._made], float)
        return np.where(self.changed, self._args[2][:, c], 0.0)

    def __len__(self) -> int:
        return len(self._made)

    def min_hard_h(self) -> np.ndarray:
        """(m,) each UAV's least hard barrier value (inf without hard rows)."""
        if self.lows is not None:
            return self.lows[:, -1].copy()
        return np.array([self.report(j).min_hard_h for j in range(len(self))], float)

    def report(self, j: int) -> ShieldReport:
        """UAV j's `ShieldReport`."""
        rep = self._made[j]
        if rep is None:
            shield, u, outs, rows, ids, share = self._args
            if self.changed[j]:
                rep = shield._changed_report(outs[j].tolist(), u[j], rows(j), ids[j], 0.0)
                rep.time_us = share
            else:
                rep = _nominal_report(rows(j), ids[j], share)
            if self.lows is not None:
                rep.lows = self.lows[j].tolist()
            self._made[j] = rep
        return rep

    def reports(self) -> list[ShieldReport]:
        """Every UAV's `ShieldReport`."""
        return [self.report(j) for j in range(len(self))]

    def summary(self, j: int) -> dict:
        """What UAV j's report says (active, correction_norm, status, active_rows, gave_up,
        slack, hard_violation, min_h, min_hard_h; `wrappers.CBFShield`'s telemetry), without
        making the report where the arrays hold it."""
        rep = self._made[j]
        if rep is not None or self.lows is None or self.rows_at is None:
            rep = self.report(j)
            min_h, min_hard_h = rep.family_minima()
            return {
                "active": rep.active, "correction_norm": rep.correction_norm,
                "status": rep.status, "active_rows": rep.active_rows, "gave_up": rep.gave_up,
                "slack": rep.slack, "hard_violation": rep.hard_violation, "min_h": min_h,
                "min_hard_h": min_hard_h,
            }  # fmt: skip
        return self._summaries([j])[0]

    def summaries(self) -> list[dict]:
        """`summary` of every UAV."""
        if self.lows is None or self.rows_at is None or self._made.count(None) < len(self):
            return [self.summary(j) for j in range(len(self))]
        return self._summaries(range(len(self)))

    def _summaries(self, js: Sequence[int]) -> list[dict]:
        """`summary` of UAVs ``js`` from the arrays (``lows`` and ``rows_at`` set)."""
        _, u, outs, _, ids, _ = self._args
        kind, index, begin = self.rows_at
        lows, changed, yaw_rates = self.lows.tolist(), self.changed.tolist(), u[:, 3].tolist()
        begins = begin.tolist()
        done = []
        for j in js:
            *family, hard = lows[j]
            min_h = {name: low for name, low in zip(KIND_NAMES, family, strict=True) if low == low}
            if not changed[j]:
                done.append({
                    "active": False, "correction_norm": 0.0, "status": "nominal",
                    "active_rows": [], "gave_up": [], "slack": 0.0, "hard_violation": 0.0,
                    "min_h": min_h, "min_hard_h": hard,
                })  # fmt: skip
                continue
            a, who, out = begins[j], ids[j], outs[j].tolist()
            active_rows, _, gave_up = _changed_names(
                out, yaw_rates[j],
                lambda r, a=a, who=who: row_name(int(kind[a + r]), int(index[a + r]), who),
            )  # fmt: skip
            done.append({
                "active": True, "correction_norm": out[11], "status": LAYER_STATUS[int(out[4])],
                "active_rows": active_rows, "gave_up": gave_up, "slack": out[7],
                "hard_violation": out[8], "min_h": min_h, "min_hard_h": hard,
            })  # fmt: skip
        return done


def _nominal_report(rows: CBFRows, ids: tuple[int, ...] | None, time_us: float) -> ShieldReport:
    """`ShieldReport` of an unchanged action (the dataclass's fields set directly: one per UAV
    and step)."""
    rep = object.__new__(ShieldReport)
    rep.__dict__.update(_NOMINAL)
    rep.__dict__.update(
        status="nominal", active=False, correction_norm=0.0, slack=0.0, active_rows=[],
        gave_up=[], slack_per_row={}, time_us=time_us, rows=rows, neighbour_ids=ids,
    )  # fmt: skip
    return rep


def _checked_nominal(u_nominal: np.ndarray, ctx: SafetyContext) -> np.ndarray:
    """``u_nominal`` as a float array; ValueError unless it is a finite (4,) action and ``ctx``
    a `SafetyContext`."""
    u = np.asarray(u_nominal, dtype=float)
    if u.shape != (4,):
        raise ValueError(f"u_nominal must have shape (4,) [v_cx, v_cy, v_cz, w_cy], got {u.shape}")
    if not math.isfinite(u.sum()):
        raise ValueError(f"u_nominal must be finite, got {u}")
    if not isinstance(ctx, SafetyContext):
        raise ValueError(f"ctx must be a SafetyContext, got {type(ctx).__name__}")
    return u
