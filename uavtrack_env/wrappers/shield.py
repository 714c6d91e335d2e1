"""``CBFShield``: the expert's CBF-QP (47) as a safety shield around any policy's actions.

Every step, each agent's proposed (normalised) action goes through `SafetyFilter.certify` with only
what that UAV knows: its own pose (``info["own"]``), the positions its neighbours sent
(``info["neighbours"]``), the known obstacle map (``env.layout``) and its own target estimate from
an `OnboardTracker` (UKF, section II-E) fed with its ``info`` after every reset/step. It never reads
``info["truth"]``. The safe action is handed to the wrapped env; ``info[agent]["shield"]`` says
what happened.

Why margins (`ShieldMargins`): the env counts ``d < R_s`` as a UAV-UAV collision and ``d > R_c`` as
a broken link, while the barriers keep ``h >= 0`` only up to the QP's round-off (~1e-10), i.e.
the closed loop can sit *at* R_s or R_c. The shield therefore certifies with ``R_s + r_s_margin``
and ``R_c - r_c_margin`` (and ``D_s <= R_c``) and re-checks eq. (28) for the inflated R_s. The
car is known only through the UKF: the shield uses a heading-free box around it (horizontal half
extent = the car's half diagonal) inflated by ``target_margin`` plus ``target_sigmas`` standard
deviations of the estimated position (capped at ``target_margin_max``). Obstacle and floor
barriers already leave a gap between the UAV's sphere and the surface (``obstacle_clearance`` and
``z_min`` vs ``uav_radius``); the shield refuses configurations where that gap is below
``surface_gap``.

Guarantees hold for the paper's single-integrator dynamics (eq. 3, ``dynamics.model =
'integrator'``), with every agent shielded and messages not dropped. Under the 'lag' model the
shield certifies with second-order rows (`ShieldOptions.lag_tau` = the env's ``dynamics.tau``
unless given), each UAV differencing its neighbours' messages into velocities; those rows assume
the commanded change of velocity is reachable, i.e. ``|u - v| / tau <= a_max`` is not clipped
(measured in `tests/test_wrappers_shield.py`). ``lag_tau=0`` under the lag model keeps the
paper's first-order rows, a best effort (a warning says so). Before a UAV has ever detected
the car it has no estimate, so no car row (documented limitation).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from uavtrack_env.config import CBFConfig
from uavtrack_env.env import UAVTrackEnv
from uavtrack_env.estimation import UKFConfig
from uavtrack_env.onboard import NeighbourVelocities, OnboardTracker, safety_context
from uavtrack_env.safety import SafetyContext, SafetyFilter, ShieldOptions, ShieldReport
from uavtrack_env.safety.margins import ShieldMargins, shield_cbf
from uavtrack_env.target import CAR_HALF_EXTENTS

_MARGIN_NAMES = {f.name for f in dataclasses.fields(ShieldMargins)}
_OPTION_NAMES = {f.name for f in dataclasses.fields(ShieldOptions)}


class CBFShield(BaseParallelWrapper):
    """PettingZoo ParallelEnv wrapper: every action passes the distributed CBF-QP (47) first.

    Arguments (all keyword, all optional):

    * ``cbf``: a `CBFConfig`, or a dict of its fields to override on ``env.config.cbf``;
      its R_s/R_c may not be looser than the env's (the env's collision/link thresholds).
    * ``solver``: QP backend of `SafetyFilter` (``'daqp-direct'``, ``'daqp'``, ``'proxqp'``).
    * ``ukf``: a `UKFConfig` for the per-agent target trackers.
    * fields of `ShieldOptions` (e.g. ``occlusion=False``) and of `ShieldMargins`.

    Unknown names raise TypeError. Bad actions raise the env's own errors (its validation runs
    first) and change nothing. ``info[agent]["shield"]`` holds ``active``, ``correction_norm``
    (SI units, camera frame), ``status``, ``slack`` (m/s of relaxed soft rows), ``active_rows``,
    ``hard_violation``, ``min_hard_h``, ``action`` (the normalised action sent to the env) and
    ``has_target_estimate``. ``last_reports`` keeps the full `ShieldReport` of each agent.
    """

    def __init__(
        self,
        env: Any,
        *,
        cbf: CBFConfig | dict | None = None,
        solver: str = "daqp-direct",
        ukf: UKFConfig | None = None,
        **config: Any,
    ) -> None:
        super().__init__(env)
        raw = env.unwrapped
        if not isinstance(raw, UAVTrackEnv):
            raise TypeError(f"CBFShield wraps a UAVTrackEnv, got {type(raw).__name__}")
        unknown = sorted(set(config) - _MARGIN_NAMES - _OPTION_NAMES)
        if unknown:
            raise TypeError(
                f"unknown CBFShield argument(s) {unknown}; valid: cbf, solver, ukf, "
                f"{sorted(_OPTION_NAMES)} (ShieldOptions), {sorted(_MARGIN_NAMES)} (ShieldMargins)"
            )
        env_cfg = raw.config
        self.margins = ShieldMargins(**{k: v for k, v in config.items() if k in _MARGIN_NAMES})
        base = self._base_cbf(env_cfg.cbf, cbf)
        gap = self.margins.surface_gap
        if base.obstacle_clearance - env_cfg.uav_radius < gap:
            raise ValueError(
                f"obstacle_clearance {base.obstacle_clearance} m leaves less than surface_gap "
                f"{gap} m around the UAV's sphere (radius {env_cfg.uav_radius} m)"
            )
        if base.z_min - env_cfg.uav_radius < gap:
            raise ValueError(
                f"z_min {base.z_min} m leaves less than surface_gap {gap} m above the ground "
                f"for the UAV's sphere (radius {env_cfg.uav_radius} m)"
            )
        self.cbf = shield_cbf(base, self.margins)
        options = {k: v for k, v in config.items() if k in _OPTION_NAMES}
        if env_cfg.dynamics.model == "lag":
            options.setdefault("lag_tau", env_cfg.dynamics.tau)
        self.filter = SafetyFilter(self.cbf, env_cfg.limits, solver=solver, **options)
        lag_tau = self.filter.options.lag_tau
        if env_cfg.dynamics.model == "lag" and lag_tau != env_cfg.dynamics.tau:
            warnings.warn(
                f"CBFShield certifies with lag_tau = {lag_tau} s but the env's velocity lag is "
                f"dynamics.tau = {env_cfg.dynamics.tau} s: the shield is a best effort",
                stacklevel=2,
            )
        if env_cfg.comms.drop_prob > 0 or env_cfg.comms.r_c < self.cbf.r_c:
            warnings.warn(
                "CBFShield's guarantees assume every message within R_c arrives (comms.drop_prob "
                f"= {env_cfg.comms.drop_prob}, comms.r_c = {env_cfg.comms.r_c} m vs the shield's "
                f"R_c = {self.cbf.r_c} m): the distributed rows (23)-(34) need both UAVs' halves",
                stacklevel=2,
            )
        self._raw = raw
        self._scale = env_cfg.limits.scale
        self._ids = {a: i for i, a in enumerate(raw.possible_agents)}
        self._trackers = {a: OnboardTracker(env_cfg.camera, ukf) for a in raw.possible_agents}
        self._differencers = (
            {a: NeighbourVelocities() for a in raw.possible_agents} if lag_tau > 0 else {}
        )
        self._neighbour_velocities: dict[str, np.ndarray] = {}
        self._infos: dict[str, dict] = {}
        hx, hy, hz = (float(x) for x in CAR_HALF_EXTENTS)
        self._car_half = np.array([math.hypot(hx, hy), math.hypot(hx, hy), hz])
        self.last_reports: dict[str, ShieldReport] = {}

    @staticmethod
    def _base_cbf(env_cbf: CBFConfig, override: CBFConfig | dict | None) -> CBFConfig:
        if override is None:
            return env_cbf
        if isinstance(override, dict):
            valid = {f.name for f in dataclasses.fields(CBFConfig)}
            bad = sorted(set(override) - valid)
            if bad:
                raise TypeError(f"unknown CBFConfig field(s) {bad}; valid: {sorted(valid)}")
            base = dataclasses.replace(env_cbf, **override)
        elif isinstance(override, CBFConfig):
            base = override
        else:
            raise TypeError(f"cbf must be a CBFConfig or a dict, got {type(override).__name__}")
        if base.r_s < env_cbf.r_s or base.r_c > env_cbf.r_c:
            raise ValueError(
                f"the shield's R_s = {base.r_s} / R_c = {base.r_c} are looser than the env's "
                f"collision range {env_cbf.r_s} m / link range {env_cbf.r_c} m"
            )
        return base

    # ------------------------------------------------------------------ API
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        obs, infos = self.env.reset(seed=seed, options=options)
        for tracker in self._trackers.values():
            tracker.reset()
        for differencer in self._differencers.values():
            differencer.reset()
        self.last_reports = {}
        self._observe(infos)
        for info in infos.values():
            info["shield"] = {
                "active": False,
                "correction_norm": 0.0,
                "status": "reset",
                "slack": 0.0,
            }
        return obs, infos

    def step(self, actions: dict[str, Any]):
        # The env's own validation: identical errors, raised before anything changes.
        u, _ = self._raw._validate(actions)
        safe, reports = {}, {}
        for agent, action in actions.items():
            u_safe, report = self.certify(agent, u[self._ids[agent]])
            reports[agent] = report
            # An unchanged action is passed through as given (bit-identical behaviour).
            safe[agent] = np.clip(u_safe / self._scale, -1.0, 1.0) if report.active else action
        obs, rewards, terms, truncs, infos = self.env.step(safe)
        self._observe(infos)
        self.last_reports = reports
        for agent, info in infos.items():
            rep = reports[agent]
            info["shield"] = {
                "active": rep.active,
                "correction_norm": rep.correction_norm,
                "status": rep.status,
                "slack": rep.slack,
                "active_rows": list(rep.active_rows),
                "hard_violation": rep.hard_violation,
                "min_hard_h": rep.min_hard_h,
                "action": np.asarray(safe[agent], np.float64).copy(),
                "has_target_estimate": self._trackers[agent].estimate is not None,
            }
        return obs, rewards, terms, truncs, infos

    # -------------------------------------------------------------- shield
    def certify(self, agent: str, u_nominal: np.ndarray) -> tuple[np.ndarray, ShieldReport]:
        """Certify one agent's SI camera-frame command with what that UAV knows now."""
        info = self._infos.get(agent)
        if info is None:
            raise RuntimeError(f"no observation of {agent!r} yet; call reset() first")
        return self.filter.certify(u_nominal, self.context(agent))

    def context(self, agent: str) -> SafetyContext:
        """The `SafetyContext` of ``agent`` from its latest info and target estimate."""
        info = self._infos[agent]
        est = self._trackers[agent].estimate
        layout = self._raw.layout
        ctx = safety_context(
            info,
            est,
            layout.obstacle_centers,
            layout.obstacle_half_extents,
            self._neighbour_velocities.get(agent),
        )
        # Fields added to the validated context; set in place (like SafetyContext's own
        # __post_init__) since a dataclasses.replace would re-validate every array (~15 us).
        put = object.__setattr__
        put(ctx, "neighbour_ids", tuple(self._ids[a] for a in info["neighbours"]))
        if est is not None:
            # Heading-free car box, inflated for the estimate's uncertainty (module docstring).
            sigma = math.sqrt(max(float(np.max(np.diag(est.covariance)[4:7])), 0.0))
            m = self.margins
            pad = min(m.target_margin + m.target_sigmas * sigma, m.target_margin_max)
            put(ctx, "target_half_extents", self._car_half + pad)
            put(ctx, "target_heading", 0.0)
        return ctx

    def _observe(self, infos: dict[str, dict]) -> None:
        """Feed every live agent's tracker (and, for second-order rows, its neighbours'
        velocities) with its new info and keep the info for certify."""
        for agent, info in infos.items():
            self._trackers[agent].update(info)
            if self._differencers:
                self._neighbour_velocities[agent] = self._differencers[agent](info["neighbours"])
        self._infos = infos
