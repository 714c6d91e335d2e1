"""Distributed CBF-QP safety filter (paper sections IV-V, eqs. 20-47).

`SafetyFilter.certify(u_nominal, ctx)` maps a camera-frame command to a safe one using only what
one UAV knows (`SafetyContext`). It is the last stage of the expert and the RL shield.
"""

from uavtrack_env.safety.cbf import (
    KIND_NAMES,
    CBFRows,
    SafetyContext,
    build_rows,
    h_box,
    h_connect,
    h_occlusion,
    h_pair,
)
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.margins import ShieldMargins, shield_cbf
from uavtrack_env.safety.shield import (
    SOLVERS,
    Certificates,
    SafetyFilter,
    ShieldOptions,
    ShieldReport,
    check_eq28,
)

__all__ = [
    "KIND_NAMES",
    "SOLVERS",
    "CBFConfig",
    "CBFRows",
    "Certificates",
    "SafetyContext",
    "SafetyFilter",
    "ShieldMargins",
    "ShieldOptions",
    "ShieldReport",
    "build_rows",
    "check_eq28",
    "h_box",
    "h_connect",
    "h_occlusion",
    "h_pair",
    "shield_cbf",
]
