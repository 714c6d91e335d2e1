"""`kernels_cached`: whether numba's cache already holds a kernel (the first run's notice)."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np

from uavtrack_env.kernels import kernels_cached, onboard_kernels


def _module_with_a_kernel(tmp_path, monkeypatch):
    """A fresh module whose one kernel has never been compiled (its cache is its own
    directory)."""
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    path = tmp_path / "fresh_kernel.py"
    path.write_text(
        "import numba\n\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2.0 * x\n"
    )
    spec = importlib.util.spec_from_file_location("fresh_kernel", path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "fresh_kernel", module)
    spec.loader.exec_module(module)
    return module


def test_a_kernel_is_cached_only_once_compiled(tmp_path, monkeypatch):
    module = _module_with_a_kernel(tmp_path, monkeypatch)
    assert not kernels_cached([module.twice])
    assert module.twice(1.5) == 3.0  # compiles and writes the cache
    assert kernels_cached([module.twice])


def test_a_shielded_step_leaves_the_onboard_kernels_cached():
    """After one shielded step and one UAV's own certification (the expert's) every kernel
    `onboard_kernels` names is in numba's cache: the list names kernels those use, and the
    runner's notice then stays silent."""
    from uavtrack_env import uavtrack_v0
    from uavtrack_env.wrappers import CBFShield

    env = CBFShield(uavtrack_v0.parallel_env(scenario="random", n_uavs=3, max_cycles=5))
    env.reset(seed=0)
    env.step({a: np.ones(4) for a in env.agents})
    env.onboard["uav_0"].certify(np.full(4, 20.0))
    env.close()
    assert len(onboard_kernels()) == 7
    assert kernels_cached()
