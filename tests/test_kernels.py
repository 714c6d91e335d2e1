"""`kernels_cached`: whether numba's cache already holds a kernel (the first run's notice)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest

from uavtrack_env.kernels import kernels_cached, onboard_kernels, shield_kernels


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
    `onboard_kernels` and `shield_kernels` name is in numba's cache: the lists name kernels
    those use, and the runner's notice then stays silent; it checks a shield's kernels only
    where a shield wraps the env."""
    from pettingzoo.utils.wrappers import BaseParallelWrapper

    from uavtrack_env import uavtrack_v0
    from uavtrack_env.runner import _kernels_used
    from uavtrack_env.wrappers import CBFShield

    raw = uavtrack_v0.parallel_env(scenario="random", n_uavs=3, max_cycles=5)
    env = CBFShield(raw)
    env.reset(seed=0)
    env.step({a: np.ones(4) for a in env.agents})
    env.onboard["uav_0"].certify(np.full(4, 20.0))
    env.close()
    assert len(onboard_kernels()) == 5 and len(shield_kernels()) == 2
    assert kernels_cached(onboard_kernels() + shield_kernels())
    assert _kernels_used(raw) == onboard_kernels()
    assert _kernels_used(BaseParallelWrapper(env)) == onboard_kernels() + shield_kernels()


@pytest.mark.slow
def test_an_expert_run_leaves_its_kernels_cached(tmp_path):
    """On a machine whose numba cache is empty, an expert episode (the README's job) compiles
    every kernel the runner's first-run notice checks for an unshielded env, the CBF-QP's
    correction kernel included though 20 steps correct nothing, so a second run prints no
    notice (run in fresh processes with their own cache)."""
    script = """
from uavtrack_env import uavtrack_v0
from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.runner import run_episode
env = uavtrack_v0.parallel_env(scenario="A", defaults="paper")
env.reset(seed=0)
expert = ExpertPolicy.from_env(env, "tuned", threads=1)
run_episode(env, expert, seed=0, steps=20, progress=True)
"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), UAVTRACK_JIT="0")
    runs = [
        subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
        for _ in range(2)
    ]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr[-2000:]
    assert "compiling the onboard stack" in runs[0].stderr
    assert "compiling the onboard stack" not in runs[1].stderr


@pytest.mark.slow
def test_the_expert_compiles_its_filter_kernels_before_the_episode():
    """`ExpertPolicy.compile_kernels` (called by the runner before its loop) gives the
    CBF-QP's correction and plan-row kernels, the NMPC's one-step prediction and the lag
    plant's rows of the fallback's car-frustum retry the argument types of the closed loop's
    own calls: a B0 episode with corrected actions, and the retry's rows built from a live
    context, add no second compiled signature (fresh process)."""
    script = """
import dataclasses
from baselines.evaluate import world_kwargs
from uavtrack_env import uavtrack_v0
from uavtrack_env.control.nmpc import _model_step
from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.safety.qp_arrays import nearest_camera_rows
from uavtrack_env.safety.qp_layers import certify_changed
from uavtrack_env.safety.second_order import second_order_rows
kernels = (certify_changed, nearest_camera_rows, _model_step, second_order_rows)
env = uavtrack_v0.parallel_env(**world_kwargs("B", 0, 400, dynamics="lag", noise=True,
                                              render=False))
obs, infos = env.reset(seed=0)
expert = ExpertPolicy.from_env(env, "tuned", threads=1)
assert not any(k.signatures for k in kernels)
expert.compile_kernels()
compiled = [list(k.signatures) for k in kernels]
corrected = 0
while env.agents:
    obs, _, _, _, infos = env.step(expert(obs, infos))
    corrected += sum(bool(s.last_report and s.last_report.active) for s in expert.planners.values())
    if env.num_cycles == 200:
        onboard = expert.onboard["uav_0"]
        onboard.filter.rows(dataclasses.replace(onboard.context(), target_frustum=True))
now = [list(k.signatures) for k in kernels]
print(sum(map(len, compiled)), corrected, now == compiled)
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    n_compiled, corrected, same = run.stdout.split()[-3:]
    assert n_compiled == "4" and int(corrected) > 0 and same == "True", run.stdout
