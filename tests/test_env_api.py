"""PettingZoo API conformance of uavtrack_v0, rendering, and argument validation."""

from __future__ import annotations

import functools
import math
import types
import warnings

import numpy as np
import pytest
from pettingzoo.test import (
    api_test,
    max_cycles_test,
    parallel_api_test,
    parallel_seed_test,
    state_test,
)
from pettingzoo.utils.conversions import parallel_to_aec

from uavtrack_env import render as rendering
from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DetectorConfig
from uavtrack_env.safety.config import CBFConfig

SCENARIOS = ["A", "random"]
MAX_CYCLES = 120


@pytest.fixture
def make_env():
    """Factory whose envs are all closed after the test (each owns a PyBullet client)."""
    made = []

    def factory(fn=uavtrack_v0.parallel_env, **kwargs):
        env = fn(**kwargs)
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()


def _tracking_module(made: list, **fixed):
    """A uavtrack_v0-like module whose constructors bind ``fixed`` and record their envs."""

    def wrap(fn):
        @functools.wraps(fn)
        def build(**kwargs):
            env = fn(**{**fixed, **kwargs})
            made.append(env)
            return env

        return build

    return types.SimpleNamespace(
        parallel_env=wrap(uavtrack_v0.parallel_env),
        env=wrap(uavtrack_v0.env),
        raw_env=wrap(uavtrack_v0.raw_env),
    )


def _without_warnings(check, *args, **kwargs) -> None:
    """Run a PettingZoo checker; its warnings flag API problems, so any warning fails."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check(*args, **kwargs)
    assert not caught, [str(w.message) for w in caught]


# ----------------------------------------------------------------- PettingZoo checkers
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_parallel_api(make_env, scenario):
    env = make_env(scenario=scenario, max_cycles=MAX_CYCLES)
    _without_warnings(parallel_api_test, env, num_cycles=MAX_CYCLES)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_aec_api_through_parallel_to_aec(make_env, scenario):
    env = make_env(scenario=scenario, max_cycles=MAX_CYCLES)
    _without_warnings(api_test, parallel_to_aec(env), num_cycles=MAX_CYCLES)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_parallel_seed(scenario):
    made: list = []
    mod = _tracking_module(made, scenario=scenario, max_cycles=MAX_CYCLES)
    try:
        _without_warnings(parallel_seed_test, mod.parallel_env, num_cycles=MAX_CYCLES)
    finally:
        for env in made:
            env.close()


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_max_cycles(scenario):
    made: list = []
    try:
        _without_warnings(max_cycles_test, _tracking_module(made, scenario=scenario))
    finally:
        for env in made:
            env.close()


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_state(make_env, scenario):
    aec = make_env(uavtrack_v0.env, scenario=scenario, max_cycles=MAX_CYCLES)
    par = make_env(scenario=scenario, max_cycles=MAX_CYCLES)
    _without_warnings(state_test, aec, par, num_cycles=20)
    par.reset(seed=0)
    state = par.state()
    assert state.shape == par.state_space.shape and state.dtype == np.float32
    # Layout documented in state(): per UAV [p, sin/cos yaw, v, alive], then the target.
    np.testing.assert_allclose(state[:3], par.position[0], rtol=1e-6)
    np.testing.assert_allclose(state[-8:-5], par.target.center(), rtol=1e-6)


def test_aec_env_runs(make_env):
    env = make_env(uavtrack_v0.env, scenario="A", max_cycles=30)
    env.reset(seed=3)
    assert env.possible_agents == ["uav_0", "uav_1", "uav_2"]
    steps = 0
    for agent in env.agent_iter():
        obs, reward, term, trunc, _info = env.last()
        assert math.isfinite(float(reward))
        assert obs.shape == env.observation_space(agent).shape and obs.dtype == np.float32
        action = None if (term or trunc) else 0.1 * env.action_space(agent).sample()
        env.step(action)
        steps += 1
    # 30 cycles x 3 agents, plus one None step per agent when they are truncated.
    assert steps == 30 * 3 + 3


def test_observation_fields_add_up(make_env):
    env = make_env(scenario="A", n_neighbours=2, n_obstacles_obs=3)
    obs, _ = env.reset(seed=0)
    size = sum(f[1] for f in env.observation_fields())
    assert size == env.observation_space("uav_0").shape[0] == obs["uav_0"].shape[0]
    assert env.observation_space("uav_0").dtype == np.float32
    assert env.action_space("uav_0").shape == (4,)
    assert np.all(env.action_space("uav_0").low == -1) and np.all(
        env.action_space("uav_0").high == 1
    )


def _legacy_bounds(cfg) -> tuple[list[float], list[float]]:
    """The observation bounds as they were written out by hand before issue 15 (a pin)."""
    v, w, r_c = 2.0 * cfg.limits.v_max, 2.0 * cfg.limits.omega_max, cfg.comms.r_c
    inv = 1 / cfg.camera.near
    own_hi = [5, 5, inv, 1, 1, 1, 1, v, v, v, w, 1, 1, 100.0, 5, 5, inv, 1, 1]
    own_lo = [-5, -5, 0, -1, -1, 0, 0, -v, -v, -v, -w, -1, -1, 0, -5, -5, 0, -1, -1]
    nb_hi, nb_lo = [r_c, r_c, r_c, 1] * cfg.n_neighbours, [-r_c, -r_c, -r_c, 0] * cfg.n_neighbours
    d = 100.0
    ob_hi = [d, d, d, d, d, d, 1] * cfg.n_obstacles_obs
    ob_lo = [-d, -d, -d, 0, 0, 0, 0] * cfg.n_obstacles_obs
    return own_lo + nb_lo + ob_lo, own_hi + nb_hi + ob_hi


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {
            "n_neighbours": 2,
            "n_obstacles_obs": 3,
            "limits": {"v_max": 4.0, "omega_max": 0.3},
            "camera": {"near": 0.25},
            "comms": {"r_c": 12.5},
        },
        {"n_neighbours": 0, "n_obstacles_obs": 0},
    ],
)
def test_observation_bounds_come_from_the_field_table(make_env, kwargs):
    """The space is derived from OWN_FIELDS / NEIGHBOUR_FIELD / OBSTACLE_FIELD, and equals the
    hand-written bounds it replaced, bit for bit."""
    from uavtrack_env.env import NEIGHBOUR_FIELD, OBSTACLE_FIELD, OWN_FIELDS

    env = make_env(scenario="A", **kwargs)
    space = env.observation_space("uav_0")
    lo, hi = _legacy_bounds(env.config)
    np.testing.assert_array_equal(space.low, np.array(lo, np.float32))
    np.testing.assert_array_equal(space.high, np.array(hi, np.float32))
    assert np.all(space.low < space.high)
    fields = env.observation_fields()
    assert [f[:2] for f in fields[: len(OWN_FIELDS)]] == [(f.name, f.size) for f in OWN_FIELDS]
    assert sum(f[1] for f in fields) == space.shape[0]
    for field in (*OWN_FIELDS, NEIGHBOUR_FIELD, OBSTACLE_FIELD):
        low, high = field.low_high(env.config)
        assert len(low) == len(high) == field.size


# ------------------------------------------------------------------------- public seams
def test_validate_actions_is_public_and_pure(make_env):
    env = make_env(scenario="A")
    env.reset(seed=0)
    rng_state = env.np_random.bit_generator.state
    acts = {"uav_0": [0.5, -1.5, 0.0, 1.0], "uav_1": np.zeros(4), "uav_2": [2.0, 0.0, 0.0, -3.0]}
    u, clipped = env.validate_actions(acts)
    assert u.dtype == np.float64 and u.shape == (3, 4)
    assert clipped.dtype == bool and clipped.tolist() == [True, False, True]
    np.testing.assert_array_equal(u[0], [5.0, -10.0, 0.0, 0.6])
    np.testing.assert_array_equal(u[2], [10.0, 0.0, 0.0, -0.6])
    assert env.num_cycles == 0 and env.np_random.bit_generator.state == rng_state
    with pytest.raises(KeyError, match="no action"):
        env.validate_actions({"uav_0": np.zeros(4)})
    with pytest.raises(ValueError, match="not finite"):
        env.validate_actions({**acts, "uav_1": [np.nan, 0, 0, 0]})
    assert not hasattr(env, "_validate")


def test_snapshot_is_a_copy_of_the_true_state(make_env):
    env = make_env(scenario="A")
    with pytest.raises(RuntimeError, match="reset"):
        env.snapshot()
    env.reset(seed=0)
    env.step({a: np.array([0.2, 0.0, 0.1, 0.1]) for a in env.agents})
    snap = env.snapshot()
    with pytest.raises(AttributeError):
        snap.positions = np.zeros((3, 3))  # frozen
    state = env.state().reshape(-1)[: 9 * 3].reshape(3, 9)
    np.testing.assert_allclose(snap.positions, state[:, :3], rtol=1e-6)
    np.testing.assert_allclose(np.sin(snap.yaws), state[:, 3], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(snap.velocities, state[:, 5:8], rtol=1e-6)
    assert snap.alive.tolist() == [True, True, True] and snap.yaw_rates.shape == (3,)
    np.testing.assert_allclose(snap.target_center, env.state()[-8:-5], rtol=1e-6)
    assert isinstance(snap.target_heading, float)
    assert snap.detection is not None and snap.detection.detected.shape == (3,)
    # Copies: scribbling on the snapshot leaves the env (and a fresh snapshot) alone.
    for arr in (snap.positions, snap.yaws, snap.velocities, snap.yaw_rates, snap.target_center):
        arr += 1.0
    snap.alive[:] = False
    snap.detection.detected[:] = ~snap.detection.detected
    fresh = env.snapshot()
    np.testing.assert_allclose(fresh.positions, state[:, :3], rtol=1e-6)
    assert fresh.alive.all()
    np.testing.assert_array_equal(fresh.detection.detected, env.last_detection.detected)
    assert not np.array_equal(fresh.detection.detected, snap.detection.detected)


def test_render_module_does_not_import_the_env():
    """render works from public seams only: no import of env, no private attribute."""
    import ast
    import inspect

    tree = ast.parse(inspect.getsource(rendering))
    modules = [
        node.module
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module is not None
    ]
    assert modules and not any(m == "env" or m.endswith(".env") for m in modules), modules
    privates = [
        node.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute) and node.attr.startswith("_")
    ]
    assert not privates, privates


# ---------------------------------------------------------------------------- rendering
def _reddish(img: np.ndarray) -> np.ndarray:
    """Pixels of the car's red (0.85, 0.1, 0.1) under shading: R dominant and bright."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 90) & (r > 2 * g) & (r > 2 * b)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_rgb_array_frames(make_env, scenario):
    env = make_env(scenario=scenario, render_mode="rgb_array", max_cycles=MAX_CYCLES)
    env.reset(seed=1)
    rng = np.random.default_rng(1)
    for k in range(3):
        frame = env.render()
        assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
        assert frame.ndim == 3 and frame.shape[2] == 3
        assert frame.shape[0] >= 100 and frame.shape[1] >= 100
        assert frame.std() > 10.0, "frame is (nearly) blank"
        # The camera panel (right of the square overview) shows the red car, seen by every camera.
        n = env.config.n_uavs
        assert _reddish(frame[:, rendering.OVERVIEW :]).sum() > 200 * n
        for i in range(n):
            thumb = rendering.camera_view(env.world, env.config, env.layout, env.snapshot(), i)
            assert thumb.dtype == np.uint8 and thumb.shape[2] == 3
            assert _reddish(thumb).sum() > 200, f"camera {i} does not show the car (step {k})"
        env.step({a: 0.05 * rng.uniform(-1, 1, 4) for a in env.agents})


def test_rgb_array_red_pixels_come_from_the_car(make_env):
    """Turning every UAV away from the car empties the camera panel of red pixels."""
    env = make_env(scenario="A", render_mode="rgb_array")
    env.reset(seed=0)
    before = _reddish(env.render()[:, rendering.OVERVIEW :]).sum()
    env.yaw += math.pi
    env.world.set_poses(env.position, env.yaw, env.alive, env.target.center(), env.target.heading)
    after = _reddish(env.render()[:, rendering.OVERVIEW :]).sum()
    assert before > 1000
    assert after < 0.05 * before


def test_render_none_returns_none(make_env):
    env = make_env(scenario="A", render_mode=None)
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gymnasium's "nothing to render" warning is expected
        assert env.render() is None


def test_human_without_display_raises(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match="DISPLAY"):
        uavtrack_v0.parallel_env(scenario="A", render_mode="human")


def test_render_mode_invalid():
    with pytest.raises(ValueError, match="render_mode"):
        uavtrack_v0.parallel_env(render_mode="ascii")


# ---------------------------------------------------------------------- argument checks
def test_unknown_kwargs_raise_type_error():
    with pytest.raises(TypeError, match="max_cycle"):
        uavtrack_v0.parallel_env(max_cycle=10)
    with pytest.raises(TypeError, match="pixel_noise"):
        uavtrack_v0.parallel_env(detector={"pixel_noise": 1.0})
    with pytest.raises(TypeError, match="detector"):
        uavtrack_v0.parallel_env(detector=3.0)


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"scenario": "D"}, "scenario"),
        ({"init": 2}, "init"),
        ({"scenario": "A", "n_uavs": 5}, "n_uavs"),
        ({"n_uavs": 0, "scenario": "random"}, "n_uavs"),
        ({"max_cycles": 0}, "max_cycles"),
        ({"terminate_on_collision": "none"}, "terminate_on_collision"),
        ({"violations": {"r_s": 0.0}}, "r_s"),
        ({"detector": {"pixel_noise_std": -1.0}}, "pixel_noise_std"),
        ({"detector": {"depth_noise_std": -0.1}}, "depth_noise_std"),
        ({"detector": {"psi_noise_std": -0.01}}, "psi_noise_std"),
        ({"detector": {"dropout_prob": 1.5}}, "dropout_prob"),
        ({"comms": {"drop_prob": -0.5}}, "drop_prob"),
        ({"uav_radius": -0.1}, "uav_radius"),
    ],
)
def test_invalid_configs_raise_value_error(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        uavtrack_v0.parallel_env(**kwargs)


def test_cbf_gamma_s_bound_of_eq_28():
    """gamma_s >= 4 alpha_v R_s / (D_s^2 - R_s^2): with Table IV, 4*10*2/(400-4) = 0.20202.

    The bound is checked once R_s, D_s, R_c are known: set, or filled from the world by
    ``resolve()`` (Table IV's R_s = 2, R_c = D_s = 20 by default)."""
    bound = 4 * 10.0 * 2.0 / (20.0**2 - 2.0**2)
    assert CBFConfig(gamma_s=bound * 1.001).resolve().gamma_s > bound
    with pytest.raises(ValueError, match=r"eq\. \(28\)"):
        CBFConfig(gamma_s=bound * 0.999).resolve()
    with pytest.raises(ValueError, match=r"eq\. \(28\)"):
        CBFConfig(gamma_s=bound * 0.999, r_s=2.0, d_s=20.0, r_c=20.0)
    # The bound moves with alpha_v and D_s.
    bound2 = 4 * 5.0 * 2.0 / (10.0**2 - 2.0**2)
    with pytest.raises(ValueError, match=r"eq\. \(28\)"):
        CBFConfig(gamma_s=bound2 * 0.99, alpha_v=5.0, r_s=2.0, d_s=10.0, r_c=20.0)
    CBFConfig(gamma_s=bound2 * 1.01, alpha_v=5.0, r_s=2.0, d_s=10.0, r_c=20.0)


def test_nested_config_objects_and_dicts_agree(make_env):
    a = make_env(scenario="A", detector=DetectorConfig.noiseless())
    b = make_env(
        scenario="A",
        detector={"pixel_noise_std": 0.0, "depth_noise_std": 0.0, "psi_noise_std": 0.0},
    )
    assert a.config.detector == b.config.detector
    oa, _ = a.reset(seed=0)
    ob, _ = b.reset(seed=5)
    for agent in a.agents:  # noiseless: the seed no longer matters for scenario A
        np.testing.assert_array_equal(oa[agent], ob[agent])
