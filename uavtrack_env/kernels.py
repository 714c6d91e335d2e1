"""Whether numba's cache holds the onboard stack's compiled kernels on this machine.

The estimator, the rows and the CBF-QP's arrays are numba kernels compiled with ``cache=True``:
the first process on a machine compiles them (about a minute here), later ones load them in a
second or two. `kernels_cached` lets a long-running command say so before it seems to hang;
`compile_filter_kernels` builds the kernels an episode would otherwise build late: the
correction at its first corrected action, the NMPC's plan rows at its first estimate.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

from .estimation.bank import _bank_step
from .onboard_pass import observe_frame_step, observe_pass, observe_step
from .safety.cbf import OBSTACLE, CBFRows
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
    pause of ~13 s in mid-episode), and the NMPC's plan rows, `qp_arrays.nearest_camera_rows`.
    Certifies a hover that one obstacle row rejects; the filter is stateless, so nothing else
    changes."""
    one = np.ones(1)
    rows = CBFRows(
        A=np.array([[1.0, 0.0, 0.0]]), b=-one, h=one, gamma=one, drift=0.0 * one,
        margin=0.0 * one, kind=np.array([OBSTACLE], np.int64), index=np.zeros(1, np.int64),
    )  # fmt: skip
    safety_filter.certify_pose(np.zeros(4), 0.0, np.zeros(3), rows)
    safety_filter.camera_rows(rows, 0.0, 1)
