"""``RecordVideo``: MP4s of a ParallelEnv's episodes (the overview beside every UAV's camera).

Gymnasium's ``RecordVideo`` takes a single-agent ``gymnasium.Env``; this is the same idea for
the PettingZoo ParallelEnv: episodes chosen by ``episode_trigger`` are written to
``video_folder/{name_prefix}-episode-{k}.mp4``, one frame of ``env.render()`` every
``frame_every`` env steps (80 Hz / 4 = 20 fps by default, played in real time). Needs the env
built with ``render_mode="rgb_array"`` and the ``video`` extra (imageio with ffmpeg):
``pip install 'uavtrack[video]'``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from pettingzoo.utils.wrappers import BaseParallelWrapper

from ..config import CONTROL_RATE_HZ


def _writer(path: Path, fps: float) -> Any:
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the MP4 backend)
    except ImportError as exc:
        raise ImportError(
            "RecordVideo writes MP4 with imageio and imageio-ffmpeg: "
            "pip install 'uavtrack[video]' (or pip install imageio imageio-ffmpeg)"
        ) from exc
    return imageio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=16)


class RecordVideo(BaseParallelWrapper):
    """Writes the chosen episodes as MP4s; ``paths`` lists the files written so far."""

    def __init__(
        self,
        env: Any,
        video_folder: str | Path,
        episode_trigger: Callable[[int], bool] | None = None,
        frame_every: int = 4,
        name_prefix: str = "uavtrack",
    ) -> None:
        super().__init__(env)
        if getattr(env, "render_mode", None) != "rgb_array":
            raise ValueError(
                "RecordVideo needs frames: build the env with render_mode='rgb_array', got "
                f"render_mode={getattr(env, 'render_mode', None)!r}"
            )
        if not isinstance(frame_every, int) or frame_every < 1:
            raise ValueError(f"frame_every must be an int >= 1 (env steps), got {frame_every!r}")
        self.video_folder = Path(video_folder)
        self.episode_trigger = episode_trigger or (lambda k: True)
        self.frame_every = frame_every
        self.fps = CONTROL_RATE_HZ / frame_every
        self.name_prefix = name_prefix
        self.episode_id = -1
        self.paths: list[Path] = []
        self._writer: Any = None
        self._steps = 0

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._finish()
        result = self.env.reset(seed=seed, options=options)
        self.episode_id += 1
        self._steps = 0
        if self.episode_trigger(self.episode_id):
            self.video_folder.mkdir(parents=True, exist_ok=True)
            path = self.video_folder / f"{self.name_prefix}-episode-{self.episode_id}.mp4"
            self._writer = _writer(path, self.fps)
            self.paths.append(path)
            self._capture()
        return result

    def step(self, actions: dict[str, Any]):
        result = self.env.step(actions)
        self._steps += 1
        if self._writer is not None and self._steps % self.frame_every == 0:
            self._capture()
        if not self.env.agents:
            self._finish()
        return result

    def _capture(self) -> None:
        self._writer.append_data(self.env.render())

    def _finish(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def close(self) -> None:
        self._finish()
        self.env.close()
