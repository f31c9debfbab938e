"""The checkpoint manifest (keep every N-th, the last and the best), restores, damaged data,
and ``load_run`` refusing a run whose config no longer builds its networks."""

from __future__ import annotations

import json

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from popsan_jax.errors import CheckpointError
from popsan_jax.training import checkpoint, checkpoint_index


@flax.struct.dataclass
class _FakeState:
    w: jax.Array
    env_steps: jax.Array


def test_manifest_keeps_every_nth_last_and_best(tmp_path):
    successes = [0.1, 0.9, 0.2, 0.3, 0.1]
    for i, s in enumerate(successes, start=1):
        state = _FakeState(w=jnp.full((2,), float(i)), env_steps=jnp.int32(100 * i))
        checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(i), i, s, 2)
    index = checkpoint_index.read_index(tmp_path)
    # every 2nd eval (2, 4), the best (eval 2, success 0.9) and the last (eval 5)
    assert [e["step"] for e in index["checkpoints"]] == [200, 400, 500]
    assert index["last"] == 500 and index["best"] == 200
    on_disk = sorted(p.name for p in (tmp_path / "checkpoints").iterdir() if p.is_dir())
    assert on_disk == ["step_000000000200", "step_000000000400", "step_000000000500"]
    template = _FakeState(w=jnp.zeros(2), env_steps=jnp.int32(0))
    state, key, entry = checkpoint.restore_checkpoint(tmp_path, template, "best")
    np.testing.assert_array_equal(state.w, [2.0, 2.0])
    np.testing.assert_array_equal(key, jax.random.PRNGKey(2))
    assert entry["success_rate"] == 0.9
    with pytest.raises(CheckpointError, match="no checkpoint at step 300"):
        checkpoint.restore_checkpoint(tmp_path, template, 300)


def test_missing_and_corrupt_checkpoints_raise_checkpoint_error(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        checkpoint_index.read_index(tmp_path / "nope")
    with pytest.raises(CheckpointError, match="no checkpoint in"):
        checkpoint_index.read_index(tmp_path)
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "index.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="corrupt checkpoint index"):
        checkpoint_index.read_index(tmp_path)
    state = _FakeState(w=jnp.ones(2), env_steps=jnp.int32(7))
    (tmp_path / "checkpoints" / "index.json").unlink()
    path = checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    for f in path.rglob("*"):
        if f.is_file() and f.stat().st_size > 0 and "manifest" in f.name:
            f.write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="is damaged"):
        checkpoint.restore_checkpoint(tmp_path, state, "last")
    wrong_shape = _FakeState(w=jnp.ones(3), env_steps=jnp.int32(0))
    shutil_path = tmp_path / "other"
    checkpoint.save_checkpoint(shutil_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    with pytest.raises(CheckpointError, match="cannot restore checkpoint"):
        checkpoint.restore_checkpoint(shutil_path, wrong_shape, "last")


def test_index_names_only_finished_checkpoints(tmp_path):
    """A directory left by a crash before the manifest update is not listed and is overwritten
    by the next save of that step."""
    state = _FakeState(w=jnp.ones(2), env_steps=jnp.int32(100))
    checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.5, 1)
    stray = tmp_path / "checkpoints" / "step_000000000200"
    stray.mkdir()
    (stray / "junk").write_text("half written")
    index = json.loads((tmp_path / "checkpoints" / "index.json").read_text())
    assert [e["step"] for e in index["checkpoints"]] == [100]
    later = _FakeState(w=jnp.full((2,), 7.0), env_steps=jnp.int32(200))
    checkpoint.save_checkpoint(tmp_path, later, jax.random.PRNGKey(1), 2, 0.1, 1)
    restored, _, entry = checkpoint.restore_checkpoint(tmp_path, state, "last")
    np.testing.assert_array_equal(restored.w, [7.0, 7.0])
    assert entry.pop("digest").startswith("sha256:")
    assert entry == {"step": 200, "eval_index": 2, "success_rate": 0.1, "dir": stray.name}
    assert checkpoint_index.read_index(tmp_path)["best"] == 100
    assert not (tmp_path / "checkpoints" / "index.json.tmp").exists()
