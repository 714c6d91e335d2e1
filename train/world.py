"""The training world of both trainers (`train.ppo` and `train.rllib_ppo`).

One definition, so that SB3 and RLlib optimise the same problem and their per-agent returns
compare: seeded random worlds, UAVs started off formation (Table VI's second rows are the
hard case), and the env's RL defaults for the reward and for what a collision ends.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from uavtrack_env.config import EnvConfig, RandomWorldConfig, RewardConfig

_ENV = EnvConfig()
_REWARD = RewardConfig()
_RANDOM = RandomWorldConfig()


@dataclass(frozen=True)
class TrainingWorld:
    """The env settings a trainer varies; every other `EnvConfig` field keeps its default."""

    n_uavs: int = field(default=3, metadata={"help": "UAVs per random world"})
    max_cycles: int = field(
        default=1200, metadata={"help": "training episode length (80 Hz steps; 1200 = 15 s)"}
    )
    dynamics: str = field(
        default="integrator",
        metadata={"help": "'integrator' (eq. 3, the shield exact) or 'lag'"},
    )
    terminate_on_collision: str = field(
        default=_ENV.terminate_on_collision,
        metadata={"help": "what a collision ends: 'agent', 'all' or 'never' (only cost)"},
    )
    reward_shape: str = field(
        default=_REWARD.shape,
        metadata={"help": "'exp' (r = exp(-c) in (0, 1]: crashing never pays) or 'cost' (-c)"},
    )
    collision_penalty: float = field(
        default=_REWARD.collision_penalty,
        metadata={"help": "reward subtracted on each step a UAV is in collision"},
    )
    image_weight: float = field(
        default=_REWARD.q[0],
        metadata={
            "help": "reward weight on each image coordinate's error (Q_s's x1 and x2, Table III: "
            "1; x3's is 100)"
        },
    )
    image_point: str = field(
        default=_REWARD.image_point,
        metadata={
            "help": "the image point the reward's x1, x2 errors score: 'box' (the bounding box's "
            "centre, which Table V's RMS measures) or 'center' (the car's centre, eq. 18)"
        },
    )
    start_offset: float = field(
        default=3.0, metadata={"help": "UAV start offset from formation, per axis (m)"}
    )
    start_heading_offset: float = field(
        default=0.3, metadata={"help": "start heading offset from facing the car (rad)"}
    )
    min_obstacles: int = field(
        default=_RANDOM.n_obstacles[0], metadata={"help": "fewest obstacles of a random world"}
    )
    max_obstacles: int = field(
        default=_RANDOM.n_obstacles[1], metadata={"help": "most obstacles of a random world"}
    )
    corridor: float = field(
        default=_RANDOM.corridor,
        metadata={"help": "half-width (m) of the car's path kept free of obstacles"},
    )

    def __post_init__(self) -> None:
        # a derived env field: name the option, not RewardConfig.q[0]
        if not (math.isfinite(self.image_weight) and self.image_weight >= 0):
            raise ValueError(
                f"image_weight (--image-weight) must be a finite number >= 0, got "
                f"{self.image_weight}"
            )

    def env_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``uavtrack_v0.parallel_env`` (checked by `EnvConfig`)."""
        kwargs = {
            "scenario": "random",
            "n_uavs": self.n_uavs,
            "max_cycles": self.max_cycles,
            "terminate_on_collision": self.terminate_on_collision,
            "dynamics": {"model": self.dynamics},
            "reward": {
                "shape": self.reward_shape,
                "collision_penalty": self.collision_penalty,
                "q": (self.image_weight, self.image_weight, *_REWARD.q[2:]),
                "image_point": self.image_point,
            },
            "random_world": {
                "start_offset": self.start_offset,
                "start_heading_offset": self.start_heading_offset,
                "n_obstacles": (self.min_obstacles, self.max_obstacles),
                "corridor": self.corridor,
            },
        }
        EnvConfig.from_kwargs(**kwargs)  # a bad value fails here, naming the field
        return kwargs

    @classmethod
    def from_fields(cls, source: Any) -> TrainingWorld:
        """The world of any object (argparse namespace, dataclass) with these attributes."""
        return cls(**{f.name: getattr(source, f.name) for f in dataclasses.fields(cls)})


WORLD_FIELDS = tuple(f.name for f in dataclasses.fields(TrainingWorld))
"""The names of `TrainingWorld`'s fields (also the trainers' option names, dashed)."""


def add_world_arguments(parser: argparse.ArgumentParser) -> None:
    """``--n-uavs``, ``--max-cycles``, ... on a parser, with `TrainingWorld`'s defaults."""
    for f in dataclasses.fields(TrainingWorld):
        kind = {"int": int, "float": float}.get(str(f.type), str)
        parser.add_argument(
            "--" + f.name.replace("_", "-"),
            type=kind,
            default=f.default,
            help=f"{f.metadata['help']} (default: {f.default})",
        )
