"""Shadowing-masking (brdfjax.core.shadowing) and the specular term's normalisations.

Layers (style.md): closed forms against the NumPy oracle, the tabulated Lambda
against the closed forms and against the oracle's projected-area integral,
physics properties (white furnace, reciprocity, G -> 1 at normal incidence),
gradients against finite differences, and the options' error messages.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax import distributions as dist, reference as ref, shadowing as sh
from brdfjax.core.fresnel import q_factor
from brdfjax.core.terms import Specular

jax.config.update("jax_enable_x64", True)

THETA_DEG = np.array([0.0, 1.0, 10.0, 30.0, 45.0, 60.0, 70.0, 75.0, 80.0, 85.0, 88.0, 89.0, 89.9])


def _in_plane(theta_deg, phi=0.0):
    t = np.deg2rad(np.asarray(theta_deg, float))
    return np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], -1)


@pytest.mark.parametrize("width", [2e-4, 0.3, 1.0])
def test_closed_forms_match_the_oracle(width):
    w = _in_plane(THETA_DEG)
    t = np.deg2rad(THETA_DEG)
    np.testing.assert_allclose(np.asarray(sh.smith_lambda(dist.Beckmann(width), w)),
                               ref.smith_lambda_beckmann(t, width), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(np.asarray(sh.smith_lambda(dist.GGX(width), w)),
                               ref.smith_lambda_ggx(t, width), rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("width", [2e-4, 0.3])
def test_tabulated_lambda_matches_the_closed_forms(width):
    w = _in_plane(THETA_DEG)
    for d in (dist.Beckmann(width), dist.GGX(width)):
        exact = np.asarray(sh.smith_lambda(d, w))
        table = np.asarray(sh.smith_lambda(d, w, method="table"))
        err = np.abs(table - exact)
        assert np.all((err <= 2e-6 * exact) | (err < 1e-9)), (type(d).__name__, width, np.max(err / np.maximum(exact, 1e-300)))


def test_anisotropic_closed_forms_use_the_projected_width():
    # along x the width is mx, along y my; at 45 deg azimuth alpha^2 = (mx^2 + my^2) / 2
    t = np.deg2rad(75.0)
    for phi, width in ((0.0, 0.1), (np.pi / 2, 0.4), (np.pi / 4, np.sqrt((0.1**2 + 0.4**2) / 2))):
        w = _in_plane([75.0], phi)
        np.testing.assert_allclose(np.asarray(sh.smith_lambda(dist.BeckmannAniso(0.1, 0.4), w)),
                                   ref.smith_lambda_beckmann(t, width), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(sh.smith_lambda(dist.GGXAniso(0.1, 0.4), w)),
                                   ref.smith_lambda_ggx(t, width), rtol=1e-9)
    # the anisotropic Student-t is a stretch of its isotropic table: along x it is StudentT(sigma_x), along y StudentT(sigma_y)
    w = np.concatenate([_in_plane([60.0, 80.0], 0.0), _in_plane([60.0, 80.0], np.pi / 2)])
    got = np.asarray(sh.smith_lambda(dist.StudentTAniso(0.1, 0.4, 3.0), w))
    np.testing.assert_allclose(got[:2], np.asarray(sh.smith_lambda(dist.StudentT(0.1, 3.0), w[:2])), rtol=1e-5)
    np.testing.assert_allclose(got[2:], np.asarray(sh.smith_lambda(dist.StudentT(0.4, 3.0), w[2:])), rtol=1e-5)


@pytest.mark.parametrize(
    "d, oracle",
    [
        (dist.CosineLobe(20.0), lambda th, ph: ref.cosine_lobe(th, 20.0)),
        (dist.StudentT(0.2, 3.0), lambda th, ph: ref.student_t(th, 0.2, 3.0)),
        (dist.BeardMaxwell(0.3), lambda th, ph: ref.beard_maxwell(th, 0.3)),
    ],
    ids=["cosine_lobe", "student_t", "beard_maxwell"],
)
def test_tabulated_lambda_matches_the_projected_area_integral(d, oracle):
    th = np.array([60.0, 75.0, 85.0])
    got = np.asarray(sh.smith_lambda(d, _in_plane(th)))
    want = ref.smith_lambda_numeric(oracle, np.deg2rad(th))
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-6)


@pytest.mark.slow  # the 2-D (Ashikhmin-Shirley) table compiles in ~20 s
def test_tabulated_lambda_anisotropic_non_stretch():
    d = dist.AshikhminShirley(10.0, 40.0)
    for phi in (np.pi, np.pi + 0.6, 1.5 * np.pi):  # azimuths from -x, as the oracle's D takes them
        w_vec = ref.direction(np.deg2rad(np.array([70.0, 85.0])), phi)
        got = np.asarray(sh.smith_lambda(d, w_vec))
        want = ref.smith_lambda_numeric(lambda th, ph: ref.ashikhmin_shirley(th, ph, 10.0, 40.0), np.deg2rad([70.0, 85.0]), phi)
        np.testing.assert_allclose(got, want, rtol=5e-3, atol=1e-5)


def test_g_tends_to_one_for_narrow_lobes_and_stays_below_one():
    for d in (dist.Beckmann(2e-4), dist.GGX(2e-4), dist.CosineLobe(5e7)):
        w = _in_plane([0.0, 20.0, 60.0])
        g1 = np.asarray(sh.smith_g1(d, w, np.array([0.0, 0.0, 1.0])))
        np.testing.assert_allclose(g1, 1.0, atol=1e-6)
    dirs = bj.Directions.from_angles(np.deg2rad(70.0), 0.0, np.deg2rad(np.linspace(0, 89.5, 60)), np.pi)
    for d in (dist.Beckmann(0.5), dist.GGX(0.5), dist.HyperCauchy(0.3, 2.5)):
        g2 = np.asarray(sh.smith_g2(d, dirs))
        assert np.all((g2 > 0) & (g2 <= 1.0))
    vc = np.asarray(sh.v_cavity(dirs))
    assert np.all((vc > 0) & (vc <= 1.0)) and vc[0] < 1.0


def _albedo(term, theta_i, m, n_r=500, n_psi=96, r_max=9.0, unit_fresnel=False):
    """Directional albedo ``integral f cos ts dw_s`` in half-vector slope coordinates (dw_s = 4 (w_i.h) dw_h)."""
    s = (np.arange(n_r) + 0.5) * (r_max * m / n_r)
    psi = (np.arange(n_psi) + 0.5) * (2 * np.pi / n_psi)
    S, P = np.meshgrid(s, psi, indexing="ij")
    x, y = S * np.cos(P), S * np.sin(P)
    norm = np.sqrt(1 + x * x + y * y)
    h = np.stack([-x / norm, -y / norm, 1 / norm], -1)
    dw_h = S * (r_max * m / n_r) * (2 * np.pi / n_psi) / norm**3
    wi = np.array([-np.sin(theta_i), 0.0, np.cos(theta_i)])
    ih = h @ wi
    ws = 2 * ih[..., None] * h - wi
    ok = ws[..., 2] > 0
    ws = np.where(ok[..., None], ws, np.array([0.0, 0.0, 1.0]))
    dirs = bj.Directions.from_vectors(np.broadcast_to(wi, ws.shape), ws)
    f = np.asarray(term(dirs, 5e-7))
    if unit_fresnel:  # F = 1: divide out the seed's Q (whose half is F only in the mirror direction)
        f = f * 2.0 / np.asarray(q_factor(term.n, dirs, term.k))
    return float(np.sum(np.where(ok, f * ws[..., 2] * 4 * ih * dw_h, 0.0)))


def test_white_furnace_albedo_at_most_one_and_f_weighted_one_for_narrow_lobes():
    # lossless microfacets (F = 1): D G / (4 cos ti cos ts) integrates to <= 1, -> 1 as the lobe narrows
    for m in (0.02, 0.2, 0.5):
        term = Specular(dist.Beckmann(m), 1.0, 1.5, shadowing="smith", normalisation="torrance_sparrow", fresnel="q_factor")
        albedo = [_albedo(term, np.deg2rad(ti), m, unit_fresnel=True) for ti in (0.0, 40.0, 70.0, 85.0)]
        assert all(0.5 < a <= 1.0 + 1e-4 for a in albedo), (m, albedo)  # quadrature error ~3e-5
        if m == 0.02:
            np.testing.assert_allclose(albedo[:3], 1.0, atol=2e-3)
    # without shadowing the Torrance-Sparrow form exceeds 1 at grazing incidence: what G2 repairs
    bare = Specular(dist.Beckmann(0.5), 1.0, 1.5, shadowing="none", normalisation="torrance_sparrow", fresnel="q_factor")
    assert _albedo(bare, np.deg2rad(85.0), 0.5, unit_fresnel=True) > 1.05
    # narrow lobe: the albedo is the Fresnel reflectance in the mirror direction (Q/2 = (F_s + F_p)/2)
    m = 0.005
    term = Specular(dist.Beckmann(m), 1.0, n=1.5, shadowing="smith", normalisation="torrance_sparrow")
    for ti in (0.0, 30.0, 60.0, 75.0):
        fs, fp = ref.fresnel(1.5, np.deg2rad(ti))
        assert _albedo(term, np.deg2rad(ti), m) == pytest.approx((fs + fp) / 2, rel=2e-3)


@pytest.mark.parametrize("shadowing, normalisation", [("smith", "torrance_sparrow"), ("v_cavity", "seed")])
def test_reciprocity(shadowing, normalisation):
    rng = np.random.default_rng(3)
    ti, ts = rng.uniform(0, 1.45, 20), rng.uniform(0, 1.45, 20)
    pi, ps = rng.uniform(0, 2 * np.pi, 20), rng.uniform(0, 2 * np.pi, 20)
    dirs = bj.Directions.from_angles(np.r_[ti, ts], np.r_[pi, ps], np.r_[ts, ti], np.r_[ps, pi])
    for d in (dist.GGXAniso(0.2, 0.4), dist.CosineLobe(30.0)):
        f = np.asarray(Specular(d, 0.7, 1.6, 0.3, shadowing=shadowing, normalisation=normalisation)(dirs, 5e-7))
        assert np.all(f[:20] > 0)
        np.testing.assert_allclose(f[:20], f[20:], rtol=1e-9)


def test_seed_form_reproduces_the_seed_and_match_the_oracle():
    ti, ts = np.deg2rad(40.0), np.deg2rad(np.linspace(0, 89, 30))
    dirs = bj.Directions.from_angles(ti, 0.0, ts, np.pi)
    seed = Specular(dist.Beckmann(0.2), 0.5, 1.5, **bj.SEED_FORM)
    explicit = Specular(dist.Beckmann(0.2), 0.5, 1.5, shadowing="none", normalisation="seed", fresnel="q_factor")
    np.testing.assert_array_equal(np.asarray(seed(dirs, 5e-7)), np.asarray(explicit(dirs, 5e-7)))
    oracle = ref.specular(ti, 0.0, ts, np.pi, lambda th, ph: ref.beckmann(th, 0.2), 0.5, 1.5)
    np.testing.assert_allclose(np.asarray(seed(dirs, 5e-7)), oracle, rtol=1e-10)
    # the default is the standard form, not the seed's
    default = Specular(dist.Beckmann(0.2), 0.5, 1.5)
    assert {k: getattr(default, k) for k in bj.STANDARD_FORM} == bj.STANDARD_FORM
    lam = lambda t: ref.smith_lambda_beckmann(t, 0.2)  # noqa: E731
    for norm in ("seed", "torrance_sparrow"):
        got = Specular(dist.Beckmann(0.2), 0.5, 1.5, shadowing="smith", normalisation=norm, fresnel="q_factor")(dirs, 5e-7)
        want = ref.specular_shadowed(ti, 0.0, ts, np.pi, lambda th, ph: ref.beckmann(th, 0.2), 0.5, 1.5, lam, norm)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-9)
    # the two normalisations agree in the mirror direction
    mirror = bj.Directions.from_angles(ti, 0.0, ti, np.pi)
    a = Specular(dist.Beckmann(0.2), 0.5, 1.5, **bj.SEED_FORM)(mirror, 5e-7)
    b = Specular(dist.Beckmann(0.2), 0.5, 1.5, shadowing="none", fresnel="q_factor")(mirror, 5e-7)
    assert float(a) == pytest.approx(float(b), rel=1e-12)


def test_gradients_are_finite_and_match_finite_differences():
    dirs = bj.Directions.from_angles(np.deg2rad([0.0, 30.0, 80.0, 80.0]), 0.0, np.deg2rad([0.0, 30.0, 85.0, 60.0]), np.pi)

    @functools.partial(jax.jit, static_argnums=(1, 2))
    def total(p, cls, shadowing):
        return jnp.sum(jnp.log(Specular(cls(p), 0.5, 1.5, shadowing=shadowing, normalisation="torrance_sparrow")(dirs, 5e-7)))

    for cls, p, shadowing in ((dist.Beckmann, 0.3, "smith"), (dist.GGX, 0.3, "v_cavity"), (dist.CosineLobe, 15.0, "smith")):
        g = float(jax.jit(jax.grad(total), static_argnums=(1, 2))(p, cls, shadowing))
        h = 1e-5 * p
        fd = (float(total(p + h, cls, shadowing)) - float(total(p - h, cls, shadowing))) / (2 * h)
        assert np.isfinite(g) and g == pytest.approx(fd, rel=1e-5, abs=1e-8), (cls.__name__, shadowing, g, fd)
    # the closed forms at normal incidence and at the horizon: finite gradients
    edge = bj.Directions.from_angles(np.array([0.0, np.pi / 2]), 0.0, np.array([0.0, 0.3]), np.pi)
    g = jax.grad(lambda m: jnp.sum(sh.smith_g2(dist.Beckmann(m), edge)))(0.2)
    assert np.isfinite(float(g))


def test_bad_options_name_the_choices():
    with pytest.raises(ValueError, match=r"unknown shadowing 'smit' \(did you mean 'smith'\?\); known: none, smith, v_cavity"):
        Specular(dist.Beckmann(0.1), 0.5, 1.5, shadowing="smit")
    with pytest.raises(ValueError, match=r"unknown normalisation 'ts'; known: seed, torrance_sparrow"):
        Specular(dist.Beckmann(0.1), 0.5, 1.5, normalisation="ts")
    with pytest.raises(ValueError, match=r"unknown method 'exact'; known: auto, table"):
        sh.smith_lambda(dist.Beckmann(0.1), _in_plane([10.0]), method="exact")
