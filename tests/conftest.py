"""Shared pytest setup: persistent compilation cache so MJX compiles are paid once per checkout."""

from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

import_mjx_quietly()
enable_compilation_cache()

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def finished_toy_run(tmp_path_factory):
    """A toy run trained to its end (2 iterations, 2 checkpoints); tests copy it, never edit it."""
    from _run_fixtures import train_finished

    return train_finished(tmp_path_factory.mktemp("finished") / "run")
