"""Sensors, collisions, dynamics, the target program and scenario layouts, on built situations."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest
from scipy.sparse.csgraph import connected_components

from uavtrack_env.config import DT, DetectorConfig
from uavtrack_env.geometry import point_box_distance, world_to_cam_vec, wrap_angle

AGENTS = ["uav_0", "uav_1", "uav_2"]
CAR_HALF = np.array([2.3, 0.9, 0.75])
F, CU, CV = 381.36, 320.0, 240.0

# Table VI of the paper, (x, y, heading) of UAV1-3, typed in from the paper.
TABLE_VI = {
    ("A", 0): [(0, 6, -1.57), (-6, 0, 0), (0, -6, 1.57)],
    ("A", 1): [(0, 6, -1.57), (-6, 3, 0), (-3, -6, 1.57)],
    ("B", 0): [(0, 6, -1.57), (-6, 0, 0), (0, -6, 1.57)],
    ("B", 1): [(-4, 5, -0.784), (-8, 0, 0), (-3, -6, 0.784)],
    ("C", 0): [(0, 6, -1.57), (-6, 0, 0), (0, -6, 1.57)],
    ("C", 1): [(-2, 6, -1.2), (-6, 0, 0), (-2, -6, 1.2)],
}


def _zeros(env) -> dict:
    return {a: np.zeros(4) for a in env.agents}


def _teleport(env, i: int, position, yaw: float) -> None:
    env.position[i] = position
    env.yaw[i] = yaw
    env.world.set_poses(env.position, env.yaw, env.alive, env.target.center(), env.target.heading)


def _offset(env, name: str) -> int:
    """Start index of an observation block, from the env's own field table."""
    start = 0
    for field, size, _ in env.observation_fields():
        if field == name:
            return start
        start += size
    raise KeyError(name)


# ------------------------------------------------------------------------ occlusion
def test_box_on_line_of_sight_hides_target(make_env):
    # The box is moved in PyBullet behind the env's back, which the skipped queries do not see
    # (uavtrack_env.broadphase): every ray goes to PyBullet here.
    env = make_env(detector=DetectorConfig.noiseless(), skip_proven_queries=False)
    _, infos = env.reset(seed=0)
    assert infos["uav_0"]["measurement"]["detected"]
    # uav_0 is at (0, 6, 0.85) looking at the car at the origin: a 1 m box 1 m in front of it.
    oid = env.world.obstacle_ids[0]
    p.resetBasePositionAndOrientation(
        oid, [0.0, 5.0, 0.85], [0, 0, 0, 1], physicsClientId=env.world.cid
    )
    _, _, term, _, infos = env.step(_zeros(env))
    assert not any(term.values())
    info = infos["uav_0"]
    assert info["measurement"]["detected"] is False
    assert info["measurement"]["u"] is None
    assert info["measurement"]["visible_fraction"] <= 0.1
    assert info["truth"]["blocked_fraction"] >= 0.9
    assert info["violations"]["occlusion"] is True
    assert info["cost"] >= 1.0
    for other in ("uav_1", "uav_2"):  # the box is not between them and the car
        assert infos[other]["measurement"]["detected"]
        assert not infos[other]["violations"]["occlusion"]
    # Take the box away: the car is seen again.
    p.resetBasePositionAndOrientation(
        oid, [80.0, 80.0, 0.5], [0, 0, 0, 1], physicsClientId=env.world.cid
    )
    _, _, _, _, infos = env.step(_zeros(env))
    assert infos["uav_0"]["measurement"]["detected"] is True
    assert infos["uav_0"]["measurement"]["visible_fraction"] >= 0.5
    assert infos["uav_0"]["violations"]["occlusion"] is False


def test_uav_behind_obstacle_cannot_see(make_env):
    env = make_env(detector=DetectorConfig.noiseless())
    env.reset(seed=0)
    c = env.layout.obstacle_centers[0]
    t = env.target.center()
    away = (c - t)[:2] / np.linalg.norm((c - t)[:2])
    behind = np.array([*(c[:2] + 1.0 * away), c[2]])  # 0.5 m behind the box's far face
    yaw = math.atan2(-away[1], -away[0])  # facing the car
    _teleport(env, 0, behind, yaw)
    det = env.detector.detect(
        env.world,
        env.position,
        env.yaw,
        env.target.center(),
        env.target.heading,
        env.target.heading,
        np.random.default_rng(0),
    )
    assert not det.detected[0] and det.blocked_fraction[0] >= 0.9
    _, _, _, _, infos = env.step(_zeros(env))
    assert infos["uav_0"]["measurement"]["detected"] is False
    assert infos["uav_0"]["violations"]["occlusion"] is True
    # Same distance and heading, but beside the box (2 m sideways): visible.
    side = np.array([-away[1], away[0]])
    _teleport(env, 0, np.array([*(behind[:2] + 2.0 * side), behind[2]]), yaw)
    _, _, _, _, infos = env.step(_zeros(env))
    assert infos["uav_0"]["measurement"]["detected"] is True


@pytest.mark.parametrize("turn", [math.pi, 1.3, -1.3])
def test_target_out_of_image_not_detected(make_env, turn):
    """The car spans +-24 deg seen from uav_0's start; the half FOV is 40 deg: turning by 1.3 rad
    (74 deg) or more puts it fully outside the image."""
    env = make_env(detector=DetectorConfig.noiseless())
    env.reset(seed=0)
    env.yaw[0] += turn
    _, _, _, _, infos = env.step(_zeros(env))
    m = infos["uav_0"]["measurement"]
    assert m["detected"] is False and m["visible_fraction"] == 0.0
    assert infos["uav_1"]["measurement"]["detected"]
    obs, _, _, _, _ = env.step(_zeros(env))
    k = _offset(env, "detection")
    assert obs["uav_0"][k] == 0.0 and obs["uav_1"][k] == 1.0
    assert np.all(obs["uav_0"][_offset(env, "features") : k] == 0.0)


# ------------------------------------------------------------------------- detector
def _hand_corners(env, i: int) -> tuple[list[float], list[float]]:
    """Pixel coordinates (u, v) of the car's 8 projected corners, not clipped."""
    c, h, y = env.target.center(), env.target.heading, env.yaw[i]
    us, vs = [], []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                lx, ly, lz = sx * CAR_HALF[0], sy * CAR_HALF[1], sz * CAR_HALF[2]
                corner = c + [
                    lx * math.cos(h) - ly * math.sin(h),
                    lx * math.sin(h) + ly * math.cos(h),
                    lz,
                ]
                d = corner - env.position[i]
                X = d[0] * math.sin(y) - d[1] * math.cos(y)
                Z = d[0] * math.cos(y) + d[1] * math.sin(y)
                assert Z > 0.1
                us.append(CU + F * X / Z)
                vs.append(CV + F * -d[2] / Z)
    return us, vs


def _hand_bbox_centre(env, i: int) -> tuple[float, float]:
    """Centre of the box around the car's 8 projected corners, clipped to the 640 x 480 image."""
    us, vs = _hand_corners(env, i)
    us, vs = np.clip(us, 0.0, 640.0), np.clip(vs, 0.0, 480.0)
    return 0.5 * (us.min() + us.max()), 0.5 * (vs.min() + vs.max())


def test_noiseless_detection_matches_projection_of_car_centre(make_env):
    """u, v: the centre of the bounding box of the projected car (exact). It differs from the
    projection of the car's centre by perspective only: < 5 px at the Table VI starts (car on the
    optical axis; it grows off-axis with the car's depth extent); depth = Z of the centre."""
    env = make_env(detector=DetectorConfig.noiseless())
    _, infos = env.reset(seed=0)
    rng = np.random.default_rng(2)
    checked = 0
    for step in range(200):
        if step % 20 == 0:
            for a in env.agents:
                i = AGENTS.index(a)
                m = infos[a]["measurement"]
                if not m["detected"]:
                    continue
                d = env.target.center() - env.position[i]
                y = env.yaw[i]
                X = d[0] * math.sin(y) - d[1] * math.cos(y)
                Y = -d[2]
                Z = d[0] * math.cos(y) + d[1] * math.sin(y)
                bu, bv = _hand_bbox_centre(env, i)
                assert m["u"] == pytest.approx(bu, abs=1e-6)
                assert m["v"] == pytest.approx(bv, abs=1e-6)
                if step == 0:
                    assert abs(m["u"] - (CU + F * X / Z)) < 5.0
                    assert abs(m["v"] - (CV + F * Y / Z)) < 5.0
                assert m["depth"] == pytest.approx(Z, rel=1e-9)
                psi = math.atan2(-d[1], -d[0]) - env.target.heading
                assert wrap_angle(m["psi"] - psi) == pytest.approx(0.0, abs=1e-9)
                checked += 1
        acts = {a: 0.08 * rng.uniform(-1, 1, 4) for a in env.agents}
        _, _, _, _, infos = env.step(acts)
    assert checked >= 25


def test_truncated_flags_mark_a_box_cut_by_the_image_border(make_env):
    """truncated_u / truncated_v: some projected corner lies outside the image along U / V."""
    env = make_env(detector=DetectorConfig.noiseless())
    env.reset(seed=0)
    seen = set()
    for z in (1.5, 3.0, 3.5, 4.0, 4.5):
        for yaw in (0.0, 0.5):
            _teleport(env, 1, [-6.0, 0.0, z], yaw)
            _, _, _, _, infos = env.step(_zeros(env))
            m = infos["uav_1"]["measurement"]
            if not m["detected"]:
                assert not (m["truncated_u"] or m["truncated_v"])
                continue
            us, vs = _hand_corners(env, 1)
            assert m["truncated_u"] == (min(us) < 0 or max(us) > 640)
            assert m["truncated_v"] == (min(vs) < 0 or max(vs) > 480)
            seen.add((m["truncated_u"], m["truncated_v"]))
    assert {(False, False), (False, True), (True, False)} <= seen, seen


def test_detector_noise_std_matches_config(make_env):
    """Two lockstep envs, noisy and noiseless, UAVs hovering: the difference of the measurements
    is the noise. 1200 samples: the std's standard error is ~2 %, the tolerance 10 %."""
    noise = {"pixel_noise_std": 3.0, "depth_noise_std": 0.2, "psi_noise_std": 0.05}
    noisy = make_env(detector=noise)
    clean = make_env(detector=DetectorConfig.noiseless())
    noisy.reset(seed=4)
    clean.reset(seed=4)
    res = {"u": [], "v": [], "depth": [], "psi": []}
    for _ in range(400):
        _, _, _, _, inf_n = noisy.step(_zeros(noisy))
        _, _, _, _, inf_c = clean.step(_zeros(clean))
        for a in AGENTS:
            mn, mc = inf_n[a]["measurement"], inf_c[a]["measurement"]
            assert mn["detected"] == mc["detected"]  # noise does not change visibility
            if mn["detected"]:
                for key in res:
                    res[key].append(mn[key] - mc[key])
    assert len(res["u"]) >= 1000
    res = {k: np.array(v) for k, v in res.items()}
    res["psi"] = wrap_angle(res["psi"])
    expected = {"u": 3.0, "v": 3.0, "depth": 0.2, "psi": 0.05}
    for key, std in expected.items():
        x = res[key]
        assert x.std() == pytest.approx(std, rel=0.10), key
        assert abs(x.mean()) < 5 * std / math.sqrt(len(x)), key
    assert abs(np.corrcoef(res["u"], res["v"])[0, 1]) < 0.15


def test_dropout_one_never_detects(make_env):
    env = make_env(detector={"dropout_prob": 1.0})
    obs, infos = env.reset(seed=0)
    k = _offset(env, "detection")
    for _ in range(60):
        for a in env.agents:
            assert infos[a]["measurement"]["detected"] is False
            assert obs[a][k] == 0.0
            assert np.all(obs[a][:k] == 0.0)
            assert infos[a]["measurement"]["visible_fraction"] > 0.5  # it was visible
        obs, _, _, _, infos = env.step(_zeros(env))


def test_dropout_rate_is_the_configured_probability(make_env):
    """900 Bernoulli trials at p = 0.3: standard error 1.5 %, tolerance 6 %."""
    env = make_env(detector={"dropout_prob": 0.3})
    env.reset(seed=1)
    hits = []
    for _ in range(300):
        _, _, _, _, infos = env.step(_zeros(env))
        hits += [infos[a]["measurement"]["detected"] for a in env.agents]
    assert 1.0 - np.mean(hits) == pytest.approx(0.3, abs=0.06)


# ---------------------------------------------------------------------------- comms
def test_comms_drop_all_hides_neighbours(make_env):
    env = make_env(comms={"drop_prob": 1.0})
    obs, infos = env.reset(seed=0)
    masks = [_offset(env, f"neighbour_{k}") + 3 for k in range(env.config.n_neighbours)]
    for _ in range(20):
        for a in env.agents:
            assert infos[a]["neighbours"] == {}
            assert np.all(obs[a][masks] == 0.0)
        obs, _, _, _, infos = env.step(_zeros(env))


def test_comms_deliver_neighbours_in_camera_frame(make_env):
    env = make_env(comms={"drop_prob": 0.0})
    obs, infos = env.reset(seed=0)
    masks = [_offset(env, f"neighbour_{k}") + 3 for k in range(env.config.n_neighbours)]
    for i, a in enumerate(AGENTS):
        nb = infos[a]["neighbours"]
        assert set(nb) == set(AGENTS) - {a}  # all within R_c = 20 m
        for b, pos in nb.items():
            np.testing.assert_array_equal(pos, env.position[AGENTS.index(b)])
        np.testing.assert_array_equal(obs[a][masks], [1.0, 1.0, 0.0, 0.0])
        # First slot: the nearest neighbour, relative position in the camera frame.
        dists = {b: np.linalg.norm(env.position[AGENTS.index(b)] - env.position[i]) for b in nb}
        j = AGENTS.index(min(dists, key=dists.get))
        rel = world_to_cam_vec(env.position[j] - env.position[i], env.yaw[i])
        k = _offset(env, "neighbour_0")
        np.testing.assert_allclose(obs[a][k : k + 3], rel, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------ collisions
def _drive(env, actions: dict, max_steps: int):
    """Step with fixed actions until someone terminates; returns (steps, term, infos, history)."""
    history = []
    for k in range(1, max_steps + 1):
        acts = {a: actions.get(a, np.zeros(4)) for a in env.agents}
        _, _, term, trunc, infos = env.step(acts)
        history.append(infos)
        if any(term.values()):
            return k, term, infos, history
        assert not any(trunc.values())
    raise AssertionError(f"no termination within {max_steps} steps")


def _check_flags(info: dict, kind: str) -> None:
    assert info["violations"]["collision"] is True
    assert info["cost"] >= 1.0
    for key, value in info["collision_with"].items():
        assert value is (key == kind), (key, info["collision_with"])


@pytest.mark.parametrize("mode", ["agent", "all"])
def test_collision_with_obstacle(make_env, mode):
    env = make_env(terminate_on_collision=mode, detector=DetectorConfig.noiseless())
    env.reset(seed=0)
    c = env.layout.obstacle_centers[0]
    _teleport(env, 0, c + [-1.51, 0.0, 0.0], 0.0)  # facing the box's -x face, 1.01 m away
    k, term, infos, history = _drive(env, {"uav_0": np.array([0, 0, 0.2, 0])}, 80)
    # 2 m/s closes the 0.76 m gap (1.51 - 0.5 - r) in 30.4 steps of 0.025 m: contact at step 31.
    assert 30 <= k <= 32
    _check_flags(infos["uav_0"], "obstacle")
    assert infos["uav_0"]["truth"]["nearest_obstacle_clearance"] <= 0.03
    assert all(h["uav_0"]["truth"]["nearest_obstacle_clearance"] > 0 for h in history[:-1])
    assert all(not h["uav_0"]["violations"]["collision"] for h in history[:-1])
    if mode == "agent":
        assert term == {"uav_0": True, "uav_1": False, "uav_2": False}
        assert env.agents == ["uav_1", "uav_2"]
        _, _, term, _, infos = env.step(_zeros(env))  # the others carry on
        assert set(term) == {"uav_1", "uav_2"} and not any(term.values())
    else:
        assert term == dict.fromkeys(AGENTS, True)
        assert env.agents == []
        assert not infos["uav_1"]["violations"]["collision"]


@pytest.mark.parametrize("mode", ["agent", "all"])
def test_collision_with_ground(make_env, mode):
    env = make_env(terminate_on_collision=mode)
    env.reset(seed=0)
    k, term, infos, history = _drive(env, {"uav_0": np.array([0, 0.29, 0, 0])}, 40)
    # Y is down: 2.9 m/s from z = 0.85 reaches z = r = 0.25 after 0.6 / 0.03625 = 16.6 steps.
    assert 16 <= k <= 18
    _check_flags(infos["uav_0"], "ground")
    assert infos["uav_0"]["own"]["position"][2] <= 0.25 + 1e-6
    assert history[-2]["uav_0"]["own"]["position"][2] > 0.25
    expect_others = mode == "all"
    assert term == {"uav_0": True, "uav_1": expect_others, "uav_2": expect_others}
    assert env.agents == ([] if expect_others else ["uav_1", "uav_2"])


@pytest.mark.parametrize("mode", ["agent", "all"])
def test_collision_with_car(make_env, mode):
    env = make_env(terminate_on_collision=mode)
    env.reset(seed=0)
    # uav_1 starts 6 m behind the car's centre, facing it; the car drives away at 0.5 m/s.
    k, term, infos, history = _drive(env, {"uav_1": np.array([0, 0, 0.3, 0])}, 200)
    # Closing speed 2.5 m/s over the 6 - 2.3 - 0.25 = 3.45 m gap: 110.4 steps.
    assert 110 <= k <= 112
    _check_flags(infos["uav_1"], "target")
    assert infos["uav_1"]["truth"]["target_clearance"] <= 0.05
    assert history[-2]["uav_1"]["truth"]["target_clearance"] > 0
    expect_others = mode == "all"
    assert term == {"uav_0": expect_others, "uav_1": True, "uav_2": expect_others}


@pytest.mark.parametrize("mode", ["agent", "all"])
def test_collision_between_uavs_closer_than_rs(make_env, mode):
    env = make_env(terminate_on_collision=mode)
    env.reset(seed=0)
    _teleport(env, 0, env.position[1] + [0.0, 2.31, 0.0], -math.pi / 2)  # facing uav_1
    k, term, infos, history = _drive(env, {"uav_0": np.array([0, 0, 0.1, 0])}, 60)
    # 1 m/s = 0.0125 m a step: the distance drops below R_s = 2 m after 0.31 m, step 25.
    assert k == 25
    for a in ("uav_0", "uav_1"):
        _check_flags(infos[a], "uav")
        assert infos[a]["truth"]["nearest_uav_distance"] < 2.0
        assert history[-2][a]["truth"]["nearest_uav_distance"] >= 2.0
    assert not infos["uav_2"]["violations"]["collision"]
    if mode == "agent":
        assert term == {"uav_0": True, "uav_1": True, "uav_2": False}
        assert env.agents == ["uav_2"]
    else:
        assert term == dict.fromkeys(AGENTS, True)


# -------------------------------------------------------------------------- dynamics
def test_velocity_lag_first_order_response(make_env):
    """v(t) = v_cmd (1 - exp(-t / tau)), tau = 0.25 s, 1 m/s command (accel 4 < 6 m/s^2).
    Forward Euler at 80 Hz differs from the closed form by < 0.01 m/s; tolerance 0.015."""
    env = make_env(dynamics={"model": "lag"})
    env.reset(seed=0)
    tau = env.config.dynamics.tau
    z0 = z_prev = env.position[0, 2]
    for k in range(1, 121):
        acts = _zeros(env)
        acts["uav_0"] = np.array([0.0, -0.1, 0.0, 0.0])  # Y down: -1 m/s on Y is +1 m/s up
        _, _, _, _, infos = env.step(acts)
        t = k * DT
        own = infos["uav_0"]["own"]
        assert own["velocity"][2] == pytest.approx(1.0 - math.exp(-t / tau), abs=0.015)
        assert np.allclose(own["velocity"][:2], 0.0, atol=1e-12)
        # Position: the closed-form integral; the Euler update leads it by about v dt.
        z = z0 + t - tau * (1.0 - math.exp(-t / tau))
        assert own["position"][2] == pytest.approx(z, abs=0.02)
        assert own["position"][2] - z_prev == pytest.approx(own["velocity"][2] * DT, abs=1e-12)
        z_prev = own["position"][2]
    assert infos["uav_1"]["own"]["velocity"] == pytest.approx(np.zeros(3))


def test_velocity_lag_acceleration_limit(make_env):
    """A 10 m/s step asks for 40 m/s^2; the model's a_max = 6 m/s^2 caps it: v = 6 t."""
    env = make_env(dynamics={"model": "lag"})
    env.reset(seed=0)
    for k in range(1, 41):
        acts = _zeros(env)
        acts["uav_0"] = np.array([0.0, -1.0, 0.0, 0.0])
        _, _, _, _, infos = env.step(acts)
        assert infos["uav_0"]["own"]["velocity"][2] == pytest.approx(6.0 * k * DT, abs=1e-9)


def test_yaw_rate_lag_and_sign(make_env):
    """omega_cy = +0.6 turns the heading at -0.6 rad/s (global yaw rate = -omega_cy), reached with
    the time constant yaw_tau = 0.1 s; the integrator model turns at once."""
    lag = make_env(dynamics={"model": "lag"})
    integ = make_env()
    lag.reset(seed=0)
    integ.reset(seed=0)
    yaw0 = lag.yaw[0]
    for k in range(1, 41):
        acts = {a: np.zeros(4) for a in AGENTS}
        acts["uav_0"] = np.array([0.0, 0.0, 0.0, 1.0])
        _, _, _, _, inf_l = lag.step(acts)
        _, _, _, _, inf_i = integ.step(acts)
        t = k * DT
        assert inf_l["uav_0"]["own"]["yaw_rate"] == pytest.approx(
            -0.6 * (1.0 - math.exp(-t / 0.1)), abs=0.03
        )
        assert inf_i["uav_0"]["own"]["yaw_rate"] == pytest.approx(-0.6, abs=1e-12)
    assert wrap_angle(integ.yaw[0] - yaw0) == pytest.approx(-0.6 * 40 * DT, abs=1e-9)


def test_integrator_moves_along_camera_axes(make_env):
    """eq. (3): u in the camera frame; uav_0 faces -y, so +v_cx (right) is -x, +v_cz is -y."""
    env = make_env()
    env.reset(seed=0)
    p0 = env.position[0].copy()
    acts = _zeros(env)
    acts["uav_0"] = np.array([0.1, 0.0, 0.2, 0.0])
    for _ in range(8):
        env.step(acts)
    # yaw is -1.57 (Table VI), not exactly -pi/2: use the actual heading.
    y = -1.57
    right = np.array([math.sin(y), -math.cos(y), 0.0])
    fwd = np.array([math.cos(y), math.sin(y), 0.0])
    np.testing.assert_allclose(env.position[0] - p0, 0.1 * (1.0 * right + 2.0 * fwd), atol=1e-12)


# --------------------------------------------------------------------- target program
def test_fig11_target_program(make_env):
    """0.5 m/s throughout; -1 rad of heading between 10 s and 15 s (turn-rate lag 0.3 s), +1 rad
    between 35 s and 40 s, straight again afterwards."""
    env = make_env()
    env.reset(seed=0)
    tgt = env.target
    n = round(48.0 / DT)
    xs, heads, speeds = np.empty((n + 1, 2)), np.empty(n + 1), np.empty(n + 1)
    for k in range(n + 1):
        xs[k] = tgt.center()[:2]
        heads[k] = tgt.heading
        speeds[k] = np.linalg.norm(tgt.velocity())
        tgt.step(DT)

    def at(t):
        return round(t / DT)

    np.testing.assert_allclose(speeds, 0.5, atol=1e-12)
    step_len = np.linalg.norm(np.diff(xs, axis=0), axis=1)
    np.testing.assert_allclose(step_len, 0.5 * DT, rtol=1e-9)
    assert np.all(heads[: at(10.0) + 1] == 0.0)
    np.testing.assert_allclose(xs[at(10.0)], [5.0, 0.0], atol=1e-9)
    turn = heads[at(10.0) : at(15.5)]
    assert np.all(np.diff(turn) <= 1e-12)  # turning right only
    assert heads[at(15.0)] == pytest.approx(-1.0, abs=0.08)  # the lag holds back ~0.06 rad
    assert heads[at(17.0)] == pytest.approx(-1.0, abs=0.01)
    assert heads[at(34.9)] == pytest.approx(-1.0, abs=0.01)
    assert np.ptp(heads[at(17.0) : at(35.0)]) < 1e-3  # straight
    assert heads[at(42.0)] == pytest.approx(0.0, abs=0.01)
    # Both turns last 5 s at 0.2 rad/s, so they cancel; the lag's state has decayed by e^-27.
    assert abs(heads[-1]) < 1e-6


# -------------------------------------------------------------------- scenario layouts
@pytest.mark.parametrize(("scenario", "init"), sorted(TABLE_VI))
def test_table_vi_initial_conditions(make_env, scenario, init):
    env = make_env(scenario=scenario, init=init)
    env.reset(seed=0)
    rows = np.array(TABLE_VI[(scenario, init)], float)
    np.testing.assert_array_equal(env.position[:, :2], rows[:, :2])
    np.testing.assert_array_equal(env.position[:, 2], 0.85)
    np.testing.assert_array_equal(env.yaw, rows[:, 2])
    np.testing.assert_array_equal(env.target.center(), [0.0, 0.0, 0.75])
    assert env.target.heading == 0.0
    for uid, pos in zip(env.world.uav_ids, env.position, strict=True):
        got, _ = p.getBasePositionAndOrientation(uid, physicsClientId=env.world.cid)
        np.testing.assert_allclose(got, pos, atol=1e-9)


def _box_dims(env, oid: int) -> np.ndarray:
    data = p.getCollisionShapeData(oid, -1, physicsClientId=env.world.cid)
    assert data[0][2] == p.GEOM_BOX
    return np.array(data[0][3])


def test_scenario_a_has_ten_unit_boxes_on_the_ground(make_env):
    env = make_env(scenario="A")
    env.reset(seed=0)
    assert len(env.world.obstacle_ids) == 10
    np.testing.assert_array_equal(env.layout.obstacle_half_extents, 0.5)
    for oid, c in zip(env.world.obstacle_ids, env.layout.obstacle_centers, strict=True):
        np.testing.assert_allclose(_box_dims(env, oid), [1.0, 1.0, 1.0], atol=1e-9)
        pos, _ = p.getBasePositionAndOrientation(oid, physicsClientId=env.world.cid)
        np.testing.assert_allclose(pos, c, atol=1e-9)
        assert pos[2] == pytest.approx(0.5)  # standing on the ground


def test_scenario_c_boxes_taller_than_b(make_env):
    env_b, env_c = make_env(scenario="B"), make_env(scenario="C")
    env_b.reset(seed=0)
    env_c.reset(seed=0)
    lb, lc = env_b.layout, env_c.layout
    assert len(lb.obstacle_centers) == len(lc.obstacle_centers) > 0
    np.testing.assert_allclose(lb.obstacle_centers[:, :2], lc.obstacle_centers[:, :2])
    np.testing.assert_allclose(lb.obstacle_half_extents[:, :2], lc.obstacle_half_extents[:, :2])
    assert np.all(lc.obstacle_half_extents[:, 2] > lb.obstacle_half_extents[:, 2])
    for env in (env_b, env_c):  # all stand on the ground
        lay = env.layout
        np.testing.assert_allclose(lay.obstacle_centers[:, 2], lay.obstacle_half_extents[:, 2])
        for oid, half in zip(env.world.obstacle_ids, lay.obstacle_half_extents, strict=True):
            np.testing.assert_allclose(_box_dims(env, oid), 2 * half, atol=1e-9)


@pytest.mark.parametrize("scenario", ["A", "B", "C"])
def test_car_path_never_touches_an_obstacle(make_env, scenario):
    """Footprint distance from the car's centre path (60 s) to every box exceeds the car's
    half-width; it even exceeds the half-diagonal (2.47 m), so the car's rectangle never touches."""
    env = make_env(scenario=scenario)
    env.reset(seed=0)
    tgt = env.target
    path = []
    for _ in range(round(60.0 / DT)):
        path.append(tgt.center()[:2].copy())
        tgt.step(DT)
    path = np.array(path)
    lay = env.layout
    gap = (
        np.abs(path[:, None, :] - lay.obstacle_centers[None, :, :2])
        - lay.obstacle_half_extents[None, :, :2]
    )
    dist = np.linalg.norm(np.maximum(gap, 0.0), axis=-1).min(axis=0)
    assert np.all(dist > CAR_HALF[1])
    assert np.all(dist > math.hypot(CAR_HALF[0], CAR_HALF[1]))
    # And the world agrees: the car never touches a box over the run (contact query).
    env.reset(seed=0)
    for _ in range(round(60.0 / DT) // 8):
        for _ in range(8):
            env.target.step(DT)
        env.world.set_poses(
            env.position, env.yaw, env.alive, env.target.center(), env.target.heading
        )
        for oid in env.world.obstacle_ids:
            assert not p.getClosestPoints(
                env.world.target_id, oid, 0.0, physicsClientId=env.world.cid
            )


@pytest.mark.parametrize(
    "n_uavs, spread",
    [
        (3, {}),
        (5, {}),
        (3, {"start_offset": 3.0, "start_heading_offset": 0.3}),
        (10, {"start_offset": 3.0, "start_heading_offset": 0.3}),  # placed UAV by UAV
        (20, {"start_offset": 3.0}),
    ],
)
def test_random_worlds_start_feasible(make_env, n_uavs, spread):
    env = make_env(scenario="random", n_uavs=n_uavs, random_world=spread)
    cfg = env.config
    offsets = []
    for seed in range(20):
        _, infos = env.reset(seed=seed)
        lay = env.layout
        pos = env.position
        assert len(pos) == n_uavs
        refs = lay.references
        slot = np.column_stack([np.cos(refs[:, 3]), np.sin(refs[:, 3])]) / refs[:, 2:3]
        offsets.append(np.abs(pos[:, :2] - slot).max())
        if len(lay.obstacle_centers):
            clear = point_box_distance(pos, lay.obstacle_centers, lay.obstacle_half_extents)
            assert clear.min() > cfg.uav_radius, seed
        d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
        assert d[~np.eye(n_uavs, dtype=bool)].min() >= cfg.violations.r_s, seed
        n_comp, _ = connected_components(d <= cfg.comms.r_c, directed=False)
        assert n_comp == 1, seed
        assert np.all(pos[:, 2] > cfg.uav_radius)
        for a in env.agents:
            assert infos[a]["measurement"]["detected"], (seed, a)
            assert not infos[a]["violations"]["collision"], (seed, a)
            assert not infos[a]["violations"]["disconnection"], (seed, a)
            assert not infos[a]["violations"]["occlusion"], (seed, a)
    limit = spread.get("start_offset", 0.2)
    assert max(offsets) <= limit * 1.5 + 0.3  # radial + tangential draws, 0.03 rad ring jitter
    assert max(offsets) > 0.5 * limit  # and the offsets do spread
