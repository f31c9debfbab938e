"""Containment of checkpoint directories and plain --name (ported from harden, issue 22)."""

import os

import pytest

from popsan_jax.errors import CheckpointError, ConfigError
from popsan_jax.training.checkpoint import contained
from popsan_jax.training.run import check_name


@pytest.mark.parametrize("name", ["../x", "/abs", "a/b", "..", ".", "", "a\nb", "x" * 201])
def test_check_name_refuses_non_plain(name):
    with pytest.raises(ConfigError, match="plain directory name"):
        check_name(name)


@pytest.mark.parametrize("name", ["run1", "pick-popsan-s0", "a.b+c=d,e_f"])
def test_check_name_accepts_plain(name):
    assert check_name(name) == name


def test_contained_accepts_own_pattern(tmp_path):
    (tmp_path / "step_000000000100").mkdir()
    assert contained(tmp_path, "step_000000000100") == tmp_path / "step_000000000100"


@pytest.mark.parametrize("name", ["../step_000000000100", "/etc", "step_1", None, 5, "x"])
def test_contained_refuses_other_names(tmp_path, name):
    with pytest.raises(CheckpointError, match="not a checkpoint name"):
        contained(tmp_path, name)


def test_contained_refuses_link_outside(tmp_path):
    root = tmp_path / "checkpoints"
    root.mkdir()
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", root / "step_000000000100")
    with pytest.raises(CheckpointError, match="resolves outside"):
        contained(root, "step_000000000100")
