"""Tracking control: the NMPC of section III (eqs. 15-19)."""

from uavtrack_env.control.config import FeatureBounds, NMPCConfig
from uavtrack_env.control.nmpc import NMPC, NMPCResult

__all__ = ["NMPC", "FeatureBounds", "NMPCConfig", "NMPCResult"]
