"""Verified checkpoints (issue 22, items 2 and 6): a SHA-256 digest per checkpoint in index.json,
checked on restore (old manifests load unverified); restored arrays must be finite; an index off
its schema and a full disk are one line each."""

from __future__ import annotations

import json
import os
import re

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from popsan_jax.errors import CheckpointError
from popsan_jax.training import checkpoint, checkpoint_index


@flax.struct.dataclass
class _S:
    w: jax.Array
    env_steps: jax.Array = 0


def _data_file(path):
    return max((f for f in path.rglob("*") if f.is_file()), key=lambda f: f.stat().st_size)


def test_digest_recorded_and_damage_names_intact_steps(tmp_path):
    first = _S(w=jnp.ones(4), env_steps=jnp.int32(1))
    state = _S(w=jnp.ones(4), env_steps=jnp.int32(2))
    checkpoint.save_checkpoint(tmp_path, first, jax.random.PRNGKey(0), 1, 0.9, 1)
    path = checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(1), 2, 0.1, 1)
    index = checkpoint_index.read_index(tmp_path)
    assert all(e["digest"].startswith("sha256:") for e in index["checkpoints"])
    checkpoint.restore_checkpoint(tmp_path, state, "last")
    f = _data_file(path)
    f.write_bytes(f.read_bytes() + b"x")
    with pytest.raises(CheckpointError, match=r"is damaged.*--step 1 or --best"):
        checkpoint.restore_checkpoint(tmp_path, state, "last")
    checkpoint.restore_checkpoint(tmp_path, state, 1)


def test_manifest_without_digest_loads_unverified(tmp_path):
    state = _S(w=jnp.ones(2), env_steps=jnp.int32(0))
    checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    p = tmp_path / "checkpoints" / "index.json"
    index = json.loads(p.read_text())
    for e in index["checkpoints"]:
        del e["digest"]
    p.write_text(json.dumps(index))
    restored, _, entry = checkpoint.restore_checkpoint(tmp_path, state, "last")
    assert "digest" not in entry
    assert checkpoint_index.verify_checkpoint(tmp_path, index, entry) is False


def test_non_finite_arrays_refused(tmp_path):
    state = _S(w=jnp.array([1.0, jnp.nan]), env_steps=jnp.int32(0))
    checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    with pytest.raises(CheckpointError, match="non-finite"):
        checkpoint.restore_checkpoint(tmp_path, state, "last")


def test_random_bytes_in_the_largest_data_file_are_caught(tmp_path):
    """The probe of issue 22: 64 random bytes over the largest file changed weights silently."""
    state = _S(w=jnp.linspace(0.0, 1.0, 4096), env_steps=jnp.int32(1))
    path = checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    f = _data_file(path)
    data = bytearray(f.read_bytes())
    at = len(data) // 2
    data[at : at + 64] = np.random.default_rng(0).bytes(64)
    f.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="is damaged.*no other checkpoint is intact"):
        checkpoint.restore_checkpoint(tmp_path, state, "last")


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda i: i["checkpoints"][0].update(dir=5), "dir must be a string"),
        (lambda i: i.update(checkpoints="xyz"), "'checkpoints' must be a list"),
        (lambda i: i["checkpoints"][0].update(step="1"), "step must be an integer"),
        (lambda i: i.update(best=7), "'best' (7) is not a listed checkpoint step"),
        (lambda i: i["checkpoints"][0].update(digest="md5:x"), "digest must be 'sha256:'"),
    ],
)
def test_index_off_its_schema_is_one_line(tmp_path, edit, match):
    state = _S(w=jnp.ones(2), env_steps=jnp.int32(1))
    checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    p = tmp_path / "checkpoints" / "index.json"
    index = json.loads(p.read_text())
    edit(index)
    p.write_text(json.dumps(index))
    for read in (checkpoint_index.read_index, lambda r: checkpoint.restore_checkpoint(r, state)):
        with pytest.raises(CheckpointError, match=re.escape(match)) as err:
            read(tmp_path)
        assert "\n" not in str(err.value)
    p.write_bytes(bytes(range(128, 256)))  # not even UTF-8
    with pytest.raises(CheckpointError, match="corrupt checkpoint index"):
        checkpoint_index.read_index(tmp_path)


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")
@pytest.mark.parametrize("precheck", [True, False], ids=["free-space-check", "orbax-fails"])
def test_disk_full_is_one_line_naming_the_last_good_checkpoint(tmp_path, monkeypatch, precheck):
    from _run_fixtures import tmpfs

    if not precheck:  # the disk fills during Orbax's own write
        monkeypatch.setattr(checkpoint, "_check_free_space", lambda *a: None, raising=False)
    small = _S(w=jnp.ones(4), env_steps=jnp.int32(1))
    noise = jax.random.normal(jax.random.PRNGKey(1), (2_000_000,))  # 8 MB that do not compress
    big = _S(w=noise, env_steps=jnp.int32(2))  # on a 4 MB disk
    with tmpfs(tmp_path / "full", size="4m") as run:
        checkpoint.save_checkpoint(run, small, jax.random.PRNGKey(0), 1, 0.0, 1)
        with pytest.raises(CheckpointError) as err:
            checkpoint.save_checkpoint(run, big, jax.random.PRNGKey(0), 2, 0.0, 1)
        line = str(err.value)
        assert "\n" not in line and "No space left on device" in line, line
        assert "the last good checkpoint is step 1" in line, line
        assert checkpoint_index.read_index(run)["last"] == 1
        left = sorted(p.name for p in (run / "checkpoints").iterdir())
        assert left == ["index.json", "step_000000000001"]  # no half-written checkpoint
        checkpoint.restore_checkpoint(run, small, "last")
