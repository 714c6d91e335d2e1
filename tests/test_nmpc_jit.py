"""`NMPCConfig.jit`: the compiled NLP gives the interpreted one's answers, a second build reuses the
cached objects, the default compiles the per-step solver only and runs interpreted when compiling
fails (the real compiles are slow, ~20-80 s each; skipped without gcc)."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from uavtrack_env.control import NMPC, NMPCConfig, jit_cache
from uavtrack_env.control import nmpc as nmpc_module

REF = np.array([0.0, 0.188, 1 / 7, math.pi / 2])
STATES = ([0.2, 0.1, 0.12, 1.3], [0.21, 0.1, 0.12, 1.31], [0.22, 0.11, 0.121, 1.33])


def _inputs(ctrl: NMPC) -> np.ndarray:
    vq = np.array([0.5, 0.0, 1.0])
    return np.array([ctrl.solve(np.array(s), vq).u for s in STATES])


@pytest.mark.slow
@pytest.mark.skipif(shutil.which(os.environ.get("CC", "gcc")) is None, reason="needs gcc")
def test_jit_matches_interpreted_and_reuses_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = tmp_path / "cache"
    monkeypatch.setenv("UAVTRACK_JIT_CACHE", str(cache))
    monkeypatch.chdir(tmp_path)
    expected = _inputs(NMPC(REF))  # cold Ipopt, then warm SQP twice

    nmpc_module._BUILT.clear()
    jitted = NMPC(REF, NMPCConfig(jit=True))
    np.testing.assert_allclose(_inputs(jitted), expected, rtol=0, atol=1e-9)
    objects = sorted(p.name for p in cache.glob("*.o"))
    assert len(objects) == 2  # the Ipopt (cold) and the SQP solver
    assert not [p for p in tmp_path.iterdir() if p.name != "cache"]  # no sources left in the cwd

    nmpc_module._BUILT.clear()  # a new process would start like this
    again = NMPC(REF, NMPCConfig(jit=True))
    np.testing.assert_allclose(_inputs(again), expected, rtol=0, atol=1e-9)
    assert sorted(p.name for p in cache.glob("*.o")) == objects  # same sources: cache hits


@pytest.mark.slow
@pytest.mark.skipif(shutil.which(os.environ.get("CC", "gcc")) is None, reason="needs gcc")
def test_default_compiles_the_per_step_solver_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture
) -> None:
    monkeypatch.setenv("UAVTRACK_JIT_CACHE", str(tmp_path))
    monkeypatch.setenv("UAVTRACK_JIT", "1")
    nmpc_module._BUILT.clear()
    expected = _inputs(NMPC(REF, NMPCConfig(jit=False)))
    nmpc_module._BUILT.clear()
    default = NMPC(REF)
    assert "compiling the NMPC's 'nmpc' functions" in capfd.readouterr().err
    assert len(list(tmp_path.glob("*.o"))) == 1  # the SQP; the cold-start Ipopt is interpreted
    np.testing.assert_allclose(_inputs(default), expected, rtol=0, atol=1e-9)
    nmpc_module._BUILT.clear()
    NMPC(REF)
    assert "compiling" not in capfd.readouterr().err  # the next process loads the object


def test_default_runs_interpreted_without_a_working_compiler(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("UAVTRACK_JIT_CACHE", str(tmp_path))
    monkeypatch.setenv("UAVTRACK_JIT", "1")
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    assert jit_cache.auto_enabled()
    nmpc_module._BUILT.clear()
    with pytest.warns(RuntimeWarning, match="compiling the solver failed, running it interpreted"):
        ctrl = NMPC(REF)
    nmpc_module._BUILT.clear()
    np.testing.assert_array_equal(_inputs(ctrl), _inputs(NMPC(REF, NMPCConfig(jit=False))))
    assert not list(tmp_path.glob("*.o"))


def test_jit_off_switches(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("UAVTRACK_JIT", "0")
    assert not jit_cache.auto_enabled()
    monkeypatch.setenv("UAVTRACK_JIT", "1")
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setenv("PATH", "")
    assert jit_cache.compiler() is None and not jit_cache.auto_enabled()
