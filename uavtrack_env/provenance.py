"""What produced a run: the resolved configuration, the command, the commit and the versions.

Every CLI writes `config_record(...)` to ``OUT/config.json`` and puts it under ``"config"`` in
its ``metrics.json``, so a number can always be traced to the settings that made it.
"""

from __future__ import annotations

import dataclasses
import shlex
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

PACKAGES = (
    "uavtrack",
    "numpy",
    "pybullet",
    "pettingzoo",
    "gymnasium",
    "casadi",
    "filterpy",
    "qpsolvers",
    "daqp",
    "proxsuite",
    "stable-baselines3",
    "torch",
    "ray",
)


def git_commit() -> str:
    """The checkout's commit (with ``-dirty`` if it has uncommitted changes), or 'unknown'."""
    root = Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha + ("-dirty" if dirty else "")


def versions() -> dict[str, str]:
    """Installed versions of the packages a result depends on (absent ones left out)."""
    out = {"python": sys.version.split()[0]}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def cli_command(module: str, argv: list[str] | None = None) -> str:
    """``python -m module args...`` as typed (``argv`` None: this process's arguments)."""
    return "python -m " + shlex.join([module, *(sys.argv[1:] if argv is None else argv)])


def config_record(
    preset: str | None,
    env: Any = None,
    expert: Any = None,
    command: str | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """The dict written to ``config.json``: ``preset``, ``command`` (default: this process's),
    ``commit``, ``versions``, the resolved ``env`` (`EnvConfig`) and ``expert``
    (`ExpertConfig`) and any ``extra``."""
    record = {
        "preset": preset,
        "command": command or cli_command(_module_name()),
        "commit": git_commit(),
        "versions": versions(),
        "env": _plain(env),
        "expert": _plain(expert),
    }
    record.update({k: _plain(v) for k, v in extra.items()})
    return record


def _module_name() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return spec.name if spec is not None and spec.name else Path(sys.argv[0]).name


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value
