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
        np.testing.assert_allclose(half, [DIAG + pad, DIAG + pad, C + 0.25])
        assert growth == 0.0


def test_pad_is_capped_and_a_stale_car_grows():
    m = ShieldMargins(target_margin=0.25, target_margin_max=1.0, target_stale_after=0.25)
    half, growth = car_box(_estimate(5.0), m, 2.0)
    assert half[0] == pytest.approx(DIAG + 1.0)
    since = round(0.75 / DT)  # 0.5 s past target_stale_after
    half, growth = car_box(_estimate(0.1, since=since), m, 2.0)
    assert growth == 2.0
    assert half[0] == pytest.approx(DIAG + 0.25 + 0.3 + 2.0 * (since * DT - 0.25))


def test_cut_boxes_pad_by_the_car_size():
    m = ShieldMargins()
    plain, _ = car_box(_estimate(), m, 2.0)
    cut_u, _ = car_box(_estimate(), m, 2.0, (True, False))
    np.testing.assert_allclose(cut_u - plain, [DIAG, DIAG, 0.0])
    # on the ground the vertical extent is known: a cut in v changes nothing
    cut_v, _ = car_box(_estimate(), m, 2.0, (False, True))
    np.testing.assert_allclose(cut_v, plain)
    off = dataclasses.replace(m, car_on_ground=False)
    free, _ = car_box(_estimate(), off, 2.0)
    free_cut, _ = car_box(_estimate(), off, 2.0, (False, True))
    np.testing.assert_allclose(free_cut - free, [0.0, 0.0, C])
    assert free[2] == pytest.approx(C + 0.25 + 0.3)


def test_truncated_detections_pad_the_box_until_recovered():
    """A cut box pads the context's car box; `truncation_recovery` s of uncut detections
    remove the pad, and undetected steps do not count towards it. The car sits on the ground."""
    env = uavtrack_v0.parallel_env(scenario="A")
    _, infos = env.reset(seed=0)
    cfg = expert_config()
    agent = OnboardAgent("uav_0", 0, env.config, cfg)
    agent.reset(env.layout, env.possible_agents)
    info = infos["uav_0"]
    assert info["measurement"]["detected"]
    recovery = round(cfg.margins.truncation_recovery / DT)

    def observe(cut: bool = False, detected: bool = True) -> np.ndarray:
        step = copy.deepcopy(info)
        step["measurement"].update(truncated_u=cut, detected=detected)
        agent.observe(step)
        ctx = agent.context()
        assert ctx.target_position[2] == pytest.approx(C)
        return ctx.target_half_extents

    for _ in range(2 * recovery):  # the covariance settles
        base = observe()
    padded = observe(cut=True)
    assert padded[0] - base[0] == pytest.approx(DIAG, abs=0.05)
    for _ in range(recovery - 1):
        observe()
    for _ in range(5):  # lost detections keep the pad
        assert observe(detected=False)[0] > base[0] + DIAG - 0.05
    last = observe()
    assert last[0] < base[0] + 0.05
    env.close()


@pytest.mark.slow
@pytest.mark.parametrize("family", ["random-held", "seek-car", "spin-dive"])
def test_the_box_holds_the_true_car_under_hostile_policies(family):
    """On seeded random worlds (lag dynamics, detector dropouts) under `CBFShield`, the true car
    never leaves the exclusion box built from the UKF, cut boxes and dropouts included."""
    result = containment.measure(family, [7001, 7002, 7003], 160, expert_config())
    assert result.steps > 1000
    assert result.outside == 0, f"{result.outside} agent-steps, worst {result.worst:.3f} m"
