"""The car's exclusion box (`onboard.car_box`): its parts by number, and, in the closed loop,
that it holds the true car under hostile policies (the assumption behind the car's row)."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest

from baselines import car_box as containment
from uavtrack_env import uavtrack_v0
from uavtrack_env.config import DT
from uavtrack_env.estimation import Estimate
from uavtrack_env.onboard import OnboardAgent, car_box
from uavtrack_env.presets import expert_config
from uavtrack_env.safety import ShieldMargins
from uavtrack_env.target import CAR_HALF_EXTENTS

A, B, C = CAR_HALF_EXTENTS
DIAG = math.hypot(A, B)


def _estimate(
    sigma_p: float = 0.1, since: int = 0, velocity=(1.0, 0.5, 0.0), position=(3.0, -1.0, 0.6)
) -> Estimate:
    P = np.eye(10) * 1e-4
    P[4:7, 4:7] = np.eye(3) * sigma_p**2
    return Estimate(
        s=np.array([0.0, 0.0, 0.2, 0.0]),
        target_position=np.asarray(position, float),
        target_velocity=np.asarray(velocity, float),
        target_acceleration=np.zeros(3),
        vq_cam=np.zeros(3),
        detected=since == 0,
        covariance=P,
        steps_since_detection=since,
    )


def test_box_is_heading_free_with_the_covariance_pad():
    m = ShieldMargins(target_margin=0.25, target_sigmas=3.0, target_margin_max=2.0)
    for velocity in ((1.0, 0.0, 0.0), (0.0, -2.0, 0.0), (0.0, 0.0, 0.0)):
        est = _estimate(0.1, velocity=velocity)
        box = car_box(est, m, 1.0)
        pad = 0.25 + 3 * 0.1
        # on the ground: from below the ground up to the car's height + target_margin
        np.testing.assert_allclose(box.half, [DIAG + pad, DIAG + pad, 2 * C + 0.25 - 0.6])
        np.testing.assert_array_equal(box.center, est.target_position)
        np.testing.assert_array_equal(box.velocity, velocity)
        np.testing.assert_array_equal(box.growth, 0.0)


def test_pad_is_capped():
    m = ShieldMargins(target_margin=0.25, target_margin_max=1.0)
    assert car_box(_estimate(5.0), m, 1.0).half[0] == pytest.approx(DIAG + 1.0)


def test_a_stale_car_is_its_reachable_set_from_the_anchor():
    """Undetected for target_stale_after, the box follows the UKF's prediction; after that it
    stands at the anchor (the last trusted estimate) with the anchor's pad and its sides move
    out at the car's speed, whatever the UKF now predicts (here a bogus 5 m/s drift and a grown
    covariance), the top of a car on the ground included."""
    m = ShieldMargins(target_margin=0.25, target_margin_max=2.0, target_stale_after=0.25)
    anchor = _estimate(0.1, since=20, position=(3.0, -1.0, 0.6))
    fresh = car_box(_estimate(0.1, since=20, velocity=(5.0, 0.0, 0.0)), m, 0.8, anchor=anchor)
    np.testing.assert_array_equal(fresh.growth, 0.0)
    np.testing.assert_array_equal(fresh.velocity, (5.0, 0.0, 0.0))
    since = 60
    now = _estimate(1.0, since=since, velocity=(5.0, 0.0, 0.0), position=(6.75, -1.0, 0.6))
    box = car_box(now, m, 0.8, anchor=anchor)
    np.testing.assert_array_equal(box.center, anchor.target_position)
    np.testing.assert_array_equal(box.velocity, 0.0)
    grown = DIAG + 0.25 + 0.3 + 0.8 * (since * DT - 0.25)
    top = 2 * C + 0.25 - 0.6 + 0.8 * (since * DT - 0.25)
    np.testing.assert_allclose(box.half, [grown, grown, top])
    np.testing.assert_array_equal(box.growth, 0.8)
    free = car_box(now, dataclasses.replace(m, car_on_ground=False), 0.8, anchor=anchor)
    np.testing.assert_allclose(
        free.half, [grown, grown, C + 0.25 + 0.3 + 0.8 * (since * DT - 0.25)]
    )
    np.testing.assert_array_equal(free.growth, 0.8)


def test_the_reachable_set_holds_any_car_within_the_speed_bound():
    """Every path at most at the speed bound from within the anchor's box stays in the grown
    box: points of the car anywhere in it, moving in any direction, after any gap."""
    m = ShieldMargins()
    anchor = _estimate(0.1, since=20)
    rng = np.random.default_rng(0)
    for since in (21, 27, 80, 400):
        box = car_box(_estimate(0.1, since=since), m, 1.0, anchor=anchor)
        stale = since * DT - m.target_stale_after
        for _ in range(50):
            d = rng.normal(size=2)
            d *= 1.0 * stale / np.linalg.norm(d)
            start = anchor.target_position[:2] + rng.uniform(-1, 1, 2) * (DIAG + 0.25 + 0.3)
            assert np.all(np.abs(start + d - box.center[:2]) <= box.half[:2] + 1e-12)


def test_cut_boxes_pad_by_the_car_size_at_twice_the_car_speed():
    """A spell of cut boxes grows the box at twice car_speed up to the car's size (and says so
    in the growth); on the ground the vertical extent stays exact."""
    m = ShieldMargins()
    plain = car_box(_estimate(), m, 1.0)
    ramp = car_box(_estimate(), m, 1.0, (0.5, 0.0))
    np.testing.assert_allclose(ramp.half - plain.half, [1.0, 1.0, 0.0])
    np.testing.assert_array_equal(ramp.growth, [2.0, 2.0, 0.0])
    full = car_box(_estimate(), m, 1.0, (10.0, 0.0))
    np.testing.assert_allclose(full.half - plain.half, [DIAG, DIAG, 0.0])
    np.testing.assert_array_equal(full.growth, 0.0)
    cut_v = car_box(_estimate(), m, 1.0, (0.0, 10.0))
    np.testing.assert_allclose(cut_v.half, plain.half)
    off = dataclasses.replace(m, car_on_ground=False)
    free = car_box(_estimate(), off, 1.0).half
    free_cut = car_box(_estimate(), off, 1.0, (0.0, 10.0)).half
    np.testing.assert_allclose(free_cut - free, [0.0, 0.0, C])
    assert free[2] == pytest.approx(C + 0.25 + 0.3)


def test_truncated_detections_pad_the_box_until_recovered():
    """A cut box starts a spell that pads the context's car box at twice the car speed; the spell
    ends after `truncation_recovery` s of uncut detections (undetected steps do not count) and
    the pad with it. The box reaches the car's height on the ground."""
    env = uavtrack_v0.parallel_env(scenario="A")
    _, infos = env.reset(seed=0)
    cfg = expert_config()
    agent = OnboardAgent("uav_0", 0, env.config, cfg)
    agent.reset(env.layout, env.possible_agents)
    speed = agent._car_speed
    info = infos["uav_0"]
    assert info["measurement"]["detected"]
    recovery = round(cfg.margins.truncation_recovery / DT)

    def observe(cut: bool = False, detected: bool = True) -> float:
        step = copy.deepcopy(info)
        step["measurement"].update(truncated_u=cut, detected=detected)
        agent.observe(step)
        ctx = agent.context()
        top = ctx.target_position[2] + ctx.target_half_extents[2]
        assert top == pytest.approx(max(2 * C + 0.25, 2 * ctx.target_position[2]))
        return float(ctx.target_half_extents[0])

    for _ in range(2 * recovery):  # the covariance settles
        base = observe()
    steps = 0
    for k in range(recovery):
        steps += 1
        pad = observe(cut=k == 0) - base
        assert pad == pytest.approx(min(2 * speed * steps * DT, DIAG), abs=0.02)
    for _ in range(5):  # lost detections keep the spell going
        steps += 1
        pad = observe(detected=False) - base
        assert pad >= min(2 * speed * steps * DT, DIAG) - 0.02
    assert observe() < base + 0.02  # the recovery-th uncut detection ends the spell
    env.close()


@pytest.mark.slow
@pytest.mark.parametrize("family", ["random-held", "seek-car", "spin-dive"])
def test_the_box_holds_the_true_car_under_hostile_policies(family):
    """On seeded random worlds (lag dynamics, detector dropouts) under `CBFShield`, the true car
    never leaves the exclusion box built from the UKF, cut boxes and dropouts included."""
    result = containment.measure(family, [7001, 7002, 7003], 160, expert_config())
    assert result.steps > 1000
    assert result.outside == 0, f"{result.outside} agent-steps, worst {result.worst:.3f} m"
