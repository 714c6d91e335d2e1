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
from typing import Any, NamedTuple

import numpy as np

from .config import DT, CameraConfig, EnvConfig
from .estimation import Estimate, Measurement, TargetEstimator, UKFConfig
from .estimation.bank import INPUT_COLUMNS, TrackerBank
from .geometry import world_to_cam_vec
from .onboard_pass import (
    BOX_COLUMNS,
    PassOutput,
    TeamState,
    believe,
    car_box_arrays,
    input_rows_of,
    observe_frame_step,
    observe_pass,
    observe_step,
    take_and_believe,
    take_messages,
)
from .presets import ExpertConfig
from .safety import (
    CBFRows,
    Certificates,
    SafetyContext,
    SafetyFilter,
    ShieldMargins,
    ShieldReport,
    shield_cbf,
)
from .scenarios import Layout
from .sensors import Detections
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
        self._estimate: Estimate | None = None
        if cfg.vectorized:
            self.bank, self.slot = bank or TrackerBank(1, camera, cfg), slot
        else:
            self.estimator, self.slot = TargetEstimator(camera, cfg), 0

    @property
    def estimate(self) -> Estimate | None:
        """The latest estimate (None until the car was first detected)."""
        return self._estimate if self.bank is None else self.bank.estimates[self.slot]

    @property
    def has_estimate(self) -> bool:
        """``estimate is not None``, without making the estimate."""
        return (
            self._estimate is not None if self.bank is None else self.bank.has_estimate(self.slot)
        )

    def reset(self) -> None:
        """Forget the estimate: the next detection initialises the filter."""
        self._estimate = None
        if self.bank is not None:
            self.bank.forget(self.slot)


def update_trackers(trackers: Sequence[OnboardTracker], data: np.ndarray) -> None:
    """Advance each UAV's filter with its `bank.INPUT_COLUMNS` row ``data[j]`` (measurement
    and own motion): the trackers of one `TrackerBank` in one compiled call, plain-filterpy
    trackers one by one (their new estimates: ``tracker.estimate``)."""
    bank = trackers[0].bank if len(trackers) else None
    if bank is not None and all(t.bank is bank for t in trackers):  # one bank: one call
        bank.step([t.slot for t in trackers], data)
        return
    groups: dict[int, tuple[TrackerBank, list[int], list[int]]] = {}
    for j, tracker in enumerate(trackers):
        bank = tracker.bank
        if bank is None:
            _step_alone(tracker, data[j])
            continue
        group = groups.get(id(bank))
        if group is None:
            group = groups[id(bank)] = (bank, [], [])
        group[1].append(tracker.slot)
        group[2].append(j)
    for bank, slots, rows in groups.values():
        bank.step(slots, data if len(rows) == len(data) else data[rows])


def input_row(info: dict) -> tuple:
    """A `TrackerBank` input row (`bank.INPUT_COLUMNS`) of one UAV's info."""
    own, m = info["own"], info["measurement"]
    x, y, z = own["position"].tolist()
    vx, vy, vz = own["velocity"].tolist()
    state = (x, y, z, own["yaw"], vx, vy, vz, own["yaw_rate"])
    if m["detected"]:
        return (*state, 1.0, m["u"], m["v"], m["depth"], m["psi"], m["truncated_u"],
                m["truncated_v"])  # fmt: skip
    return (*state, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def input_rows(det: Detections, state: tuple[np.ndarray, ...]) -> np.ndarray:
    """`bank.INPUT_COLUMNS` rows (..., 15) of a detector frame ``det`` and the UAVs' own state
    (position, yaw, velocity, yaw rate), arrays with the same leading axes: what `input_row`
    reads from each UAV's info (`infos.sensor_infos`), without the dicts (one compiled call)."""
    lead = det.detected.shape
    return input_rows_of(*_flat_frame(det, state)).reshape(*lead, 15)


def _flat_frame(det: Detections, state: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """`input_rows_of`'s arrays of a frame: its leading axes flattened into one."""
    arrays = (det.detected, det.u, det.v, det.depth, det.psi, det.truncated, *state)
    lead = len(det.detected.shape)
    if lead == 1:  # one team: the arrays as they are
        return arrays
    return tuple(np.ascontiguousarray(a).reshape(-1, *a.shape[lead:]) for a in arrays)


def _step_alone(tracker: OnboardTracker, row: np.ndarray) -> None:
    """One plain-filterpy tracker's step (`TargetEstimator.reset`/`step`) from its
    `bank.INPUT_COLUMNS` row."""
    x, y, z, yaw, vx, vy, vz, yaw_rate, detected, u, v, depth, psi, cut_u, cut_v = row.tolist()
    pos = np.array((x, y, z))
    meas = None
    if detected > 0.5:
        meas = Measurement.trusted(u, v, depth, psi, cut_u > 0.5, cut_v > 0.5)
    est = tracker.estimator
    if tracker._estimate is None:
        if meas is not None:
            tracker._estimate = est.reset(meas, pos, yaw)
        return
    # The UAV's own velocity (IMU/odometry) in the camera frame, as applied over the step.
    cx, cy, cz = world_to_cam_vec(np.array((vx, vy, vz)), yaw).tolist()
    u_meas = np.array((cx, cy, cz, -yaw_rate))
    tracker._estimate = est.step(u_meas, pos, yaw, meas)


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
        self._bound = False

    def bind(self, p: np.ndarray, v: np.ndarray, v_err: np.ndarray, age: np.ndarray,
             known: np.ndarray) -> None:  # fmt: skip
        """Keep the table in these arrays (a `TeamState` slot's: (k, 3), (k, 3), (k,), (k,)
        int64, (k,) bool), which `reset` fills in place."""
        self._pos, self._vel, self._vel_err, self._age, self._known = p, v, v_err, age, known
        self._bound = True

    def reset(self, names: list[str], positions: np.ndarray, own: str, r_c: float) -> None:
        """A new episode: the team ``names`` at ``positions`` (n, 3); ``own`` is this UAV."""
        positions = np.asarray(positions, float).reshape(-1, 3)
        me = names.index(own)
        keep = [k for k in range(len(names)) if k != me]
        self._names = [names[k] for k in keep]
        self._ids = keep
        self._index = {a: k for k, a in enumerate(self._names)}
        self._all = (tuple(self._names), tuple(keep))
        if not self._bound:
            k = len(keep)
            self._pos, self._vel = np.zeros((k, 3)), np.zeros((k, 3))
            self._vel_err, self._age = np.zeros(k), np.zeros(k, np.int64)
            self._known = np.zeros(k, bool)
        elif len(self._age) != len(keep):
            raise ValueError(
                f"this table holds {len(self._age)} team-mates, the team {names} has {len(keep)}"
            )
        self._pos[:] = positions[keep]
        self._vel[:] = 0.0
        self._vel_err[:] = 0.0
        self._age[:] = 0
        self._known[:] = np.linalg.norm(self._pos - positions[me], axis=1) <= r_c

    def member(self, name: str) -> int | None:
        """Team-mate ``name``'s index in the team (None: not a team-mate of this table)."""
        k = self._index.get(name)
        return None if k is None else self._ids[k]

    def update(self, messages: dict[str, np.ndarray]) -> None:
        """Take this step's messages (team-mate -> position); the others age by one step."""
        take_messages(*self._messages(messages), *self._state(), self.timeout)

    def take(self, messages: dict[str, np.ndarray]) -> NeighbourBelief:
        """`update` with this step's messages, then the `belief` (one compiled call)."""
        return self.wrap(
            take_and_believe(
                *self._messages(messages), *self._state(), self.timeout, self._believe_accel
            )
        )

    def belief(self) -> NeighbourBelief:
        """The known team-mates now."""
        return self.wrap(
            believe(
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

    def wrap(self, believed: tuple) -> NeighbourBelief:
        """A `NeighbourBelief` from `onboard_pass.believe`'s arrays."""
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


class OnboardAgent:
    """One UAV's onboard stack (UKF, team-mates' messages, known map, CBF-QP (47)).

    Call `reset` with each new layout (the one place a new map arrives), then `observe` with the
    agent's ``info`` after every env reset/step; `rows` and `certify` use the latest observation.
    R_s and R_c come from the world (`EnvConfig.violations.r_s`, `EnvConfig.comms.r_c`) with the
    config's margins; under the env's 'lag' dynamics and ``lag_aware`` the rows are second order
    and respect the acceleration bound (`ShieldOptions.lag_tau` = ``dynamics.tau``,
    ``accel_bound`` = ``dynamics.a_max``). What this guarantees: docs/safety.md.

    What the agent remembers between steps lives in slot ``slot`` of ``team`` (a `TeamState`
    its team shares, `onboard_team`; None: one of its own), so that `observe_team` takes a
    whole team's step in one compiled pass (`onboard_pass.observe_pass`).
    """

    def __init__(
        self,
        name: str,
        index: int,
        env_config: EnvConfig,
        config: ExpertConfig,
        tracker: OnboardTracker | None = None,
        team: TeamState | None = None,
        slot: int | None = None,
    ) -> None:
        self.name, self.index, self.config = name, index, config
        margins = config.margins
        cbf = config.cbf.resolve(
            env_config.violations.r_s, env_config.comms.r_c, env_config.uav_radius
        )
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
        self._car_speed = car_speed = (
            fastest if margins.target_speed_max is None else margins.target_speed_max
        )
        self._recovery = round(margins.truncation_recovery / DT)
        table = self.neighbours
        self._pass_params = (
            np.array((DT, table.accel_bound or 0.0, table.speed_bound, table.timeout,
                      table._believe_accel)),
            np.array((margins.target_margin, margins.target_sigmas, margins.target_margin_max,
                      margins.target_stale_after, margins.car_on_ground, car_speed, DT,
                      self._recovery, margins.truncated_box_pad)),
            *self.filter.row_builder.pass_params(),
        )  # fmt: skip
        """`observe_pass`'s table_p, box_p, row_p, flags, gammas and margins."""
        self.team, self.slot = team, index if slot is None else slot
        self._own_team = team is None
        """No team was given: the agent keeps a `TeamState` of its own, made anew for a team of
        another size."""
        if team is not None:
            self._bind()
        self.obstacle_centers = np.zeros((0, 3))
        self.obstacle_half_extents = np.zeros((0, 3))
        self.info: dict | None = None
        """The latest info observed (None where the step came as arrays: `observe_arrays`)."""
        self._seen: tuple | None = None
        """The last `observe_pass`'s outputs and this agent's row in them."""
        self._belief: NeighbourBelief | None = None
        self._context: SafetyContext | None = None
        self._rows: CBFRows | None = None

    def _bind(self) -> None:
        team, s = self.team, self.slot
        self.neighbours.bind(team.nb_p[s], team.nb_v[s], team.nb_err[s], team.nb_age[s],
                             team.nb_known[s])  # fmt: skip

    @property
    def estimate(self) -> Estimate | None:
        """The UKF's target estimate (None until the car was first detected)."""
        return self.tracker.estimate

    @property
    def belief(self) -> NeighbourBelief | None:
        """The team-mates as believed at the latest observation (None before one)."""
        if self._belief is None and self._seen is not None:
            out, j = self._seen
            bi, bf = out.belief_ints[j], out.belief_floats[j]
            k = int(bi[0])
            motion, radii = bf[: 6 * k].reshape(2, k, 3), bf[6 * k : 8 * k].reshape(2, k)
            self._belief = self.neighbours.wrap((bi[1 : 1 + 2 * k].reshape(2, k), motion, radii))
        return self._belief

    def reset(self, layout: Layout, agents: list[str]) -> None:
        """A new episode on ``layout`` (its known obstacle map); ``agents`` names the team in
        index order. Forgets the estimate and the neighbours' histories."""
        if self.team is None or self.team.n != len(agents):
            if not self._own_team:
                raise ValueError(
                    f"{self.name}: its team's state (onboard_team) holds teams of {self.team.n} "
                    f"UAVs, got the team {agents}; build the team's stacks for this team anew"
                )
            self.team, self.slot = TeamState(len(agents)), agents.index(self.name)
            self._bind()
        self.obstacle_centers = np.asarray(layout.obstacle_centers, float).reshape(-1, 3)
        self.obstacle_half_extents = np.asarray(layout.obstacle_half_extents, float).reshape(-1, 3)
        team, s = self.team, self.slot
        team.set_map(s // team.n, self.obstacle_centers, self.obstacle_half_extents)
        team.uncut[s], team.cut_steps[s], team.has_anchor[s] = self._recovery, 0, False
        self.tracker.reset()
        self.neighbours.reset(agents, layout.uav_positions, self.name, self._r_c)
        self.info, self._seen = None, None
        self._belief, self._context, self._rows = None, None, None

    def observe(self, info: dict) -> Estimate | None:
        """Take this step's ``info`` (measurement, own state, messages); returns the estimate."""
        observe_team([self], [info])
        return self.tracker.estimate

    def context(self) -> SafetyContext:
        """The CBF-QP's view of the latest observation: own pose and velocity, the team-mates
        as believed (and, for second-order rows, their velocities), the known obstacles, the
        car's box (`car_box`)."""
        if self._context is None:
            if self._seen is None:
                raise RuntimeError(
                    f"{self.name}: no observation yet; call observe(info) after reset"
                )
            out, j = self._seen
            belief, own, box = self.belief, out.data[j], out.box[j]
            if not self.tracker.has_estimate:  # no estimate: no target rows
                target: dict = {
                    "target_velocity": np.zeros(3),
                    "target_half_extents": np.array(CAR_HALF_EXTENTS, float),
                    "target_heading": 0.0,
                }
            else:
                target = {
                    "target_position": box[0:3],
                    "target_velocity": box[3:6],
                    "target_half_extents": box[6:9],
                    "target_heading": 0.0,
                    "target_growth": box[9:12],
                    "target_frustum": bool(box[12]),
                }
            # The pass's input rows, the env's own values, float64 and finite: no re-validation.
            self._context = SafetyContext.trusted(
                position=own[0:3],
                yaw=float(own[3]),
                velocity=own[4:7],
                neighbours=belief.positions,
                neighbour_velocities=belief.velocities if self._lag else None,
                neighbour_radius=belief.position_radius,
                neighbour_velocity_radius=belief.velocity_radius if self._lag else None,
                obstacle_centers=self.obstacle_centers,
                obstacle_half_extents=self.obstacle_half_extents,
                neighbour_ids=belief.ids,
                own_id=self.index,
                **target,
            )
        return self._context

    def rows(self) -> CBFRows:
        """The CBF rows of the latest observation (`observe_pass` built them; equal to
        ``self.filter.rows(self.context())``)."""
        if self._rows is None:
            if self._seen is None:
                self.context()  # raises: no observation yet
            out, j = self._seen
            self._rows = out.rows(j)
        return self._rows

    def certify(self, u_nominal: np.ndarray) -> tuple[np.ndarray, ShieldReport]:
        """The safe camera-frame command (SI units) closest to ``u_nominal``, and a report
        (`SafetyFilter.certify` on this UAV's context and rows; a finite (4,) command goes the
        unchecked way, `certify_trusted`, with the same result)."""
        u = np.asarray(u_nominal, dtype=float)
        if u.shape == (4,) and math.isfinite(u.sum()):
            return self.certify_trusted(u)
        return self.filter.certify(u_nominal, self.context(), self.rows())  # its clear errors

    def certify_trusted(self, u: np.ndarray) -> tuple[np.ndarray, ShieldReport]:
        """`certify` without checks (`SafetyFilter.certify_trusted`)."""
        rows = self.rows()
        out, j = self._seen
        own = out.data[j]
        done = self.filter.certify_pose(u, float(own[3]), own[4:7], rows, self.neighbour_ids())
        if done[1].status != "fallback" and not self.filter.may_climb_over_occluders(done[1]):
            return done  # no context to build
        return self.filter.settle(u, self.context(), done)

    def neighbour_ids(self, known: int | None = None) -> tuple[int, ...]:
        """The team indices of the team-mates believed at the latest observation (they name
        the rows: 'uav:<id>'); ``known``: how many, if the caller has read it from the pass."""
        if known is None and self._seen is not None:
            known = int(self._seen[0].belief_ints[self._seen[1], 0])
        everyone = self.neighbours._all[1]
        return everyone if known == len(everyone) else self.belief.ids


def certify_team(agents: Sequence[OnboardAgent], u: np.ndarray) -> Certificates:
    """`OnboardAgent.certify_trusted` of ``u[j]`` (m, 4) for each of m agents with one
    configuration (`SafetyFilter.certify_many`: one compiled call); the reports are made when
    read (`Certificates.report`)."""
    seen = [agent._seen for agent in agents]
    out, shield = seen[0][0], agents[0].filter
    js = [j for pass_out, j in seen if pass_out is out]
    if len(js) == len(agents):  # one pass: its arrays as they are
        if js == list(range(len(out.data))):  # all of the pass, in its order
            data, lows, begin, end = out.data, out.lows, out.start[:-1], out.start[1:]
            known = out.belief_ints[:, 0].tolist()
        else:
            at = np.array(js)
            data, lows, begin, end = out.data[at], out.lows[at], out.start[at], out.start[at + 1]
            known = out.belief_ints[at, 0].tolist()
        ids = [a.neighbour_ids(k) for a, k in zip(agents, known, strict=True)]
        packed = (out.A, out.floats[0], out.ints[0], out.floats[1], begin, end)
        done = shield.certify_many(
            u, data[:, 3], data[:, 4:7], lambda j: out.rows(js[j]), ids, packed
        )
        done.lows, done.rows_at = lows, (out.ints[0], out.ints[1], begin)
        return _settle(agents, u, done)
    ids = [agent.neighbour_ids() for agent in agents]
    own = np.array([agent._seen[0].data[agent._seen[1]] for agent in agents]).reshape(-1, 15)
    done = shield.certify_many(u, own[:, 3], own[:, 4:7], [a.rows() for a in agents], ids)
    return _settle(agents, u, done)


def _settle(agents: Sequence[OnboardAgent], u: np.ndarray, done: Certificates) -> Certificates:
    """`SafetyFilter.settle` for the agents whose certificate is a fallback or may climb over
    an occluder (`SafetyFilter.may_climb_over_occluders`; the others' certificates unchanged)."""
    retry = np.flatnonzero(done.fallback).tolist()
    for j in np.flatnonzero(done.relaxed).tolist():
        shield = agents[j].filter
        if shield.climbs_over_occluders and shield.may_climb_over_occluders(done.report(j)):
            retry.append(j)
    if not retry:
        return done
    action, reports = done.action.copy(), done.reports()
    for j in retry:
        agent = agents[j]
        action[j], reports[j] = agent.filter.settle(u[j], agent.context(), (action[j], reports[j]))
    return Certificates.of_reports(action, reports)


def onboard_team(
    names: Sequence[str], env_config: EnvConfig, config: ExpertConfig, worlds: int = 1
) -> list[list[OnboardAgent]]:
    """The onboard stacks of ``worlds`` teams ``names`` (one list per world), their target
    filters in one `TrackerBank` and their memories in one `TeamState` (`observe_team` steps
    them in two compiled calls)."""
    n, camera, ukf = len(names), env_config.camera, config.ukf
    bank = TrackerBank(n * worlds, camera, ukf) if ukf.vectorized else None
    team = TeamState(n, worlds)
    return [
        [
            OnboardAgent(a, i, env_config, config, OnboardTracker(camera, ukf, bank, s), team, s)
            for i, a in enumerate(names)
            for s in (k * n + i,)
        ]
        for k in range(worlds)
    ]


def observe_team(agents: Sequence[OnboardAgent], infos: Sequence[dict]) -> None:
    """`OnboardAgent.observe` for several UAVs (`observe_arrays` of their infos, per
    `TeamState`)."""
    groups: dict[int, list[int]] = {}
    for j, agent in enumerate(agents):
        groups.setdefault(id(agent.team), []).append(j)
    for members in groups.values():
        team = agents[members[0]].team
        heard, sent = np.zeros((len(members), team.n), bool), np.zeros((team.worlds, team.n, 3))
        for row, j in enumerate(members):
            agent = agents[j]
            table, w = agent.neighbours, agent.slot // team.n
            for name, pos in infos[j]["neighbours"].items():
                i = table.member(name)
                if i is not None:
                    heard[row, i], sent[w, i] = True, pos
        data = np.array([input_row(infos[j]) for j in members], float).reshape(-1, 15)
        observe_arrays([agents[j] for j in members], data, heard, sent, [infos[j] for j in members])


def observe_arrays(
    agents: Sequence[OnboardAgent],
    data: np.ndarray,
    heard: np.ndarray,
    sent: np.ndarray,
    infos: Sequence[dict] | None = None,
) -> None:
    """What several UAVs take from a step: agent j's `bank.INPUT_COLUMNS` row ``data[j]``
    (`input_rows`) and the messages it heard, ``heard[j, i]`` from team member i, whose
    message carries ``sent[w, i]`` (the positions of world w's team, w = slot // team size).
    Their UKFs step in one batched pass, then everything else (messages, cut boxes, the car's
    box, the CBF rows) in one `observe_pass` per `TeamState`; both in one compiled call
    (`observe_step`) when the agents are one team whose trackers share a bank slot for slot.
    ``infos``: the infos the rows came from (``agent.info``), if any."""
    if _one_bank(agents):
        _fused_step(agents, data, heard, sent, infos, observe_step)
        return
    update_trackers([a.tracker for a in agents], data)
    groups: dict[int, list[int]] = {}
    for j, agent in enumerate(agents):
        groups.setdefault(id(agent.team), []).append(j)
    for members in groups.values():
        pick = members if len(members) < len(agents) else slice(None)
        _observe_pass(
            [agents[j] for j in members], data[pick], heard[pick], sent,
            None if infos is None else [infos[j] for j in members],
        )  # fmt: skip


def observe_frame(
    agents: Sequence[OnboardAgent],
    det: Detections,
    state: tuple[np.ndarray, ...],
    uavs: np.ndarray,
    received: np.ndarray,
    sent: np.ndarray,
    infos: Sequence[dict] | None = None,
) -> None:
    """`observe_arrays` of the UAVs ``uavs`` of a frame: a detector frame ``det``, the UAVs'
    own ``state`` (their input rows: `input_rows`) and the messages ``received`` (the
    frame's leading axes, then one flag per team member), ``uavs`` being flat indices over
    those leading axes (world n + index). The rows are built in the same compiled call
    (`observe_frame_step`) where `observe_arrays` takes one."""
    uavs = np.asarray(uavs, np.int64)
    heard = received.reshape(-1, received.shape[-1])
    if not _one_bank(agents):
        rows = input_rows(det, state).reshape(-1, len(INPUT_COLUMNS))
        observe_arrays(agents, rows[uavs], heard[uavs], sent, infos)
        return
    data = np.empty((len(uavs), len(INPUT_COLUMNS)))
    frame = _flat_frame(det, state)
    _fused_step(agents, data, heard, sent, infos, observe_frame_step, uavs, frame)


def _one_bank(agents: Sequence[OnboardAgent]) -> bool:
    """The agents are of one team, their trackers of one bank, slot for slot (`observe_step`)."""
    team, bank = agents[0].team, agents[0].tracker.bank
    if bank is None:
        return False
    for a in agents:
        if a.team is not team or a.tracker.bank is not bank or a.tracker.slot != a.slot:
            return False
    return True


def _fused_step(
    agents: Sequence[OnboardAgent],
    data: np.ndarray,
    heard: np.ndarray,
    sent: np.ndarray,
    infos: Sequence[dict] | None,
    kernel: Any,
    *lead: Any,
) -> None:
    """``kernel(*lead, slots, team_n, data, heard, sent, ...)``: `observe_step`'s arguments for
    `_one_bank` agents; the bank and the agents then take its outputs."""
    team, bank = agents[0].team, agents[0].tracker.bank
    slots, outputs = bank.prepare([a.slot for a in agents], data)
    out = PassOutput.allocate(data, team.n - 1, team.obs_c.shape[1])
    kernel(
        *lead, slots, team.n, data, heard, sent, bank.kernel_args, *outputs, team.arrays(),
        agents[0]._pass_params, out[1:],
    )  # fmt: skip
    bank.estimates.set(slots.tolist(), outputs, bank._ready)
    _take_pass(agents, out, infos)


def _observe_pass(
    agents: list[OnboardAgent],
    data: np.ndarray,
    heard: np.ndarray,
    sent: np.ndarray,
    infos: list[dict] | None,
) -> None:
    """`observe_pass` for UAVs of one `TeamState` whose trackers have taken the step."""
    team = agents[0].team
    slots = np.array([a.slot for a in agents], np.int64)
    out = PassOutput.allocate(data, team.n - 1, team.obs_c.shape[1])
    observe_pass(
        slots, team.n, data, heard, sent, *_estimate_arrays(agents), *team.arrays(),
        *agents[0]._pass_params, *out[1:],
    )  # fmt: skip
    _take_pass(agents, out, infos)


def _take_pass(agents: Sequence[OnboardAgent], out: PassOutput, infos: Sequence[dict] | None):
    """Agent j's latest observation is row j of the pass ``out`` (and ``infos[j]``)."""
    for j, agent in enumerate(agents):
        agent.info, agent._seen = None if infos is None else infos[j], (out, j)
        agent._belief, agent._context, agent._rows = None, None, None


def _estimate_arrays(agents: list[OnboardAgent]) -> tuple:
    """`observe_pass`'s estimate inputs (est_slots, x, P, ready, counts): the state arrays of
    the agents' `TrackerBank`, or, for trackers outside one bank, arrays of their estimates."""
    bank = agents[0].tracker.bank
    if bank is not None and all(a.tracker.bank is bank for a in agents):
        slots = np.array([a.tracker.slot for a in agents], np.int64)
        return slots, bank._x, bank._P, bank._ready, bank._counts
    m = len(agents)
    x, P = np.zeros((m, 10)), np.zeros((m, 10, 10))
    ready, counts = np.zeros(m, bool), np.zeros((m, 2), np.int64)
    for j, agent in enumerate(agents):
        est = agent.tracker.estimate
        if est is not None:
            x[j] = np.concatenate((est.s, est.target_position, est.target_velocity))
            P[j], ready[j], counts[j, 0] = est.covariance, True, est.steps_since_detection
    return np.arange(m), x, P, ready, counts


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
    out = np.empty(BOX_COLUMNS)
    P = est.covariance
    has_anchor = anchor is not None
    A = anchor.covariance if has_anchor else P
    params = np.array(
        (margins.target_margin, margins.target_sigmas, margins.target_margin_max,
         margins.target_stale_after, margins.car_on_ground, car_speed, DT)
    )  # fmt: skip
    car_box_arrays(
        est.target_position, est.target_velocity, np.array((P[4, 4], P[5, 5], P[6, 6])),
        est.steps_since_detection, (anchor if has_anchor else est).target_position,
        np.array((A[4, 4], A[5, 5], A[6, 6])), has_anchor, float(cut_time[0]),
        float(cut_time[1]), params, out,
    )  # fmt: skip
    return CarBox(out[0:3], out[3:6], out[6:9], out[9:12], bool(out[12]))
