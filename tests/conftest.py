"""Test configuration: 64-bit JAX for oracles and finite differences; the one slow switch.

Float32 behaviour is tested explicitly through ``precision="float32"``.

Long checks (full-resolution runs, statistical studies, long compilations) carry the registered ``slow``
marker (``@pytest.mark.slow``) and run only with ``pytest --slow``; ``BRDFJAX_SLOW=1`` in the environment is
the same switch.  A test that needs to know at run time takes the ``run_slow`` fixture.
"""

import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
# The CLI turns on JAX's persistent compilation cache in the user's cache folder; tests that call
# brdfjax.cli.main in this process leave it alone (tests/runtime/test_compile_cache.py turns it on in a subprocess).
os.environ.setdefault("BRDFJAX_NO_CACHE", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true", default=False,
                     help="also run the tests marked slow (full-resolution and long runs); BRDFJAX_SLOW=1 is the same")


def slow_enabled(config) -> bool:
    """``--slow`` given, or ``BRDFJAX_SLOW`` set to anything but empty or ``0``."""
    return bool(config.getoption("--slow")) or os.environ.get("BRDFJAX_SLOW", "") not in ("", "0")


def pytest_collection_modifyitems(config, items):
    if slow_enabled(config):
        return
    skip = pytest.mark.skip(reason="slow: run with --slow (or BRDFJAX_SLOW=1)")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def run_slow(request) -> bool:
    """Whether the slow tests run (``--slow`` or ``BRDFJAX_SLOW=1``)."""
    return slow_enabled(request.config)


@pytest.fixture
def assert_jacobian_matches_jacfwd():
    """``check(problem, v, residual_rtol=1e-9)``: the structured Jacobian at ``v`` equals ``jax.jacfwd``'s to 1e-10
    of each column's norm (every column non-zero), and its residuals equal ``evaluate``'s."""
    import equinox as eqx  # noqa: PLC0415 -- only the Jacobian tests need the fit stack
    import numpy as np  # noqa: PLC0415

    from brdfjax.fit import _problem  # noqa: PLC0415
    from brdfjax.fit._jacobian import supports  # noqa: PLC0415

    def check(problem, v, residual_rtol=1e-9):
        assert supports(problem)
        J = np.asarray(_problem.jacobian(v, problem))
        ref = np.asarray(_problem.jacobian_jacfwd(v, problem))
        assert J.shape == ref.shape == (sum(problem.counts), problem.u0.shape[0])
        norms = np.linalg.norm(ref, axis=0)
        assert np.all(norms > 0)
        err = np.max(np.abs(J - ref), axis=0) / norms
        assert np.all(err < 1e-10), err
        r_struct = np.asarray(eqx.filter_jit(_problem._residuals_and_jacobian)(v, problem)[0])
        # the same residuals (the FFT box sums the terms after the transform: rounding of the largest value)
        np.testing.assert_allclose(r_struct, np.asarray(_problem.evaluate(v, problem)[1]),
                                   rtol=residual_rtol, atol=residual_rtol)

    return check
