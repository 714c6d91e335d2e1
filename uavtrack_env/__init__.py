"""uavtrack: cooperative, safe visual tracking with drones.

``from uavtrack_env import uavtrack_v0; env = uavtrack_v0.parallel_env(scenario="A")``
"""

from . import uavtrack_v0
from .config import EnvConfig
from .env import UAVTrackEnv
from .sensors import UAVSnapshot
from .uavtrack_v0 import env, parallel_env, raw_env, vector_env

__version__ = "0.1.0"
__all__ = [
    "EnvConfig",
    "UAVSnapshot",
    "UAVTrackEnv",
    "__version__",
    "env",
    "parallel_env",
    "raw_env",
    "uavtrack_v0",
    "vector_env",
]
