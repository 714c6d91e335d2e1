"""The PyBullet queries of a step whose answer the geometry already proves, so they are skipped.

A detector ray runs from a UAV's centre to a sample point inside the car's box, so PyBullet
reports the car as its first hit unless another body lies on it first. When the segment, widened
by `RAY_MARGIN`, meets no obstacle's box, no other UAV's sphere and not the ground, and the UAV
is outside the car's bounding sphere, the ray reaches the car. When it passes through another
UAV's sphere (by more than the margin) that lies outside the car's bounding sphere, that sphere
comes first: the ray is blocked. Either way its cast is skipped. Likewise a
UAV farther than `CONTACT_MARGIN` from every obstacle, the car and the ground touches none of
them, so a world whose UAVs all are gets no contact query. Everything else goes to PyBullet.
tests/test_broadphase.py checks that the results equal PyBullet's on every query, near-misses
included, and that rollouts are bit-identical with `EnvConfig.skip_proven_queries` on and off.

The geometry is the env's record of the episode's bodies (its obstacle boxes, the UAVs' state,
the car's pose): bodies moved in the PyBullet client behind the env's back are not seen.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

RAY_MARGIN = 1.0e-3
"""Width (m) added to every body when deciding that a ray cannot hit it: far above PyBullet's
single-precision rounding at the world's scale (~1e-5 m)."""
CONTACT_MARGIN = 0.1
"""A UAV whose clearance to every obstacle, the car and the ground exceeds this (m) is in no
PyBullet contact (a contact needs clearance <= 0)."""
FAR = 1.0e3
"""A UAV or car farther than this (m) from the origin always gets its rays cast: the UAVs that
left the episode are parked in PyBullet ~1.4e4 m away, out of every shorter segment's reach."""


REACHES, BLOCKED, UNKNOWN = 1, 0, -1
"""A ray's answers: its first hit is the car, is another body, or is for PyBullet."""


class Bodies(NamedTuple):
    """What a ray to the car may meet first, as the env records it."""

    alive: np.ndarray
    """(K, n) bool: the UAVs posed in PyBullet (the others are parked)."""
    box_centres: np.ndarray
    """(K, M, 3) centres of the axis-aligned obstacle boxes (padding: far away, zero size)."""
    box_half_extents: np.ndarray
    """(K, M, 3) their half extents."""
    uav_radius: float


@numba.njit(cache=True)
def _known_rays(p, alive, car, samples, R, car_radius, box_c, box_h, r, margin=RAY_MARGIN):
    """`known_answers`' answers as int8 (K, n, s). Each ray to a sample lies within R (the
    samples' largest distance from the car's centre) of the segment to the car's centre, so only
    the bodies near that capsule are tested ray by ray."""
    K, n, s, M = p.shape[0], p.shape[1], samples.shape[1], box_c.shape[1]
    known = np.full((K, n, s), REACHES, np.int8)
    reach2, inside2 = (r + margin) ** 2, max(r - margin, 0.0) ** 2
    blocker2 = (car_radius + r + margin) ** 2  # a sphere this far from the car is hit first
    capsule2 = (r + R + margin) ** 2
    boxes, uavs = np.empty(M, np.int64), np.empty(n, np.int64)
    for k in range(K):
        c = car[k]
        car_far = max(abs(c[0]), abs(c[1]), abs(c[2])) >= FAR
        for i in range(n):
            a = p[k, i]
            c0, c1, c2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
            if (
                car_far
                or np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) <= car_radius + margin  # at or in the car
                or a[2] <= margin  # the ground: a segment above it never meets it
                or max(abs(a[0]), abs(a[1]), abs(a[2])) >= FAR
            ):
                known[k, i] = UNKNOWN
                continue
            nb = 0
            for m in range(M):
                if _segment_meets_box(a, c0, c1, c2, box_c[k, m], box_h[k, m], R + margin):
                    boxes[nb] = m
                    nb += 1
            nu = 0
            axis2 = max(c0 * c0 + c1 * c1 + c2 * c2, 1e-300)
            for q in range(n):
                if q != i and alive[k, q]:  # a ray starts at its own sphere's centre
                    if _point_segment2(p[k, q], a, c0, c1, c2, axis2) <= capsule2:
                        uavs[nu] = q
                        nu += 1
            for j in range(s):
                e = samples[k, j]
                if e[2] <= margin:
                    known[k, i, j] = UNKNOWN
                    continue
                if nb == 0 and nu == 0:
                    continue
                d0, d1, d2 = e[0] - a[0], e[1] - a[1], e[2] - a[2]
                answer = REACHES
                for b in range(nb):
                    m = boxes[b]
                    if _segment_meets_box(a, d0, d1, d2, box_c[k, m], box_h[k, m], margin):
                        answer = UNKNOWN
                        break
                if nu:
                    length2 = max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
                    for b in range(nu):
                        q = p[k, uavs[b]]
                        gap2 = _point_segment2(q, a, d0, d1, d2, length2)
                        if gap2 > reach2:
                            continue
                        s0, s1, s2 = q[0] - a[0], q[1] - a[1], q[2] - a[2]
                        g0, g1, g2 = q[0] - c[0], q[1] - c[1], q[2] - c[2]
                        if (
                            gap2 <= inside2
                            and s0 * s0 + s1 * s1 + s2 * s2 > reach2  # starts outside it
                            and g0 * g0 + g1 * g1 + g2 * g2 > blocker2
                        ):
                            answer = BLOCKED
                            break
                        answer = UNKNOWN
                known[k, i, j] = answer
    return known


def known_answers(
    position: np.ndarray,
    car_centres: np.ndarray,
    samples: np.ndarray,
    sample_radius: float,
    car_radius: float,
    bodies: Bodies,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whether the ray from UAV i of world k to sample j `REACHES` the car, is `BLOCKED`, or is
    `UNKNOWN` (cast it), as (reaches (K, n, s) bool, unknown (K, n, s) bool, the worlds with a
    ray to cast (int64)); a ray neither reaching nor unknown is blocked. One compiled call.

    position (K, n, 3) are the ray starts, car_centres (K, 3), samples (K, s, 3) the ray ends
    inside the car's box, at most ``sample_radius`` from its centre, all float64 and C-ordered
    (the env's own arrays); ``car_radius`` is the car box's half diagonal."""
    return _known_answers(
        position, bodies.alive, car_centres, samples, sample_radius, car_radius,
        bodies.box_centres, bodies.box_half_extents, bodies.uav_radius,
    )  # fmt: skip


@numba.njit(cache=True)
def _known_answers(p, alive, car, samples, R, car_radius, box_c, box_h, r):  # pragma: no cover
    known = _known_rays(p, alive, car, samples, R, car_radius, box_c, box_h, r)
    reaches, unknown = known == REACHES, known == UNKNOWN
    K = known.shape[0]
    worlds = np.empty(K, np.int64)
    count = 0
    for k in range(K):
        if unknown[k].any():
            worlds[count] = k
            count += 1
    return reaches, unknown, worlds[:count]


@numba.njit(cache=True)
def _point_segment2(x, a, d0, d1, d2, length2):
    """Squared distance from point x to segment a -> a + d (|d|^2 = length2)."""
    r0, r1, r2 = x[0] - a[0], x[1] - a[1], x[2] - a[2]
    t = min(max((r0 * d0 + r1 * d1 + r2 * d2) / length2, 0.0), 1.0)
    g0, g1, g2 = r0 - t * d0, r1 - t * d1, r2 - t * d2
    return g0 * g0 + g1 * g1 + g2 * g2


@numba.njit(cache=True)
def _segment_meets_box(a, d0, d1, d2, centre, half, widen):
    """Segment a -> a + d meets the box widened by ``widen`` (slab test)."""
    enter, leave = 0.0, 1.0
    for axis, d in ((0, d0), (1, d1), (2, d2)):
        lo = centre[axis] - half[axis] - widen
        hi = centre[axis] + half[axis] + widen
        if d == 0.0:
            if a[axis] < lo or a[axis] > hi:
                return False
            continue
        t1, t2 = (lo - a[axis]) / d, (hi - a[axis]) / d
        if t1 > t2:
            t1, t2 = t2, t1
        enter, leave = max(enter, t1), min(leave, t2)
        if enter > leave:
            return False
    return True


def contacts_in_doubt(
    obstacle_clearance: np.ndarray,
    target_clearance: np.ndarray,
    altitude: np.ndarray,
    uav_radius: float,
    alive: np.ndarray,
) -> np.ndarray:
    """(K,) bool: some posed UAV of world k is within `CONTACT_MARGIN` of an obstacle (clearance
    (K, n, M)), the car (K, n) or the ground (altitude (K, n)); the others touch nothing."""
    near = (target_clearance <= CONTACT_MARGIN) | (altitude - uav_radius <= CONTACT_MARGIN)
    if obstacle_clearance.shape[-1]:
        near |= obstacle_clearance.min(axis=-1) <= CONTACT_MARGIN
    return (near & alive).any(axis=-1)
