"""Every configuration field is validated at construction (issue 15, item 3).

Each error names the field, the value and what is expected (choices listed for enumerations).
The table below has at least one bad value for every field of every configuration class; the
env-level table checks that the known holes raise at ``parallel_env(**kw)``, before any PyBullet
client exists.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time

import numpy as np
import pytest

from uavtrack_env import uavtrack_v0
from uavtrack_env import world as world_module
from uavtrack_env.config import (
    DT,
    MAX_EPISODE_STEPS,
    MAX_RANDOM_OBSTACLES,
    MAX_RAYS_PER_STEP,
    CameraConfig,
    CommsConfig,
    ControlLimits,
    DetectorConfig,
    DynamicsConfig,
    EnvConfig,
    RandomWorldConfig,
    RewardConfig,
    ViolationConfig,
)
from uavtrack_env.control.config import FeatureBounds, NMPCConfig
from uavtrack_env.control.viewpoint import ViewpointConfig
from uavtrack_env.estimation.ukf import UKFConfig
from uavtrack_env.presets import PRESETS, expert_config
from uavtrack_env.safety.config import CBFConfig
from uavtrack_env.safety.margins import ShieldMargins
from uavtrack_env.safety.shield import ShieldOptions
from uavtrack_env.target import random_program
from uavtrack_env.validation import check_number

INF, NAN = math.inf, math.nan
V, T = ValueError, TypeError

CLASSES = [
    CameraConfig,
    ControlLimits,
    DynamicsConfig,
    DetectorConfig,
    CommsConfig,
    ViolationConfig,
    RewardConfig,
    RandomWorldConfig,
    EnvConfig,
    FeatureBounds,
    NMPCConfig,
    CBFConfig,
    UKFConfig,
    ShieldOptions,
    ShieldMargins,
    ViewpointConfig,
]

POS = "a finite number > 0"
NONNEG = "a finite number >= 0"
INT = "an integer"


def case(cls, name, value, error, expected, named=True, **extra):
    """One row: ``cls(name=value, **extra)`` raises ``error`` whose message contains
    ``expected`` (a regex); ``named``: the message starts with ``Class.name``."""
    return pytest.param(
        cls, name, {name: value, **extra}, error, expected, named, id=f"{cls.__name__}.{name}"
    )


BAD = [
    # ------------------------------------------------------------------ CameraConfig
    case(CameraConfig, "fx", 0.0, V, rf"fx must be {POS}, got 0\.0 \(float\)"),
    case(CameraConfig, "fy", -381.0, V, rf"fy must be {POS}, got -381\.0"),
    case(CameraConfig, "cu", NAN, V, r"cu must be a finite number in \[0, 640\], got nan"),
    case(CameraConfig, "cv", 481.0, V, r"cv must be a finite number in \[0, 480\], got 481"),
    case(CameraConfig, "width", 640.5, V, rf"width must be {INT} >= 1, got 640\.5"),
    case(CameraConfig, "height", "480", T, rf"height must be {INT} >= 1, got '480' \(str\)"),
    case(CameraConfig, "near", INF, V, rf"near must be {POS}, got inf"),
    # ------------------------------------------------------------------ ControlLimits
    case(ControlLimits, "v_max", INF, V, rf"v_max must be {POS}, got inf"),
    case(ControlLimits, "omega_max", 0, V, rf"omega_max must be {POS}, got 0 \(int\)"),
    # ------------------------------------------------------------------ DynamicsConfig
    case(DynamicsConfig, "model", "lagged", V, r"must be 'integrator' or 'lag', got 'lagged'"),
    case(DynamicsConfig, "tau", 0.0, V, rf"tau must be {POS}"),
    case(DynamicsConfig, "a_max", -6.0, V, rf"a_max must be {POS}"),
    case(DynamicsConfig, "yaw_tau", NAN, V, rf"yaw_tau must be {POS}, got nan"),
    # ------------------------------------------------------------------ DetectorConfig
    case(DetectorConfig, "pixel_noise_std", -1.0, V, rf"pixel_noise_std must be {NONNEG}"),
    case(DetectorConfig, "depth_noise_std", INF, V, rf"depth_noise_std must be {NONNEG}"),
    case(DetectorConfig, "psi_noise_std", "0.03", T, rf"psi_noise_std must be {NONNEG}"),
    case(
        DetectorConfig, "dropout_prob", 1.5, V, r"dropout_prob must be a finite number in \[0, 1\]"
    ),
    case(
        DetectorConfig,
        "min_visible_fraction",
        0.0,
        V,
        r"min_visible_fraction must be a finite number in \(0, 1\]",
    ),
    case(DetectorConfig, "samples_per_axis", (3, 2), V, r"must be a tuple of 3 numbers"),
    case(DetectorConfig, "samples_per_axis", (3, 0, 2), V, r"samples_per_axis\[1\] must be"),
    case(DetectorConfig, "samples_per_axis", (3, 2.5, 2), V, rf"\[1\] must be {INT} >= 1"),
    case(DetectorConfig, "samples_per_axis", 12, T, r"must be a tuple of 3 numbers, got 12"),
    case(DetectorConfig, "samples_per_axis", (200, 200, 1), V, r"40000 rays .* at most 16383"),
    # ------------------------------------------------------------------ CommsConfig
    case(CommsConfig, "r_c", 0.0, V, rf"r_c must be {POS}"),
    case(CommsConfig, "drop_prob", NAN, V, r"drop_prob must be a finite number in \[0, 1\]"),
    # ------------------------------------------------------------------ ViolationConfig
    case(ViolationConfig, "r_s", -2.0, V, rf"r_s must be {POS}"),
    # ------------------------------------------------------------------ RewardConfig
    case(RewardConfig, "q", (INF, 1, 1, 1), V, rf"q\[0\] must be {NONNEG}, got inf"),
    case(RewardConfig, "r", (0.1, 0.1, 0.1), V, r"r must be a tuple of 4 numbers"),
    case(RewardConfig, "lost_penalty", INF, V, rf"lost_penalty must be {NONNEG}, got inf"),
    case(RewardConfig, "shape", "linear", V, r"shape must be 'cost' or 'exp', got 'linear'"),
    case(RewardConfig, "collision_penalty", INF, V, rf"collision_penalty must be {NONNEG}"),
    case(RewardConfig, "image_point", "corner", V, r"image_point must be 'center' or 'box'"),
    # ------------------------------------------------------------------ RandomWorldConfig
    case(RandomWorldConfig, "n_obstacles", (16, 8), V, r"ordered range \(lo, hi\) with lo <= hi"),
    case(RandomWorldConfig, "n_obstacles", (1.5, 3), V, rf"n_obstacles\[0\] must be {INT}"),
    case(
        RandomWorldConfig,
        "n_obstacles",
        (0, 10**6),
        V,
        rf"n_obstacles\[1\] must be {INT} in \[0, {MAX_RANDOM_OBSTACLES}\]",
    ),
    case(RandomWorldConfig, "size", (0.0, 1.0), V, rf"size\[0\] must be {POS}"),
    case(RandomWorldConfig, "height", (1.0, NAN), V, rf"height\[1\] must be {POS}, got nan"),
    case(RandomWorldConfig, "extent", 0.0, V, rf"extent must be {POS}"),
    case(RandomWorldConfig, "corridor", -1.0, V, rf"corridor must be {POS}"),
    case(RandomWorldConfig, "target_speed", (-1.0, 1.0), V, rf"target_speed\[0\] must be {NONNEG}"),
    case(RandomWorldConfig, "target_turn_rate", INF, V, rf"target_turn_rate must be {NONNEG}"),
    case(
        RandomWorldConfig,
        "start_offset",
        6.0,
        V,
        r"start_offset must be a finite number in \[0, 5\]",
    ),
    case(
        RandomWorldConfig,
        "start_heading_offset",
        2.0,
        V,
        r"start_heading_offset must be a finite number in \[0, 1\]",
    ),
    case(RandomWorldConfig, "min_start_altitude", -1.0, V, rf"min_start_altitude must be {NONNEG}"),
    # ------------------------------------------------------------------ EnvConfig
    case(EnvConfig, "scenario", "D", V, r"scenario must be 'A', 'B', 'C' or 'random', got 'D'"),
    case(EnvConfig, "init", 2, V, rf"init must be {INT} in \[0, 1\], got 2"),
    case(
        EnvConfig, "n_uavs", "3", T, r"^EnvConfig\.n_uavs must be an integer >= 1, got '3' \(str\)$"
    ),
    case(EnvConfig, "n_uavs", True, T, rf"n_uavs must be {INT} >= 1, got True \(bool\)"),
    case(EnvConfig, "n_uavs", 5, V, r"n_uavs must be 3 for scenario 'A'"),
    case(
        EnvConfig,
        "n_uavs",
        MAX_RAYS_PER_STEP // 12 + 1,
        V,
        r"n_uavs = 1366 UAVs x detector\.samples_per_axis = \(3, 2, 2\) cast 16392 rays",
        scenario="random",
    ),
    case(
        EnvConfig,
        "max_cycles",
        10**10,
        V,
        rf"max_cycles must be {INT} in \[1, {MAX_EPISODE_STEPS}\], got 10000000000",
    ),
    case(EnvConfig, "max_cycles", 0, V, rf"max_cycles must be {INT} in \[1, "),
    case(
        EnvConfig,
        "render_mode",
        "ascii",
        V,
        r"render_mode must be None, 'rgb_array' or 'human', got 'ascii'",
    ),
    case(
        EnvConfig,
        "terminate_on_collision",
        "none",
        V,
        r"terminate_on_collision must be 'agent', 'all' or 'never', got 'none'",
    ),
    case(EnvConfig, "n_neighbours", 2.5, V, rf"n_neighbours must be {INT} >= 0, got 2\.5"),
    case(EnvConfig, "n_obstacles_obs", -1, V, rf"n_obstacles_obs must be {INT} >= 0"),
    case(EnvConfig, "uav_radius", INF, V, rf"uav_radius must be {POS}"),
    case(EnvConfig, "skip_proven_queries", "yes", T, r"skip_proven_queries must be True or False"),
    case(EnvConfig, "camera", {"fx": 1.0}, T, r"camera must be a CameraConfig, got \{"),
    case(EnvConfig, "limits", CameraConfig(), T, r"limits must be a ControlLimits"),
    case(EnvConfig, "violations", 2.0, T, r"violations must be a ViolationConfig"),
    case(EnvConfig, "dynamics", "lag", T, r"dynamics must be a DynamicsConfig"),
    case(EnvConfig, "detector", None, T, r"detector must be a DetectorConfig"),
    case(EnvConfig, "comms", 20.0, T, r"comms must be a CommsConfig"),
    case(EnvConfig, "reward", "exp", T, r"reward must be a RewardConfig"),
    case(EnvConfig, "random_world", {}, T, r"random_world must be a RandomWorldConfig"),
    case(
        EnvConfig,
        "violations",
        ViolationConfig(r_s=25.0),
        V,
        r"violations\.r_s = 25\.0 m must be < comms\.r_c = 20\.0 m",
    ),
    # ------------------------------------------------------------------ FeatureBounds
    case(
        FeatureBounds,
        "x1",
        (0.84, -0.84),
        V,
        r"x1 must be an ordered range \(lo, hi\) with lo < hi",
    ),
    case(FeatureBounds, "x2", (-0.63, NAN), V, r"x2\[1\] must be a finite number, got nan"),
    case(FeatureBounds, "x3", (0.0, 1.0), V, rf"x3\[0\] must be {POS}"),
    # ------------------------------------------------------------------ NMPCConfig
    case(NMPCConfig, "horizon", 0, V, rf"horizon must be {INT} >= 1"),
    case(NMPCConfig, "q_s", (1.0, 1.0, -100.0, 1.0), V, rf"q_s\[2\] must be {NONNEG}"),
    case(NMPCConfig, "r_u", (NAN, 0.03, 0.01, 0.3), V, rf"r_u\[0\] must be {NONNEG}, got nan"),
    case(
        NMPCConfig,
        "r_u",
        (0.0, 0.03, 0.01, 0.3),
        V,
        r"needs every r_u > 0",
        named=False,
        terminal_weight="lqr",
    ),
    case(NMPCConfig, "w_s", (1.0, 1.0, 100.0), V, r"w_s must be a tuple of 4 numbers"),
    case(NMPCConfig, "terminal_weight", "riccati", V, r"terminal_weight must be 'w_s' or 'lqr'"),
    case(NMPCConfig, "solver", "osqp", V, r"solver must be 'sqp', 'ipopt' or 'rti', got 'osqp'"),
    case(NMPCConfig, "max_iter", 0, V, rf"max_iter must be {INT} >= 1"),
    case(NMPCConfig, "yaw_rate_reference", "heading", V, r"must be 'zero' or 'target-turn'"),
    case(NMPCConfig, "turn_rate_min_speed", 0.0, V, rf"turn_rate_min_speed must be {POS}"),
    case(NMPCConfig, "safety_rows", -1, V, rf"safety_rows must be {INT} >= 0"),
    case(
        NMPCConfig,
        "safety_row_stages",
        51,
        V,
        rf"safety_row_stages must be None \(whole horizon\) or {INT} in \[1, 50\], got 51",
    ),
    case(NMPCConfig, "safety_row_slack", "max", V, r"safety_row_slack must be 'shared' or 'stage'"),
    case(NMPCConfig, "integrator", "euler2", V, r"integrator must be 'rk4' or 'euler'"),
    case(NMPCConfig, "error_signal", "False", T, r"error_signal must be True or False"),
    case(NMPCConfig, "eps_max", (0.1, -0.1, 0.05, 0.2), V, rf"eps_max\[1\] must be {NONNEG}"),
    case(NMPCConfig, "slack_weight", 0.0, V, rf"slack_weight must be {POS}"),
    case(NMPCConfig, "slack_hessian", -1.0, V, rf"slack_hessian must be {NONNEG}"),
    case(NMPCConfig, "hessian", "bfgs", V, r"hessian must be 'gauss-newton' or 'exact'"),
    case(NMPCConfig, "qpsol", "", V, r"qpsol must be a non-empty string"),
    case(NMPCConfig, "qpsol", None, T, r"qpsol must be a non-empty string, got None"),
    case(NMPCConfig, "qrqp_min_lam", NAN, V, rf"qrqp_min_lam must be {NONNEG}"),
    case(NMPCConfig, "qrqp_max_iter", 0, V, rf"qrqp_max_iter must be {INT} >= 1"),
    case(NMPCConfig, "line_search_steps", -1, V, rf"line_search_steps must be {INT} >= 0"),
    case(NMPCConfig, "tol", 0.0, V, rf"tol must be {POS}"),
    case(NMPCConfig, "ipopt_tol", -1e-6, V, rf"ipopt_tol must be {POS}"),
    case(NMPCConfig, "expand", "true", T, r"expand must be True or False"),
    case(NMPCConfig, "jit", 1, V, r"jit must be None, True or False, got 1 \(int\)"),
    case(NMPCConfig, "rescue_with_ipopt", None, T, r"rescue_with_ipopt must be True or False"),
    case(NMPCConfig, "max_fallback_steps", 2.5, V, rf"max_fallback_steps must be {INT} >= 0"),
    # ------------------------------------------------------------------ CBFConfig
    case(CBFConfig, "r_s", 0.0, V, rf"r_s must be None \(the world's collision range\) or {POS}"),
    case(CBFConfig, "r_c", "20", T, rf"r_c must be None \(the world's link range\) or {POS}"),
    case(CBFConfig, "d_s", NAN, V, rf"d_s must be None \(R_c\) or {POS}, got nan"),
    case(
        CBFConfig, "d_s", 30.0, V, r"R_s < D_s <= R_c \(eq\. 27\)", named=False, r_s=2.0, r_c=20.0
    ),
    case(
        CBFConfig, "theta_star_deg", 90.0, V, r"theta_star_deg must be a finite number in \(0, 90\)"
    ),
    case(CBFConfig, "gamma_s", -3.0, V, rf"gamma_s must be {POS}"),
    case(CBFConfig, "gamma_s", 0.1, V, r"eq\. \(28\)", named=False, r_s=2.0, r_c=20.0, d_s=20.0),
    case(CBFConfig, "gamma_c", 0.0, V, rf"gamma_c must be {POS}"),
    case(CBFConfig, "gamma_o", INF, V, rf"gamma_o must be {POS}"),
    case(CBFConfig, "alpha_v", 0.0, V, rf"alpha_v must be {POS}"),
    case(CBFConfig, "alpha_omega", NAN, V, rf"alpha_omega must be {POS}"),
    case(CBFConfig, "obstacle_clearance", 0.0, V, rf"obstacle_clearance must be {POS}"),
    case(CBFConfig, "gamma_obstacle", -1.0, V, rf"gamma_obstacle must be {POS}"),
    case(CBFConfig, "z_min", -0.5, V, rf"z_min must be {NONNEG}"),
    case(CBFConfig, "gamma_z", 0.0, V, rf"gamma_z must be {POS}"),
    case(CBFConfig, "occlusion_model", "static", V, r"must be 'paper' or 'moving-target'"),
    case(CBFConfig, "occlusion_point", "corner", V, r"must be 'centre', 'axis' or 'edges'"),
    case(CBFConfig, "occlusion_size_margin", 1, T, r"must be True or False, got 1 \(int\)"),
    case(
        CBFConfig,
        "team_mate_radius",
        -0.25,
        V,
        rf"team_mate_radius must be None \(the world's UAV radius\) or {NONNEG}",
    ),
    # ------------------------------------------------------------------ UKFConfig
    case(UKFConfig, "q_features", (1e-4, 1e-4, 1e-5), V, r"q_features must be a tuple of 4"),
    case(UKFConfig, "q_position", 0.0, V, rf"q_position must be {POS}"),
    case(UKFConfig, "q_velocity", (0.05, INF, 0.002), V, rf"q_velocity\[1\] must be {POS}"),
    case(UKFConfig, "pixel_std", 0.0, V, rf"pixel_std must be {POS}"),
    case(UKFConfig, "depth_std", NAN, V, rf"depth_std must be {POS}"),
    case(UKFConfig, "psi_std", -0.03, V, rf"psi_std must be {POS}"),
    case(
        UKFConfig, "truncated_variance_scale", 0.5, V, r"truncated_variance_scale must be .* >= 1"
    ),
    case(UKFConfig, "gps_std", INF, V, rf"gps_std must be {POS}"),
    case(UKFConfig, "init_position_std", "0.5", T, rf"init_position_std must be {POS}"),
    case(UKFConfig, "init_velocity_std", (3.0, 3.0), V, r"init_velocity_std must be a tuple of 3"),
    case(UKFConfig, "alpha", 0.0, V, rf"alpha must be {POS}"),
    case(UKFConfig, "beta", NAN, V, r"beta must be a finite number, got nan"),
    case(UKFConfig, "kappa", -10.0, V, r"kappa must be a finite number > -10"),
    case(UKFConfig, "x3_bounds", (10.0, 0.01), V, r"x3_bounds must be an ordered range"),
    case(UKFConfig, "x12_limit", 0.0, V, rf"x12_limit must be {POS}"),
    case(UKFConfig, "max_std", (1.0,) * 4, V, r"max_std must be a tuple of 10 numbers"),
    case(UKFConfig, "fit_window", -3.0, V, rf"fit_window must be {POS}"),
    case(UKFConfig, "fit_order", 1.5, V, rf"fit_order must be {INT} >= 0"),
    case(UKFConfig, "fit_velocity_weight", -0.25, V, rf"fit_velocity_weight must be {NONNEG}"),
    case(UKFConfig, "fit_min_samples", 2, V, rf"fit_min_samples must be {INT} >= 3, got 2"),
    case(UKFConfig, "fit_settle_time", -1.0, V, rf"fit_settle_time must be {NONNEG}"),
    case(UKFConfig, "fit_every", 0, V, rf"fit_every must be {INT} >= 1"),
    case(UKFConfig, "max_target_accel", INF, V, rf"max_target_accel must be {POS}"),
    case(UKFConfig, "truncated_v_hold_height", "yes", T, r"must be True or False, got 'yes'"),
    case(UKFConfig, "planar_target", None, T, r"planar_target must be True or False"),
    case(UKFConfig, "dropout_use_fit_velocity", 0, T, r"must be True or False"),
    case(UKFConfig, "vectorized", 1.0, T, r"vectorized must be True or False"),
    # ------------------------------------------------------------------ ShieldOptions
    case(ShieldOptions, "obstacle_model", "sphere", V, r"obstacle_model must be 'box' or 'point'"),
    case(ShieldOptions, "target_as_obstacle", 1, T, r"target_as_obstacle must be True or False"),
    case(ShieldOptions, "occlusion", "no", T, r"occlusion must be True or False"),
    case(
        ShieldOptions,
        "connectivity_margin",
        -0.1,
        V,
        rf"connectivity_margin must be None .* or {NONNEG}",
    ),
    case(ShieldOptions, "soft_penalty", 0.0, V, rf"soft_penalty must be {POS}"),
    case(ShieldOptions, "occlusion_price", -1.0, V, rf"occlusion_price must be None .* {POS}"),
    case(ShieldOptions, "hard_penalty", INF, V, rf"hard_penalty must be {POS}"),
    case(
        ShieldOptions, "slack_regularization", -1e-6, V, rf"slack_regularization must be {NONNEG}"
    ),
    case(ShieldOptions, "norm_cuts", 4.5, V, rf"norm_cuts must be {INT} >= 0"),
    case(ShieldOptions, "prune", None, T, r"prune must be True or False"),
    case(ShieldOptions, "make_way", 1, T, r"make_way must be True or False"),
    case(
        ShieldOptions,
        "climb_over_occluders",
        "yes",
        T,
        r"climb_over_occluders must be True or False",
    ),
    case(ShieldOptions, "tol", NAN, V, rf"tol must be {NONNEG}"),
    case(ShieldOptions, "verify_tol", -1.0, V, rf"verify_tol must be {NONNEG}"),
    case(ShieldOptions, "lag_tau", INF, V, rf"lag_tau must be {NONNEG}"),
    case(ShieldOptions, "accel_bound", -1.0, V, rf"accel_bound must be {NONNEG}"),
    case(
        ShieldOptions,
        "occlusion_urgency",
        100.0,
        V,
        r"occlusion_urgency must be a finite number in \[1, 100\), got 100",
    ),
    case(ShieldOptions, "occlusion_leverage", 0.0, V, r"occlusion_leverage must be .*> 0"),
    # ------------------------------------------------------------------ ShieldMargins
    case(ShieldMargins, "r_s_margin", NAN, V, rf"r_s_margin must be {NONNEG}, got nan"),
    case(ShieldMargins, "r_c_margin", -0.05, V, rf"r_c_margin must be {NONNEG}"),
    case(ShieldMargins, "target_margin", "0.25", T, rf"target_margin must be {NONNEG}"),
    case(ShieldMargins, "target_sigmas", INF, V, rf"target_sigmas must be {NONNEG}"),
    case(ShieldMargins, "target_margin_max", 0.1, V, r"target_margin_max must be >= target_margin"),
    case(ShieldMargins, "surface_gap", -0.1, V, rf"surface_gap must be {NONNEG}"),
    case(ShieldMargins, "message_timeout", 0.0, V, r"message_timeout must be a finite number > 0"),
    case(ShieldMargins, "target_stale_after", -1.0, V, rf"target_stale_after must be {NONNEG}"),
    case(ShieldMargins, "target_speed_max", INF, V, rf"target_speed_max must be {NONNEG}"),
    case(ShieldMargins, "car_on_ground", "yes", T, r"car_on_ground must be True or False"),
    case(ShieldMargins, "truncated_box_pad", 1, T, r"truncated_box_pad must be True or False"),
    case(ShieldMargins, "truncation_recovery", NAN, V, rf"truncation_recovery must be {NONNEG}"),
    # ------------------------------------------------------------------ ViewpointConfig
    case(ViewpointConfig, "enabled", "on", T, r"enabled must be True or False"),
    case(ViewpointConfig, "horizon_s", -1.0, V, rf"horizon_s must be {NONNEG}"),
    case(ViewpointConfig, "samples", 0, V, rf"samples must be {INT} >= 1"),
    case(ViewpointConfig, "target_height_m", NAN, V, rf"target_height_m must be {NONNEG}"),
    case(ViewpointConfig, "visible_height_m", -0.6, V, rf"visible_height_m must be {NONNEG}"),
    case(ViewpointConfig, "top_margin_m", INF, V, rf"top_margin_m must be {NONNEG}"),
    case(ViewpointConfig, "footprint_margin_m", -0.2, V, rf"footprint_margin_m must be {NONNEG}"),
    case(ViewpointConfig, "x2_max", 1.0, V, r"x2_max must be a finite number in \(0, 1\)"),
    case(ViewpointConfig, "max_box_offset", -0.15, V, rf"max_box_offset must be {NONNEG}"),
    case(ViewpointConfig, "rate", 0.0, V, rf"rate must be {POS}"),
    case(ViewpointConfig, "replan_period_s", 0.0, V, rf"replan_period_s must be {POS}"),
]


@pytest.mark.parametrize(("cls", "name", "kwargs", "error", "expected", "named"), BAD)
def test_bad_field_raises_naming_field_value_and_expectation(
    cls, name, kwargs, error, expected, named
):
    with pytest.raises(error) as info:
        cls(**kwargs)
    message = str(info.value)
    assert re.search(expected, message), f"{expected!r} not in {message!r}"
    if named:
        assert message.startswith(f"{cls.__name__}.{name}"), message


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_field_has_a_bad_value_in_the_table(cls):
    covered = {p.values[1] for p in BAD if p.values[0] is cls}
    missing = {f.name for f in dataclasses.fields(cls)} - covered
    assert not missing, f"{cls.__name__} fields without a bad-value case: {sorted(missing)}"


# ----------------------------------------------------------------- env construction
ENV_BAD = [
    ({"limits": {"v_max": INF}}, V, r"ControlLimits\.v_max must be a finite number > 0, got inf"),
    ({"reward": {"q": (INF, 1, 1, 1)}}, V, r"RewardConfig\.q\[0\] must be .* >= 0, got inf"),
    ({"reward": {"lost_penalty": INF}}, V, r"RewardConfig\.lost_penalty must be .*, got inf"),
    ({"reward": {"collision_penalty": INF}}, V, r"RewardConfig\.collision_penalty .* got inf"),
    ({"camera": {"cu": NAN}}, V, r"CameraConfig\.cu must be a finite number in \[0, 640\]"),
    ({"max_cycles": 10**10}, V, r"EnvConfig\.max_cycles must be an integer in \[1, 1000000\]"),
    (
        {"scenario": "random", "n_uavs": 1366},
        V,
        r"EnvConfig\.n_uavs = 1366 UAVs x detector\.samples_per_axis = \(3, 2, 2\) .* 16383",
    ),
    (
        {"scenario": "random", "n_uavs": 2, "detector": {"samples_per_axis": (40, 40, 6)}},
        V,
        r"EnvConfig\.n_uavs = 2 UAVs x detector\.samples_per_axis = \(40, 40, 6\) cast 19200",
    ),
    ({"n_uavs": "3"}, T, r"EnvConfig\.n_uavs must be an integer >= 1, got '3' \(str\)"),
    ({"n_uavs": True}, T, r"EnvConfig\.n_uavs must be an integer >= 1, got True \(bool\)"),
    ({"n_neighbours": 2.5}, V, r"EnvConfig\.n_neighbours must be an integer >= 0, got 2\.5"),
    (
        {"dynamics": {"model": "lagged"}},
        V,
        r"DynamicsConfig\.model must be 'integrator' or 'lag', got 'lagged'",
    ),
    ({"detector": {"samples_per_axis": [3, 2]}}, V, r"samples_per_axis must be a tuple of 3"),
    ({"violations": {"r_s": 25.0}}, V, r"violations\.r_s = 25\.0 m must be < comms\.r_c"),
    ({"random_world": {"n_obstacles": (8, 10**7)}}, V, r"n_obstacles\[1\] must be an integer in"),
    ({"init": 1.0}, V, r"EnvConfig\.init must be an integer in \[0, 1\], got 1\.0"),
]


@pytest.fixture
def no_pybullet(monkeypatch):
    """Creating a PyBullet client fails the test: bad configs must raise before it."""

    def refuse(*args, **kwargs):
        raise AssertionError("a PyBullet client was created for a bad configuration")

    monkeypatch.setattr(world_module.p, "connect", refuse)


@pytest.mark.parametrize(("kwargs", "error", "expected"), ENV_BAD, ids=lambda v: str(v)[:60])
def test_bad_env_kwargs_raise_before_any_pybullet_client(no_pybullet, kwargs, error, expected):
    with pytest.raises(error, match=expected):
        EnvConfig.from_kwargs(**kwargs)
    with pytest.raises(error, match=expected):
        uavtrack_v0.parallel_env(**kwargs)


def test_numpy_integer_n_uavs_is_accepted_as_int():
    cfg = EnvConfig.from_kwargs(n_uavs=np.int64(3), max_cycles=np.int32(100))
    assert cfg.n_uavs == 3 and type(cfg.n_uavs) is int
    assert type(cfg.max_cycles) is int
    env = uavtrack_v0.parallel_env(n_uavs=np.int64(3))
    try:
        assert env.possible_agents == ["uav_0", "uav_1", "uav_2"]
        assert type(env.config.n_uavs) is int
    finally:
        env.close()


def test_values_are_normalised_to_plain_python_types():
    cam = CameraConfig(fx=np.float32(381.0), width=np.int64(640), cu=np.int16(320))
    assert type(cam.fx) is float and type(cam.width) is int and type(cam.cu) is float
    reward = RewardConfig(q=np.array([1, 1, 100, 1]), r=[0.02, 0.03, 0.01, 0.3])
    assert reward.q == (1.0, 1.0, 100.0, 1.0) and type(reward.q) is tuple
    assert all(type(w) is float for w in (*reward.q, *reward.r))
    hash(reward)  # tuples keep the frozen dataclass hashable
    det = DetectorConfig(samples_per_axis=np.array([2, 2, 2]))
    assert det.samples_per_axis == (2, 2, 2) and all(type(k) is int for k in det.samples_per_axis)
    assert CBFConfig(occlusion_size_margin=np.bool_(True)).occlusion_size_margin is True
    assert NMPCConfig(safety_row_stages=np.int64(5)).safety_row_stages == 5
    # Values that are already right are kept as they are.
    assert EnvConfig() == EnvConfig.from_kwargs()


def test_limits_are_inclusive():
    assert EnvConfig(max_cycles=MAX_EPISODE_STEPS).max_cycles == MAX_EPISODE_STEPS
    n = MAX_RAYS_PER_STEP // 12
    assert EnvConfig(scenario="random", n_uavs=n).n_uavs == n
    assert DetectorConfig(samples_per_axis=(MAX_RAYS_PER_STEP, 1, 1)).samples_per_axis[0] > 1
    assert RandomWorldConfig(n_obstacles=(0, MAX_RANDOM_OBSTACLES)).n_obstacles[1] > 0
    # inf is a number where a field allows it (no field does today).
    assert check_number("X", "y", INF, lo=0, allow_inf=True) == INF
    with pytest.raises(ValueError, match=r"X\.y must be a number > 0, got nan"):
        check_number("X", "y", NAN, lo=0, lo_open=True, allow_inf=True)


def test_max_episode_length_keeps_the_program_cheap():
    """The random scenario precomputes the car's program for the whole episode at reset."""
    start = time.perf_counter()
    program = random_program(np.random.default_rng(0), (0.3, 1.0), 0.25, MAX_EPISODE_STEPS * DT)
    assert time.perf_counter() - start < 2.0
    assert program[-2].t_end >= MAX_EPISODE_STEPS * DT


def test_cbf_none_ranges_still_resolve_and_check():
    cbf = CBFConfig()
    assert cbf.r_s is None and cbf.r_c is None and cbf.d_s is None and not cbf.resolved
    resolved = cbf.resolve(2.0, 20.0)
    assert (resolved.r_s, resolved.r_c, resolved.d_s) == (2.0, 20.0, 20.0)
    with pytest.raises(ValueError, match=r"eq\. \(28\)"):
        CBFConfig(gamma_s=0.1).resolve(2.0, 20.0)
    with pytest.raises(ValueError, match="below the world's collision range"):
        CBFConfig(r_s=1.0).resolve(2.0, 20.0)


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_defaults_construct(cls):
    default = cls()
    assert dataclasses.replace(default) == default


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_constructs(name):
    cfg = expert_config(name)
    assert cfg == PRESETS[name]
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            assert dataclasses.replace(value) == value  # re-runs its __post_init__
