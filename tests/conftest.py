"""Test configuration: 64-bit JAX for oracles and finite differences.

Float32 behaviour is tested explicitly through ``precision="float32"``.
"""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
# The CLI turns on JAX's persistent compilation cache in the user's cache folder; tests that call
# brdfjax.cli.main in this process leave it alone (tests/test_compile_cache.py turns it on in a subprocess).
os.environ.setdefault("BRDFJAX_NO_CACHE", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
