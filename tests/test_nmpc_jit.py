"""`NMPCConfig(jit=True)`: the compiled NLP gives the interpreted one's answers, and a second build
reuses the cached objects (slow: one real gcc compile, ~30-80 s; skipped without gcc)."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from uavtrack_env.control import NMPC, NMPCConfig
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
