"""The onboard controller's configuration (`ExpertConfig`) and its named presets.

`EnvConfig` describes the world; everything the UAVs' own stack decides (UKF, NMPC, CBF rows and
gains, QP options, margins, the viewpoint layer) is one `ExpertConfig`. `ExpertPolicy`,
`CBFShield`, `baselines.*` and `train.*` all start from ``PRESETS[DEFAULT_PRESET]``:

* ``"tuned"``: the UAVs' default. The tuned planner (LQR terminal weight, the car's turn rate in
  u_d, the shield's rows on the plan's first stages), occlusion rows on the boxes' edges with the
  car's estimated velocity, second-order rows under the velocity-lag model, the viewpoint layer.
* ``"paper"``: the paper's equations exactly: NMPC (18)-(19), occlusion rows (38)-(45) on the box
  centres with n-dot = 0 (43), first-order CBF rows (integrator (3)), the constant x2*.
* ``"paper-planner"``: the paper's NMPC (18)-(19) with the tuned preset's rows and viewpoint.
* ``"rl"`` (`RL_PRESET`, the trainers' default): ``"tuned"`` whose occlusion rows also cover the
  team-mates (`CBFConfig.team_mate_radius` = the UAV radius). The env's occlusion cost counts a
  team-mate on the sight line, so the shield of a learned policy keeps it off that line too.

``expert_config("tuned", cbf={"gamma_o": 0.5})`` overrides fields; `apply_overrides` reads the
CLIs' ``--set cbf.gamma_o=0.5``.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from uavtrack_env.control.config import FeatureBounds, NMPCConfig
from uavtrack_env.control.viewpoint import ViewpointConfig
from uavtrack_env.estimation import UKFConfig
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.margins import ShieldMargins
from uavtrack_env.safety.shield import SOLVERS, ShieldOptions


@dataclass(frozen=True)
class ExpertConfig:
    """Every setting of one UAV's onboard stack: UKF (II-E) -> NMPC (18)-(19) -> CBF-QP (47).

    The defaults are the paper's equations (the ``"paper"`` preset)."""

    ukf: UKFConfig = field(default_factory=lambda: UKFConfig(truncated_v_hold_height=True))
    """Target filter (section II-E); a box cut by the image border gives v from the held height."""
    nmpc: NMPCConfig = field(default_factory=NMPCConfig)
    """The planner of eqs. (18)-(19) (Table III) and how it is solved (integrator, SQP/QP
    settings, JIT; not in the paper)."""
    feature_bounds: FeatureBounds = field(default_factory=FeatureBounds)
    """State constraints S of eq. (19) (Table I)."""
    cbf: CBFConfig = field(default_factory=lambda: CBFConfig(occlusion_point="centre"))
    """CBF rows (25), (34), (45) and their gains (Table IV); R_s and R_c from the world."""
    shield: ShieldOptions = field(default_factory=ShieldOptions)
    """The QP (47): layers, penalties, tolerances (not in Table IV)."""
    margins: ShieldMargins = field(default_factory=ShieldMargins)
    """Margins between the barriers and the env's violation thresholds (not in the paper)."""
    viewpoint: ViewpointConfig = field(default_factory=lambda: ViewpointConfig(enabled=False))
    """The x2* layer that looks over tall boxes (not in the paper; off: the constant x2*)."""
    qp_solver: str = "daqp-direct"
    """QP backend of the CBF-QP (one of `SOLVERS`)."""
    use_cbf: bool = True
    """False: the expert sends the NMPC's input unfiltered (the ``--no-cbf`` ablation)."""
    lag_aware: bool = False
    """Not in the paper: under the env's 'lag' dynamics, certify with second-order rows on the
    actual velocity (`ShieldOptions.lag_tau` = the env's ``dynamics.tau``); False: the paper's
    first-order rows."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value, kind = getattr(self, f.name), _field_type(type(self), f.name)
            if kind is bool:
                if not isinstance(value, bool):
                    raise ValueError(f"{f.name} must be True or False, got {value!r}")
            elif isinstance(kind, type) and not isinstance(value, kind):
                raise TypeError(
                    f"{f.name} must be a {kind.__name__}, got {type(value).__name__}: {value!r}"
                )
        if self.qp_solver not in SOLVERS:
            raise ValueError(f"qp_solver must be one of {SOLVERS}, got {self.qp_solver!r}")
        for name, source in (("lag_tau", "tau"), ("accel_bound", "a_max")):
            if getattr(self.shield, name) != 0.0:
                raise ValueError(
                    f"shield.{name} is set from the env's dynamics.{source} (lag_aware=True); "
                    f"leave it 0, got {getattr(self.shield, name)}"
                )


def expert_config(preset: str | ExpertConfig | None = None, **overrides: Any) -> ExpertConfig:
    """A preset (name or config; None: `DEFAULT_PRESET`) with fields replaced.

    Nested configs may be given as dicts of their fields: ``expert_config("tuned",
    cbf={"gamma_o": 0.5}, use_cbf=False)``. Unknown names raise TypeError listing the valid ones.
    """
    if preset is None:
        preset = DEFAULT_PRESET
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; presets are {sorted(PRESETS)}")
        base = PRESETS[preset]
    elif isinstance(preset, ExpertConfig):
        base = preset
    else:
        raise TypeError(f"preset must be a name or an ExpertConfig, got {type(preset).__name__}")
    return _replace(base, overrides, "")


def apply_overrides(config: ExpertConfig, assignments: list[str]) -> ExpertConfig:
    """Apply ``["cbf.gamma_o=0.5", "use_cbf=false", ...]`` (the CLIs' ``--set``).

    Values are parsed by the field's type: numbers, booleans (true/false), strings, None
    (``none``) and tuples (comma-separated, ``q_s=1,1,100,1``).
    """
    nested: dict[str, Any] = {}
    for item in assignments:
        path, sep, text = item.partition("=")
        if not sep or not path:
            raise ValueError(f"--set takes FIELD=VALUE (e.g. cbf.gamma_o=0.5), got {item!r}")
        *parents, name = path.strip().split(".")
        owner, node = type(config), nested
        for p in parents:
            owner = _nested_type(owner, p, path)
            node = node.setdefault(p, {})
        node[name] = _parse(_field_type(owner, name, path), text.strip(), path)
    return _replace(config, nested, "")


def _replace(obj: Any, overrides: dict[str, Any], prefix: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        where = f" in {prefix.rstrip('.')}" if prefix else ""
        raise TypeError(f"unknown field(s) {unknown}{where}; valid fields are {sorted(names)}")
    values = {}
    for name, value in overrides.items():
        current = getattr(obj, name)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            value = _replace(current, value, f"{prefix}{name}.")
        values[name] = value
    return dataclasses.replace(obj, **values)


def _field_type(owner: type, name: str, path: str | None = None) -> Any:
    hints = typing.get_type_hints(owner)
    if name not in hints:
        fields = sorted(f.name for f in dataclasses.fields(owner))
        raise TypeError(f"unknown field {path or name!r}; {owner.__name__} has {fields}")
    return hints[name]


def _nested_type(owner: type, name: str, path: str) -> type:
    kind = _field_type(owner, name, path)
    if not dataclasses.is_dataclass(kind):
        raise TypeError(f"{path!r}: {owner.__name__}.{name} is not a group of fields")
    return kind


def _parse(kind: Any, text: str, path: str) -> Any:
    """``text`` as a value of type ``kind`` (the annotation of the field at ``path``)."""
    options = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        if text.lower() == "none" and type(None) in options:
            return None
        kind = next(k for k in options if k is not type(None))
        options = typing.get_args(kind)
    origin = typing.get_origin(kind)
    try:
        if kind is bool:
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError("expected true or false")
            return text.lower() in ("true", "1")
        if kind in (int, float):
            return kind(text)
        if origin is tuple:
            items = [t for t in text.split(",") if t.strip()]
            return tuple(_parse(options[0], t.strip(), path) for t in items)
        if origin is typing.Literal:
            if text not in options:
                raise ValueError(f"expected one of {list(options)}")
            return text
        return text
    except (ValueError, StopIteration) as exc:
        raise ValueError(f"--set {path}={text}: cannot read it as {kind}: {exc}") from exc


_TUNED_ROWS = CBFConfig(occlusion_model="moving-target", occlusion_point="edges")
_TUNED = ExpertConfig(
    ukf=UKFConfig(truncated_v_hold_height=True, fit_settle_time=2.0),
    nmpc=NMPCConfig(
        terminal_weight="lqr",
        yaw_rate_reference="target-turn",
        safety_rows=4,
        safety_row_stages=10,
    ),
    cbf=_TUNED_ROWS,
    viewpoint=ViewpointConfig(),
    lag_aware=True,
)

PRESETS: dict[str, ExpertConfig] = {
    "tuned": _TUNED,
    "paper": ExpertConfig(),
    "paper-planner": ExpertConfig(cbf=_TUNED_ROWS, viewpoint=ViewpointConfig(), lag_aware=True),
    "rl": dataclasses.replace(_TUNED, cbf=dataclasses.replace(_TUNED_ROWS, team_mate_radius=None)),
}
"""Named `ExpertConfig` s (module docstring)."""

DEFAULT_PRESET = "tuned"
"""The preset of every entry point but the trainers (`RL_PRESET`) unless told otherwise."""

RL_PRESET = "rl"
"""The trainers' preset (`train.ppo`, `train.rllib_ppo`): their shield and demonstrating expert."""


def add_preset_arguments(parser: Any, default: str = DEFAULT_PRESET) -> None:
    """``--preset NAME`` (``default``) and repeatable ``--set FIELD=VALUE`` on an argparse
    parser; read them back with ``expert_config_from(args.preset, args.set)``."""
    parser.add_argument(
        "--preset",
        default=default,
        choices=sorted(PRESETS),
        help=f"the UAVs' controller settings (uavtrack_env.presets; default {default})",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override an ExpertConfig field, dotted for nested ones (repeatable), "
        "e.g. --set cbf.gamma_o=0.5 --set nmpc.terminal_weight=w_s",
    )


def expert_config_from(preset: str, assignments: list[str] | None = None) -> ExpertConfig:
    """The preset with the CLI's ``--set`` assignments applied."""
    return apply_overrides(expert_config(preset), list(assignments or []))
