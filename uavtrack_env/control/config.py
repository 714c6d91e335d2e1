"""Settings of the NMPC of section III (Tables I and III): part of `ExpertConfig`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from uavtrack_env.validation import Fields as _Fields
from uavtrack_env.validation import require as _require


@dataclass(frozen=True)
class FeatureBounds:
    """State constraints on the feature vector s = [x1, x2, x3, psi] (Table I).

    Table I bounds psi to [0, 180 deg], which the paper's own references (psi* = -pi/2 for UAV3)
    violate; psi is therefore left unbounded here (see docs/conventions.md).
    """

    x1: tuple[float, float] = (-0.84, 0.84)
    """x1 = X/Z bounds (Table I); +-0.84 is the image's horizontal half-width 320/381.36."""
    x2: tuple[float, float] = (-0.63, 0.63)
    """x2 = Y/Z bounds (Table I); +-0.63 is the image's vertical half-height 240/381.36."""
    x3: tuple[float, float] = (0.07, 1.0)
    """x3 = 1/Z bounds (Table I): depth between 1 m and about 14.3 m."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        f.range_pair("x1", strict=True)
        f.range_pair("x2", strict=True)
        f.range_pair("x3", lo=0, lo_open=True, strict=True)  # 1/Z: the target is in front


@dataclass(frozen=True)
class NMPCConfig:
    """Nonlinear MPC of eqs. (18)-(19): Table III, the planner's extensions (not in the paper),
    then the implementation settings Table III does not fix (integrator, SQP/QP options, JIT).

    The frozen config is the key of the built NLPs (`uavtrack_env.control.nmpc`): UAVs with
    equal configs share one build, or one JIT compile."""

    horizon: int = 50
    """Prediction horizon N_p (Table III)."""
    q_s: tuple[float, float, float, float] = (1.0, 1.0, 100.0, 1.0)
    """Diagonal of Q_s, stage feature weight (Table III; as printed it is indefinite)."""
    r_u: tuple[float, float, float, float] = (0.02, 0.03, 0.01, 0.3)
    """Diagonal of R_u, input weight (Table III; diagonal intent)."""
    w_s: tuple[float, float, float, float] = (1.0, 1.0, 100.0, 1.0)
    """Diagonal of the terminal weight W_s of eq. (18); the paper gives no value, Q_s is used."""
    terminal_weight: Literal["w_s", "lqr"] = "w_s"
    """W_s of eq. (18): 'w_s' = diag(w_s); 'lqr' = the solution P of the discrete Riccati equation
    for Q_s, R_u and the model (19) linearised at the NMPC's reference with the target still, i.e.
    the infinite-horizon cost-to-go. N_p = 50 steps is only 0.625 s, and with W_s = Q_s the loop
    is ~3x slower than the LQR with the same Q_s, R_u (not in the paper)."""
    solver: Literal["sqp", "ipopt", "rti"] = "sqp"
    """NLP solver: 'ipopt' as in the paper, 'sqp' (sqpmethod + qrqp, warm-started), 'rti'."""
    max_iter: int = 20
    """Iteration cap per solve."""
    yaw_rate_reference: Literal["zero", "target-turn"] = "zero"
    """omega_cy of the desired input u_d in (19): 'zero' (the paper) or 'target-turn', the
    target's turn rate from its estimated velocity and acceleration (not in the paper): R_u
    then stops pulling the yaw rate to 0 while the formation turns with the target."""
    turn_rate_min_speed: float = 0.2
    """Below this target speed (m/s) the turn rate is undefined and 0 is used."""
    safety_rows: int = 0
    """Not in the paper: how many of the shield's CBF half-spaces (47) the plan respects on its
    velocities (0 = the paper's NMPC, which does not know the CBF-QP exists). See
    `uavtrack_env.control.nmpc` and docs/conventions.md."""
    safety_row_stages: int | None = None
    """Plan stages 0..K-1 that respect those half-spaces (None: the whole horizon)."""
    safety_row_slack: Literal["shared", "stage"] = "stage"
    """L1 slack of those half-spaces: 'shared', one per half-space over the K stages (its
    penalty prices the worst stage's violation), or 'stage', one per half-space and stage (the
    sum over stages; the QP keeps the stage-banded structure of (19))."""

    # Implementation settings that Table III does not fix.
    integrator: Literal["rk4", "euler"] = "rk4"
    """Discretisation of eq. (15) over one step dt to get F_m of eq. (19)."""
    error_signal: bool = True
    """Use the error signal eps_k of eq. (16) in s_d = s* - eps_k of eq. (17); False: s_d = s*."""
    eps_max: tuple[float, float, float, float] = (0.1, 0.1, 0.05, 0.2)
    """Cap on |eps_k| per feature (not in the paper): a UKF jump must not move s_d far."""
    slack_weight: float = 1000.0
    """L1 penalty on Table I bound violations (exact penalty; not in the paper)."""
    slack_hessian: float = 1.0
    """Curvature added on the slacks in the Gauss-Newton SQP Hessian (step only, not the cost)."""
    hessian: Literal["gauss-newton", "exact"] = "gauss-newton"
    """SQP/RTI Hessian: the constant Hessian of cost (18) ('gauss-newton') or the exact one."""
    qpsol: str = "qrqp"
    """CasADi QP plugin used by 'sqp' and 'rti'."""
    qrqp_min_lam: float = 1e-3
    """qrqp's ``min_lam``: warm-start multipliers below this start inactive. With 0 (qrqp's
    default) the shifted multipliers of the plan's safety rows made qrqp cycle between two
    degenerate active sets (146 SQP failures in the first 12 s of C0 with the tuned planner, 12
    with 1e-3; BENCHMARKS.md, NMPC)."""
    qrqp_max_iter: int = 20
    """qrqp's active-set iterations per QP. The SQP judges convergence on the NLP (`tol`), so a
    QP stopped at the cap only shortens a step, not the solution's accuracy; at 200 the ~3 % of
    C0's solves whose QPs change the active set 40-200 times took 30-390 ms, a third of the
    NMPC's time there (BENCHMARKS.md, NMPC)."""
    tol: float = 3e-3
    """Primal and dual stopping tolerance of 'sqp'. 3e-3 stops after ~2.2 iterations (~3.6 at
    1e-4) with u_k within 1e-3 of Ipopt's (tol 1e-6) in the benchmark loop (BENCHMARKS.md, NMPC)."""
    line_search_steps: int = 0
    """Backtracking steps of the SQP's line search (sqpmethod's ``max_iter_ls``); 0: full steps.
    From the shifted warm start the full step is the accepted one anyway (the same iterations and
    solutions); skipping the merit evaluations makes a solve ~5 % faster. Convergence is judged
    by `tol` either way, and a solve that does not converge goes to Ipopt (BENCHMARKS.md, NMPC)."""
    ipopt_tol: float = 1e-6
    """Stopping tolerance of 'ipopt' (the paper's solver, and the cold starts and rescues)."""
    expand: bool = True
    """Expand the MX graph to SX (faster evaluation)."""
    jit: bool | None = None
    """JIT-compile the NLP's functions with the system C compiler (``$CC``, else gcc or cc) and
    keep the objects in `jit_cache`, so later processes with the same settings load them.
    None (default): compile the per-step solver's functions (sqp, rti or the warm Ipopt; about 20 s
    once per machine and settings, announced on stderr) when a compiler is found and
    ``$UAVTRACK_JIT`` is not ``0``, else run them interpreted; cold starts and rescues stay
    interpreted. True: compile every solver, the cold-start Ipopt too (30-80 s once; needs the
    compiler). False: interpreted. Compiled and interpreted solves agree to 1e-9. See
    BENCHMARKS.md, NMPC."""
    rescue_with_ipopt: bool = True
    """If 'sqp'/'rti' fails, re-solve the same problem with Ipopt before falling back."""
    max_fallback_steps: int = 10
    """Consecutive failures served from the shifted previous plan before hovering."""

    def __post_init__(self) -> None:
        f = _Fields(self)
        horizon = f.integer("horizon", lo=1)
        for name in ("q_s", "r_u", "w_s"):
            f.tuple(name, 4, lo=0)
        f.choice("terminal_weight", ("w_s", "lqr"))
        f.choice("solver", ("sqp", "ipopt", "rti"))
        f.integer("max_iter", lo=1)
        f.choice("yaw_rate_reference", ("zero", "target-turn"))
        f.number("turn_rate_min_speed", lo=0, lo_open=True)
        f.integer("safety_rows", lo=0)
        f.number("safety_row_stages", integer=True, lo=1, hi=horizon, none_means="whole horizon")
        f.choice("safety_row_slack", ("shared", "stage"))
        f.choice("integrator", ("rk4", "euler"))
        f.flag("error_signal")
        f.tuple("eps_max", 4, lo=0)
        f.number("slack_weight", lo=0, lo_open=True)
        f.number("slack_hessian", lo=0)
        f.choice("hessian", ("gauss-newton", "exact"))
        f.text("qpsol")  # any CasADi conic plugin name; CasADi reports unknown ones
        f.number("qrqp_min_lam", lo=0)
        f.integer("qrqp_max_iter", lo=1)
        f.integer("line_search_steps", lo=0)
        f.number("tol", lo=0, lo_open=True)
        f.number("ipopt_tol", lo=0, lo_open=True)
        for name in ("expand", "rescue_with_ipopt"):
            f.flag(name)
        f.choice("jit", (None, True, False))
        f.integer("max_fallback_steps", lo=0)
        _require(
            self.terminal_weight != "lqr" or min(self.r_u) > 0,
            f"NMPCConfig.terminal_weight='lqr' needs every r_u > 0, got r_u = {self.r_u}",
        )
