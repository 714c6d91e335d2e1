"""Initial conditions and obstacle layouts: the paper's scenarios A-C (Table VI) and random worlds.

Table VI gives the UAVs' initial (x, y, heading) exactly; we use them with the altitude 0.85 m of
section VI-A. The paper shows the obstacle layouts only as pictures (Figs. 10, 11, 21, 22), so we
place them from the text, relative to the target's Fig. 11 path:

* A: ten 1 m cubes; 1-5 on UAV1's side (left of the path) where the target is at 12-28 s, 6-10 on
  UAV3's side (right) at 32-48 s, alternating 4.5 m and 6 m from the path, i.e. between the UAV and
  the target (occlusion) and on the UAV's route (collision).
* B: twelve 1 m cubes on both sides every 4 s from 6 s to 50 s, 4 m and 5.5 m from the path.
* C: B's footprints with 2.5 m tall boxes ("larger tracking errors ... due to the higher
  obstacles").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import DT, EnvConfig
from .geometry import segment_hits_boxes, world_to_cam_vec
from .rewards import connected
from .target import CAR_HALF_EXTENTS, Segment, fig11_program, random_program, sample_path

PAPER_ALTITUDE = 0.85
"""Initial UAV altitude of section VI-A (m)."""
PAPER_REFERENCE = (0.0, 0.188, 1.0 / 7.0)
"""[x1*, x2*, x3*] of every UAV's reference s^{i,*} (section VI-A)."""
PAPER_PSI_REF = (math.pi / 2, math.pi, -math.pi / 2)
"""psi* of UAV1-3 under eq. (4); the paper prints 0 for UAV2, which starts behind the car (pi)."""

# Table VI: (x, y, heading) of UAV1-3 for each scenario and initial condition.
TABLE_VI_INITIAL = {
    ("A", 0): ((0, 6, -1.57), (-6, 0, 0), (0, -6, 1.57)),
    ("A", 1): ((0, 6, -1.57), (-6, 3, 0), (-3, -6, 1.57)),
    ("B", 0): ((0, 6, -1.57), (-6, 0, 0), (0, -6, 1.57)),
    ("B", 1): ((-4, 5, -0.784), (-8, 0, 0), (-3, -6, 0.784)),
    ("C", 0): ((0, 6, -1.57), (-6, 0, 0), (0, -6, 1.57)),
    ("C", 1): ((-2, 6, -1.2), (-6, 0, 0), (-2, -6, 1.2)),
}


@dataclass(frozen=True)
class Layout:
    """Everything static about an episode's start."""

    name: str
    uav_positions: np.ndarray
    """(n, 3) initial positions (m)."""
    uav_yaws: np.ndarray
    """(n,) initial headings (rad)."""
    references: np.ndarray
    """(n, 4) reference features s^{i,*} = [x1*, x2*, x3*, psi*] (section VI-A)."""
    obstacle_centers: np.ndarray
    """(m, 3) box centres (m)."""
    obstacle_half_extents: np.ndarray
    """(m, 3) box half sizes (m)."""
    target_start: tuple[float, float, float]
    """Target (x, y, heading) at t = 0."""
    target_program: tuple[Segment, ...]


def _boxes_along_path(
    path: np.ndarray, times: list[float], offsets: list[float], size: float, height: float
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes at signed lateral ``offsets`` (left > 0) from the path poses at ``times``."""
    centers = []
    for t, off in zip(times, offsets, strict=True):
        x, y, th = path[round(t / DT)]
        centers.append([x - off * math.sin(th), y + off * math.cos(th), height / 2])
    half = np.tile([size / 2, size / 2, height / 2], (len(times), 1))
    return np.array(centers, float), half


def paper_layout(scenario: str, init: int) -> Layout:
    """Scenario A, B or C with initial condition 0 or 1 (Table VI)."""
    program = fig11_program()
    path = sample_path(program, 0.0, 0.0, 0.0, 60.0, DT)
    if scenario == "A":
        t1, t2 = [12.0, 16.0, 20.0, 24.0, 28.0], [32.0, 36.0, 40.0, 44.0, 48.0]
        lateral = [4.5, 6.0, 4.5, 6.0, 4.5]
        centers, half = _boxes_along_path(path, t1 + t2, lateral + [-v for v in lateral], 1.0, 1.0)
    elif scenario in ("B", "C"):
        times = [6.0 + 4.0 * k for k in range(12)]
        offsets = [(4.0 if k % 4 < 2 else 5.5) * (1 if k % 2 == 0 else -1) for k in range(12)]
        centers, half = _boxes_along_path(
            path, times, offsets, 1.0, 1.0 if scenario == "B" else 2.5
        )
    else:
        raise ValueError(f"unknown paper scenario {scenario!r}; expected 'A', 'B' or 'C'")
    rows = np.array(TABLE_VI_INITIAL[(scenario, init)], float)
    positions = np.column_stack([rows[:, :2], np.full(3, PAPER_ALTITUDE)])
    refs = np.array([[*PAPER_REFERENCE, psi] for psi in PAPER_PSI_REF])
    return Layout(
        name=f"{scenario}{init}",
        uav_positions=positions,
        uav_yaws=rows[:, 2].copy(),
        references=refs,
        obstacle_centers=centers,
        obstacle_half_extents=half,
        target_start=(0.0, 0.0, 0.0),
        target_program=program,
    )


def formation_references(n: int, x2: float = PAPER_REFERENCE[1]) -> np.ndarray:
    """References for n UAVs: rings of depth 7, 10, 13 m spread over the target's back half.

    psi* runs from pi/2 (left) through pi (behind) to -pi/2 (right); for n = 3 this is the
    paper's formation. Neighbours on a ring are at least 3 m apart (R_s = 2 m).
    """
    refs, left, depth = [], n, 7.0
    while left > 0:
        capacity = int(math.pi * depth / 3.0) + 1
        m = min(capacity, left)
        angles = [math.pi] if m == 1 else list(np.linspace(math.pi / 2, 1.5 * math.pi, m))
        refs += [[0.0, x2, 1.0 / depth, math.atan2(math.sin(a), math.cos(a))] for a in angles]
        left -= m
        depth += 3.0
    return np.array(refs)


def _car_in_view(positions: np.ndarray, yaws: np.ndarray, cfg: EnvConfig) -> bool:
    """Whether the car's centre projects into the inner 70 % of every UAV's image."""
    cam = cfg.camera
    for p, yaw in zip(positions, yaws, strict=True):
        xc, yc, zc = world_to_cam_vec(np.array([0.0, 0.0, CAR_HALF_EXTENTS[2]]) - p, yaw)
        if zc <= cam.near or abs(cam.fx * xc / zc) > 0.7 * cam.cu:
            return False
        if abs(cam.fy * yc / zc) > 0.7 * cam.cv:
            return False
    return True


def _draw_poses(
    rng: np.random.Generator, refs: np.ndarray, offset: float, heading: float
) -> tuple[np.ndarray, np.ndarray]:
    """Uniformly jittered formation poses of the UAVs whose references are ``refs``."""
    n, depth = len(refs), 1.0 / refs[:, 2]
    angle = refs[:, 3] + rng.uniform(-0.03, 0.03, n)
    horizontal = depth + rng.uniform(-offset, offset, n)
    positions = np.column_stack(
        [
            horizontal * np.cos(angle),
            horizontal * np.sin(angle),
            CAR_HALF_EXTENTS[2] + refs[:, 1] * depth + rng.uniform(-offset, offset, n),
        ]
    )
    if offset > 0.2:  # also move along the ring
        tangent = np.column_stack([-np.sin(angle), np.cos(angle)])
        positions[:, :2] += tangent * rng.uniform(-offset, offset, (n, 1))
    yaws = np.arctan2(-positions[:, 1], -positions[:, 0])
    if heading > 0:
        yaws = yaws + rng.uniform(-heading, heading, n)
    return positions, yaws


def _formation_start(
    rng: np.random.Generator, refs: np.ndarray, offset: float, heading: float, cfg: EnvConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Start poses near the formation: uniform offsets, redrawn until every UAV is 0.4 m above
    the floor and R_s + 0.4 m from the others, the graph is connected and (beyond the default
    0.2 m) every camera sees the car; the default's first draw always passes. A large team
    whose whole draws keep failing is placed UAV by UAV, each redrawn on its own."""
    n = len(refs)
    min_gap, floor = cfg.violations.r_s + 0.4, cfg.random_world.min_start_altitude

    def feasible(positions: np.ndarray, yaws: np.ndarray) -> bool:
        if offset > 0.2 and not _car_in_view(positions, yaws, cfg):
            return False
        pair = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
        apart = len(positions) < 2 or pair[~np.eye(len(positions), dtype=bool)].min() >= min_gap
        return bool(positions[:, 2].min() >= floor and apart)

    def connected_team(positions: np.ndarray) -> bool:
        pair = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
        return connected(pair, np.ones(n, bool), cfg.comms.r_c)

    for _ in range(1000):
        positions, yaws = _draw_poses(rng, refs, offset, heading)
        if feasible(positions, yaws) and connected_team(positions):
            return positions, yaws
    for _ in range(100):
        positions, yaws = np.zeros((n, 3)), np.zeros(n)
        for i in range(n):
            for _attempt in range(1000):
                pose, yaw = _draw_poses(rng, refs[i : i + 1], offset, heading)
                positions[i], yaws[i] = pose[0], yaw[0]
                if feasible(positions[: i + 1], yaws[: i + 1]):
                    break
            else:
                break
        else:
            if connected_team(positions):
                return positions, yaws
    raise ValueError(
        f"no feasible start within start_offset = {offset} m for {n} UAVs: 1000 team draws and "
        "100 UAV-by-UAV placements failed; lower random_world.start_offset"
    )


def random_layout(rng: np.random.Generator, cfg: EnvConfig) -> Layout:
    """A seeded cluttered world whose start is feasible.

    Guarantees: the target's corridor is free; every UAV starts at its formation pose (small
    jitter), clear of obstacles by 1.5 m and of other UAVs by R_s + 0.4 m, all UAVs connected
    within R_c, and no obstacle on the line of sight from any UAV to the car's centre or corners.
    """
    rw = cfg.random_world
    duration = cfg.max_cycles * DT
    program = random_program(rng, rw.target_speed, rw.target_turn_rate, duration)
    path = sample_path(program, 0.0, 0.0, 0.0, min(duration, 120.0), 0.1)

    refs = formation_references(cfg.n_uavs)
    positions, yaws = _formation_start(rng, refs, rw.start_offset, rw.start_heading_offset, cfg)

    centers, halves = [], []
    for _ in range(int(rng.integers(rw.n_obstacles[0], rw.n_obstacles[1] + 1))):
        for _attempt in range(50):
            half = np.array([*(rng.uniform(*rw.size, 2) / 2), rng.uniform(*rw.height) / 2], float)
            c = np.array([rng.uniform(-15.0, rw.extent), rng.uniform(-20.0, 20.0), half[2]], float)
            reach = float(np.hypot(half[0], half[1]))
            if np.min(np.hypot(*(path[:, :2] - c[:2]).T)) < rw.corridor + reach:
                continue
            gap = np.abs(positions - c) - half
            if np.min(np.linalg.norm(np.maximum(gap, 0.0), axis=1)) < 1.5:
                continue
            if any(
                np.all(np.abs(c - oc) < half + oh + 0.5)
                for oc, oh in zip(centers, halves, strict=True)
            ):
                continue
            centers.append(c)
            halves.append(half)
            break
    centers_a = np.array(centers, float).reshape(-1, 3)
    halves_a = np.array(halves, float).reshape(-1, 3)

    # Clear every line of sight to the target's centre and top corners.
    target_points = np.array(
        [[0.0, 0.0, CAR_HALF_EXTENTS[2]]]
        + [
            [sx * CAR_HALF_EXTENTS[0], sy * CAR_HALF_EXTENTS[1], 2 * CAR_HALF_EXTENTS[2]]
            for sx in (-1, 1)
            for sy in (-1, 1)
        ]
    )
    keep = np.ones(len(centers_a), bool)
    for p in positions:
        for q in target_points:
            keep &= ~segment_hits_boxes(p, q, centers_a, halves_a)
    return Layout(
        name="random",
        uav_positions=positions,
        uav_yaws=yaws,
        references=refs,
        obstacle_centers=centers_a[keep],
        obstacle_half_extents=halves_a[keep],
        target_start=(0.0, 0.0, 0.0),
        target_program=program,
    )


def make_layout(cfg: EnvConfig, rng: np.random.Generator) -> Layout:
    """The layout for ``cfg.scenario`` (the random one drawn from ``rng``)."""
    if cfg.scenario == "random":
        return random_layout(rng, cfg)
    return paper_layout(cfg.scenario, cfg.init)
