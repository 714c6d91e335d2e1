"""Tracking control: the NMPC of section III (eqs. 15-19)."""

from uavtrack_env.control.nmpc import NMPC, NMPCOptions, NMPCResult

__all__ = ["NMPC", "NMPCOptions", "NMPCResult"]
