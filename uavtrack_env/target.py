"""Target (car) motion: a kinematic unicycle driven by a program of (speed, turn-rate) segments.

The paper's program (Fig. 11) reads: 0.5 m/s straight for 10 s, "turned at -0.1 m/s^2" from 10 s
to 15 s, straight to 35 s, "turned at 0.1 m/s^2" to 40 s, then straight. We read the turn
accelerations as lateral (centripetal) accelerations at constant speed 0.5 m/s, so the turn rate is
a / v = -0.2 rad/s then +0.2 rad/s: two opposite turns of 1 rad (57 deg), a z-shaped path, the
speed staying 0.5 m/s as the caption says ("kept moving at 0.5 m/s"). Random programs are
piecewise-constant turn rates with smooth (first-order) transitions, bounded speed and turn rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CAR_SIZE = (4.6, 1.8, 1.5)
"""Length x width x height of the target car in metres (section VI-A)."""
CAR_HALF_EXTENTS = np.array(CAR_SIZE) / 2.0


@dataclass(frozen=True)
class Segment:
    """Drive at ``speed`` (m/s) turning at ``turn_rate`` (rad/s) until time ``t_end`` (s)."""

    t_end: float
    speed: float
    turn_rate: float


def fig11_program(speed: float = 0.5, lateral_accel: float = 0.1) -> tuple[Segment, ...]:
    """The z-shaped path of Fig. 11 (see the module docstring for how the turns are read)."""
    w = lateral_accel / speed
    return (
        Segment(10.0, speed, 0.0),
        Segment(15.0, speed, -w),
        Segment(35.0, speed, 0.0),
        Segment(40.0, speed, w),
        Segment(math.inf, speed, 0.0),
    )


def random_program(
    rng: np.random.Generator,
    speed_range: tuple[float, float],
    max_turn_rate: float,
    duration: float,
) -> tuple[Segment, ...]:
    """Seeded random program: one cruise speed, segments of 2-6 s, turn rates in +-max_turn_rate."""
    speed = float(rng.uniform(*speed_range))
    segments, t = [], 0.0
    while t < duration:
        t += float(rng.uniform(2.0, 6.0))
        straight = rng.random() < 0.4
        rate = 0.0 if straight else float(rng.uniform(-max_turn_rate, max_turn_rate))
        segments.append(Segment(t, speed, rate))
    segments.append(Segment(math.inf, speed, 0.0))
    return tuple(segments)


class TargetMotion:
    """Integrates the car's planar pose; the turn rate follows the program through a 0.3 s lag."""

    TURN_LAG = 0.3

    def __init__(self, program: tuple[Segment, ...], x: float, y: float, heading: float) -> None:
        self.program = program
        self._start = (float(x), float(y), float(heading))
        self.reset()

    def reset(self) -> None:
        self.x, self.y, self.heading = self._start
        self.t = 0.0
        self.turn_rate = 0.0
        self._seg = 0
        self.speed = self.program[0].speed

    def _command(self) -> Segment:
        # The tolerance keeps float accumulation of t from switching one step late.
        while self.t >= self.program[self._seg].t_end - 1e-9:
            self._seg += 1
        return self.program[self._seg]

    def step(self, dt: float) -> None:
        seg = self._command()
        # The paper's turns are sharp steps; the lag keeps the acceleration finite for the UKF.
        self.turn_rate += (seg.turn_rate - self.turn_rate) * min(1.0, dt / self.TURN_LAG)
        self.speed = seg.speed
        mid = self.heading + 0.5 * self.turn_rate * dt
        self.x += self.speed * math.cos(mid) * dt
        self.y += self.speed * math.sin(mid) * dt
        self.heading = math.atan2(
            math.sin(self.heading + self.turn_rate * dt),
            math.cos(self.heading + self.turn_rate * dt),
        )
        self.t += dt

    def center(self) -> np.ndarray:
        """Car body centre (global), half its height above the ground."""
        return np.array([self.x, self.y, CAR_HALF_EXTENTS[2]])

    def velocity(self) -> np.ndarray:
        return np.array(
            [self.speed * math.cos(self.heading), self.speed * math.sin(self.heading), 0.0]
        )

    def acceleration(self) -> np.ndarray:
        a = self.speed * self.turn_rate
        return np.array([-a * math.sin(self.heading), a * math.cos(self.heading), 0.0])

    def kinematics(self) -> np.ndarray:
        """(3, 3): `center`, `velocity` and `acceleration` as rows, in one array."""
        v, a = self.speed, self.speed * self.turn_rate
        c, s = math.cos(self.heading), math.sin(self.heading)
        return np.array(
            [self.x, self.y, CAR_HALF_EXTENTS[2], v * c, v * s, 0.0, -a * s, a * c, 0.0]
        ).reshape(3, 3)


def sample_path(
    program: tuple[Segment, ...], x: float, y: float, heading: float, duration: float, dt: float
) -> np.ndarray:
    """Poses (T, 3) = (x, y, heading) of a program integrated for ``duration`` seconds."""
    motion = TargetMotion(program, x, y, heading)
    out = np.empty((round(duration / dt) + 1, 3))
    for k in range(out.shape[0]):
        out[k] = motion.x, motion.y, motion.heading
        motion.step(dt)
    return out
