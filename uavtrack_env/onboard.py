"""One UAV's onboard stack: what it knows (`OnboardAgent.observe`) and its CBF-QP (`certify`).

`ExpertPolicy` is this stack plus the planner (NMPC, viewpoint); `CBFShield` is this stack alone
around any policy. Both therefore see exactly a real UAV's information: the detector's report, its
own GPS/IMU state, its neighbours' messages and the known obstacle map, never ``info["truth"]``.

The car is known only through the UKF. Its row (a hard row keeping the UAV out of the car) uses a
heading-free box (horizontal half extent = the car's half diagonal) that stands on the ground,
inflated by ``target_margin`` plus ``target_sigmas`` standard deviations of the estimated
position (capped at ``target_margin_max``), by up to the car's size while the detector's box is
cut by the image border, and growing while the car is undetected (`car_box`, `ShieldMargins`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from .config import DT, CameraConfig, EnvConfig
from .estimation import Estimate, Measurement, TargetEstimator, UKFConfig
from .estimation.bank import TrackerBank
from .geometry import world_to_cam_vec
from .presets import ExpertConfig
from .safety import (
    CBFRows,
    SafetyContext,
    SafetyFilter,
    ShieldMargins,
    ShieldReport,
    shield_cbf,
)
from .scenarios import Layout
from .target import CAR_HALF_EXTENTS


class OnboardTracker:
    """One UAV's UKF, fed step by step from its info (`update_trackers`); ``estimate`` is None
    until a detection. With ``UKFConfig.vectorized`` (the default) it is slot ``slot`` of a
    `TrackerBank` its team shares (a bank of its own if ``bank`` is None), otherwise its own
    `TargetEstimator` (plain filterpy)."""

    def __init__(
        self,
        camera: CameraConfig,
        cfg: UKFConfig | None = None,
        bank: TrackerBank | None = None,
        slot: int = 0,
    ) -> None:
        cfg = cfg or UKFConfig()
        self.bank: TrackerBank | None = None
        self.estimator: TargetEstimator | None = None
        self.estimate: Estimate | None = None
        """The latest estimate (None until the car was first detected)."""
        if cfg.vectorized:
            self.bank, self.slot = bank or TrackerBank(1, camera, cfg), slot
        else:
            self.estimator, self.slot = TargetEstimator(camera, cfg), 0

    def reset(self) -> None:
        """Forget the estimate: the next detection initialises the filter."""
        self.estimate = None
        if self.bank is not None:
            self.bank.forget(self.slot)


def update_trackers(trackers: Sequence[OnboardTracker], infos: Sequence[dict]) -> list:
    """Advance each UAV's filter with its info (measurement and own motion): the trackers of one
    `TrackerBank` in one compiled call, plain-filterpy trackers one by one; returns each
    tracker's estimate (None until its first detection)."""
    groups: dict[int, tuple[TrackerBank, list[OnboardTracker], list[tuple]]] = {}
    for tracker, info in zip(trackers, infos, strict=True):
        bank = tracker.bank
        if bank is None:
            _step_alone(tracker, info)
            continue
        group = groups.get(id(bank))
        if group is None:
            group = groups[id(bank)] = (bank, [], [])
        group[1].append(tracker)
        group[2].append(_input_row(info))
    for bank, members, rows in groups.values():
        bank.step([t.slot for t in members], np.array(rows, float))
        estimates = bank.estimates
        for t in members:
            t.estimate = estimates[t.slot]
    return [t.estimate for t in trackers]


def _input_row(info: dict) -> tuple:
    """A `TrackerBank` input row (`bank.INPUT_COLUMNS`) of one UAV's info."""
    own, m = info["own"], info["measurement"]
    x, y, z = own["position"].tolist()
    vx, vy, vz = own["velocity"].tolist()
    state = (x, y, z, own["yaw"], vx, vy, vz, own["yaw_rate"])
    if m["detected"]:
        return (*state, 1.0, m["u"], m["v"], m["depth"], m["psi"], m["truncated_u"],
                m["truncated_v"])  # fmt: skip
    return (*state, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def _step_alone(tracker: OnboardTracker, info: dict) -> None:
    """One plain-filterpy tracker's step (`TargetEstimator.reset`/`step`)."""
    own, m = info["own"], info["measurement"]
    pos, yaw = own["position"], own["yaw"]
    meas = None
    if m["detected"]:
        meas = Measurement.trusted(
            m["u"], m["v"], m["depth"], m["psi"], m["truncated_u"], m["truncated_v"]
        )
    est = tracker.estimator
    if tracker.estimate is None:
        if meas is not None:
            tracker.estimate = est.reset(meas, pos, yaw)
        return
    # The UAV's own velocity (IMU/odometry) in the camera frame, as applied over the step.
    vx, vy, vz = world_to_cam_vec(own["velocity"], yaw).tolist()
    u_meas = np.array((vx, vy, vz, -float(own["yaw_rate"])))
    tracker.estimate = est.step(u_meas, pos, yaw, meas)


@dataclass(frozen=True)
class NeighbourBelief:
    """What one UAV believes of its team-mates now (k known team-mates, in team order)."""

    names: tuple[str, ...]
    positions: np.ndarray
    """(k, 3) positions: the last message, propagated at its velocity under the lag model."""
    velocities: np.ndarray
    """(k, 3) velocities differenced from consecutive messages (kept while messages are lost)."""
    position_radius: np.ndarray
    """(k,) the true position lies within this distance (m) of ``positions``."""
    velocity_radius: np.ndarray
    """(k,) the true velocity lies within this distance (m/s) of ``velocities``."""
    ages: np.ndarray
    """(k,) control steps since each team-mate's last message (0: heard this step)."""
    ids: tuple[int, ...]
    """Their indices in the team."""


class NeighbourTable:
    """Each team-mate's last message, its age and a reachable-set bound on where it is now.

    A UAV hears positions only (section III), and a message may be lost. A team-mate stays
    known after a lost message: it is at its last message's position (propagated at its last
    differenced velocity under the lag model) within a radius that grows with the message's age
    t: ``speed_bound t`` (every UAV flies at ``||V|| <= alpha_v``, the QP's speed bound (47)),
    and under the lag model ``accel_bound t (t + dt) / 2`` around the propagated position
    (``||v-dot|| <= a_max``, forward Euler) if that is smaller. Velocities are differenced from
    consecutive messages (exact with the env's forward-Euler step; over a gap of g steps the mean
    velocity, within ``a_max (g - 1) dt / 2`` of the last one). At reset every team-mate within
    ``r_c`` is known at its start position, at rest (the formation is known before take-off); a
    team-mate silent for ``timeout`` steps is forgotten (it collided, was parked or left R_c).
    """

    def __init__(
        self,
        speed_bound: float,
        accel_bound: float | None = None,
        timeout: int = 40,
        dt: float = DT,
    ) -> None:
        self.speed_bound, self.accel_bound = float(speed_bound), accel_bound
        self.timeout, self.dt = int(timeout), dt
        self._believe_accel = -1.0 if accel_bound is None else accel_bound
        """`_believe`'s acceleration bound (-1: none, the integrator model)."""
        self._names: list[str] = []
        self._ids: list[int] = []
        self._index: dict[str, int] = {}
        self._all: tuple[tuple[str, ...], tuple[int, ...]] = ((), ())
        self._pos = np.zeros((0, 3))
        self._vel = np.zeros((0, 3))
        self._vel_err = np.zeros(0)
        self._age = np.zeros(0, int)
        self._known = np.zeros(0, bool)

    def reset(self, names: list[str], positions: np.ndarray, own: str, r_c: float) -> None:
        """A new episode: the team ``names`` at ``positions`` (n, 3); ``own`` is this UAV."""
        positions = np.asarray(positions, float).reshape(-1, 3)
        me = names.index(own)
        keep = [k for k in range(len(names)) if k != me]
        self._names = [names[k] for k in keep]
        self._ids = keep
        self._index = {a: k for k, a in enumerate(self._names)}
        self._all = (tuple(self._names), tuple(keep))
        self._pos = positions[keep].copy()
        self._vel = np.zeros_like(self._pos)
        self._vel_err = np.zeros(len(keep))
        self._age = np.zeros(len(keep), int)
        self._known = np.linalg.norm(self._pos - positions[me], axis=1) <= r_c

    def update(self, messages: dict[str, np.ndarray]) -> None:
        """Take this step's messages (team-mate -> position); the others age by one step."""
        _take_messages(*self._messages(messages), *self._state(), self.timeout)

    def take(self, messages: dict[str, np.ndarray]) -> NeighbourBelief:
        """`update` with this step's messages, then the `belief` (one compiled call)."""
        return self._wrap(
            _take_and_believe(
                *self._messages(messages), *self._state(), self.timeout, self._believe_accel
            )
        )

    def belief(self) -> NeighbourBelief:
        """The known team-mates now."""
        return self._wrap(
            _believe(
                self._known,
                self._pos,
                self._vel,
                self._vel_err,
                self._age,
                self.dt,
                self.speed_bound,
                self._believe_accel,
            )
        )

    def _messages(self, messages: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(team-mate indices, positions) of the messages from known team members."""
        ks, heard = [], []
        for name, pos in messages.items():
            k = self._index.get(name)
            if k is not None:
                ks.append(k)
                heard.append(pos)
        return np.array(ks, np.int64), np.array(heard, float) if heard else _NO_POSITIONS

    def _state(self) -> tuple:
        """The table's arrays and bounds in `_take_messages`'s order (before ``timeout``)."""
        return (
            self._pos, self._vel, self._vel_err, self._age, self._known, self.dt,
            self.accel_bound or 0.0, self.speed_bound,
        )  # fmt: skip

    def _wrap(self, believed: tuple) -> NeighbourBelief:
        """A `NeighbourBelief` from `_believe`'s arrays."""
        (k, ages), (pos, vel), (radius, vel_radius) = believed
        if len(k) == len(self._names):
            names, ids = self._all
        else:
            known = k.tolist()
            names = tuple([self._names[i] for i in known])
            ids = tuple([self._ids[i] for i in known])
        belief = object.__new__(NeighbourBelief)  # frozen: fields set as dataclasses do
        belief.__dict__.update(
            names=names, positions=pos, velocities=vel, position_radius=radius,
            velocity_radius=vel_radius, ages=ages, ids=ids,
        )  # fmt: skip
        return belief


_NO_POSITIONS = np.zeros((0, 3))


@numba.njit(cache=True)
def _take_messages(
    ks, pos, p, v, v_err, age, known, dt, accel, speed, timeout
):  # pragma: no cover (compiled)
    """`NeighbourTable.update` on its arrays, in place: messages ``pos[i]`` from team-mate
    ``ks[i]``."""
    for j in range(age.shape[0]):
        age[j] += 1
    for i in range(ks.shape[0]):
        k = ks[i]
        if known[k]:
            gap = age[k]
            for a in range(3):
                v[k, a] = (pos[i, a] - p[k, a]) / (gap * dt)
            v_err[k] = 0.5 * accel * (gap - 1) * dt
        else:  # first heard: its velocity is unknown within the speed bound
            for a in range(3):
                v[k, a] = 0.0
            v_err[k] = speed
        for a in range(3):
            p[k, a] = pos[i, a]
        age[k] = 0
        known[k] = True
    for j in range(age.shape[0]):
        known[j] = known[j] and age[j] < timeout


@numba.njit(cache=True)
def _believe(known, p, v, v_err, age, dt, speed, accel):  # pragma: no cover (compiled)
    """`NeighbourTable.belief`'s arrays for the ``known`` team-mates (``accel`` < 0: none), in
    three blocks (each array returned to Python costs ~0.5 us): [indices, ages] (2, m),
    [positions, velocities] (2, m, 3) and [position radii, velocity radii] (2, m)."""
    ks = np.flatnonzero(known)
    m = ks.shape[0]
    ints = np.empty((2, m), np.int64)
    motion = np.empty((2, m, 3))
    radii = np.zeros((2, m))
    pos, vel, radius, vel_radius = motion[0], motion[1], radii[0], radii[1]
    for i in range(m):
        k = ks[i]
        ints[0, i], ints[1, i] = k, age[k]
        t = age[k] * dt
        for a in range(3):
            vel[i, a] = v[k, a]
            pos[i, a] = p[k, a]
        radius[i] = speed * t
        if accel >= 0.0:
            err = v_err[k]
            s = math.sqrt(v[k, 0] * v[k, 0] + v[k, 1] * v[k, 1] + v[k, 2] * v[k, 2])
            # forward Euler, p(k+1) = p(k) + v(k+1) dt: the drift is a sum, not an integral
            propagated = 0.5 * accel * t * (t + dt) + err * t
            radius[i] = min((speed + s) * t, propagated)
            for a in range(3):
                pos[i, a] = p[k, a] + v[k, a] * t
            vel_radius[i] = min(err + accel * t, 2.0 * speed)
    return ints, motion, radii


class OnboardAgent:
    """One UAV's onboard stack (UKF, team-mates' messages, known map, CBF-QP (47)).

    Call `reset` with each new layout (the one place a new map arrives), then `observe` with the
    agent's ``info`` after every env reset/step; `rows` and `certify` use the latest observation.
    R_s and R_c come from the world (`EnvConfig.violations.r_s`, `EnvConfig.comms.r_c`) with the
    config's margins; under the env's 'lag' dynamics and ``lag_aware`` the rows are second order
    and respect the acceleration bound (`ShieldOptions.lag_tau` = ``dynamics.tau``,
    ``accel_bound`` = ``dynamics.a_max``). What this guarantees: docs/safety.md.
    """

    def __init__(
        self,
        name: str,
        index: int,
        env_config: EnvConfig,
        config: ExpertConfig,
        tracker: OnboardTracker | None = None,
    ) -> None:
        self.name, self.index, self.config = name, index, config
        margins = config.margins
        cbf = config.cbf.resolve(env_config.violations.r_s, env_config.comms.r_c)
        for what, level in (("obstacle_clearance", cbf.obstacle_clearance), ("z_min", cbf.z_min)):
            if level - env_config.uav_radius < margins.surface_gap:
                raise ValueError(
                    f"cbf.{what} = {level} m leaves less than margins.surface_gap = "
                    f"{margins.surface_gap} m around the UAV's sphere (uav_radius "
                    f"{env_config.uav_radius} m)"
                )
        self.cbf = shield_cbf(cbf, margins)
        lag = config.lag_aware and env_config.dynamics.model == "lag"
        lag_tau = env_config.dynamics.tau if lag else 0.0
        accel = env_config.dynamics.a_max if lag else 0.0
        options = dataclasses.replace(config.shield, lag_tau=lag_tau, accel_bound=accel)
        self.filter = SafetyFilter(
            self.cbf, env_config.limits, solver=config.qp_solver, **dataclasses.asdict(options)
        )
        self.tracker = tracker or OnboardTracker(env_config.camera, config.ukf)
        self._lag = lag
        self.neighbours = NeighbourTable(
            speed_bound=self.cbf.alpha_v,
            accel_bound=env_config.dynamics.a_max if env_config.dynamics.model == "lag" else None,
            timeout=max(1, round(margins.message_timeout / DT)),
        )
        self._r_c = env_config.comms.r_c
        fastest = max(0.5, env_config.random_world.target_speed[1])  # Fig. 11: 0.5 m/s
        self._car_speed = fastest if margins.target_speed_max is None else margins.target_speed_max
        self._anchor: Estimate | None = None
        """The last estimate trusted as the car's box: the reachable set grows from it
        (`car_box`)."""
        self._recovery = round(margins.truncation_recovery / DT)
        self._uncut = [self._recovery] * 2
        """Detections since the last box cut by the image border in u and in v."""
        self._cut_steps = [0, 0]
        """Steps since each axis's spell of cut boxes began (0: none)."""
        self.obstacle_centers = np.zeros((0, 3))
        self.obstacle_half_extents = np.zeros((0, 3))
        self.info: dict | None = None
        self.belief: NeighbourBelief | None = None
        self._context: SafetyContext | None = None
        self._rows: CBFRows | None = None

    @property
    def estimate(self) -> Estimate | None:
        """The UKF's target estimate (None until the car was first detected)."""
        return self.tracker.estimate

    def reset(self, layout: Layout, agents: list[str]) -> None:
        """A new episode on ``layout`` (its known obstacle map); ``agents`` names the team in
        index order. Forgets the estimate and the neighbours' histories."""
        self.obstacle_centers = np.asarray(layout.obstacle_centers, float).reshape(-1, 3)
        self.obstacle_half_extents = np.asarray(layout.obstacle_half_extents, float).reshape(-1, 3)
        self.tracker.reset()
        self._anchor = None
        self._uncut = [self._recovery] * 2
        self._cut_steps = [0, 0]
        self.neighbours.reset(agents, layout.uav_positions, self.name, self._r_c)
        self.info, self.belief, self._context, self._rows = None, None, None, None

    def observe(self, info: dict) -> Estimate | None:
        """Take this step's ``info`` (measurement, own state, messages); returns the estimate."""
        observe_team([self], [info])
        return self.tracker.estimate

    def _take(self, info: dict) -> None:
        """The messages, the cut-box spells and the safety context of ``info`` (the tracker has
        taken it)."""
        m, full = info["measurement"], self._recovery
        uncut, steps = self._uncut, self._cut_steps
        for axis, key in enumerate(("truncated_u", "truncated_v")):
            if m["detected"]:
                uncut[axis] = 0 if m[key] else min(uncut[axis] + 1, full)
            steps[axis] = steps[axis] + 1 if uncut[axis] < full else 0
        self.belief = self.neighbours.take(info["neighbours"])
        self.info, self._rows = info, None
        self._context = self._make_context(info, self.belief)

    def context(self) -> SafetyContext:
        """The CBF-QP's view of the latest observation."""
        if self._context is None:
            raise RuntimeError(f"{self.name}: no observation yet; call observe(info) after reset")
        return self._context

    def rows(self) -> CBFRows:
        """The CBF rows of the latest observation (built once per observation)."""
        if self._rows is None:
            self._rows = self.filter.rows(self.context())
        return self._rows

    def certify(self, u_nominal: np.ndarray) -> tuple[np.ndarray, ShieldReport]:
        """The safe camera-frame command (SI units) closest to ``u_nominal``, and a report."""
        return self.filter.certify(u_nominal, self.context(), self.rows())

    def certify_trusted(self, u: np.ndarray) -> tuple[np.ndarray, ShieldReport]:
        """`certify` without checks (`SafetyFilter.certify_trusted`)."""
        return self.filter.certify_trusted(u, self.context(), self.rows())

    def _make_context(self, info: dict, belief: NeighbourBelief) -> SafetyContext:
        """The CBF-QP's view: own pose and velocity, the team-mates as believed (and, for
        second-order rows, their velocities), the known obstacles, the car's estimate."""
        own, est = info["own"], self.tracker.estimate
        if est is None:  # no estimate: no target rows (SafetyContext's defaults)
            target: dict = {
                "target_velocity": np.zeros(3),
                "target_half_extents": np.array(CAR_HALF_EXTENTS, float),
                "target_heading": 0.0,
            }
        else:
            margins = self.config.margins
            cut_time = (
                (self._cut_steps[0] * DT, self._cut_steps[1] * DT)
                if margins.truncated_box_pad
                else (0.0, 0.0)
            )
            box = car_box(est, margins, self._car_speed, cut_time, self._anchor)
            if not box.stale:
                self._anchor = est
            target = {
                "target_position": box.center,
                "target_velocity": box.velocity,
                "target_half_extents": box.half,
                "target_heading": 0.0,
                "target_growth": box.growth,
                "target_frustum": box.stale,
            }
        # The env's own arrays, already float64 and finite: no re-validation.
        return SafetyContext.trusted(
            position=own["position"],
            yaw=float(own["yaw"]),
            velocity=own["velocity"],
            neighbours=belief.positions,
            neighbour_velocities=belief.velocities if self._lag else None,
            neighbour_radius=belief.position_radius,
            neighbour_velocity_radius=belief.velocity_radius if self._lag else None,
            obstacle_centers=self.obstacle_centers,
            obstacle_half_extents=self.obstacle_half_extents,
            neighbour_ids=belief.ids,
            **target,
        )


@numba.njit(cache=True)
def _take_and_believe(
    ks, pos, p, v, v_err, age, known, dt, accel, speed, timeout, believe_accel
):  # pragma: no cover (compiled)
    """`_take_messages`, then `_believe`: one step of `NeighbourTable.take`."""
    _take_messages(ks, pos, p, v, v_err, age, known, dt, accel, speed, timeout)
    return _believe(known, p, v, v_err, age, dt, speed, believe_accel)


def onboard_team(
    names: Sequence[str], env_config: EnvConfig, config: ExpertConfig, worlds: int = 1
) -> list[list[OnboardAgent]]:
    """The onboard stacks of ``worlds`` teams ``names`` (one list per world), their target
    filters in one `TrackerBank` (`observe_team` steps them in one compiled call)."""
    n, camera, ukf = len(names), env_config.camera, config.ukf
    bank = TrackerBank(n * worlds, camera, ukf) if ukf.vectorized else None
    return [
        [
            OnboardAgent(a, i, env_config, config, OnboardTracker(camera, ukf, bank, k * n + i))
            for i, a in enumerate(names)
        ]
        for k in range(worlds)
    ]


def observe_team(agents: Sequence[OnboardAgent], infos: Sequence[dict], rows: bool = False) -> None:
    """`OnboardAgent.observe` for several UAVs of one team, their UKFs in one batched pass.
    ``rows``: build each agent's CBF rows now, while its context is in the CPU's caches (a
    shield certifies every agent at its next step)."""
    update_trackers([a.tracker for a in agents], infos)
    for agent, info in zip(agents, infos, strict=True):
        agent._take(info)
        if rows:
            agent.rows()


_CAR_DIAG = math.hypot(*CAR_HALF_EXTENTS[:2].tolist())
"""The car footprint's half diagonal (m)."""
_CAR_HALF_HEIGHT = float(CAR_HALF_EXTENTS[2])


class CarBox(NamedTuple):
    """The car's exclusion box (`car_box`), heading-free (axis-aligned in the world)."""

    center: np.ndarray
    """(3,) its centre (m)."""
    velocity: np.ndarray
    """(3,) the velocity (m/s) at which the whole box moves."""
    half: np.ndarray
    """(3,) half extents (m)."""
    growth: np.ndarray
    """(3,) speeds (m/s) at which its faces move outwards along x, y, z."""
    stale: bool
    """The car's reachable set (undetected for longer than ``target_stale_after``): its row is
    the frustum over the box (`barrier_rows.target_row`)."""


def car_box(
    est: Estimate,
    margins: ShieldMargins,
    car_speed: float,
    cut_time: np.ndarray | tuple[float, float] = (0.0, 0.0),
    anchor: Estimate | None = None,
) -> CarBox:
    """The car's exclusion box from a UKF estimate.

    The box is heading-free: the car (4.6 x 1.8 x 1.5 m, section VI-A) may point anywhere, so
    both horizontal half extents are its footprint's half diagonal (the UKF's velocity direction
    is too unreliable to orient it: ``python -m baselines.car_box``). It is inflated by
    ``target_margin`` plus ``target_sigmas`` position standard deviations (capped at
    ``target_margin_max``). It is centred at the estimate and moves with the estimated velocity
    while the car is detected and for ``target_stale_after`` s without a detection (the pad
    covers the prediction's error). After that it is the car's reachable set from ``anchor``,
    the estimate at that moment (the caller keeps it; None: ``est`` itself): the car drives at
    most at ``car_speed``, so the box stands still and its faces move out at that speed,
    whatever the UKF predicts (after a hostile manoeuvre its velocity estimate can be off by
    more than the car's speed), and the car's row is the frustum over it, which a UAV beside it
    keeps by climbing. The top rises too, although the car stays on the ground: a UAV
    over a car it has lost climbs at the car's speed instead of holding a ceiling over it,
    through which team-mates crowding above can press it when the rows of a dense team conflict
    and the car's (the estimate) is the one given up (`SafetyFilter`; seek-car in
    ``python -m baselines.shield_adversary``).

    ``cut_time`` (u, v): how long (s) the estimate has carried the bias of boxes cut by the image
    border (`ShieldMargins.truncated_box_pad`; 0: none). That bias is at most the part of the car
    outside the image: the box grows by up to the footprint's half diagonal horizontally (u) and
    the car's half height vertically (v), at twice ``car_speed`` (a bias enters the UKF over
    several updates, not at once). A car on the ground (`ShieldMargins.car_on_ground`) has an
    exact vertical extent while tracked: the box reaches from the ground (or below) to the car's
    height plus ``target_margin``, whatever the estimated height.
    """
    diag, c = _CAR_DIAG, _CAR_HALF_HEIGHT
    stale = est.steps_since_detection * DT - margins.target_stale_after
    ref = est if stale <= 0.0 or anchor is None else anchor
    P = ref.covariance
    sigma_p = math.sqrt(max(P[4, 4], P[5, 5], P[6, 6], 0.0))
    pad = min(margins.target_margin + margins.target_sigmas * sigma_p, margins.target_margin_max)
    hxy, hz = diag + pad, c + pad
    g_xy = g_z = 0.0
    t_u, t_v = cut_time
    bias_speed = 2.0 * car_speed
    if t_u > 0.0:
        hxy += min(bias_speed * t_u, diag)
        g_xy += bias_speed if bias_speed * t_u < diag else 0.0
    if t_v > 0.0:
        hz += min(bias_speed * t_v, c)
        g_z += bias_speed if bias_speed * t_v < c else 0.0
    center = ref.target_position
    if margins.car_on_ground:  # the box spans [<= 0, the car's height + target_margin]
        top, z = 2.0 * c + margins.target_margin, float(center[2])
        hz, g_z = max(top - z, z), 0.0
    if stale > 0.0:  # the reachable set from the anchor, its top included
        hxy += car_speed * stale
        hz += car_speed * stale
        g_xy += car_speed
        g_z += car_speed
    velocity = _ZEROS3 if stale > 0.0 else est.target_velocity
    return CarBox(
        center, velocity, np.array((hxy, hxy, hz)), np.array((g_xy, g_xy, g_z)), stale > 0.0
    )


_ZEROS3 = np.zeros(3)
