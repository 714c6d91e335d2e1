"""Barrier functions h and their CBF constraint rows (paper section IV, eqs. 20-45).

Every row is a linear inequality on the UAV's *global-frame* translational velocity V = p-dot
(single integrator, eq. 3)::

    A V <= b,    b = gamma * h + drift - margin,

and it encodes ``h-dot >= -gamma * h + margin`` because, along the dynamics, ``h-dot = -A V + drift``
(``drift`` collects what the UAV does not control: the target's estimated motion). Rows never
involve the yaw rate: the A matrices of (25), (34) and (45) have zeros in the omega block, so the
angular part of the paper's 6-vector u^g is decoupled from every barrier.

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
from dataclasses import dataclass, field

import numpy as np

from uavtrack_env.config import CBFConfig

KIND_NAMES = ("uav", "obstacle", "target", "floor", "connect", "occlusion")
"""Row family names, indexed by `CBFRows.kind`."""
UAV, OBSTACLE, TARGET, FLOOR, CONNECT, OCCLUSION = range(6)
HARD_KINDS = (UAV, OBSTACLE, TARGET, FLOOR)
"""Row families that are never relaxed (collision and altitude)."""

DEFAULT_CAR_HALF_EXTENTS = (2.3, 0.9, 0.75)
"""Half size of the target car, 4.6 x 1.8 x 1.5 m (section VI-A)."""

_EMPTY3 = np.zeros((0, 3))


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
    neighbour_ids: tuple[int, ...] | None = None
    """Optional agent ids of `neighbours`, used only to name rows ("uav:<id>")."""

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
        if self.neighbour_ids is not None and len(self.neighbour_ids) != len(self.neighbours):
            raise ValueError(
                f"neighbour_ids has {len(self.neighbour_ids)} entries for "
                f"{len(self.neighbours)} neighbours"
            )


@dataclass(frozen=True)
class CBFRows:
    """A stack of CBF rows ``A V <= b`` on the global velocity V, with their bookkeeping."""

    A: np.ndarray
    """(k, 3) row coefficients on V^g (the omega block of (25)/(34)/(45) is zero and dropped)."""
    b: np.ndarray
    """(k,) right-hand sides, ``gamma * h + drift - margin``."""
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
    """(k,) index of the neighbour/obstacle the row refers to (0 for target and floor)."""

    @property
    def hard(self) -> np.ndarray:
        """(k,) True for collision and altitude rows (never relaxed)."""
        return self.kind < CONNECT

    def __len__(self) -> int:
        return len(self.b)

    def name(self, r: int, neighbour_ids=None) -> str:
        """Name of row r, e.g. 'uav:2', 'obstacle:5', 'occlusion:5', 'connect:1', 'target'."""
        k = int(self.kind[r])
        if k in (TARGET, FLOOR):
            return KIND_NAMES[k]
        i = int(self.index[r])
        if neighbour_ids is not None and k in (UAV, CONNECT):
            i = neighbour_ids[i]
        return f"{KIND_NAMES[k]}:{i}"

    def names(self, neighbour_ids=None) -> list[str]:
        """Names of all rows."""
        return [self.name(r, neighbour_ids) for r in range(len(self))]


# --------------------------------------------------------------------------- barrier functions
def h_pair(p: np.ndarray, q: np.ndarray, radius: float) -> np.ndarray:
    """||p - q||^2 - radius^2: collision barrier (20) and the point-obstacle model."""
    d = np.asarray(p, float) - np.asarray(q, float)
    return np.einsum("...i,...i->...", d, d) - radius**2


def h_connect(p: np.ndarray, q: np.ndarray, r_c: float) -> np.ndarray:
    """R_c^2 - ||p - q||^2: connectivity barrier (29)."""
    return -h_pair(p, q, r_c)


def _box_distance_grad(local: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed squared box distance and its gradient for points in box coordinates (m, 3).

    Outside: ``dist^2`` with gradient ``2 (p - closest point)``. Inside (penetration depth e to
    the nearest face with outward normal n): ``-e^2`` with gradient ``2 e n``. The function is
    C^1 across the surface (value and gradient both vanish there).
    """
    excess = np.abs(local) - half
    outside = np.maximum(excess, 0.0)
    sign = np.where(local >= 0.0, 1.0, -1.0)
    grad = 2.0 * sign * outside
    d2 = np.einsum("ij,ij->i", outside, outside)
    inside = (excess < 0.0).all(axis=1)
    if inside.any():
        ex = excess[inside]
        axis = np.argmax(ex, axis=1)  # the face closest to the point (least negative excess)
        depth = -ex[np.arange(len(ex)), axis]
        g = np.zeros_like(ex)
        g[np.arange(len(ex)), axis] = 2.0 * depth * sign[inside][np.arange(len(ex)), axis]
        grad[inside] = g
        d2[inside] = -(depth**2)
    return d2, grad


def h_box(
    p: np.ndarray, centers: np.ndarray, half: np.ndarray, clearance: float, yaw: float = 0.0
) -> np.ndarray:
    """Box barrier ``sdist(p, box)^2 - clearance^2`` for boxes rotated by ``yaw`` about z.

    ``sdist^2`` is the squared distance outside and minus the squared penetration depth inside.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(p, float)[None, :] - np.atleast_2d(centers)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    d2, _ = _box_distance_grad(local, np.atleast_2d(half))
    return d2 - clearance**2


def h_occlusion(p: np.ndarray, p_o: np.ndarray, n: np.ndarray, theta_star: float) -> np.ndarray:
    """theta - theta* of eqs. (37)-(39): angle between p_o - p and n = target - p."""
    d = np.atleast_2d(p_o) - np.asarray(p, float)
    x = (d @ n) / (np.linalg.norm(d, axis=1) * np.linalg.norm(n))
    return np.arccos(np.clip(x, -1.0, 1.0)) - theta_star


# --------------------------------------------------------------------------- row builders
_Rows = tuple  # (A, h, gamma, drift, margin, index) raw arrays of one family


def collision_rows(p: np.ndarray, neighbours: np.ndarray, cbf: CBFConfig) -> _Rows:
    """Rows (25) for j in N_si = {||p - p_j|| <= D_s}: ``-2 (p - p_j)^T V <= gamma_s h / 2``.

    The halved rate is the distributed split (23)-(24): UAV j enforces the mirrored half.
    """
    d = p - neighbours
    d2 = np.einsum("ij,ij->i", d, d)
    idx = np.flatnonzero(d2 <= cbf.d_s**2)
    d, d2 = d[idx], d2[idx]
    return -2.0 * d, d2 - cbf.r_s**2, 0.5 * cbf.gamma_s, 0.0, 0.0, idx


def connectivity_rows(
    p: np.ndarray, neighbours: np.ndarray, cbf: CBFConfig, margin: float
) -> _Rows:
    """Rows (34) for j in N_ci = {||p - p_j|| <= R_c}: ``2 (p - p_j)^T V <= gamma_c h / 2 - margin``.

    h = R_c^2 - ||p - p_j||^2 is concave, so one forward-Euler step of length dt loses up to
    ``dt^2 ||V_i - V_j||^2 <= 4 dt^2 alpha_v^2`` against its linearisation. Each of the two UAVs
    subtracts ``margin = 2 dt alpha_v^2`` (h-dot units) from its half, so the pair gains
    ``2 margin dt = 4 dt^2 alpha_v^2`` per step, restoring ``h(k+1) >= (1 - gamma_c dt) h(k)``.
    """
    d = p - neighbours
    d2 = np.einsum("ij,ij->i", d, d)
    idx = np.flatnonzero(d2 <= cbf.r_c**2)
    d, d2 = d[idx], d2[idx]
    return 2.0 * d, cbf.r_c**2 - d2, 0.5 * cbf.gamma_c, 0.0, margin, idx


def point_obstacle_rows(p: np.ndarray, centers: np.ndarray, cbf: CBFConfig) -> _Rows:
    """Paper's point model: ``h = ||p - p_o||^2 - R_s^2``, ``-2 (p - p_o)^T V <= gamma h``.

    Obstacles are static, so the UAV takes the whole rate (no 1/2 split as in (23)).
    """
    d = p - centers
    h = np.einsum("ij,ij->i", d, d) - cbf.r_s**2
    return -2.0 * d, h, cbf.gamma_obstacle, 0.0, 0.0, np.arange(len(centers))


def box_obstacle_rows(
    p: np.ndarray, centers: np.ndarray, half: np.ndarray, cbf: CBFConfig
) -> _Rows:
    """Box model: ``h = sdist(p, box)^2 - c^2``, ``-grad h^T V <= gamma h`` (static boxes).

    Outside the box grad h = 2 (p - closest point). h is convex outside, so forward Euler never
    decreases it faster than its linearisation (no discrete-time margin needed).
    """
    d2, grad = _box_distance_grad(p - centers, half)
    h = d2 - cbf.obstacle_clearance**2
    return -grad, h, cbf.gamma_obstacle, 0.0, 0.0, np.arange(len(centers))


def target_rows(
    p: np.ndarray,
    q: np.ndarray,
    vq: np.ndarray,
    half: np.ndarray,
    heading: float,
    cbf: CBFConfig,
) -> _Rows:
    """The target car as an oriented box moving at V_q: ``-grad h^T V <= gamma h - grad h^T V_q``.

    h-dot = grad h . (V - V_q) for a translating box (its heading rate is neglected).
    """
    c, s = math.cos(heading), math.sin(heading)
    d = p - q
    local = np.array([[c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]]])
    d2, gl = _box_distance_grad(local, half[None, :])
    g = np.array([c * gl[0, 0] - s * gl[0, 1], s * gl[0, 0] + c * gl[0, 1], gl[0, 2]])
    h = d2 - cbf.obstacle_clearance**2
    return -g[None, :], h, cbf.gamma_obstacle, np.array([-(g @ vq)]), 0.0, np.zeros(1, int)


def floor_rows(p: np.ndarray, cbf: CBFConfig) -> _Rows:
    """Altitude floor ``h = z - z_min``: ``-V_z <= gamma_z h`` (linear h: exact in discrete time)."""
    A = np.array([[0.0, 0.0, -1.0]])
    return A, np.array([p[2] - cbf.z_min]), cbf.gamma_z, 0.0, 0.0, np.zeros(1, int)


def occlusion_rows(
    p: np.ndarray,
    centers: np.ndarray,
    q: np.ndarray,
    vq: np.ndarray,
    cbf: CBFConfig,
    model: str | None = None,
) -> _Rows:
    """Occlusion rows (41)-(45) for j in N_oi = {||p_o^j - p|| <= ||n||}, n = r_q - p (36).

    With x = cos(theta) and d = p_o - p, ``theta-dot = -(dx/dd . d-dot + dx/dn . n-dot) / sin``:

    * 'paper' (43): n-dot = 0, d-dot = -V, giving A = -(1/sin) dx/dd, b = gamma_o h (45).
    * 'moving-target': n-dot = V_q - V, giving A = -(1/sin)(dx/dd + dx/dn) and the
      target term ``drift = -(1/sin) dx/dn . V_q`` in b.
    """
    model = model or cbf.occlusion_model
    n = q - p
    nn = math.sqrt(n @ n)
    d = centers - p
    nd = np.sqrt(np.einsum("ij,ij->i", d, d))
    idx = np.flatnonzero((nd <= nn) & (nd > 1e-9))
    if nn < 1e-9 or len(idx) == 0:
        return _EMPTY3, np.zeros(0), cbf.gamma_o, 0.0, 0.0, idx
    d, nd = d[idx], nd[idx]
    x = (d @ n) / (nd * nn)
    x = np.clip(x, -1.0, 1.0)
    h = np.arccos(x) - cbf.theta_star
    inv_sin = 1.0 / np.sqrt(np.maximum(1.0 - x * x, 1e-12))
    dx_dd = n[None, :] / (nd * nn)[:, None] - (x / nd**2)[:, None] * d
    if model == "paper":
        return -inv_sin[:, None] * dx_dd, h, cbf.gamma_o, 0.0, 0.0, idx
    if model != "moving-target":
        raise ValueError(f"occlusion_model must be 'paper' or 'moving-target', got {model!r}")
    dx_dn = d / (nd * nn)[:, None] - (x / nn**2)[:, None] * n[None, :]
    A = -inv_sin[:, None] * (dx_dd + dx_dn)
    drift = -inv_sin * (dx_dn @ vq)
    return A, h, cbf.gamma_o, drift, 0.0, idx


def build_rows(
    ctx: SafetyContext,
    cbf: CBFConfig,
    *,
    obstacle_model: str = "box",
    connectivity_margin: float = 0.0,
    target_as_obstacle: bool = True,
    occlusion: bool = True,
) -> CBFRows:
    """All rows of UAV i's QP (47) from its `SafetyContext`, hard families first."""
    p = ctx.position
    groups: list[tuple[int, _Rows]] = []
    if len(ctx.neighbours):
        groups.append((UAV, collision_rows(p, ctx.neighbours, cbf)))
    if len(ctx.obstacle_centers):
        if obstacle_model == "box":
            rows = box_obstacle_rows(p, ctx.obstacle_centers, ctx.obstacle_half_extents, cbf)
        elif obstacle_model == "point":
            rows = point_obstacle_rows(p, ctx.obstacle_centers, cbf)
        else:
            raise ValueError(f"obstacle_model must be 'box' or 'point', got {obstacle_model!r}")
        groups.append((OBSTACLE, rows))
    has_target = ctx.target_position is not None
    if has_target and target_as_obstacle:
        groups.append(
            (
                TARGET,
                target_rows(
                    p,
                    ctx.target_position,
                    ctx.target_velocity,
                    ctx.target_half_extents,
                    ctx.target_heading,
                    cbf,
                ),
            )
        )
    groups.append((FLOOR, floor_rows(p, cbf)))
    if len(ctx.neighbours):
        groups.append((CONNECT, connectivity_rows(p, ctx.neighbours, cbf, connectivity_margin)))
    if has_target and occlusion and len(ctx.obstacle_centers):
        groups.append(
            (
                OCCLUSION,
                occlusion_rows(
                    p, ctx.obstacle_centers, ctx.target_position, ctx.target_velocity, cbf
                ),
            )
        )
    sizes = [len(g[1][5]) for g in groups]
    k = sum(sizes)
    A = np.concatenate([g[1][0] for g in groups]) if k else _EMPTY3
    h = np.concatenate([np.broadcast_to(g[1][1], (s,)) for g, s in zip(groups, sizes)])
    gamma = np.repeat([g[1][2] for g in groups], sizes)
    drift = np.concatenate([np.broadcast_to(g[1][3], (s,)) for g, s in zip(groups, sizes)])
    margin = np.repeat([g[1][4] for g in groups], sizes)
    kind = np.repeat([g[0] for g in groups], sizes)
    index = np.concatenate([g[1][5] for g in groups]).astype(int)
    b = gamma * h + drift - margin
    return CBFRows(A, b, h, gamma, drift, margin, kind, index)
