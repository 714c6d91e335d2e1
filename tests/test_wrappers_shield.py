"""CBFShield: zero violations under hostile policies, minimal corrections, API and bad input."""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import warnings

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test
from pettingzoo.utils.conversions import parallel_to_aec

from uavtrack_env import uavtrack_v0
from uavtrack_env.geometry import world_to_cam_vec
from uavtrack_env.presets import expert_config
from uavtrack_env.runner import run_episode
from uavtrack_env.safety import ShieldMargins, shield_cbf
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.wrappers import CBFShield

EPISODES = 20
STEPS = 200  # 2.5 s at 80 Hz: a full-speed UAV crosses 25 m, the whole random world's formation
MODES = ("uav", "obstacle", "car", "ground", "flee")


@pytest.fixture
def make_env():
    made = []

    def factory(shield: bool = True, **kwargs):
        env = uavtrack_v0.parallel_env(**kwargs)
        made.append(env)
        return CBFShield(env) if shield else env

    yield factory
    for env in made:
        env.close()


# ----------------------------------------------------------------------------- adversaries
def _towards(info: dict, target: np.ndarray, yaw_rate: float) -> np.ndarray:
    """Normalised action flying at full speed (10 m/s) from the UAV towards ``target``."""
    p = info["own"]["position"]
    d = np.asarray(target, float) - p
    d /= max(float(np.linalg.norm(d)), 1e-9)
    return np.r_[world_to_cam_vec(d, info["own"]["yaw"]), yaw_rate]


def collision_seeker(env, infos: dict, rng: np.random.Generator, modes: dict) -> dict:
    """Each UAV dives at its target: nearest UAV, nearest obstacle point, the car, the ground,
    or away from the team (to break the links). Built from ground truth: only a test may."""
    raw = env.unwrapped
    actions = {}
    for agent in env.agents:
        info = infos[agent]
        p = info["own"]["position"]
        others = np.array([infos[b]["own"]["position"] for b in env.agents if b != agent])
        mode = modes[agent]
        if mode in ("uav", "flee") and not len(others):
            mode = "ground"
        if mode == "obstacle" and not len(raw.layout.obstacle_centers):
            mode = "car"
        if mode == "uav":
            goal = others[np.argmin(np.linalg.norm(others - p, axis=1))]
        elif mode == "flee":
            goal = 2 * p - others.mean(axis=0)
        elif mode == "obstacle":
            c, h = raw.layout.obstacle_centers, raw.layout.obstacle_half_extents
            closest = np.clip(p, c - h, c + h)
            goal = closest[np.argmin(np.linalg.norm(closest - p, axis=1))]
        elif mode == "car":
            goal = info["truth"]["target_position"]
        else:
            goal = p - [0.0, 0.0, 10.0]
        actions[agent] = _towards(info, goal, rng.uniform(-1, 1))
    return actions


def uniform_random(env, infos, rng, modes) -> dict:
    return {a: rng.uniform(-1.0, 1.0, 4) for a in env.agents}


POLICIES = {"random": uniform_random, "seeker": collision_seeker}


def _modes(ep: int, agents: list[str]) -> dict[str, str]:
    """Every fifth episode the whole team scatters (links break); otherwise mixed dives."""
    if ep % 5 == 4:
        return dict.fromkeys(agents, "flee")
    return {a: MODES[(ep + i) % 4] for i, a in enumerate(agents)}


EXACT_HARD = ("uav", "obstacle", "floor", "connect")
"""Hard row families whose h the UAV knows exactly (the car's comes from its UKF estimate)."""


@functools.cache
def run_episodes(
    policy: str,
    shield: bool,
    a_max: float | None = None,
    lag_aware: bool = True,
    episodes: int = EPISODES,
    drop: float = 0.0,
) -> dict:
    """Violation counts over seeded random worlds (every step, every agent), and with the shield
    the least barrier value of each `EXACT_HARD` family over every certify call. ``a_max``: run
    under the 'lag' plant with that acceleration bound (None: the integrator); ``lag_aware``:
    the shield's second-order rows under the lag (False: the paper's first-order rows);
    ``drop``: the probability that a message is lost."""
    totals = {"collision": 0, "disconnection": 0, "active": 0, "agent_steps": 0, "statuses": {}}
    totals["min_h"] = dict.fromkeys(EXACT_HARD, math.inf)
    dynamics = {} if a_max is None else {"dynamics": {"model": "lag", "a_max": a_max}}
    for ep in range(episodes):
        raw = uavtrack_v0.parallel_env(
            scenario="random",
            max_cycles=STEPS,
            terminate_on_collision="agent",
            comms={"drop_prob": drop},
            **dynamics,
        )
        if shield:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # first-order rows warn; that is tested apart
                env = CBFShield(raw, expert_config(lag_aware=lag_aware))
        else:
            env = raw
        rng = np.random.default_rng(ep)
        modes = _modes(ep, env.possible_agents)

        def adversary(_obs, infos, env=env, rng=rng, modes=modes):
            return POLICIES[policy](env, infos, rng, modes)

        def tally(infos, env=env):
            for agent, info in infos.items():
                rep = info["shield"]
                totals["active"] += rep["active"]
                totals["statuses"][rep["status"]] = totals["statuses"].get(rep["status"], 0) + 1
                for name, h in env.last_reports[agent].h.items():
                    kind = name.split(":")[0]
                    if kind in EXACT_HARD:
                        totals["min_h"][kind] = min(totals["min_h"][kind], h)

        try:
            m = run_episode(
                env, adversary, seed=100 + ep, steps=STEPS, on_step=tally if shield else None
            ).metrics
        finally:
            env.close()
        totals["collision"] += m["violation_steps"]["collision"]
        totals["disconnection"] += m["violation_steps"]["disconnection"]
        totals["agent_steps"] += m["agent_steps"]
    return totals


@pytest.mark.slow
@pytest.mark.parametrize("policy", sorted(POLICIES))
def test_shield_prevents_every_collision_and_disconnection(policy):
    shielded = run_episodes(policy, True)
    assert shielded["collision"] == 0, shielded
    assert shielded["disconnection"] == 0, shielded
    assert shielded["agent_steps"] == EPISODES * STEPS * 3  # nobody terminated
    assert shielded["active"] > 0.05 * shielded["agent_steps"], shielded  # it did work


@pytest.mark.slow
@pytest.mark.parametrize("policy", sorted(POLICIES))
def test_same_policies_unshielded_violate(policy):
    free = run_episodes(policy, False)
    assert free["collision"] > 0, free
    if policy == "seeker":  # the 'flee' agents break the team's links
        assert free["disconnection"] > 0, free


def _hold(info: dict, goal: np.ndarray) -> np.ndarray:
    """Normalised action flying to ``goal`` (full speed from 2 m away) while facing the car."""
    p, yaw = info["own"]["position"], info["own"]["yaw"]
    to_car = info["truth"]["target_position"] - p
    turn = math.atan2(math.sin(math.atan2(to_car[1], to_car[0]) - yaw),
                      math.cos(math.atan2(to_car[1], to_car[0]) - yaw))  # fmt: skip
    return np.clip(np.r_[world_to_cam_vec(goal - p, yaw) / 2.0, -turn / 0.6], -1.0, 1.0)


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["tuned", "rl"])
def test_the_rl_preset_keeps_a_team_mate_off_the_sight_line(preset):
    """``uav_0`` flies into the shadow of ``uav_1`` (2.6 m behind it on the line from the car,
    12 m away), where the env counts the car occluded. The tuned preset's occlusion rows cover
    the obstacles only and let it; the rl preset's cover the team-mates too and keep the line
    clear."""
    env = uavtrack_v0.parallel_env(
        scenario="random", random_world={"n_obstacles": (0, 0)}, max_cycles=240
    )
    shield = CBFShield(env, expert_config(preset))
    shield.reset(seed=0)
    car = env.unwrapped.target.center()
    posts = {"uav_1": [-12.0, 0.0, 2.0], "uav_2": [-12.0, -8.0, 2.0]}
    start = {"uav_0": car + [-16.0, 6.0, 2.0], **{a: car + o for a, o in posts.items()}}
    infos = _place(shield, start)
    occluded = collided = 0
    for _ in range(200):
        car = infos["uav_1"]["truth"]["target_position"]
        mate = infos["uav_1"]["own"]["position"]
        shadow = car + (mate - car) * (1.0 + 2.6 / np.linalg.norm(mate - car))
        actions = {a: _hold(infos[a], car + posts[a]) for a in posts}
        actions["uav_0"] = _hold(infos["uav_0"], shadow)
        infos = shield.step(actions)[4]
        assert set(infos) == {"uav_0", "uav_1", "uav_2"}
        occluded += infos["uav_0"]["violations"]["occlusion"]
        collided += any(i["violations"]["collision"] for i in infos.values())
    shield.close()
    assert collided == 0
    if preset == "rl":
        assert occluded == 0
    else:
        assert occluded > 30  # the case is hostile: without the team-mate rows it occludes


# ------------------------------------------------------------------ the velocity-lag plant
def test_lag_plant_gets_second_order_rows_by_default(make_env):
    raw = make_env(False, scenario="A", dynamics={"model": "lag"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        shielded = CBFShield(raw)
    assert shielded.filter.options.lag_tau == raw.config.dynamics.tau
    with pytest.warns(UserWarning, match="best effort"):
        CBFShield(raw, expert_config(lag_aware=False))
    assert CBFShield(make_env(False, scenario="A")).filter.options.lag_tau == 0.0


@pytest.mark.slow
def test_second_order_rows_keep_the_barriers_of_the_lag_plant():
    """Without the acceleration clip (the plant the rows assume), hostile seekers never drive an
    exactly known hard barrier below 0 through the second-order rows; the paper's first-order
    rows let the obstacle and floor barriers go negative in the same episodes."""
    second = run_episodes("seeker", True, a_max=1e6, episodes=10)
    assert min(second["min_h"].values()) >= -1e-9, second
    first = run_episodes("seeker", True, a_max=1e6, lag_aware=False, episodes=10)
    assert min(first["min_h"]["obstacle"], first["min_h"]["floor"]) < -0.05, first


@pytest.mark.slow
def test_lag_shield_prevents_collisions_with_the_acceleration_bound():
    """With the env's |a| <= a_max the rows' model is only approximate (a clipped braking
    command brakes less): still no collision and no broken link, thanks to the margins."""
    out = run_episodes("seeker", True, a_max=6.0, episodes=10)
    assert out["collision"] == 0 and out["disconnection"] == 0, out


@pytest.mark.slow
@pytest.mark.parametrize("a_max", [None, 6.0], ids=["integrator", "lag"])
def test_lost_messages_break_neither_collision_nor_connectivity(a_max):
    """Half the messages lost: UAVs steered at each other, at obstacles, the car, the ground
    and away from the team still neither collide nor disconnect (the lost sender's rows stay,
    on its reachable set)."""
    out = run_episodes("seeker", True, a_max=a_max, episodes=10, drop=0.5)
    assert out["collision"] == 0 and out["disconnection"] == 0, out
    free = run_episodes("seeker", False, a_max=a_max, episodes=10, drop=0.5)
    assert free["collision"] > 0 and free["disconnection"] > 0, free


# ---------------------------------------------------------------- unchanged / minimal action
def test_safe_actions_pass_bit_identical(make_env):
    """Far from everything, small actions are not touched: the whole run equals the bare env."""
    shielded, bare = make_env(scenario="A", max_cycles=40), make_env(False, scenario="A")
    obs_s, _ = shielded.reset(seed=3)
    obs_b, _ = bare.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(40):
        actions = {a: (0.05 * rng.uniform(-1, 1, 4)).astype(np.float32) for a in bare.agents}
        obs_s, rew_s, _, _, info_s = shielded.step(actions)
        obs_b, rew_b, _, _, _ = bare.step(actions)
        for a in actions:
            assert info_s[a]["shield"]["active"] is False
            assert info_s[a]["shield"]["status"] == "nominal"
            assert info_s[a]["shield"]["correction_norm"] == 0.0
            np.testing.assert_array_equal(obs_s[a], obs_b[a])
            assert rew_s[a] == rew_b[a]
            np.testing.assert_array_equal(
                info_s[a]["own"]["applied_u"], actions[a] * [10, 10, 10, 0.6]
            )


def _place(env, positions: dict[str, list[float]]) -> dict:
    """Teleport UAVs (test-only), then one zero step so every info reflects the new poses."""
    raw = env.unwrapped
    for agent, p in positions.items():
        raw.position[raw.possible_agents.index(agent)] = p
    _obs, _r, _t, _tr, infos = env.step({a: np.zeros(4) for a in env.agents})
    return infos


def test_floor_correction_is_the_projection(make_env):
    """Only the floor row -V_z <= gamma_z (z - z_min) is active: v_cy is cut to its bound, the
    other components stay (Euclidean projection onto one half-space)."""
    env = make_env(scenario="A", max_cycles=50)
    env.reset(seed=0)
    _place(env, {"uav_1": [-6.0, 0.0, 0.6]})
    cbf = env.cbf
    z = env.unwrapped.position[1, 2]
    nominal = np.array([0.3, 0.8, -0.2, 0.5])  # v_cy = +8 m/s: straight down at 8 m/s
    _o, _r, _t, _tr, infos = env.step(
        {a: nominal if a == "uav_1" else np.zeros(4) for a in env.agents}
    )
    rep = infos["uav_1"]["shield"]
    assert rep["active"] and rep["status"] == "optimal" and rep["active_rows"] == ["floor"]
    expected = nominal * [10, 10, 10, 0.6]
    expected[1] = cbf.gamma_z * (z - cbf.z_min)  # = 3 * 0.1 = 0.3 m/s down
    np.testing.assert_allclose(infos["uav_1"]["own"]["applied_u"], expected, atol=1e-9)
    assert rep["correction_norm"] == pytest.approx(8.0 - expected[1], abs=1e-9)


def test_uav_pair_correction_is_the_projection(make_env):
    """Two UAVs 2.5 m apart, one flying at the other: the half-space of (25) with the shield's
    R_s + 0.05, V_safe = V - max(0, a.V - b) a / |a|^2."""
    env = make_env(scenario="A", max_cycles=50)
    env.reset(seed=0)
    _place(env, {"uav_0": [-6.0, 2.5, 0.85]})
    raw = env.unwrapped
    p0, p1 = raw.position[0].copy(), raw.position[1].copy()
    yaw0 = raw.yaw[0]
    cbf = env.cbf  # the world's R_s = 2 m plus the 5 cm margin
    assert cbf.r_s == pytest.approx(2.05)
    v_world = np.array([0.5, -5.0, 0.0])  # towards uav_1, a little sideways
    nominal = np.r_[world_to_cam_vec(v_world, yaw0) / 10.0, 0.0]
    _o, _r, _t, _tr, infos = env.step(
        {a: nominal if a == "uav_0" else np.zeros(4) for a in env.agents}
    )
    a = -2.0 * (p0 - p1)
    b = 0.5 * cbf.gamma_s * (np.sum((p0 - p1) ** 2) - cbf.r_s**2)
    assert a @ v_world > b  # the nominal violates the row
    v_safe = v_world - (a @ v_world - b) * a / (a @ a)
    rep = infos["uav_0"]["shield"]
    assert rep["active"] and rep["active_rows"] == ["uav:1"], rep
    np.testing.assert_allclose(
        infos["uav_0"]["own"]["applied_u"][:3], world_to_cam_vec(v_safe, yaw0), atol=1e-8
    )
    assert rep["correction_norm"] == pytest.approx(np.linalg.norm(v_safe - v_world), abs=1e-8)


# --------------------------------------------------------------------------- configuration
def test_margins_and_eq28():
    base = CBFConfig().resolve(2.0, 20.0)
    cbf = shield_cbf(base, ShieldMargins())
    assert cbf.r_s == pytest.approx(2.05) and cbf.r_c == pytest.approx(19.95)
    assert cbf.d_s <= cbf.r_c
    # gamma_s = 0.205 satisfies eq. (28) for R_s = 2 (bound 0.2020) but not for 2.05 (0.2082).
    tight = dataclasses.replace(base, gamma_s=0.205)
    bound = 4 * tight.alpha_v * 2.05 / (min(tight.d_s, 19.95) ** 2 - 2.05**2)
    assert tight.gamma_s < bound
    with pytest.raises(ValueError, match=r"eq. \(28\)"):
        shield_cbf(tight, ShieldMargins())


def test_bad_configuration(make_env):
    raw = make_env(False, scenario="A")
    with pytest.raises(TypeError, match="unknown field"):
        CBFShield(raw, expert_config(not_an_option=1))
    with pytest.raises(ValueError, match="unknown preset 'safest'"):
        CBFShield(raw, "safest")
    with pytest.raises(TypeError, match="preset must be a name or an ExpertConfig"):
        CBFShield(raw, 3)
    with pytest.raises(ValueError, match="below the world's collision range"):
        CBFShield(raw, expert_config(cbf={"r_s": 1.0}))
    with pytest.raises(ValueError, match="surface_gap"):
        CBFShield(raw, expert_config(cbf={"z_min": 0.3}))
    with pytest.raises(ValueError, match="r_s_margin"):
        CBFShield(raw, expert_config(margins={"r_s_margin": math.nan}))
    cfg = expert_config(
        shield={"occlusion": False}, margins={"r_s_margin": 0.1}, cbf={"gamma_o": 0.5}
    )
    shielded = CBFShield(raw, cfg)
    assert shielded.filter.options.occlusion is False
    assert shielded.cbf.r_s == pytest.approx(2.1) and shielded.cbf.gamma_o == 0.5
    stricter = CBFShield(raw, expert_config(cbf={"r_s": 3.0, "r_c": 15.0}))
    assert stricter.cbf.r_s == pytest.approx(3.05) and stricter.cbf.r_c == pytest.approx(14.95)


# -------------------------------------------------------------------------- PettingZoo API
def _no_warnings(check, *args, **kwargs) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check(*args, **kwargs)
    assert not caught, [str(w.message) for w in caught]


def test_parallel_api(make_env):
    _no_warnings(parallel_api_test, make_env(scenario="random", max_cycles=60), num_cycles=60)


def test_aec_api(make_env):
    env = make_env(scenario="random", max_cycles=60)
    _no_warnings(api_test, parallel_to_aec(env), num_cycles=60)


def test_parallel_seed():
    made = []

    def build():
        raw = uavtrack_v0.parallel_env(scenario="random", max_cycles=60)
        made.append(raw)
        return CBFShield(raw)

    try:
        _no_warnings(parallel_seed_test, build, num_cycles=60)
    finally:
        for env in made:
            env.close()


def test_multi_step_determinism(make_env):
    envs = [make_env(scenario="random", max_cycles=100) for _ in range(2)]
    runs = []
    for env in envs:
        obs, _ = env.reset(seed=11)
        rng = np.random.default_rng(4)
        trace = []
        for _ in range(100):
            obs, _r, _t, _tr, infos = env.step({a: rng.uniform(-1, 1, 4) for a in env.agents})
            trace.append(
                (
                    np.concatenate([obs[a] for a in sorted(obs)]),
                    [infos[a]["shield"]["action"] for a in sorted(infos)],
                )
            )
        runs.append(trace)
    for (o1, a1), (o2, a2) in zip(*runs, strict=True):
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(np.array(a1), np.array(a2))


# ------------------------------------------------------------------------------ bad input
def _snapshot(env) -> dict:
    raw = env.unwrapped
    return {
        "position": raw.position.copy(),
        "yaw": raw.yaw.copy(),
        "num_cycles": raw.num_cycles,
        "rng": copy.deepcopy(raw.np_random.bit_generator.state),
        "agents": list(raw.agents),
        "estimate": env.onboard["uav_0"].estimate.target_position.copy(),
    }


BAD = [
    ({"uav_0": [np.nan, 0, 0, 0]}, ValueError, "not finite"),
    ({"uav_0": np.zeros(3)}, ValueError, "shape"),
    ({"uav_0": "fast"}, ValueError, "cannot be read"),
    ({"uav_9": np.zeros(4)}, KeyError, "unknown agent"),
    ({}, KeyError, "no action for live agent"),
]


@pytest.mark.parametrize(("patch", "error", "message"), BAD)
def test_bad_actions_raise_like_the_env_and_change_nothing(make_env, patch, error, message):
    env, bare = make_env(scenario="A"), make_env(False, scenario="A")
    env.reset(seed=2)
    bare.reset(seed=2)
    good = {a: np.zeros(4) for a in env.agents}
    actions = {**good, **patch} if patch else {}
    before = _snapshot(env)
    with pytest.raises(error, match=message) as from_shield:
        env.step(actions)
    with pytest.raises(error) as from_env:
        bare.step(actions)
    assert str(from_shield.value) == str(from_env.value)
    after = _snapshot(env)
    for key, value in before.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(after[key], value, err_msg=key)
        else:
            assert after[key] == value, key
    env.step(good)  # still usable


def test_step_before_reset_raises(make_env):
    env = make_env(scenario="A")
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"uav_0": np.zeros(4)})


# ------------------------------------------------------------------------------- telemetry
def test_telemetry_and_the_envs_own_signals(make_env):
    """A 1e30 action is clipped and counted as the bare env would; the info says what the
    policy proposed, what was sent, the least barrier per family and, at the end, a summary."""
    env = make_env(scenario="A", max_cycles=6)
    env.reset(seed=0)
    huge = np.array([1e30, 0.0, 0.0, 0.0])
    steps = 0
    while env.agents:
        steps += 1
        _o, _r, _t, _tr, infos = env.step({a: huge for a in env.agents})
        for info in infos.values():
            rep = info["shield"]
            assert info["action_clipped"] and info["n_clipped_actions"] == steps
            np.testing.assert_array_equal(rep["proposed"], [1.0, 0.0, 0.0, 0.0])
            assert rep["action"].shape == (4,) and np.abs(rep["action"]).max() <= 1.0
            assert {"floor", "uav", "connect"} <= set(rep["min_h"])
            assert rep["min_h"]["floor"] == pytest.approx(info["own"]["position"][2] - 0.5)
            assert rep["min_hard_h"] == min(
                rep["min_h"][k] for k in ("uav", "obstacle", "target", "floor") if k in rep["min_h"]
            )
            assert isinstance(rep["gave_up"], list) and rep["status"] in (
                "nominal", "optimal", "relaxed", "fallback"
            )  # fmt: skip
    for info in infos.values():
        ep = info["shield"]["episode"]
        assert ep["steps"] == 6 and 0 <= ep["interventions"] <= 6
        assert ep["intervention_rate"] == pytest.approx(ep["interventions"] / 6)
        assert ep["mean_correction"] >= 0.0


@pytest.mark.parametrize("live", [[0, 1, 2], [0, 2], [1]])
def test_shield_actions_equal_the_numpy_formulation(live):
    """The certified actions as `CBFShield.step` hands them on: clipped, the env's own u where
    the shield left an action unchanged, finished UAVs untouched."""
    from uavtrack_env.wrappers.shield import shield_actions

    rng = np.random.default_rng(len(live))
    scale = np.array([10.0, 10.0, 10.0, 0.6])
    u = np.zeros((3, 4))
    u[live] = rng.uniform(-1, 1, (len(live), 4)) * scale
    action = u[live] + rng.uniform(-15, 15, (len(live), 4))
    changed_live = np.arange(len(live)) % 2 == 0
    action[~changed_live] = u[live][~changed_live]
    proposed, certified, changed, u_env = shield_actions(
        u, action, changed_live, np.array(live, np.int64), scale
    )
    want_certified = u / scale
    want_certified[live] = np.clip(action / scale, -1.0, 1.0)
    want_changed = np.zeros(3, bool)
    want_changed[live] = changed_live
    np.testing.assert_array_equal(proposed, u / scale)
    np.testing.assert_array_equal(certified, want_certified)
    np.testing.assert_array_equal(changed, want_changed)
    np.testing.assert_array_equal(u_env, np.where(want_changed[:, None], want_certified * scale, u))
