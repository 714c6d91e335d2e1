"""Adversary harness for `CBFShield`: hostile policy families and a search, shielded vs not.

    python -m baselines.shield_adversary --workers 2 --out runs/adv   # 60 worlds x 200 steps

Every adversary *family* (a factory ``make(env, rng) -> policy(obs, infos) -> {agent: action}``,
normalised camera-frame actions [v_cx, v_cy, v_cz, omega_cy] in [-1, 1]^4, X right, Y down, Z
forward) runs shielded (``CBFShield(env, preset)``) and unshielded on the same seeded random
worlds: the grid n in {3, 6, 10} x dynamics in {integrator, lag} x comms drop in {0, 0.5}
(``--team-sizes``, ``--drops``: other n and drops), with detector dropouts (0.2) and
``terminate_on_collision="agent"``. An adversary is a test tool: it may read ``info["truth"]``
and ``env.unwrapped.layout``; the shield never does.

The ``cem`` family is a search: the cross-entropy method over open-loop, piecewise-constant action
sequences (`SearchOptions.knots` knots per agent) that minimises the least barrier margin of the
closed loop (`barrier_margin`), every candidate on the same world seed; it runs on the first
``--search-worlds`` worlds (default 12: one per grid cell), searching shielded and unshielded apart.

``--obstacles MIN MAX`` and ``--corridor M`` make the worlds denser than the default random
world (8-16 obstacles, 2.5 m of free corridor along the car's path); ``--car-speed MIN MAX``
and ``--start-offset M`` set the car's cruise speed (0.3-1 m/s) and how far from formation the
UAVs start (0.2 m).

Prints and writes OUT/report.md (violations per million agent-steps by kind, least true
clearances, per grid cell totals, shield statuses, failing shielded runs), OUT/metrics.json
(every run and the tables) and OUT/config.json (`uavtrack_env.provenance.config_record`).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import multiprocessing
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from uavtrack_env import uavtrack_v0
from uavtrack_env.config import RandomWorldConfig
from uavtrack_env.geometry import world_to_cam_vec
from uavtrack_env.presets import (
    DEFAULT_PRESET,
    ExpertConfig,
    add_preset_arguments,
    expert_config_from,
)
from uavtrack_env.provenance import cli_command, config_record
from uavtrack_env.runner import run_episode
from uavtrack_env.target import CAR_HALF_EXTENTS

Policy = Callable[[dict, dict], dict[str, np.ndarray]]
"""``policy(obs, infos) -> {agent: normalised action (4,)}`` for every live agent."""
Factory = Callable[[Any, np.random.Generator], Policy]
"""``make(env, rng) -> policy``: one adversary family, built fresh for each episode."""

CONSTRAINTS = ("uav", "obstacle", "car", "ground", "link")
"""Barrier margins: nearest UAV - R_s, obstacle clearance, car clearance, altitude - radius,
R_c - the longest link the team's connectivity needs."""
KINDS = ("collision", "uav", "obstacle", "ground", "car", "disconnection", "occlusion")
"""Violation counters: any collision, then by kind, then the broken-link steps and the steps
with the car occluded (soft: not a failure of the shield)."""
CONTACT_KEYS = {"uav": "uav", "obstacle": "obstacle", "ground": "ground", "car": "target"}
"""Violation kind -> key of ``info["collision_with"]``."""
GRID_N = (3, 6, 10)
GRID_DYNAMICS = ("integrator", "lag")
GRID_DROP = (0.0, 0.5)
SEARCH_FAMILY = "cem"


# ------------------------------------------------------------------------------ options
@dataclass(frozen=True)
class SearchOptions:
    """The cross-entropy search over open-loop, piecewise-constant action sequences."""

    population: int = 12
    """Candidates per iteration."""
    iterations: int = 3
    """CEM iterations."""
    elite: int = 3
    """Best candidates the next sampling distribution is fitted to."""
    knots: int = 8
    """Constant pieces per agent over the episode."""
    init_std: float = 1.0
    """Initial standard deviation of every action entry (mean 0; samples clipped to [-1, 1])."""
    min_std: float = 0.05
    """Floor added to the elites' standard deviation (keeps exploring)."""


@dataclass(frozen=True)
class MarginScales:
    """Each barrier margin is divided by its scale (m) before the least one is taken."""

    uav: float = 1.0
    obstacle: float = 1.0
    car: float = 1.0
    ground: float = 1.0
    link: float = 1.0


@dataclass(frozen=True)
class HarnessOptions:
    """What the harness runs (the CLI's options)."""

    worlds: int = 60
    """Seeded random worlds, spread round-robin over the 12 grid cells."""
    steps: int = 200
    """Steps per episode (80 Hz; 2.5 s: a full-command UAV crosses 25 m, more than R_c). At
    400 steps (5 s) the default run would take about 50 min of two cores; at 200 about 25."""
    preset: str = DEFAULT_PRESET
    """The shield's preset (`uavtrack_env.presets`)."""
    overrides: tuple[str, ...] = ()
    """``--set FIELD=VALUE`` assignments on the preset."""
    families: tuple[str, ...] = ()
    """Families to run (empty: every family, with the search unless ``search`` is False)."""
    search: bool = True
    """Run the CEM search family."""
    search_worlds: int = 12
    """The search runs on the first this-many worlds only (12: one per grid cell; it costs
    ``population x iterations`` episodes a world)."""
    out: Path = Path("runs/shield_adversary")
    seed: int = 0
    """World k has seed ``seed + k``; the adversaries' generators derive from it too."""
    workers: int = 1
    """Processes (a multiprocessing Pool over (world, family) runs)."""
    progress: bool = True
    search_options: SearchOptions = field(default_factory=SearchOptions)
    scales: MarginScales = field(default_factory=MarginScales)
    n_obstacles: tuple[int, int] | None = None
    """Fewest and most obstacles of a world (None: `RandomWorldConfig.n_obstacles`)."""
    corridor: float | None = None
    """Half-width (m) of the car's path kept free of obstacles (None:
    `RandomWorldConfig.corridor`)."""
    car_speed: tuple[float, float] | None = None
    """Slowest and fastest cruise speed of the car (m/s; None: `RandomWorldConfig.target_speed`)."""
    start_offset: float | None = None
    """UAV start offset from formation (m; None: `RandomWorldConfig.start_offset`)."""
    team_sizes: tuple[int, ...] = GRID_N
    """The grid's team sizes n."""
    drops: tuple[float, ...] = GRID_DROP
    """The grid's message drop probabilities."""

    def random_world(self) -> dict[str, Any]:
        """The ``random_world`` overrides of ``parallel_env`` these options make."""
        out: dict[str, Any] = {}
        if self.n_obstacles is not None:
            out["n_obstacles"] = tuple(self.n_obstacles)
        if self.corridor is not None:
            out["corridor"] = self.corridor
        if self.car_speed is not None:
            out["target_speed"] = tuple(self.car_speed)
        if self.start_offset is not None:
            out["start_offset"] = self.start_offset
        return out

    def grid_worlds(self) -> list[WorldSpec]:
        """The worlds these options run (`make_worlds` over their grid)."""
        return make_worlds(self.worlds, self.seed, self.team_sizes, self.drops)


@dataclass(frozen=True)
class WorldSpec:
    """One seeded random world of the grid."""

    index: int
    n: int
    dynamics: str
    drop: float
    seed: int

    @property
    def cell(self) -> str:
        """The grid cell's label, e.g. ``n6-lag-drop0.5``."""
        return f"n{self.n}-{self.dynamics}-drop{self.drop:g}"


def make_worlds(
    count: int,
    seed: int = 0,
    team_sizes: Sequence[int] = GRID_N,
    drops: Sequence[float] = GRID_DROP,
) -> list[WorldSpec]:
    """``count`` worlds: world k in grid cell k mod the cells (n, dynamics, drop; 12 by default),
    seed ``seed + k``."""
    cells = list(itertools.product(team_sizes, GRID_DYNAMICS, drops))
    return [WorldSpec(k, *cells[k % len(cells)], seed + k) for k in range(count)]


def make_env(
    world: WorldSpec,
    steps: int,
    shield: ExpertConfig | None,
    random_world: dict[str, Any] | None = None,
) -> Any:
    """The world's env (``terminate_on_collision="agent"``; ``random_world``: overrides of its
    `RandomWorldConfig`, e.g. ``HarnessOptions.random_world()``), in `CBFShield` unless
    ``shield`` is None."""
    env = uavtrack_v0.parallel_env(
        scenario="random",
        n_uavs=world.n,
        max_cycles=steps,
        dynamics={"model": world.dynamics},
        comms={"drop_prob": world.drop},
        detector={"dropout_prob": 0.2},
        terminate_on_collision="agent",
        random_world=random_world or {},
    )
    if shield is None:
        return env
    from uavtrack_env.wrappers import CBFShield

    return CBFShield(env, shield)


# ----------------------------------------------------------------------------- families
def _to_box(v: np.ndarray) -> np.ndarray:
    """Scale a direction so its largest entry is +-1 (the fastest command along it)."""
    return v / max(float(np.abs(v).max()), 1e-9)


def _towards(info: dict, goal: np.ndarray, yaw_rate: float) -> np.ndarray:
    """Normalised action flying at full command from the UAV towards ``goal`` (world)."""
    d = np.asarray(goal, float) - info["own"]["position"]
    if not np.any(d):
        d = np.array([0.0, 0.0, -1.0])
    return np.r_[_to_box(world_to_cam_vec(d, info["own"]["yaw"])), yaw_rate]


def _team(env: Any, infos: dict, agent: str) -> np.ndarray:
    """Positions (k, 3) of the other live agents."""
    return np.array([infos[b]["own"]["position"] for b in env.agents if b != agent]).reshape(-1, 3)


def _goal(mode: str, env: Any, infos: dict, agent: str) -> np.ndarray:
    """A seeker's goal point: nearest UAV, nearest obstacle point, the car, the ground, or away
    from the team's centroid (``flee``); modes without a goal fall back to the ground."""
    p = infos[agent]["own"]["position"]
    others = _team(env, infos, agent)
    layout = env.unwrapped.layout
    if mode == "uav" and len(others):
        return others[np.argmin(np.linalg.norm(others - p, axis=1))]
    if mode == "flee" and len(others):
        return 2 * p - others.mean(axis=0)
    if mode == "obstacle" and len(layout.obstacle_centers):
        c, h = layout.obstacle_centers, layout.obstacle_half_extents
        closest = np.clip(p, c - h, c + h)
        return closest[np.argmin(np.linalg.norm(closest - p, axis=1))]
    if mode in ("car", "obstacle"):
        return infos[agent]["truth"]["target_position"]
    return p - [0.0, 0.0, 10.0]


def _signs(env: Any, rng: np.random.Generator) -> dict[str, float]:
    """A random yaw direction (+-1) per agent."""
    return {a: float(rng.choice([-1.0, 1.0])) for a in env.possible_agents}


def seeker(mode: str) -> Factory:
    """Each UAV flies at full command towards its ``mode`` goal while yawing at full rate."""

    def make(env: Any, rng: np.random.Generator) -> Policy:
        spin = _signs(env, rng)

        def policy(_obs: dict, infos: dict) -> dict[str, np.ndarray]:
            return {a: _towards(infos[a], _goal(mode, env, infos, a), spin[a]) for a in env.agents}

        return policy

    return make


def constant(action: Sequence[float]) -> Factory:
    """Every agent holds ``action`` for the whole episode."""
    fixed = np.asarray(action, float)

    def make(env: Any, rng: np.random.Generator) -> Policy:
        return lambda _obs, _infos: {a: fixed.copy() for a in env.agents}

    return make


CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=4)))
"""The 16 corners of the action box."""


def corners(env: Any, rng: np.random.Generator) -> Policy:
    """Agent i holds corner (i + offset) mod 16 of the action box (random offset per world)."""
    offset = int(rng.integers(len(CORNERS)))
    held = {a: CORNERS[(i + offset) % len(CORNERS)] for i, a in enumerate(env.possible_agents)}
    return lambda _obs, _infos: {a: held[a].copy() for a in env.agents}


def bang_bang(period: int) -> Factory:
    """Every ``period`` steps each agent jumps to a new random corner of the action box."""

    def make(env: Any, rng: np.random.Generator) -> Policy:
        state = {"t": 0, "held": {}}

        def policy(_obs: dict, _infos: dict) -> dict[str, np.ndarray]:
            if state["t"] % period == 0:
                picks = rng.integers(len(CORNERS), size=len(env.possible_agents))
                state["held"] = dict(zip(env.possible_agents, CORNERS[picks], strict=True))
            state["t"] += 1
            return {a: state["held"][a].copy() for a in env.agents}

        return policy

    return make


def spin(vertical: float) -> Factory:
    """Full yaw rate (random sign per agent), full forward and full up (-1) or down (+1)."""

    def make(env: Any, rng: np.random.Generator) -> Policy:
        sign = _signs(env, rng)
        return lambda _obs, _infos: {a: np.array([0.0, vertical, 1.0, sign[a]]) for a in env.agents}

    return make


class BlockCar:
    """Each UAV holds a post on the car's path (`posts`), so the car drives at it: ``ahead`` m
    in front of the car's front, ``side`` m beside its centre line, ``height`` m over the
    ground (drawn per agent: 0.2-3, +-1.5, 0.3-1.2; the car is 1.5 m tall). It flies there with
    a command proportional to the distance (full at 1 m) and turns to face the car. Among
    obstacles this pins UAVs between the car and a box (`SafetyFilter.climb_over_car`)."""

    def __init__(self, env: Any, rng: np.random.Generator) -> None:
        self.env = env
        n = len(env.possible_agents)
        self.offsets = np.column_stack(
            [
                CAR_HALF_EXTENTS[0] + rng.uniform(0.2, 3.0, n),
                rng.uniform(-1.5, 1.5, n),
                rng.uniform(0.3, 1.2, n),
            ]
        )
        """(n, 3): each agent's ahead, side and height (m)."""

    def posts(self, infos: dict) -> dict[str, np.ndarray]:
        """Each live agent's post (world, m) at the car's pose in ``infos``."""
        raw = self.env.unwrapped
        c, s = math.cos(raw.target.heading), math.sin(raw.target.heading)
        out = {}
        for i, a in enumerate(raw.possible_agents):
            if a in infos:
                ahead, side, height = self.offsets[i]
                x, y, _ = infos[a]["truth"]["target_position"]
                out[a] = np.array([x + ahead * c - side * s, y + ahead * s + side * c, height])
        return out

    def __call__(self, _obs: dict, infos: dict) -> dict[str, np.ndarray]:
        posts, out = self.posts(infos), {}
        for a in self.env.agents:
            own = infos[a]["own"]
            d = world_to_cam_vec(posts[a] - own["position"], own["yaw"])
            to_car = infos[a]["truth"]["target_position"] - own["position"]
            turn = math.atan2(to_car[1], to_car[0]) - own["yaw"]
            turn = math.atan2(math.sin(turn), math.cos(turn))
            out[a] = np.clip(np.r_[d, -turn], -1.0, 1.0)  # omega_cy = -(world yaw rate)
        return out


class BlockAndPress(BlockCar):
    """`BlockCar` for the even-numbered agents; each odd-numbered one flies at full command to
    0.5 m above the even one before it (while it lives) and so presses it down, towards the
    car and the ground, from R_s away: a team-mate that never yields."""

    def __call__(self, obs: dict, infos: dict) -> dict[str, np.ndarray]:
        out = super().__call__(obs, infos)
        names = self.env.unwrapped.possible_agents
        for i in range(1, len(names), 2):
            a, below = names[i], names[i - 1]
            if a in out and below in infos:
                goal = infos[below]["own"]["position"] + np.array([0.0, 0.0, 0.5])
                out[a] = _towards(infos[a], goal, out[a][3])
        return out


def random_held(env: Any, rng: np.random.Generator) -> Policy:
    """Each agent holds a uniform action in [-1, 1]^4 for a random 1-40 steps, then redraws."""
    held: dict[str, tuple[np.ndarray, int]] = {}

    def policy(_obs: dict, _infos: dict) -> dict[str, np.ndarray]:
        out = {}
        for a in env.agents:
            action, left = held.get(a, (np.zeros(4), 0))
            if left <= 0:
                action, left = rng.uniform(-1.0, 1.0, 4), int(rng.integers(1, 41))
            held[a] = (action, left - 1)
            out[a] = action.copy()
        return out

    return policy


def mixed(env: Any, rng: np.random.Generator) -> Policy:
    """Each agent follows a different family (a random permutation of `MIXABLE`)."""
    names = [MIXABLE[k] for k in rng.permutation(len(MIXABLE))]
    pick = {a: names[i % len(names)] for i, a in enumerate(env.possible_agents)}
    # in the order of first use, not a set's: the families draw from one generator in turn
    policies = {name: FAMILIES[name](env, rng) for name in dict.fromkeys(pick.values())}

    def policy(obs: dict, infos: dict) -> dict[str, np.ndarray]:
        proposals = {name: p(obs, infos) for name, p in policies.items()}
        return {a: proposals[pick[a]][a] for a in env.agents}

    return policy


def _axis_families() -> dict[str, Factory]:
    """``const-vx+``, ``const-vx-`` ... ``const-wy-``: one axis at +-1, the others 0."""
    out = {}
    for k, axis in enumerate(("vx", "vy", "vz", "wy")):
        for sign, tag in ((1.0, "+"), (-1.0, "-")):
            action = np.zeros(4)
            action[k] = sign
            out[f"const-{axis}{tag}"] = constant(action)
    return out


FAMILIES: dict[str, Factory] = {
    **_axis_families(),
    "const-corners": corners,
    **{f"bang-bang-{p}": bang_bang(p) for p in (1, 8, 40)},
    "spin-climb": spin(-1.0),
    "spin-dive": spin(1.0),
    **{f"seek-{m}": seeker(m) for m in ("uav", "obstacle", "car", "ground")},
    "flee": seeker("flee"),
    "random-held": random_held,
}
"""Every closed-loop family by name (``mixed``, the search and `AFTER_SEARCH` are added below)."""
MIXABLE = tuple(FAMILIES)
"""The families ``mixed`` draws from."""
FAMILIES["mixed"] = mixed
# ALL_FAMILIES is append-only: a family's generator derives from its index (`family_rng`).
AFTER_SEARCH = {"block-car": BlockCar, "block-and-press": BlockAndPress}
FAMILIES.update(AFTER_SEARCH)
ALL_FAMILIES = (*(f for f in FAMILIES if f not in AFTER_SEARCH), SEARCH_FAMILY, *AFTER_SEARCH)


def sequence_policy(env: Any, knots: np.ndarray, steps: int) -> Policy:
    """Open loop: agent i plays ``knots[i, k]`` (knots (n, K, 4)) during the k-th of K equal
    pieces of ``steps``."""
    ids = {a: i for i, a in enumerate(env.possible_agents)}
    state = {"t": 0}
    pieces = knots.shape[1]

    def policy(_obs: dict, _infos: dict) -> dict[str, np.ndarray]:
        k = min(state["t"] * pieces // max(steps, 1), pieces - 1)
        state["t"] += 1
        return {a: knots[ids[a], k].copy() for a in env.agents}

    return policy


# ---------------------------------------------------------------------------- margins
def link_margin(positions: np.ndarray, r_c: float) -> float:
    """R_c minus the longest edge of the minimum spanning tree of ``positions`` (k, 3): the
    longest link the team's connectivity needs (inf for fewer than two UAVs)."""
    k = len(positions)
    if k < 2:
        return math.inf
    d = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    best = d[0].copy()
    done = np.zeros(k, bool)
    done[0] = True
    longest = 0.0
    for _ in range(k - 1):
        j = int(np.argmin(np.where(done, np.inf, best)))
        longest = max(longest, float(best[j]))
        done[j] = True
        best = np.minimum(best, d[j])
    return r_c - longest


def step_margins(infos: dict, r_s: float, r_c: float, radius: float) -> dict[str, float]:
    """This step's least true margin (m) of every constraint over the agents in ``infos``."""
    if not infos:
        return dict.fromkeys(CONSTRAINTS, math.inf)
    truth = [i["truth"] for i in infos.values()]
    pos = np.array([i["own"]["position"] for i in infos.values()])
    return {
        "uav": min(t["nearest_uav_distance"] for t in truth) - r_s,
        "obstacle": min(t["nearest_obstacle_clearance"] for t in truth),
        "car": min(t["target_clearance"] for t in truth),
        "ground": float(pos[:, 2].min()) - radius,
        "link": link_margin(pos, r_c),
    }


def barrier_margin(margins: dict[str, float], scales: MarginScales) -> float:
    """The least normalised margin (the search's objective: below 0 is a violation)."""
    return min(margins[k] / getattr(scales, k) for k in CONSTRAINTS)


# ------------------------------------------------------------------------------ tally
@dataclass
class EpisodeStats:
    """What one episode did: agent-steps, violation counts, least margins, shield statuses."""

    agent_steps: int = 0
    steps: int = 0
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(KINDS, 0))
    least: dict[str, float] = field(default_factory=lambda: dict.fromkeys(CONSTRAINTS, math.inf))
    statuses: dict[str, int] = field(default_factory=dict)
    objective: float = math.inf
    """The least normalised barrier margin (`barrier_margin`) over the episode."""

    def add(self, infos: dict, margins: dict[str, float], scales: MarginScales) -> None:
        """Count one step's infos (every agent that acted) with its margins."""
        self.steps += 1
        for info in infos.values():
            self.agent_steps += 1
            self.counts["collision"] += bool(info["violations"]["collision"])
            self.counts["disconnection"] += bool(info["violations"]["disconnection"])
            self.counts["occlusion"] += bool(info["violations"]["occlusion"])
            for kind, key in CONTACT_KEYS.items():
                self.counts[kind] += bool(info["collision_with"].get(key, False))
            if "shield" in info:
                status = info["shield"]["status"]
                self.statuses[status] = self.statuses.get(status, 0) + 1
        for k, v in margins.items():
            self.least[k] = min(self.least[k], v)
        self.objective = min(self.objective, barrier_margin(margins, scales))

    @property
    def violations(self) -> int:
        """Collision plus disconnection agent-steps."""
        return self.counts["collision"] + self.counts["disconnection"]


def run_policy(
    env: Any, policy: Policy, seed: int, steps: int, scales: MarginScales
) -> EpisodeStats:
    """One episode of ``policy`` on ``env`` (`uavtrack_env.runner.run_episode`), tallied."""
    raw = env.unwrapped
    cfg = raw.config
    stats = EpisodeStats()

    def on_step(infos: dict) -> None:
        margins = step_margins(infos, cfg.violations.r_s, cfg.comms.r_c, cfg.uav_radius)
        stats.add(infos, margins, scales)

    run_episode(env, policy, seed=seed, steps=steps, on_step=on_step)
    return stats


# ----------------------------------------------------------------------------- search
@dataclass
class SearchResult:
    """The best point a search found, its value and payload, and the best value per iteration."""

    best_x: np.ndarray
    best_value: float
    best_payload: Any
    history: list[float]
    evaluations: int


def cem_minimize(
    f: Callable[[np.ndarray], tuple[float, Any]],
    shape: tuple[int, ...],
    rng: np.random.Generator,
    options: SearchOptions,
) -> SearchResult:
    """Cross-entropy method on [-1, 1]^shape: ``f(x) -> (value, payload)``, lower is better."""
    mean, std = np.zeros(shape), np.full(shape, options.init_std)
    best: tuple[float, np.ndarray, Any] = (math.inf, mean.copy(), None)
    history, evaluations = [], 0
    for _ in range(options.iterations):
        samples = np.clip(mean + std * rng.standard_normal((options.population, *shape)), -1, 1)
        scored = []
        for x in samples:
            value, payload = f(x)
            evaluations += 1
            scored.append(value)
            if value < best[0]:
                best = (value, x.copy(), payload)
        elite = samples[np.argsort(scored, kind="stable")[: options.elite]]
        mean, std = elite.mean(axis=0), elite.std(axis=0) + options.min_std
        history.append(best[0])
    return SearchResult(best[1], best[0], best[2], history, evaluations)


def search_episode(
    env: Any, world: WorldSpec, opts: HarnessOptions, rng: np.random.Generator
) -> tuple[EpisodeStats, SearchResult]:
    """CEM over open-loop knot sequences on ``env`` (every candidate on the world's seed): the
    stats of the worst episode found, and the search's record."""
    shape = (world.n, opts.search_options.knots, 4)

    def evaluate(x: np.ndarray) -> tuple[float, EpisodeStats]:
        stats = run_policy(
            env, sequence_policy(env, x, opts.steps), world.seed, opts.steps, opts.scales
        )
        return stats.objective, stats

    result = cem_minimize(evaluate, shape, rng, opts.search_options)
    return result.best_payload, result


# ----------------------------------------------------------------------------- one run
def family_rng(world: WorldSpec, family: str, base_seed: int) -> np.random.Generator:
    """The adversary's generator for (world, family): the same shielded and unshielded."""
    return np.random.default_rng([base_seed, world.index, ALL_FAMILIES.index(family)])


def run_one(
    world: WorldSpec, family: str, shielded: bool, opts: HarnessOptions, config: ExpertConfig
) -> dict[str, Any]:
    """One (world, family, shielded?) episode (the search for ``cem``) -> a run record."""
    env = make_env(world, opts.steps, config if shielded else None, opts.random_world())
    rng = family_rng(world, family, opts.seed)
    wall = time.perf_counter()
    record: dict[str, Any] = {}
    try:
        if family == SEARCH_FAMILY:
            stats, result = search_episode(env, world, opts, rng)
            record["search"] = {"history": result.history, "evaluations": result.evaluations}
        else:
            stats = run_policy(env, FAMILIES[family](env, rng), world.seed, opts.steps, opts.scales)
    finally:
        env.close()
    record.update(
        world=world.index,
        seed=world.seed,
        cell=world.cell,
        n=world.n,
        dynamics=world.dynamics,
        drop=world.drop,
        family=family,
        shielded=shielded,
        wall_s=time.perf_counter() - wall,
        **dataclasses.asdict(stats),
    )
    return record


def run_task(task: tuple[WorldSpec, str, HarnessOptions, ExpertConfig]) -> list[dict[str, Any]]:
    """A (world, family) task: the shielded and the unshielded run."""
    world, family, opts, config = task
    return [run_one(world, family, s, opts, config) for s in (True, False)]


def run_harness(opts: HarnessOptions, config: ExpertConfig) -> list[dict[str, Any]]:
    """Every (world, family) task, in a Pool of ``opts.workers`` processes (1: in-process)."""
    families = selected_families(opts)
    worlds = opts.grid_worlds()
    # The search first: the longest tasks start early and the workers finish together.
    order = sorted(families, key=lambda f: f != SEARCH_FAMILY)
    tasks = [
        (w, f, opts, config)
        for f in order
        for w in worlds
        if f != SEARCH_FAMILY or w.index < opts.search_worlds
    ]
    bar = tqdm(total=len(tasks), desc="adversary runs", disable=not opts.progress)
    records: list[dict[str, Any]] = []
    if opts.workers <= 1:
        for task in tasks:
            records += run_task(task)
            bar.update()
    else:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(opts.workers) as pool:
            for out in pool.imap_unordered(run_task, tasks):
                records += out
                bar.update()
    bar.close()
    return sorted(
        records, key=lambda r: (r["world"], ALL_FAMILIES.index(r["family"]), r["shielded"])
    )


def selected_families(opts: HarnessOptions) -> list[str]:
    """The families to run, in `ALL_FAMILIES` order; unknown names raise."""
    names = list(opts.families) or [f for f in ALL_FAMILIES if opts.search or f != SEARCH_FAMILY]
    unknown = [f for f in names if f not in ALL_FAMILIES]
    if unknown:
        raise ValueError(f"unknown families {unknown}; families are {list(ALL_FAMILIES)}")
    if not opts.search:
        names = [f for f in names if f != SEARCH_FAMILY]
    return [f for f in ALL_FAMILIES if f in names]


# ----------------------------------------------------------------------------- report
def aggregate(records: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """Sum agent-steps, counts and statuses and take the least margins over ``records``."""
    out: dict[str, Any] = {
        "runs": 0,
        "agent_steps": 0,
        "counts": dict.fromkeys(KINDS, 0),
        "least": dict.fromkeys(CONSTRAINTS, math.inf),
        "statuses": Counter(),
    }
    for r in records:
        out["runs"] += 1
        out["agent_steps"] += r["agent_steps"]
        for k in KINDS:
            out["counts"][k] += r["counts"][k]
        for k in CONSTRAINTS:
            out["least"][k] = min(out["least"][k], r["least"][k])
        out["statuses"].update(r["statuses"])
    out["per_million"] = {
        k: 1e6 * v / out["agent_steps"] if out["agent_steps"] else math.nan
        for k, v in out["counts"].items()
    }
    out["statuses"] = dict(sorted(out["statuses"].items()))
    return out


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The report's tables: per family x (shielded, unshielded), per grid cell (shielded) and
    the failing shielded (family, cell) pairs."""
    families = [f for f in ALL_FAMILIES if any(r["family"] == f for r in records)]
    cells = sorted({(r["n"], r["dynamics"], r["drop"]) for r in records})
    by_family = {
        f: {
            mode: aggregate(r for r in records if r["family"] == f and r["shielded"] == s)
            for mode, s in (("shielded", True), ("unshielded", False))
        }
        for f in families
    }
    by_cell = {
        f"n{n}-{d}-drop{p:g}": aggregate(
            r for r in records if r["shielded"] and (r["n"], r["dynamics"], r["drop"]) == (n, d, p)
        )
        for n, d, p in cells
    }
    failures = sorted(
        {(r["family"], r["cell"]) for r in records if r["shielded"] and _violated(r)},
        key=lambda fc: (ALL_FAMILIES.index(fc[0]), fc[1]),
    )
    return {"families": by_family, "cells": by_cell, "failures": [list(f) for f in failures]}


def _violated(record: dict[str, Any]) -> bool:
    return record["counts"]["collision"] + record["counts"]["disconnection"] > 0


def _num(x: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(x) else f"{x:.{digits}f}"


HEADER = (
    "| {key} | agent-steps | coll/M | uav/M | obst/M | ground/M | car/M | disc/M | occl/M "
    "| min uav-R_s | min obst | min car | min z-r | min R_c-link |"
)


def _row(label: str, agg: dict[str, Any]) -> str:
    rates = " | ".join(_num(agg["per_million"][k], 0) for k in KINDS)
    least = " | ".join(_num(agg["least"][k]) for k in CONSTRAINTS)
    return f"| {label} | {agg['agent_steps']} | {rates} | {least} |"


def _table(key: str, rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    head = HEADER.format(key=key)
    return [head, "|" + "---|" * head.count(" | ") + "---|", *(_row(k, a) for k, a in rows)]


def _density(meta: dict[str, Any]) -> str:
    """How the worlds differ from the default random world, for the report's header, e.g.
    " (24-48 obstacles, corridor 1.5 m)"; empty for the default random worlds."""
    parts = []
    if meta.get("n_obstacles") is not None:
        lo, hi = meta["n_obstacles"]
        parts.append(f"{lo}-{hi} obstacles")
    if meta.get("corridor") is not None:
        parts.append(f"corridor {meta['corridor']:g} m")
    if meta.get("car_speed") is not None:
        lo, hi = meta["car_speed"]
        parts.append(f"car at {lo:g}-{hi:g} m/s")
    if meta.get("start_offset") is not None:
        parts.append(f"starts {meta['start_offset']:g} m off formation")
    return f" ({', '.join(parts)})" if parts else ""


def format_report(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    """The markdown report: family table, grid-cell table, shield statuses, failures."""
    lines = [
        "# CBFShield adversary harness",
        "",
        f"`{meta.get('command', '')}`: {meta.get('worlds', '?')} worlds{_density(meta)} x "
        f"{meta.get('steps', '?')} steps, preset `{meta.get('preset', '?')}`, commit "
        f"`{meta.get('commit', '?')}`, wall {meta.get('wall_s', math.nan):.0f} s.",
        "",
        "Violations per million agent-steps (coll = any collision; uav = closer than R_s; obst, "
        "ground, car = contacts; disc = broken links; occl = the car occluded, a soft "
        "constraint) and the least TRUE margins in m "
        "(nearest UAV - R_s, obstacle, car, altitude - UAV radius, R_c - longest needed link).",
        "",
        "## Per family",
        "",
    ]
    rows = [
        (f"{f} ({mode})", agg)
        for f, modes in summary["families"].items()
        for mode, agg in modes.items()
    ]
    lines += _table("family", rows)
    lines += ["", "## Shielded runs per grid cell (n, dynamics, drop)", ""]
    lines += _table("cell", list(summary["cells"].items()))
    lines += ["", "## Shield statuses (agent-steps)", "", "| family | statuses |", "|---|---|"]
    for f, modes in summary["families"].items():
        st = ", ".join(f"{k}: {v}" for k, v in modes["shielded"]["statuses"].items())
        lines.append(f"| {f} | {st or '-'} |")
    lines += ["", "## Shielded (family, cell) pairs with a violation", ""]
    failures = summary["failures"]
    lines += [f"- {f} in {c}" for f, c in failures] if failures else ["- none"]
    return "\n".join(lines) + "\n"


def _jsonable(value: Any) -> Any:
    """Non-finite floats -> None, recursively (strict JSON)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def write_outputs(
    opts: HarnessOptions,
    config: ExpertConfig,
    records: list[dict[str, Any]],
    command: str,
    wall_s: float,
) -> str:
    """Write OUT/config.json, OUT/metrics.json and OUT/report.md; return the report."""
    opts.out.mkdir(parents=True, exist_ok=True)
    harness = {k: v for k, v in dataclasses.asdict(opts).items() if k != "out"}
    harness["out"] = str(opts.out)
    harness["families"] = selected_families(opts)
    worlds = [dataclasses.asdict(w) for w in opts.grid_worlds()]
    record = config_record(opts.preset, None, config, command, harness=harness, worlds=worlds)
    summary = summarize(records)
    meta = {**harness, "command": command, "commit": record["commit"], "wall_s": wall_s}
    report = format_report(summary, meta)
    (opts.out / "config.json").write_text(json.dumps(_jsonable(record), indent=2) + "\n")
    metrics = {"config": record, "wall_s": wall_s, "summary": summary, "runs": records}
    (opts.out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=1) + "\n")
    (opts.out / "report.md").write_text(report)
    return report


# -------------------------------------------------------------------------------- CLI
def parse_args(argv: list[str] | None = None) -> HarnessOptions:
    """The CLI's options as `HarnessOptions`."""
    d = HarnessOptions()
    p = argparse.ArgumentParser(
        prog="python -m baselines.shield_adversary",
        description=__doc__.split("\n")[0],
    )
    p.add_argument("--worlds", type=int, default=d.worlds, help="seeded random worlds")
    p.add_argument("--steps", type=int, default=d.steps, help="steps per episode (80 Hz)")
    p.add_argument(
        "--families",
        nargs="+",
        default=[],
        metavar="NAME",
        help=f"subset of families (default all): {', '.join(ALL_FAMILIES)}",
    )
    p.add_argument(
        "--search",
        action=argparse.BooleanOptionalAction,
        default=d.search,
        help="run the CEM search family",
    )
    p.add_argument(
        "--search-worlds",
        type=int,
        default=d.search_worlds,
        help="search on the first N worlds only (12: one per grid cell)",
    )
    p.add_argument(
        "--obstacles",
        type=int,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=None,
        help="fewest and most obstacles of a world (default: the random world's, 8 16)",
    )
    p.add_argument(
        "--corridor",
        type=float,
        default=None,
        help="half-width (m) of the car's path kept free of obstacles (default 2.5)",
    )
    p.add_argument(
        "--car-speed",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=None,
        help="the car's cruise speed range (m/s; default: the random world's, 0.3 1.0)",
    )
    p.add_argument(
        "--start-offset",
        type=float,
        default=None,
        help="UAV start offset from formation (m; default: the random world's, 0.2)",
    )
    p.add_argument(
        "--team-sizes",
        type=int,
        nargs="+",
        default=list(d.team_sizes),
        metavar="N",
        help="the grid's team sizes (default 3 6 10)",
    )
    p.add_argument(
        "--drops",
        type=float,
        nargs="+",
        default=list(d.drops),
        metavar="P",
        help="the grid's message drop probabilities (default 0 0.5)",
    )
    p.add_argument("--out", type=Path, default=d.out, help="output directory")
    p.add_argument("--seed", type=int, default=d.seed, help="world k has seed SEED + k")
    p.add_argument("--workers", type=int, default=d.workers, help="processes")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    s = SearchOptions()
    p.add_argument("--population", type=int, default=s.population, help="CEM population")
    p.add_argument("--iterations", type=int, default=s.iterations, help="CEM iterations")
    p.add_argument("--elite", type=int, default=s.elite, help="CEM elite size")
    p.add_argument("--knots", type=int, default=s.knots, help="action pieces per agent")
    add_preset_arguments(p)
    a = p.parse_args(argv)
    search = SearchOptions(
        population=a.population, iterations=a.iterations, elite=a.elite, knots=a.knots
    )
    if not 0 < search.elite <= search.population or search.knots < 1 or search.iterations < 1:
        p.error("need 0 < --elite <= --population, --knots >= 1, --iterations >= 1")
    if a.worlds < 1 or a.steps < 1 or a.workers < 1:
        p.error("--worlds, --steps and --workers must be >= 1")
    if min(a.team_sizes) < 1 or not all(0.0 <= q < 1.0 for q in a.drops):
        p.error("--team-sizes must be >= 1 and --drops in [0, 1)")
    opts = HarnessOptions(
        worlds=a.worlds,
        steps=a.steps,
        preset=a.preset,
        overrides=tuple(a.set),
        families=tuple(a.families),
        search=a.search,
        search_worlds=a.search_worlds,
        out=a.out,
        seed=a.seed,
        workers=a.workers,
        progress=not a.no_progress,
        search_options=search,
        n_obstacles=None if a.obstacles is None else tuple(a.obstacles),
        corridor=a.corridor,
        car_speed=None if a.car_speed is None else tuple(a.car_speed),
        start_offset=a.start_offset,
        team_sizes=tuple(a.team_sizes),
        drops=tuple(a.drops),
    )
    try:
        selected_families(opts)
        RandomWorldConfig(**opts.random_world())  # checked here, not in the workers
    except ValueError as exc:
        p.error(str(exc))
    return opts


def main(argv: list[str] | None = None) -> int:
    """Run the harness, print the report and write OUT/."""
    argv = sys.argv[1:] if argv is None else argv
    opts = parse_args(argv)
    config = expert_config_from(opts.preset, list(opts.overrides))
    wall = time.perf_counter()
    records = run_harness(opts, config)
    wall = time.perf_counter() - wall
    report = write_outputs(
        opts, config, records, cli_command("baselines.shield_adversary", argv), wall
    )
    print(report)
    print(f"wrote {opts.out}/report.md, metrics.json, config.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
