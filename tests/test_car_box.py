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


def _estimate(sigma_p: float = 0.1, since: int = 0, velocity=(1.0, 0.5, 0.0)) -> Estimate:
    P = np.eye(10) * 1e-4
    P[4:7, 4:7] = np.eye(3) * sigma_p**2
    return Estimate(
        s=np.array([0.0, 0.0, 0.2, 0.0]),
        target_position=np.array([3.0, -1.0, 0.6]),
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
        half, growth = car_box(_estimate(0.1, velocity=velocity), m, 2.0)
        pad = 0.25 + 3 * 0.1
        # on the ground: from below the ground up to the car's height + target_margin
        np.testing.assert_allclose(half, [DIAG + pad, DIAG + pad, 2 * C + 0.25 - 0.6])
        assert growth == 0.0


def test_pad_is_capped_and_a_stale_car_grows():
    m = ShieldMargins(target_margin=0.25, target_margin_max=1.0, target_stale_after=0.25)
    half, growth = car_box(_estimate(5.0), m, 2.0)
    assert half[0] == pytest.approx(DIAG + 1.0)
    since = round(0.75 / DT)  # 0.5 s past target_stale_after
    half, growth = car_box(_estimate(0.1, since=since), m, 2.0)
    assert growth == 2.0
    assert half[0] == pytest.approx(DIAG + 0.25 + 0.3 + 2.0 * (since * DT - 0.25))


def test_cut_boxes_pad_by_the_car_size_at_the_car_speed():
    """A spell of cut boxes grows the box at car_speed up to the car's size (and says so in the
    growth); on the ground the vertical extent stays exact."""
    m = ShieldMargins()
    plain, growth = car_box(_estimate(), m, 2.0)
    assert growth == 0.0
    ramp, growth = car_box(_estimate(), m, 2.0, (0.5, 0.0))
    np.testing.assert_allclose(ramp - plain, [1.0, 1.0, 0.0])
    assert growth == 2.0
    full, growth = car_box(_estimate(), m, 2.0, (10.0, 0.0))
    np.testing.assert_allclose(full - plain, [DIAG, DIAG, 0.0])
    assert growth == 0.0
    cut_v, _ = car_box(_estimate(), m, 2.0, (0.0, 10.0))
    np.testing.assert_allclose(cut_v, plain)
    off = dataclasses.replace(m, car_on_ground=False)
    free, _ = car_box(_estimate(), off, 2.0)
    free_cut, _ = car_box(_estimate(), off, 2.0, (0.0, 10.0))
    np.testing.assert_allclose(free_cut - free, [0.0, 0.0, C])
    assert free[2] == pytest.approx(C + 0.25 + 0.3)


def test_truncated_detections_pad_the_box_until_recovered():
    """A cut box starts a spell that pads the context's car box at the car speed; the spell
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
        assert pad == pytest.approx(min(speed * steps * DT, DIAG), abs=0.02)
    for _ in range(5):  # lost detections keep the spell going
        steps += 1
        pad = observe(detected=False) - base
        assert pad >= min(speed * steps * DT, DIAG) - 0.02
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
