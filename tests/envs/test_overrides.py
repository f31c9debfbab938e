"""Env overrides keep their types and ranges (issue 22, item 6): numbers stay finite numbers,
integers integers, tuples tuples of their length (``target_low``, ``pad_solimp``), nested
mappings are checked key by key; each mistake is one EnvConfigError line (envs' own error)."""

from __future__ import annotations

import re

import pytest

from envs import franka_pick, franka_reach
from envs.errors import EnvConfigError
from envs.panda import apply_overrides, merge_overrides

REACH = franka_reach.default_config()
PICK = franka_pick.default_config()


@pytest.mark.parametrize(
    "config, overrides, match",
    [
        (REACH, {"reward_scales": {"dist": "abc"}}, "bad value 'abc' for 'reward_scales.dist'"),
        (REACH, {"sim_dt": 0}, "sim_dt must be > 0"),
        (REACH, {"ctrl_dt": -0.02}, "ctrl_dt must be > 0"),
        (REACH, {"target_low": "abc"}, "bad value 'abc' for 'target_low'"),
        (REACH, {"target_low": [0.1, 0.2]}, "expected a list of 3"),
        (REACH, {"target_low": [0.1, 0.2, "z"]}, "'target_low[2]'"),
        (REACH, {"episode_length": 10.5}, "expected an integer"),
        (REACH, {"iterations": 0}, "iterations must be >= 1"),
        (REACH, {"ctrl_dt": float("nan")}, "expected a finite number"),
        (REACH, {"action_scale": True}, "expected a number"),
        (REACH, {"init_joint_noise": -1}, "init_joint_noise must be >= 0"),
        (PICK, {"pad_solimp": [0.9, 0.99]}, "expected a list of 5"),
        (PICK, {"pad_solimp": "0.9"}, "bad value '0.9' for 'pad_solimp'"),
    ],
)
def test_bad_overrides_are_one_line(config, overrides, match):
    with pytest.raises(EnvConfigError, match=re.escape(match)) as err:
        apply_overrides(config, overrides, "env")
    assert "\n" not in str(err.value)


def test_good_overrides_keep_the_default_types():
    out = apply_overrides(REACH, {"target_low": [0.3, -0.2, 0.1], "episode_length": 50.0}, "r")
    assert out.target_low == (0.3, -0.2, 0.1) and out.episode_length == 50
    assert isinstance(out.episode_length, int)
    pick = apply_overrides(PICK, {"pad_solimp": [0.9, 0.95, 0.001, 0.5, 2], "sim_dt": 0.02}, "p")
    assert pick.pad_solimp == (0.9, 0.95, 0.001, 0.5, 2.0) and pick.sim_dt == 0.02


def test_merge_overrides_later_layers_win_key_by_key():
    # A revision's legacy scales, the warm-up's and the user's: each layer keeps the scales the
    # others set unless it sets the same one; plain keys are replaced; inputs are not mutated.
    legacy = {"reward_scales": {"object_speed": 0.0, "climb": 0.0}, "lift_ramp": 0.0}
    user = {"reward_scales": {"climb": 8.0, "lift": 2.0}, "lift_ramp": 0.01, "sim_dt": 0.02}
    merged = merge_overrides(legacy, user)
    assert merged == {
        "reward_scales": {"object_speed": 0.0, "climb": 8.0, "lift": 2.0},
        "lift_ramp": 0.01,
        "sim_dt": 0.02,
    }
    assert legacy["reward_scales"] == {"object_speed": 0.0, "climb": 0.0}
    assert merge_overrides() == {} and merge_overrides(user) == user
    # a plain value replaces a mapping and the other way round (apply_overrides judges them)
    assert merge_overrides({"reward_scales": {"lift": 1.0}}, {"reward_scales": 3}) == {
        "reward_scales": 3
    }
    merged = merge_overrides({"lift_ramp": 1}, {"lift_ramp": {"a": 1}})
    assert merged == {"lift_ramp": {"a": 1}}
