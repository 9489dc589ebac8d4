"""brdfjax.instrument.radiometry: Eq 45, its inverse and Eq 87, written once and used by every caller."""

from __future__ import annotations

import math
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from brdfjax.instrument import radiometry, reduce, synthetic, uncertainty
from brdfjax.instrument.radiometry import brdf_from_flux, flux_from_brdf, incident_flux

RNG = np.random.default_rng(20261204)
THETA = RNG.uniform(0.0, 1.4, (7, 9))  # up to 80 degrees
OMEGA = RNG.uniform(1e-10, 5e-10, (7, 9))
BRDF = 10 ** RNG.uniform(-4, 6, (7, 9))
PHI_I = 9.828e9


def test_forward_of_inverse_is_identity_numpy_float64():
    phi_s = flux_from_brdf(BRDF, PHI_I, THETA, OMEGA)
    assert phi_s.dtype == np.float64
    np.testing.assert_allclose(brdf_from_flux(phi_s, PHI_I, THETA, OMEGA), BRDF, rtol=4e-16 * 8)
    np.testing.assert_allclose(flux_from_brdf(brdf_from_flux(phi_s, PHI_I, THETA, OMEGA), PHI_I, THETA, OMEGA),
                               phi_s, rtol=4e-16 * 8)


def test_forward_of_inverse_is_identity_jax_float32_and_under_jit():
    b, t, o = (jnp.asarray(a, jnp.float32) for a in (BRDF, THETA, OMEGA))
    back = jax.jit(lambda b: brdf_from_flux(flux_from_brdf(b, PHI_I, t, o), PHI_I, t, o))(b)
    assert isinstance(back, jax.Array) and back.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(back), np.asarray(b), rtol=6e-7 * 4)


def test_old_numbers_unchanged():
    # the formulas as each caller wrote them before they shared this module, evaluated the same way
    phi_s = RNG.uniform(1.0, 1e7, (7, 9))
    old_reduce_jax = phi_s / (PHI_I * jnp.cos(jnp.asarray(THETA)) * OMEGA)  # uncertainty.brdf_eq45 (jax)
    new = brdf_from_flux(phi_s, PHI_I, jnp.asarray(THETA), OMEGA)
    assert np.array_equal(np.asarray(new), np.asarray(old_reduce_jax))
    old_live = phi_s * 10 ** 2.1 / (PHI_I * np.cos(THETA) * OMEGA)  # devices.liveview
    assert np.array_equal(brdf_from_flux(phi_s * 10 ** 2.1, PHI_I, THETA, OMEGA), old_live)
    old_synth = BRDF * np.cos(THETA)  # instrument.synthetic.scatter_flux_image, in float64 then float32
    old_synth *= OMEGA
    old_synth *= PHI_I
    got = synthetic.scatter_flux_image(BRDF.astype(np.float32), THETA, OMEGA, PHI_I)
    assert got.dtype == np.float32
    old_synth32 = (BRDF.astype(np.float32).astype(np.float64) * np.cos(THETA) * OMEGA * PHI_I).astype(np.float32)
    assert np.array_equal(got, old_synth32)
    assert np.array_equal(synthetic.scatter_flux_image(BRDF, THETA, OMEGA, PHI_I), old_synth.astype(np.float32))


def test_seed_figures_through_eq45_and_eq87():
    # seed §4.2: noise-equivalent BRDF 17.07 sr^-1, 1.36 at OD_b - OD_m = 1.1, 1.08e-4 at OD_m = 0;
    # maximum measurable 5.82e6, 4.62e5, 36.7
    assert reduce.noise_equivalent_brdf(48.05, 9.828e9, 5.2, 5.2) == pytest.approx(17.07, rel=2e-3)
    assert reduce.noise_equivalent_brdf(48.05, 9.828e9, 5.2, 4.1) == pytest.approx(1.36, rel=5e-3)
    assert reduce.noise_equivalent_brdf(48.05, 9.828e9, 5.2, 0.0) == pytest.approx(1.08e-4, rel=5e-3)
    assert reduce.max_measurable_brdf(1.6383e7, 9.828e9, 5.2, 5.2) == pytest.approx(5.82e6, rel=2e-3)
    assert reduce.max_measurable_brdf(1.6383e7, 9.828e9, 5.2, 4.1) == pytest.approx(4.62e5, rel=2e-3)
    assert reduce.max_measurable_brdf(1.6383e7, 9.828e9, 5.2, 0.0) == pytest.approx(36.7, rel=2e-3)
    assert incident_flux(2.0, 3.0, 1.0) == pytest.approx(200.0, rel=1e-15)
    assert reduce.incident_flux is incident_flux


def test_gradients_pass_through():
    # d ln f_r / d theta_s = tan theta_s (the Eq 71 sensitivity)
    g = jax.grad(lambda t: jnp.log(brdf_from_flux(1.0, 1.0, t, 3e-10)))(0.7)
    assert float(g) == pytest.approx(math.tan(0.7), rel=1e-6)
    assert uncertainty.brdf_eq45 is brdf_from_flux


def test_eq45_is_written_once():
    root = Path(radiometry.__file__).resolve().parents[1]
    pattern = re.compile(r"cos\((theta_s|th)\)\s*\*\s*(omega|solid_angle|om)\b")
    hits = sorted(str(p.relative_to(root)) for p in root.rglob("*.py") if pattern.search(p.read_text()))
    assert hits == ["instrument/radiometry.py"]
