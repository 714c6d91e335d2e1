"""CasADi NMPC of section III: model (15), error signal (16)-(17), OCP (18)-(19).

The NLP (direct multiple shooting, N_p = 50 nodes) is built once in ``NMPC.__init__`` with
``nlpsol`` and solved every control step from the shifted previous solution.

Decisions where the paper is silent or inconsistent (see the module-level notes below and
docs/conventions.md):

* psi is fed relative to its reference, ``psi* + wrap(psi - psi*)``, so the cost sees the
  wrapped angle error; psi is not bounded (Table I's [0, 180 deg] contradicts psi* = -pi/2).
* Table I's bounds on x1, x2, x3 are soft with an exact L1 penalty, so a state outside them
  (target at the image edge, too close) never makes the NLP infeasible. Table II is hard.
* Error signal (16): eps_k = s_k - s_m,k with s_m,k the model's one-step prediction made at
  the previous step from the state and input of that step; (19)'s ``s_m,k = s_k`` is read as
  the initial node of the new prediction. s_d = s* - eps_k is constant over the horizon (17).
* u_d of (19): u_d,k = [vq_cam, 0], u_d,k+n+1 = u_d,k+n + [aq_cam dt, 0]; the target velocity
  inside the prediction model follows the same ramp.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import math
import os
import shutil
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field, replace

import casadi as ca
import numba
import numpy as np

from uavtrack_env.config import DT, ControlLimits
from uavtrack_env.control import jit_cache
from uavtrack_env.control.config import FeatureBounds, NMPCConfig
from uavtrack_env.geometry import feature_rates, wrap_scalar

_TWO_PI = 2.0 * math.pi


@dataclass
class NMPCResult:
    """Outcome of one NMPC step."""

    u: np.ndarray
    """First input u_k (4,), camera frame, SI units, within Table II."""
    success: bool
    """True when the solver converged (or, for 'rti', when its single QP solved)."""
    status: str
    """Solver return status ('Solve_Succeeded' for every converged warm solve, whose statistics
    are not read), or 'fallback-shifted' / 'fallback-hover'."""
    iterations: int
    """Solver iterations; -1 for a warm solve that succeeded, whose statistics are not read
    (CasADi's ``stats()`` costs ~65 us per solve; `NMPC.last_stats` reads them)."""
    solve_time_s: float
    predicted_s: np.ndarray
    """Predicted features (N_p+1, 4), psi relative to the reference (psi* +- pi)."""
    predicted_u: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    """Planned inputs (N_p, 4) of the plan that ``u`` comes from."""
    solver_status: str = ""
    """Raw solver status, also on a fallback."""
    solver_used: str = ""
    """'ipopt' or 'sqpmethod': cold starts always use Ipopt."""
    eps: np.ndarray = field(default_factory=lambda: np.zeros(4))
    """Error signal eps_k of eq. (16) used in this solve."""


_BUILT: dict[tuple, dict] = {}
"""Built NLPs by (cfg, limits, bounds, W_s): every UAV with the same settings shares one
(the reference enters as a parameter; the warm start lives in the NMPC instance), so a fleet
pays the build, or the JIT compile, once per process."""
_BUILT_ATTRS = (
    "_ix", "_iu", "_isig", "_lbg", "_ubg", "_lbx", "_ubx", "_nw", "_ng", "_shift_w",
    "_shift_g", "_nlp", "_cold_nlpsol", "_nlpsol", "_solver_plugin", "_irow",
)  # fmt: skip


def _vec(name: str, value, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


def _jit_options(build: str) -> dict:
    """CasADi options to JIT-compile a solver's functions through `jit_cache`.

    Sources get fixed names (no random suffix), so the same settings give the same C file and the
    cache hits. CasADi writes the sources to the working directory: build the solvers inside
    `_jit_build_dir` (a private directory per process, removed when the process ends).
    """
    compiler = f'"{sys.executable}" "{jit_cache.__file__}"'
    return {
        "jit": True,
        "compiler": "shell",
        "jit_temp_suffix": False,
        "jit_cleanup": False,
        "jit_options": {
            "flags": ["-O1"],
            "directory": os.path.join(build, ""),
            "compiler": compiler,
            "cleanup": False,
        },
    }


@contextlib.contextmanager
def _jit_build_dir():
    """A fresh directory, made the working directory for the duration (JIT sources land here)."""
    build = tempfile.mkdtemp(prefix="uavtrack-jit-")
    atexit.register(shutil.rmtree, build, True)
    cwd = os.getcwd()
    os.chdir(build)
    try:
        yield build
    finally:
        os.chdir(cwd)


_compiled_rates = numba.njit(cache=True)(feature_rates)


@numba.njit(cache=True)
def _model_step(s, u, vq, dt, rk4):  # pragma: no cover (compiled)
    """`_discrete_model` compiled for numpy arrays (``rk4`` False: Euler): the same formulas,
    equal to CasADi's F_m to ~1e-15."""
    k1 = _compiled_rates(s, u, vq)
    out, x = np.empty(4), np.empty(4)
    if not rk4:
        for i in range(4):
            out[i] = s[i] + dt * k1[i]
        return out
    for i in range(4):
        x[i] = s[i] + dt / 2 * k1[i]
    k2 = _compiled_rates(x, u, vq)
    for i in range(4):
        x[i] = s[i] + dt / 2 * k2[i]
    k3 = _compiled_rates(x, u, vq)
    for i in range(4):
        x[i] = s[i] + dt * k3[i]
    k4 = _compiled_rates(x, u, vq)
    for i in range(4):
        out[i] = s[i] + dt / 6 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i])
    return out


@numba.njit(cache=True)
def _capped_error(s_rel, s_pred, cap):  # pragma: no cover (compiled)
    """eps = s_rel - s_pred of eq. (16) with psi's difference wrapped to (-pi, pi], each
    entry clipped to +-cap."""
    eps = s_rel - s_pred
    eps[3] = math.pi - (math.pi - eps[3]) % _TWO_PI
    for i in range(4):
        eps[i] = min(max(eps[i], -cap[i]), cap[i])
    return eps


@functools.cache
def _discrete_model(dt: float, integrator: str) -> ca.Function:
    """F_m of eq. (19): eq. (15) integrated over one sampling time dt."""
    s, u, vq = ca.SX.sym("s", 4), ca.SX.sym("u", 4), ca.SX.sym("vq", 3)

    def f(x):
        return ca.vertcat(*feature_rates(x, u, vq))

    if integrator == "euler":
        s_next = s + dt * f(s)
    else:
        k1 = f(s)
        k2 = f(s + dt / 2 * k1)
        k3 = f(s + dt / 2 * k2)
        k4 = f(s + dt * k3)
        s_next = s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("F_m", [s, u, vq], [s_next], ["s", "u", "vq"], ["s_next"])


class _BufferedSolver:
    """An nlpsol called through CasADi's buffer API: numpy arrays in and out.

    Converting the ~550-long vectors to and from DM cost ~0.5 ms per solve here (10 % of it).
    Offers the two methods `NMPC._call` uses of a Function: ``call(dict)`` and ``stats()``.
    """

    def __init__(self, function: ca.Function) -> None:
        self.function = function
        self._buf, self._run = function.buffer()
        self._names_in, self._names_out = function.name_in(), function.name_out()
        self._in = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        self._out = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        for i, a in enumerate(self._in):
            self._buf.set_arg(i, memoryview(a))
        for i, a in enumerate(self._out):
            self._buf.set_res(i, memoryview(a))

    def call(self, args: dict) -> dict[str, np.ndarray]:
        """Evaluate with the given inputs (missing ones are zero); returns copies of the outputs."""
        for name, a in zip(self._names_in, self._in, strict=True):
            a[:] = args.get(name, 0.0)
        self._run()
        return {name: a.copy() for name, a in zip(self._names_out, self._out, strict=True)}

    def stats(self) -> dict:
        """Statistics of the last call."""
        return self._buf.stats()


class NMPC:
    """The tracking NMPC of eqs. (18)-(19) for one UAV; the NLP is built once here.

    ``solve(s, vq_cam, aq_cam)`` returns the first optimal input; a solver failure falls back to
    the shifted previous plan, else to hovering with the target (u = [vq_cam, 0], clipped).
    Solvers: 'ipopt' (the paper's), 'sqp' (sqpmethod + qrqp, Gauss-Newton Hessian,
    warm-started) and 'rti' (one SQP iteration per step).
    """

    def __init__(
        self,
        reference: np.ndarray,
        cfg: NMPCConfig = NMPCConfig(),  # noqa: B008 (frozen dataclass)
        limits: ControlLimits = ControlLimits(),  # noqa: B008
        bounds: FeatureBounds = FeatureBounds(),  # noqa: B008
        **overrides,
    ) -> None:
        """``overrides``: `NMPCConfig` fields replaced in ``cfg``, e.g. ``error_signal=False``."""
        self.reference = _vec("reference", reference, 4).copy()
        if overrides:
            cfg = replace(cfg, **overrides)
        if cfg.solver not in ("sqp", "ipopt", "rti"):
            raise ValueError(f"solver must be 'sqp', 'ipopt' or 'rti', got {cfg.solver!r}")
        self.cfg, self.limits, self.bounds = cfg, limits, bounds
        self.N = cfg.horizon
        self._F = _discrete_model(DT, cfg.integrator)
        self.w_terminal = (
            self._lqr_weight() if cfg.terminal_weight == "lqr" else np.diag(cfg.w_s).astype(float)
        )
        """W_s of eq. (18) in this controller's NLP (4, 4)."""
        key = (cfg, limits, bounds, self.w_terminal.tobytes())
        built = _BUILT.get(key)
        if built is None:
            self._build()
            built = _BUILT[key] = {k: self.__dict__[k] for k in _BUILT_ATTRS}
        self.__dict__.update(built)
        # Per instance: the buffers hold this controller's solver memory.
        self._solver = _BufferedSolver(self._nlpsol)
        self._cold_solver = _BufferedSolver(self._cold_nlpsol)
        self._umax = limits.scale  # Table II
        self._eps_cap = np.asarray(cfg.eps_max, float)
        self.reset()

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        """Build the NLP of eqs. (18)-(19) by direct multiple shooting, and its solvers."""
        nr, K = self.cfg.safety_rows, self.cfg.safety_row_stages or self.N
        nw = self._layout(K)
        w = ca.MX.sym("w", nw)
        # Parameters: s_k (4), s_d (4), vq_cam (3), aq_cam (3), omega_d (1), then nr rows
        # a_c (3 nr) and b (nr).
        p = ca.MX.sym("p", 15 + 4 * nr)
        cost, g, lbg, ubg = self._tracking_problem(w, p)
        if nr:
            cost = self._add_safety_rows(w, p, K, cost, g, lbg, ubg)
        g = ca.vertcat(*g)
        self._lbg, self._ubg = np.concatenate(lbg), np.concatenate(ubg)
        self._nw, self._ng = nw, g.shape[0]
        self._lbx, self._ubx = self._variable_bounds()
        self._shift_w, self._shift_g = self._shift_indices(K)

        nlp = {"x": w, "p": p, "f": cost, "g": g}
        self._nlp = nlp
        if self.cfg.jit is False or (self.cfg.jit is None and not jit_cache.auto_enabled()):
            self._make_solvers(nlp, {}, {})
            return
        with _jit_build_dir() as build:
            jit = _jit_options(build)
            if self.cfg.jit:
                self._make_solvers(nlp, jit, jit)
                return
            try:
                self._make_solvers(nlp, {}, jit)
            except RuntimeError as err:  # a compiler that fails: run interpreted
                warnings.warn(
                    f"NMPC: compiling the solver failed, running it interpreted ({err})",
                    RuntimeWarning,
                    stacklevel=2,
                )
                self._make_solvers(nlp, {}, {})

    def _layout(self, K: int) -> int:
        """Index the decision vector (safety half-spaces on stages 0..K-1); returns its length.

        Stage-wise: x_0, u_0, rho_0, x_1, u_1, rho_1, sig_1, ..., x_N, sig_N (sig: slacks of
        Table I's soft bounds; rho: the safety half-spaces' L1 slacks on stages 0..K-1, or one
        set after x_N when `NMPCConfig.safety_row_slack` is 'shared').
        """
        N, nr = self.N, self.cfg.safety_rows
        per_stage = nr > 0 and self.cfg.safety_row_slack == "stage"
        names, sizes = [], []
        for n in range(N + 1):
            names.append(("x", n))
            sizes.append(4)
            if n < N:
                names.append(("u", n))
                sizes.append(4)
            if per_stage and n < K:
                names.append(("rho", n))
                sizes.append(nr)
            if n >= 1:
                names.append(("sig", n))
                sizes.append(3)
        if nr and not per_stage:
            names.append(("rho", 0))
            sizes.append(nr)
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        index = {key: np.arange(offsets[i], offsets[i + 1]) for i, key in enumerate(names)}
        self._ix = np.stack([index[("x", n)] for n in range(N + 1)])  # (N+1, 4)
        self._iu = np.stack([index[("u", n)] for n in range(N)])  # (N, 4)
        self._isig = np.stack([index[("sig", n)] for n in range(1, N + 1)])  # (N, 3)
        # L1 slacks of the safety half-spaces: (K, nr) per stage, (1, nr) shared
        rho = [index[key] for key in names if key[0] == "rho"]
        self._irow = np.stack(rho) if rho else np.zeros((0, 0), int)
        return int(offsets[-1])

    def _tracking_problem(self, w: ca.MX, p: ca.MX) -> tuple[ca.MX, list, list, list]:
        """Cost (18) and constraints (19) with Table I's bounds softened: cost, g, lbg, ubg.

        g rows: 4 for the initial node, then per stage 4 dynamics and 6 soft bounds.
        """
        N, cfg = self.N, self.cfg
        s0, s_d, vq, aq, w_d = p[0:4], p[4:8], p[8:11], p[11:14], p[14]
        Q, R = (ca.diag(ca.DM(v)) for v in (cfg.q_s, cfg.r_u))
        # W_s of (18): diagonal, or a full matrix for 'lqr' (it is part of the build key)
        W = ca.sparsify(ca.DM(self.w_terminal))
        lo = np.array([self.bounds.x1[0], self.bounds.x2[0], self.bounds.x3[0]])
        hi = np.array([self.bounds.x1[1], self.bounds.x2[1], self.bounds.x3[1]])

        def X(n):
            return w[int(self._ix[n, 0]) : int(self._ix[n, 0]) + 4]

        def U(n):
            return w[int(self._iu[n, 0]) : int(self._iu[n, 0]) + 4]

        def SIG(n):
            return w[int(self._isig[n - 1, 0]) : int(self._isig[n - 1, 0]) + 3]

        cost = 0
        g, lbg, ubg = [X(0) - s0], [np.zeros(4)], [np.zeros(4)]  # (19): s_m,k = s_k
        for n in range(N):
            vq_n = vq + aq * (n * DT)  # (19): u_d,k+n = u_d,k + n [a_q dt, 0]
            u_d = ca.vertcat(vq_n, w_d)  # w_d = 0 in the paper
            e_s, e_u = X(n) - s_d, U(n) - u_d
            cost += ca.bilin(Q, e_s, e_s) + ca.bilin(R, e_u, e_u)  # stage cost of (18)
            g.append(X(n + 1) - self._F(X(n), U(n), vq_n))  # (19): s_m,k+n+1 = F_m(...)
            lbg.append(np.zeros(4))
            ubg.append(np.zeros(4))
            # Table I as soft bounds: lo - sig <= x_{1:3} <= hi + sig, sig >= 0, L1 penalty.
            xs, sig = X(n + 1)[0:3], SIG(n + 1)
            g += [xs + sig, xs - sig]
            lbg += [lo, np.full(3, -np.inf)]
            ubg += [np.full(3, np.inf), hi]
            cost += cfg.slack_weight * ca.sum1(sig)
        e_N = X(N) - s_d
        cost += ca.bilin(W, e_N, e_N)  # terminal cost of (18)
        return cost, g, lbg, ubg

    def _add_safety_rows(
        self, w: ca.MX, p: ca.MX, K: int, cost: ca.MX, g: list, lbg: list, ubg: list
    ) -> ca.MX:
        """Append the shield's half-spaces a_c v <= b (47) on the velocities of plan stages
        0..K-1, L1-softened, to g, lbg, ubg; returns the cost with their penalty."""
        nr = self.cfg.safety_rows
        rows_a = ca.reshape(p[15 : 15 + 3 * nr], 3, nr).T
        rows_b = p[15 + 3 * nr :]
        for n in range(K):  # stage n's slacks, or the shared ones (penalised once)
            first = int(self._irow[min(n, len(self._irow) - 1), 0])
            slack = w[first : first + nr]
            u_n = w[int(self._iu[n, 0]) : int(self._iu[n, 0]) + 4]
            g.append(rows_a @ u_n[0:3] - slack - rows_b)
            lbg.append(np.full(nr, -np.inf))
            ubg.append(np.zeros(nr))
            if n < len(self._irow):
                cost += self.cfg.slack_weight * ca.sum1(slack)
        return cost

    def _variable_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """lbx, ubx: Table II on the inputs (hard), slacks >= 0, the states free."""
        lbx, ubx = np.full(self._nw, -np.inf), np.full(self._nw, np.inf)
        umax = self.limits.scale
        lbx[self._iu] = -umax  # Table II, hard
        ubx[self._iu] = umax
        lbx[self._isig] = 0.0
        lbx[self._irow] = 0.0
        return lbx, ubx

    def _shift_indices(self, K: int) -> tuple[np.ndarray, np.ndarray]:
        """Warm start by shifting one stage: new node n takes old node n+1 (last one repeated).

        Returns the permutations of the primal vector w and of the constraint rows g.
        """
        N, nr = self.N, self.cfg.safety_rows
        shift_w = np.arange(self._nw)
        for n in range(N + 1):
            m = min(n + 1, N)
            shift_w[self._ix[n]] = self._ix[m]
            if n < N:
                shift_w[self._iu[n]] = self._iu[min(n + 1, N - 1)]
            if n >= 1:
                shift_w[self._isig[n - 1]] = self._isig[m - 1]
        for n in range(len(self._irow)):  # per-stage row slacks shift; a shared one stays
            shift_w[self._irow[n]] = self._irow[min(n + 1, len(self._irow) - 1)]
        # g rows: 4 initial, then per stage 4 dynamics + 6 soft bounds.
        shift_g = np.arange(self._ng)
        for n in range(N):
            m = min(n + 1, N - 1)
            shift_g[4 + 10 * n : 14 + 10 * n] = np.arange(4 + 10 * m, 14 + 10 * m)
        row0 = 4 + 10 * N  # then K blocks of the safety half-spaces
        for n in range(K):
            m = row0 + nr * min(n + 1, K - 1)
            shift_g[row0 + nr * n : row0 + nr * (n + 1)] = np.arange(m, m + nr)
        return shift_w, shift_g

    def _make_solvers(self, nlp: dict, cold_jit: dict, jit: dict) -> None:
        """The Ipopt solver of cold starts and rescues, and the configured solver; ``cold_jit``
        and ``jit``: their JIT options (`_jit_options`, or empty for interpreted)."""
        cfg = self.cfg
        # NaN at a trial point is the solvers' to handle (a failed SQP goes to Ipopt, which cuts
        # the step); a failed solve is reported in NMPCResult, not as one console line per NaN.
        common: dict = {
            # the parameters' multipliers cost a gradient evaluation per solve (~8 %); unused
            "calc_lam_p": False,
            "print_time": False,
            "expand": cfg.expand,
            "error_on_fail": False,
            "show_eval_warnings": False,
        }
        solver = self.cfg.solver
        loud = {"error_on_fail": self._raises_on_failure}
        ipopt_opts = {
            **common,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "ipopt.tol": cfg.ipopt_tol,
            "ipopt.max_iter": max(cfg.max_iter, 100),
        }
        # Cold starts (first step, after a hover fallback) go to Ipopt: an active-set QP
        # from a poor guess can take hundreds of ms, the interior point ~10 ms.
        self._cold_nlpsol = ca.nlpsol(
            "nmpc_cold", "ipopt", nlp, {**ipopt_opts, **cold_jit, "jit_name": "cold"}
        )
        if solver == "ipopt":
            plug = "ipopt"
            sopts = {**ipopt_opts, "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-3}
        else:
            plug = "sqpmethod"
            sopts = {
                **common,
                "qpsol": cfg.qpsol,
                "print_header": False,
                "print_iteration": False,
                "print_status": False,
                "tol_pr": cfg.tol,
                "tol_du": cfg.tol,
                "max_iter": 1 if solver == "rti" else cfg.max_iter,
                "max_iter_ls": cfg.line_search_steps,
                "qpsol_options": self._qp_options(cfg),
            }
            if cfg.hessian == "gauss-newton":
                sopts["hess_lag"] = self._gauss_newton_hessian(nlp)
            else:
                sopts["convexify_strategy"] = "regularize"
        self._nlpsol = ca.nlpsol("nmpc", plug, nlp, {**sopts, **loud, **jit, "jit_name": "nmpc"})
        self._solver_plugin = plug

    def _lqr_weight(self) -> np.ndarray:
        """P of the discrete Riccati equation for (Q_s, R_u) and F_m linearised at s*, u = 0,
        target still (`NMPCConfig.terminal_weight` = 'lqr'). psi* does not enter F_m."""
        from scipy.linalg import solve_discrete_are

        s, u, vq = ca.SX.sym("s", 4), ca.SX.sym("u", 4), ca.SX.sym("vq", 3)
        nxt = self._F(s, u, vq)
        lin = ca.Function("linearised", [s, u, vq], [ca.jacobian(nxt, s), ca.jacobian(nxt, u)])
        A, B = (np.array(m) for m in lin(self.reference, np.zeros(4), np.zeros(3)))
        P = solve_discrete_are(A, B, np.diag(self.cfg.q_s), np.diag(self.cfg.r_u))
        return 0.5 * (P + P.T)

    @staticmethod
    def _qp_options(cfg: NMPCConfig) -> dict:
        qpsol = cfg.qpsol
        base: dict = {"error_on_fail": False}
        if qpsol == "qrqp":
            base.update(print_iter=False, print_header=False, print_info=False)
            base.update(max_iter=cfg.qrqp_max_iter, min_lam=cfg.qrqp_min_lam)
        elif qpsol in ("osqp", "proxqp", "daqp", "hpipm", "qpoases"):
            base["print_time"] = False
            if qpsol == "qpoases":
                base["printLevel"] = "none"
            if qpsol == "osqp":
                base["osqp"] = {"verbose": False}
        return base

    def _gauss_newton_hessian(self, nlp: dict) -> ca.Function:
        """Hessian of cost (18) only, plus a small curvature on the L1 slacks.

        Both only change the SQP step, not the KKT point it converges to; the slack term keeps
        the QPs strictly convex (an active-set QP stalls on the LP-like slack directions).
        """
        w, p = nlp["x"], nlp["p"]
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", nlp["g"].shape[0])
        reg = np.zeros(self._nw)
        reg[self._isig] = self.cfg.slack_hessian
        reg[self._irow] = self.cfg.slack_hessian
        H = lam_f * ca.hessian(nlp["f"], w)[0] + ca.diag(ca.DM(reg))
        return ca.Function(
            "gn_hess", [w, p, lam_f, lam_g], [H], ["x", "p", "lam_f", "lam_g"], ["hess"]
        ).expand()

    # ------------------------------------------------------------------ run
    def reset(self) -> None:
        """Forget the warm start, the last plan and the error signal."""
        self._w: np.ndarray | None = None
        self._lam_g: np.ndarray | None = None
        self._lam_x: np.ndarray | None = None
        self._fallback_count = 0
        # (s_rel, vq, u) of the last step: s_m,k of (16) is predicted from them when needed
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._row_normals: list | None = None  # the plan rows' a_c by slot at the last step

    def relative_state(self, s: np.ndarray) -> np.ndarray:
        """s with psi replaced by psi* + wrap(psi - psi*), so s - s* is the wrapped error."""
        out = np.array(s, dtype=float)
        out[3] = self.reference[3] + wrap_scalar(float(out[3] - self.reference[3]))
        return out

    def predict_one_step(self, s: np.ndarray, u: np.ndarray, vq_cam: np.ndarray) -> np.ndarray:
        """F_m(s, u) of eq. (19) with target velocity vq_cam (numpy in, numpy out).

        A compiled kernel with the same formulas as the CasADi ``F_m`` in the NLP (equal to
        ~1e-15): calling that Function from Python costs ~100x more.
        """
        return _model_step(
            np.asarray(s, float),
            np.asarray(u, float),
            np.asarray(vq_cam, float),
            DT,
            self.cfg.integrator == "rk4",
        )

    def solve(
        self,
        s: np.ndarray,
        vq_cam: np.ndarray,
        aq_cam: np.ndarray | None = None,
        u_applied: np.ndarray | None = None,
        safety_rows: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> NMPCResult:
        """One NMPC step at time t_k.

        s: UKF feature estimate [x1, x2, x3, psi] (psi in any wrap, x3 > 0); vq_cam, aq_cam:
        target velocity and acceleration in the camera frame (for u_d of (19)); u_applied: the
        input actually applied at the previous step if it differs from the NMPC's (e.g. after
        the CBF shield), used for the one-step prediction s_m,k of the error signal (16).
        safety_rows: (A_c (k, 3), b (k,)) half-spaces A_c v <= b on the camera-frame velocity that
        the plan must respect (L1-softened), k <= `NMPCConfig.safety_rows`; only with that > 0.
        """
        s = _vec("s", s, 4)
        if s[2] <= 0:
            raise ValueError(f"s[2] = x3 = 1/Z must be > 0 (target in front), got {s[2]}")
        vq = _vec("vq_cam", vq_cam, 3)
        aq = np.zeros(3) if aq_cam is None else _vec("aq_cam", aq_cam, 3)
        if u_applied is not None:
            u_applied = _vec("u_applied", u_applied, 4)
        t0 = time.perf_counter()
        s_rel = self.relative_state(s)

        eps = self._error_signal(s_rel, u_applied)
        s_d = self.reference - eps  # (17)
        w_d = self.turn_rate_reference(vq, aq)
        p = self._parameters(s_rel, s_d, vq, aq, w_d, safety_rows)
        solver, args = self._initial_guess(s_rel, vq, aq, w_d)
        args.update(p=p, lbx=self._lbx, ubx=self._ubx, lbg=self._lbg, ubg=self._ubg)

        ok, sol, status, iters, used = self._solve_or_rescue(solver, args)
        if ok:
            u, X, Uplan = self._accept(sol, used)
            result_status = status
        else:
            u, X, Uplan, result_status = self._fallback(s_rel, vq)
        self._last = (s_rel, vq, u.copy())
        return NMPCResult(
            u=u,
            success=ok,
            status=result_status,
            iterations=iters,
            solve_time_s=time.perf_counter() - t0,
            predicted_s=X,
            predicted_u=Uplan,
            solver_status=status,
            solver_used=used,
            eps=eps,
        )

    def _error_signal(self, s_rel: np.ndarray, u_applied: np.ndarray | None) -> np.ndarray:
        """eps_k = s_k - s_m,k of eq. (16), psi wrapped, capped at `NMPCConfig.eps_max`.

        s_m,k is the one-step prediction from the last step's state with ``u_applied``, else
        with the input that step returned; zero after a reset or with
        `NMPCConfig.error_signal` off.
        """
        if not self.cfg.error_signal or self._last is None:
            return np.zeros(4)
        s_prev, vq_prev, u_prev = self._last
        s_pred = self.predict_one_step(s_prev, u_prev if u_applied is None else u_applied, vq_prev)
        return _capped_error(s_rel, s_pred, self._eps_cap)

    def _initial_guess(
        self, s_rel: np.ndarray, vq: np.ndarray, aq: np.ndarray, w_d: float
    ) -> tuple[_BufferedSolver, dict]:
        """The solver for this step and its start: Ipopt from `_cold_start` without a previous
        plan, else the configured solver from the shifted previous primal and dual solution."""
        if self._w is None:
            w0 = self._cold_start(s_rel, vq, aq, w_d)
            return self._cold_solver, {"x0": w0}
        w0 = self._w[self._shift_w]
        w0[self._ix[0]] = s_rel
        args = {
            "x0": w0,
            "lam_g0": self._lam_g[self._shift_g],
            "lam_x0": self._lam_x[self._shift_w],
        }
        return self._solver, args

    def _solve_or_rescue(
        self, solver: _BufferedSolver, args: dict
    ) -> tuple[bool, dict | None, str, int, str]:
        """Run ``solver``; if the configured solver fails, re-solve with Ipopt
        (`NMPCConfig.rescue_with_ipopt`). Success, solution, status, iterations, solver used."""
        ok, sol, status, iters = self._call(solver, args)
        used = "ipopt" if solver is self._cold_solver else self._solver_plugin
        if not ok and solver is not self._cold_solver and self.cfg.rescue_with_ipopt:
            ok, sol, status, more = self._call(self._cold_solver, args)
            iters += more
            used = f"{used}+ipopt"
        return ok, sol, status, iters, used

    def _accept(self, sol: dict, used: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keep a converged solution as the next warm start; returns u_k (clipped to Table II),
        the predicted features and the planned inputs."""
        w_opt = self._w = sol["x"]
        self._lam_g, self._lam_x = sol["lam_g"], sol["lam_x"]
        if used != self._solver_plugin and self._solver_plugin != "ipopt":
            # Ipopt's inactive multipliers are tiny but nonzero; an active-set QP would
            # read them as an all-active guess and spend hundreds of iterations dropping them.
            self._lam_g[np.abs(self._lam_g) < 1e-5] = 0.0
            self._lam_x[np.abs(self._lam_x) < 1e-5] = 0.0
        self._fallback_count = 0
        X, Uplan = w_opt[self._ix], w_opt[self._iu]
        u = np.minimum(np.maximum(Uplan[0], -self._umax), self._umax)
        return u, X, Uplan

    def _parameters(
        self,
        s_rel: np.ndarray,
        s_d: np.ndarray,
        vq: np.ndarray,
        aq: np.ndarray,
        w_d: float,
        rows: tuple[np.ndarray, np.ndarray] | None,
    ) -> np.ndarray:
        """The NLP's parameter vector: s_k, s_d, vq_cam, aq_cam, omega_d, then the safety
        half-spaces (a_c row by row, then b; unused slots are 0 <= 1)."""
        nr = self.cfg.safety_rows
        given = None if rows is None else self._check_rows(rows, nr)
        p = np.empty(15 + 4 * nr)
        p[0:4], p[4:8], p[8:11], p[11:14], p[14] = s_rel, s_d, vq, aq, w_d
        a, b = p[15 : 15 + 3 * nr].reshape(nr, 3), p[15 + 3 * nr :]
        a[:], b[:] = 0.0, 1.0
        if given is not None:
            slots = self._row_slots(given[0])
            a[slots], b[slots] = given
        self._row_normals = a.tolist()
        return p

    def _row_slots(self, A: np.ndarray) -> list[int]:
        """The slot of each plan row: the one it had at the last step (the same half-space:
        its normal within 0.05), else a free one. The NLP does not depend on the rows' order,
        but the warm start does: the shifted multipliers of a slot belong to the row that was
        in it (a row moved to another slot cost the SQP ~50 % more iterations on A0)."""
        prev, free = self._row_normals, list(range(self.cfg.safety_rows))
        slots = [-1] * len(A)
        if prev is not None:
            for i, row in enumerate(A.tolist()):
                for j in free:
                    q = prev[j]
                    if max(abs(row[0] - q[0]), abs(row[1] - q[1]), abs(row[2] - q[2])) < 0.05:
                        slots[i] = j
                        free.remove(j)
                        break
        for i in range(len(A)):
            if slots[i] < 0:
                slots[i] = free.pop(0)
        return slots

    @staticmethod
    def _check_rows(rows: tuple[np.ndarray, np.ndarray], nr: int) -> tuple[np.ndarray, np.ndarray]:
        """``rows`` as (A (k, 3), b (k,)) finite arrays with k <= nr, else a ValueError."""
        A_in, b_in = np.asarray(rows[0], float), np.asarray(rows[1], float).reshape(-1)
        k = len(b_in)
        if A_in.shape != (k, 3) or k > nr or not np.isfinite(A_in).all():
            raise ValueError(
                f"safety_rows must be (A (k, 3), b (k,)) with k <= {nr} finite rows, got "
                f"shapes {np.shape(rows[0])}, {np.shape(rows[1])}"
            )
        if not np.isfinite(b_in).all():
            raise ValueError(f"safety_rows b must be finite, got {b_in}")
        return A_in, b_in

    def last_stats(self) -> dict:
        """CasADi's statistics of the per-step solver's last call (return status, iterations,
        time per function)."""
        return self._solver.stats()

    @property
    def _raises_on_failure(self) -> bool:
        """The per-step solver raises on failure, so a success needs no stats() (`_call`); not
        RTI, whose normal exit is the iteration limit, which only stats() tells apart."""
        return self.cfg.solver != "rti"

    def _call(self, solver, args: dict) -> tuple[bool, dict | None, str, int]:
        """Run one nlpsol; success flag, solution, return status, iterations (-1: not read)."""
        loud = solver is self._solver and self._raises_on_failure
        try:
            sol = solver.call(args)
        except RuntimeError as err:  # the per-step solver failed, or a plugin raised
            if not loud:
                return False, None, f"exception: {err}", 0
            stats = solver.stats()
            return False, None, str(stats.get("return_status", err)), stats.get("iter_count", 0)
        if loud:  # it returned, so it converged
            ok = bool(np.isfinite(sol["x"]).all())
            return ok, sol, "Solve_Succeeded" if ok else "non-finite solution", -1
        stats = solver.stats()
        status = str(stats.get("return_status", "unknown"))
        ok = bool(stats.get("success", False))
        if solver is self._solver and self.cfg.solver == "rti":
            # one SQP iteration is the point of RTI: an iteration limit is its normal exit
            ok = ok or stats.get("unified_return_status") == "SOLVER_RET_LIMITED"
        ok = ok and bool(np.isfinite(sol["x"]).all())
        return ok, sol, status, int(stats.get("iter_count", 0))

    def turn_rate_reference(self, vq: np.ndarray, aq: np.ndarray) -> float:
        """omega_cy of u_d in (19): 0 as in the paper, or with `NMPCConfig.yaw_rate_reference`
        = 'target-turn' the target's turn rate -(v x a)_up / |v_h|^2 from the camera-frame
        velocity and acceleration (camera y points down; its x-z plane is horizontal)."""
        if self.cfg.yaw_rate_reference != "target-turn":
            return 0.0
        vx, vz, ax, az = float(vq[0]), float(vq[2]), float(aq[0]), float(aq[2])
        v2 = vx * vx + vz * vz
        if v2 < self.cfg.turn_rate_min_speed**2:
            return 0.0
        w = (vz * ax - vx * az) / v2
        wmax = float(self._umax[3])
        return min(max(w, -wmax), wmax)

    def _cold_start(
        self, s_rel: np.ndarray, vq: np.ndarray, aq: np.ndarray, w_d: float = 0.0
    ) -> np.ndarray:
        """Initial guess: move with the target (u = u_d), features stay where they are."""
        w0 = np.zeros(self._nw)
        w0[self._ix] = s_rel
        n = np.arange(self.N)[:, None] * DT
        u_d = np.hstack([vq + aq * n, np.full((self.N, 1), w_d)])
        w0[self._iu] = np.clip(u_d, -self._umax, self._umax)
        lo = np.array([self.bounds.x1[0], self.bounds.x2[0], self.bounds.x3[0]])
        hi = np.array([self.bounds.x1[1], self.bounds.x2[1], self.bounds.x3[1]])
        w0[self._isig] = np.maximum(np.maximum(lo - s_rel[:3], s_rel[:3] - hi), 0.0)
        return w0

    def _fallback(self, s_rel: np.ndarray, vq: np.ndarray) -> tuple[np.ndarray, ...]:
        """Defined action on solver failure: shifted previous plan, else hover with the target."""
        umax = self._umax
        if self._w is not None and self._fallback_count < self.cfg.max_fallback_steps:
            self._w = self._w[self._shift_w]
            self._lam_g = self._lam_g[self._shift_g]
            self._fallback_count += 1
            u = np.clip(self._w[self._iu[0]], -umax, umax)
            return u, self._w[self._ix], self._w[self._iu], "fallback-shifted"
        self.reset()
        u = np.clip(np.append(vq, 0.0), -umax, umax)
        return u, np.tile(s_rel, (self.N + 1, 1)), np.tile(u, (self.N, 1)), "fallback-hover"
