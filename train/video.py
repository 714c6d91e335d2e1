"""Videos of a policy during training (``--video-every``): one episode on the paper's scenario A
(Table VI's first row; shielded if the run is), written by `RecordVideo` as MP4."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from uavtrack_env.config import DT
from uavtrack_env.presets import ExpertConfig
from uavtrack_env.runner import Policy

VIDEO_WORLD = ("A", 0)
"""(scenario, init) of the training videos."""


def record_policy(
    policy: Policy,
    folder: Path,
    name: str,
    *,
    shield: ExpertConfig | None,
    dynamics: str,
    seconds: float = 10.0,
) -> Path:
    """One episode of ``policy`` for ``seconds`` on `VIDEO_WORLD` as an MP4 in ``folder``; returns
    its path (``name-episode-0.mp4``)."""
    from baselines import evaluate
    from uavtrack_env import uavtrack_v0
    from uavtrack_env.wrappers import CBFShield
    from uavtrack_env.wrappers.video import RecordVideo

    steps = max(1, round(seconds / DT))
    kw = evaluate.world_kwargs(*VIDEO_WORLD, steps, dynamics=dynamics, render=True)
    env: Any = RecordVideo(uavtrack_v0.parallel_env(**kw), folder, name_prefix=name)
    if shield is not None:
        env = CBFShield(env, shield)
    obs, infos = env.reset(seed=0)
    while env.agents:
        obs, _, _, _, infos = env.step(policy(obs, infos))
    env.close()
    return env.paths[-1]
