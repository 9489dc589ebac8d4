"""The forward kernel's building blocks (issue 19): component-wise directions, the one-program frame,
the vectorising float32 trigonometry, the folded Q factor and the pooled display image."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax.core.fresnel import q_factor, q_factor_parts
from brdfjax.core.geometry import fast_cos, fast_sin, fast_sinc
from brdfjax.plotting import _log10_pooled, _max_pool, log10_floor


def test_directions_accept_arrays_or_components_and_keep_a_per_frame_incident_direction():
    det = bj.Detector.seed()
    h, v = np.array([-1647.0, 0.0, 1648.0]), np.array([-1235.0, 0.0, 1236.0])
    d = det.directions(h, v, 0.3)
    # one incident direction per frame: its components stay scalars, the stacked arrays broadcast
    assert jnp.shape(d.i[0]) == () and d.shape == (3,)
    assert d.w_i.shape == d.w_s.shape == d.w_sum.shape == (3, 3)
    np.testing.assert_allclose(np.asarray(d.w_i[1]), [-np.sin(0.3), 0.0, np.cos(0.3)], rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d.w_s), axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(d.w_sum), np.asarray(d.w_i + d.w_s), atol=1e-6)
    again = bj.Directions(d.w_i, d.w_s, d.w_sum)  # arrays (..., 3) in, the same components out
    for a, b in zip((*again.i, *again.s, *again.t), (*d.i, *d.s, *d.t), strict=True):
        np.testing.assert_array_equal(np.broadcast_to(np.asarray(a), (3,)), np.broadcast_to(np.asarray(b), (3,)))
    with pytest.raises(ValueError, match="last axis of length 3"):
        bj.Directions(np.zeros((4, 2)), d.w_s, d.w_sum)
    with pytest.raises(ValueError, match="needs 3 of them"):
        bj.Directions((0.0, 1.0), d.w_s, d.w_sum)


def test_rotated_z_equals_the_matrix_rotation():
    d = bj.Directions.from_angles(0.4, 0.1, np.linspace(0.1, 1.2, 5), np.linspace(0.0, 6.0, 5))
    a, b = d.rotated_z(0.7), d.rotated(bj.core.geometry.Rz(0.7))
    np.testing.assert_allclose(np.asarray(a.w_s), np.asarray(b.w_s), atol=1e-15)
    np.testing.assert_allclose(np.asarray(a.w_sum), np.asarray(b.w_sum), atol=1e-15)


def test_render_frame_is_render_per_term_and_geometry_in_one_program():
    model, frame = bj.solar_cell(), bj.Conditions.from_degrees(20.0)
    kw = dict(step=64)
    out = bj.render(model, frame, outputs="all", **kw)
    terms = bj.render(model, frame, per_term=True, **kw)
    geo = bj.render(None, frame, outputs=("theta_s", "phi_s", "omega"), **kw)
    np.testing.assert_array_equal(np.asarray(out["brdf"]), np.asarray(bj.render(model, frame, **kw)))
    for k in terms:
        np.testing.assert_array_equal(np.asarray(out["terms"][k]), np.asarray(terms[k]))
    for k in geo:
        np.testing.assert_array_equal(np.asarray(out[k]), np.asarray(geo[k]))
    single = bj.render(bj.Lambertian(0.3), frame, outputs="all", **kw)  # a bare term is a one-term model
    assert list(single["terms"]) == ["model"]
    np.testing.assert_allclose(np.asarray(single["brdf"]), 0.3 / np.pi, rtol=1e-6)


def test_render_casts_inside_the_program_and_does_not_recompile_for_new_values():
    frame = bj.Conditions.from_degrees(20.0)
    a = bj.render(bj.solar_cell(m1=2e-4), frame, step=256)
    b = bj.render(bj.solar_cell(m1=3e-4), frame, step=256)  # same structure, new value: the same executable
    assert a.dtype == jnp.float32 and not np.array_equal(np.asarray(a), np.asarray(b))
    from brdfjax.core.render import _program

    before = _program._cached._cache_size()
    bj.render(bj.solar_cell(m1=4e-4), frame, step=256)
    assert _program._cached._cache_size() == before


def test_float32_sin_cos_sinc_polynomials():
    x = np.concatenate([np.linspace(-300, 300, 200_001), np.linspace(-1e-3, 1e-3, 101), [0.0]]).astype(np.float32)
    ref = x.astype(np.float64)
    assert np.max(np.abs(np.asarray(jax.jit(fast_sin)(x)) - np.sin(ref))) < 2e-7
    assert np.max(np.abs(np.asarray(jax.jit(fast_cos)(x)) - np.cos(ref))) < 2e-7
    assert np.max(np.abs(np.asarray(jax.jit(fast_sinc)(x)) - np.sinc(ref))) < 2e-7
    # float64 goes to jnp's functions; the derivative of sinc is 0 at 0 and right elsewhere
    assert float(fast_sin(np.float64(1.0))) == np.sin(1.0) if jax.config.jax_enable_x64 else True
    assert float(jax.grad(fast_sinc)(jnp.float32(0.0))) == 0.0
    assert float(jax.grad(fast_sinc)(jnp.float32(0.3))) == pytest.approx(float(jax.grad(jnp.sinc)(jnp.float32(0.3))), rel=1e-5)


def test_q_factor_parts_and_the_specular_reduction():
    rng = np.random.default_rng(1)
    ti, ts = rng.uniform(0, 1.4, 50), rng.uniform(0, 1.4, 50)
    d = bj.Directions.from_angles(ti, rng.uniform(0, 6, 50), ts, rng.uniform(0, 6, 50))
    num, den = q_factor_parts(1.7, d, 0.3)
    assert np.all(np.asarray(den) > 0)
    np.testing.assert_allclose(np.asarray(num / den), np.asarray(q_factor(1.7, d, 0.3)), rtol=1e-6)
    # in the specular direction Q = F_s + F_p (physics.md), also at normal incidence (no azimuth)
    t = np.array([0.0, 0.3, 1.0])
    mirror = bj.Directions.from_angles(t, 0.0, t, np.pi)
    fs, fp = bj.fresnel(1.7, t, 0.3)
    np.testing.assert_allclose(np.asarray(q_factor(1.7, mirror, 0.3)), np.asarray(fs + fp), rtol=2e-6)


def test_pooled_log_image_equals_pooling_the_log_image():
    rng = np.random.default_rng(0)
    b = (10 ** rng.uniform(-12, 5, (1900, 1000))).astype(np.float32)
    b[rng.random(b.shape) < 0.1] = 0
    b[0, 0], b[1, 1], b[2, 2] = np.nan, -1.0, np.inf
    shown, vmin, vmax = _log10_pooled(b)
    img, vmin0, vmax0 = log10_floor(b.astype(np.float64))
    np.testing.assert_array_equal(shown, _max_pool(img)[0])
    assert (vmin, vmax) == (vmin0, vmax0)
    zeros = _log10_pooled(np.zeros((5, 4), np.float32))
    assert zeros[1:] == (-1.0, 0.0) and np.all(zeros[0] == 0)
