"""Shared pytest setup: persistent compilation cache so MJX compiles are paid once per checkout."""

from popsan_jax.jax_setup import enable_compilation_cache

enable_compilation_cache()
