"""Whether numba's cache holds the onboard stack's compiled kernels on this machine.

The estimator, the rows and the CBF-QP's arrays are numba kernels compiled with ``cache=True``:
the first process on a machine compiles them (about a minute here), later ones load them in a
second or two. `kernels_cached` lets a long-running command say so before it seems to hang;
`compile_filter_kernels` builds the kernels an episode would otherwise build late: the
correction at its first corrected action, the NMPC's plan rows at its first estimate, and a lag
plant's rows as the fallback's car-frustum retry builds them.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

from .estimation.bank import _bank_step
from .onboard_pass import observe_frame_step, observe_pass, observe_step
from .safety.cbf import OBSTACLE, CBFRows, SafetyContext
from .safety.qp_arrays import nominal_holds
from .safety.qp_layers import certify_changed, certify_many

if TYPE_CHECKING:
    from .safety.shield import SafetyFilter


def onboard_kernels() -> list[Any]:
    """The kernels every onboard stack compiles: its observation (the team's UKF step and
    rows, `onboard.observe_arrays`) and its own certification (`OnboardAgent.certify`, the
    expert's)."""
    return [_bank_step, observe_pass, observe_step, nominal_holds, certify_changed]


def shield_kernels() -> list[Any]:
    """The kernels a shield compiles besides `onboard_kernels`: the observation from the env's
    frame (`onboard.observe_frame`) and the team's certification (`onboard.certify_team`)."""
    return [observe_frame_step, certify_many]


def kernels_cached(kernels: Iterable[Any] | None = None) -> bool:
    """True when numba's cache holds compiled code of every kernel (default: `onboard_kernels`)
    for their current source; True as well when numba's cache cannot be read (nothing to say)."""
    for kernel in onboard_kernels() if kernels is None else kernels:
        try:
            if not kernel._cache._cache_file._load_index():
                return False
        except Exception:  # numba's cache internals differ: do not guess
            continue
    return True


def compile_filter_kernels(safety_filter: SafetyFilter) -> None:
    """Compile now (or load from numba's cache) the kernels ``safety_filter`` calls late in an
    episode, with the argument types of its own calls: the CBF-QP's correction,
    `qp_layers.certify_changed` (at the first corrected action: on a machine's first run, a
    pause of ~13 s in mid-episode), the NMPC's plan rows, `qp_arrays.nearest_camera_rows`,
    and under a lag plant the rows `SafetyFilter.climb_over_car` builds from a context,
    `second_order.second_order_rows` (at the first such fallback: ~6 s). Certifies a hover that
    one obstacle row rejects and builds the rows of a small context; the filter is stateless,
    so nothing else changes."""
    one = np.ones(1)
    rows = CBFRows(
        A=np.array([[1.0, 0.0, 0.0]]), b=-one, h=one, gamma=one, drift=0.0 * one,
        margin=0.0 * one, kind=np.array([OBSTACLE], np.int64), index=np.zeros(1, np.int64),
    )  # fmt: skip
    safety_filter.certify_pose(np.zeros(4), 0.0, np.zeros(3), rows)
    safety_filter.camera_rows(rows, 0.0, 1)
    if safety_filter.row_builder.lag_tau > 0.0:
        safety_filter.rows(
            SafetyContext(
                position=np.array([0.0, 0.0, 2.0]), yaw=0.0,
                neighbours=np.array([[3.0, 0.0, 2.0]]), neighbour_velocities=np.zeros((1, 3)),
                obstacle_centers=np.array([[0.0, 5.0, 1.0]]),
                obstacle_half_extents=np.ones((1, 3)), target_position=np.array([6.0, 6.0, 0.75]),
                target_velocity=np.zeros(3), target_half_extents=np.array([2.3, 0.9, 0.75]),
                target_heading=0.0, target_frustum=True, velocity=np.zeros(3),
            )
        )  # fmt: skip
