"""A full-frame render and a fit's residuals split over 2 host devices equal the single-device ones.

The device count must be set before JAX initialises, so the check runs in a
subprocess with ``XLA_FLAGS=--xla_force_host_platform_device_count=2``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = textwrap.dedent('''
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import brdfjax as bj
    from brdfjax.fit import Param, get_solver, render_noisy_frames, shard_problem
    from brdfjax.fit.internal import prepare_problem
    from brdfjax.fit._problem import jacobian, residuals
    assert len(jax.devices()) == 2, jax.devices()
    model, frame = bj.solar_cell(), bj.Conditions.from_degrees(20.0)
    for precision in ("float32", "float64"):
        with jax.numpy_dtype_promotion("strict" if precision == "float32" else "standard"):
            one = np.asarray(bj.render(model, frame, step=32, precision=precision))
            two = bj.render(model, frame, step=32, precision=precision, devices="all")
        assert len(two.sharding.device_set) == 2, two.sharding
        two = np.asarray(two)
        assert two.shape == one.shape, (two.shape, one.shape)
        # the same arithmetic per pixel; XLA may fuse the two programs differently: float rounding
        rel = np.max(np.abs(two - one) / np.maximum(np.abs(one), 1e-3 * np.max(one)))
        assert rel < (5e-5 if precision == "float32" else 1e-12), (precision, rel)
        print(precision, "max relative difference", rel)
    frames = render_noisy_frames(model, [20.0, 40.0], step=16, noise_rel=0.03, floor=0.1, seed=1)
    spec = {k: Param(float(np.asarray(v)) * 1.05) for k, v in model.params().items() if k in ("m1", "rho_s1", "a", "c")}
    prep = prepare_problem(model, frames, spec, solver=get_solver("lm"))
    sharded = shard_problem(prep.problem)
    assert len(sharded.stack.blocks.data.sharding.device_set) == 2
    v = jax.numpy.asarray([0.1, -0.2, 0.05, 0.3])
    r1 = np.asarray(jax.jit(residuals)(v, prep.problem))
    r2 = np.asarray(jax.jit(residuals)(v, sharded))
    assert r1.shape == r2.shape and np.max(np.abs(r1 - r2)) <= 1e-10 * max(1.0, np.max(np.abs(r1))), np.max(np.abs(r1 - r2))
    # the Jacobian (its shared program entered in the solver's tracing context) on the sharded problem too
    J1 = np.asarray(jacobian(v, prep.problem))
    J2 = np.asarray(jacobian(v, sharded))
    assert J1.shape == J2.shape and np.max(np.abs(J1 - J2)) <= 1e-10 * np.max(np.abs(J1)), np.max(np.abs(J1 - J2))
    print("SHARDED_OK", r1.size)
''')


def test_render_and_residuals_on_two_host_devices_equal_one_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu",
               PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "SHARDED_OK" in proc.stdout
