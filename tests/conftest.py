"""Test configuration: 64-bit JAX for oracles and finite differences.

Float32 behaviour is tested explicitly through ``precision="float32"``.
"""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
