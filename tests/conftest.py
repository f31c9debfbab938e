"""Shared pytest setup: persistent compilation cache so MJX compiles are paid once per checkout."""

from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

import_mjx_quietly()
enable_compilation_cache()
