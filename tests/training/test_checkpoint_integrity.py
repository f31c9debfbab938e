"""SHA-256 digests per checkpoint in index.json, checked on restore; old manifests load
unverified; restored arrays must be finite (ported from harden, issue 22)."""

from __future__ import annotations

import json

import flax.struct
import jax
import jax.numpy as jnp
import pytest

from popsan_jax.errors import CheckpointError
from popsan_jax.training import checkpoint


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
    index = checkpoint.read_index(tmp_path)
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
    assert checkpoint.verify_checkpoint(tmp_path, index, entry) is False


def test_non_finite_arrays_refused(tmp_path):
    state = _S(w=jnp.array([1.0, jnp.nan]), env_steps=jnp.int32(0))
    checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    with pytest.raises(CheckpointError, match="non-finite"):
        checkpoint.restore_checkpoint(tmp_path, state, "last")
