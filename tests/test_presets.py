"""ExpertConfig presets, overrides and the CLIs' --set parsing."""

from __future__ import annotations

import dataclasses

import pytest

from uavtrack_env.control.config import NMPCConfig
from uavtrack_env.presets import (
    DEFAULT_PRESET,
    PRESETS,
    RL_PRESET,
    ExpertConfig,
    apply_overrides,
    expert_config,
)


def test_presets_differ_where_documented():
    paper, tuned, planner = PRESETS["paper"], PRESETS["tuned"], PRESETS["paper-planner"]
    assert paper == ExpertConfig()  # the defaults are the paper's equations
    assert paper.nmpc == NMPCConfig() and planner.nmpc == NMPCConfig()
    assert (paper.cbf.occlusion_model, paper.cbf.occlusion_point) == ("paper", "centre")
    assert not paper.viewpoint.enabled and not paper.lag_aware
    assert tuned.nmpc.terminal_weight == "lqr" and tuned.nmpc.safety_rows == 4
    assert (tuned.cbf.occlusion_model, tuned.cbf.occlusion_point) == ("moving-target", "edges")
    assert planner.cbf == tuned.cbf and planner.viewpoint == tuned.viewpoint
    assert tuned.lag_aware and planner.lag_aware
    assert DEFAULT_PRESET == "tuned" and expert_config() == tuned
    for cfg in PRESETS.values():  # R_s and R_c always come from the world
        assert cfg.cbf.r_s is None and cfg.cbf.r_c is None


def test_the_rl_preset_is_tuned_with_the_team_mates_in_the_occlusion_rows():
    tuned, rl = PRESETS["tuned"], PRESETS[RL_PRESET]
    assert tuned.cbf.team_mate_radius == 0.0  # as in the paper: the obstacles only
    assert rl.cbf.team_mate_radius is None  # the world's UAV radius
    assert rl.cbf.resolve(uav_radius=0.3).team_mate_radius == 0.3
    assert rl == dataclasses.replace(
        tuned, cbf=dataclasses.replace(tuned.cbf, team_mate_radius=None)
    )


def test_overrides_replace_nested_fields_only():
    cfg = expert_config("tuned", cbf={"gamma_o": 0.5}, use_cbf=False)
    assert cfg.cbf == dataclasses.replace(PRESETS["tuned"].cbf, gamma_o=0.5)
    assert cfg.nmpc == PRESETS["tuned"].nmpc and cfg.use_cbf is False
    assert expert_config(cfg) == cfg


@pytest.mark.parametrize(
    "assignment, path, value",
    [
        ("cbf.gamma_o=0.5", ("cbf", "gamma_o"), 0.5),
        ("use_cbf=false", ("use_cbf",), False),
        ("nmpc.q_s=1,1,50,1", ("nmpc", "q_s"), (1.0, 1.0, 50.0, 1.0)),
        ("nmpc.safety_row_stages=none", ("nmpc", "safety_row_stages"), None),
        ("nmpc.horizon=20", ("nmpc", "horizon"), 20),
        ("cbf.occlusion_point=axis", ("cbf", "occlusion_point"), "axis"),
        ("qp_solver=proxqp", ("qp_solver",), "proxqp"),
    ],
)
def test_set_parses_by_field_type(assignment, path, value):
    cfg = apply_overrides(PRESETS["tuned"], [assignment])
    got = cfg
    for name in path:
        got = getattr(got, name)
    assert got == value and type(got) is type(value)


@pytest.mark.parametrize(
    "assignments, error, message",
    [
        (["cbf.nope=1"], TypeError, r"unknown field 'cbf.nope'.*gamma_o"),
        (["gamma_o"], ValueError, "FIELD=VALUE"),
        (["cbf.gamma_o=fast"], ValueError, "cbf.gamma_o=fast"),
        (["cbf.occlusion_point=side"], ValueError, r"one of \['centre', 'axis', 'edges'\]"),
        (["use_cbf=maybe"], ValueError, "true or false"),
        (["use_cbf.x=1"], TypeError, "not a group of fields"),
        (["qp_solver=osqp"], ValueError, "qp_solver must be one of"),
        (["cbf.gamma_o=-1"], ValueError, "gamma_o"),
    ],
)
def test_bad_set_says_what_is_expected(assignments, error, message):
    with pytest.raises(error, match=message):
        apply_overrides(PRESETS["tuned"], assignments)


def test_bad_config_values_are_refused():
    with pytest.raises(ValueError, match=r"unknown preset 'fast'.*paper"):
        expert_config("fast")
    with pytest.raises(TypeError, match=r"unknown field\(s\) \['gama'\] in cbf"):
        expert_config(cbf={"gama": 1.0})
    with pytest.raises(ValueError, match="use_cbf must be True or False"):
        ExpertConfig(use_cbf="yes")
    with pytest.raises(TypeError, match="cbf must be a CBFConfig"):
        ExpertConfig(cbf={"gamma_o": 1.0})
    with pytest.raises(ValueError, match="lag_tau is set from the env"):
        expert_config(shield={"lag_tau": 0.25})
