"""daqp's C entry point ``daqp_quadprog`` called from compiled (numba) code.

The shield solves a few tiny QPs per UAV-step; through `daqp.solve` each costs a Python call
with its argument conversions on top of the solve. `quadprog` calls the same C function of the
same installed daqp (its extension module exports the symbol) from inside a numba kernel, so a
whole sequence of QP layers runs in one compiled call (`qp_layers`). The problem and result
structs are filled by their field offsets (daqp's ``DAQPProblem``: ``n, m, ms`` then the
pointers ``H, f, A, bupper, blower, sense``, the remaining fields zero; ``DAQPResult``: ``x,
lam`` then ``fval, soft_slack, exitflag``), and the settings are daqp's own defaults
(``daqp_default_settings``) with the shield's primal tolerance. `AVAILABLE` is True only when
a self-check at import gives `daqp.solve`'s answers bit for bit (tests/test_qp_layers.py); the
shield otherwise keeps calling `daqp.solve`.
"""

from __future__ import annotations

import ctypes

import daqp
import llvmlite.binding as llvm
import numba
import numpy as np
from numba import types

_SETTINGS_SLOTS = 64
"""float64 slots reserved for ``DAQPSettings`` (daqp 0.11 uses 17)."""


def _load() -> ctypes.CDLL | None:
    try:
        lib = ctypes.CDLL(daqp.__file__)
        address = ctypes.cast(lib.daqp_quadprog, ctypes.c_void_p).value
    except (OSError, AttributeError):
        return None
    llvm.add_symbol("daqp_quadprog", address)
    return lib


_LIB = _load()
_quadprog = types.ExternalFunction(
    "daqp_quadprog", types.int32(types.voidptr, types.voidptr, types.voidptr)
)


def settings(primal_tol: float) -> np.ndarray:
    """daqp's default settings with ``primal_tol``, as the float64 buffer `quadprog` takes."""
    out = np.zeros(_SETTINGS_SLOTS)
    if _LIB is not None:
        _LIB.daqp_default_settings(ctypes.c_void_p(out.ctypes.data))
    out[0] = primal_tol  # DAQPSettings' first field
    return out


@numba.njit(cache=True)
def quadprog(H, f, G, bu, bl, sense, settings):  # pragma: no cover (compiled)
    """`daqp.solve(H, f, G, bu, bl, sense)` with ``settings``: (x, exitflag). ``bu``/``bl``
    stack the variable bounds then the rows; ``sense`` must be zero (daqp marks it)."""
    nv = f.shape[0]
    m = bu.shape[0]
    problem = np.zeros(16, np.int64)
    problem[0] = nv | (m << 32)  # int n, int m
    problem[1] = m - G.shape[0]  # int ms: the simple bounds
    problem[2] = H.ctypes.data
    problem[3] = f.ctypes.data
    problem[4] = G.ctypes.data
    problem[5] = bu.ctypes.data
    problem[6] = bl.ctypes.data
    problem[7] = sense.ctypes.data
    x = np.zeros(nv)
    lam = np.zeros(m)
    result = np.zeros(16, np.int64)
    result[0] = x.ctypes.data
    result[1] = lam.ctypes.data
    _quadprog(result.ctypes, problem.ctypes, settings.ctypes)
    flag = result[4] & 0xFFFFFFFF  # int exitflag after two pointers and two doubles
    if flag >= 2**31:
        flag -= 2**32
    return x, flag


def _self_check() -> bool:
    """`quadprog` gives `daqp.solve`'s answers bit for bit on a few QPs of the shield's form."""
    if _LIB is None:
        return False
    rng = np.random.default_rng(0)
    tol = 1e-10
    buf = settings(tol)
    for _ in range(20):
        nv, m = 3 + int(rng.integers(0, 3)), int(rng.integers(1, 6))
        H = np.eye(nv)
        H[3:, 3:] *= 1e-6
        f, G = rng.normal(size=nv), rng.normal(size=(m, nv))
        bu = np.concatenate([np.full(nv, 2.0), rng.normal(size=m)])
        bl = np.concatenate([np.full(nv, -2.0), np.full(m, -1e30)])
        x1, _, flag1, _ = daqp.solve(H, f, G, bu, bl, np.zeros(nv + m, np.int32), primal_tol=tol)
        x2, flag2 = quadprog(H, f, G, bu, bl, np.zeros(nv + m, np.int32), buf)
        if flag1 != flag2 or (flag1 >= 1 and not np.array_equal(x1, x2)):
            return False
    return True


AVAILABLE = _self_check()
"""`quadprog` matches `daqp.solve` here (else the shield calls `daqp.solve`)."""
