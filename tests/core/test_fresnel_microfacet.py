"""The microfacet Fresnel option of the specular terms (``fresnel = "microfacet"``: F_s + F_p at theta_d)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax import distributions as dist, reference as ref
from brdfjax.config import ConfigError
from brdfjax.config.model import ModelConfig, build_model
from brdfjax.core.fresnel import fresnel_microfacet, q_factor
from brdfjax.core.terms import Lobe, MultiLobeSpecular, Specular

jax.config.update("jax_enable_x64", True)

RNG = np.random.default_rng(11)
TI, TS = RNG.uniform(0, 1.5, 40), RNG.uniform(0, 1.5, 40)
PI, PS = RNG.uniform(0, 2 * np.pi, 40), RNG.uniform(0, 2 * np.pi, 40)
DIRS = bj.Directions.from_angles(TI, PI, TS, PS)
SWAP = bj.Directions.from_angles(TS, PS, TI, PI)
#: aluminium near 633 nm, a dielectric, and a low-index metal
INDICES = [(1.37, 7.62), (1.5, 0.0), (0.2, 3.0)]


def _theta_d(ti, pi, ts, ps):
    wi, ws = ref.direction(ti, pi), ref.direction(ts, ps)
    h = (wi + ws) / np.linalg.norm(wi + ws, axis=-1, keepdims=True)
    return np.arccos(np.clip(np.sum(wi * h, -1), -1.0, 1.0))


@pytest.mark.parametrize("n, k", INDICES)
def test_microfacet_fresnel_matches_numpy_at_theta_d(n, k):
    fs, fp = ref.fresnel(n + 1j * k, _theta_d(TI, PI, TS, PS))
    np.testing.assert_allclose(np.asarray(fresnel_microfacet(n, DIRS, k)), fs + fp, rtol=1e-10)


@pytest.mark.parametrize("n, k", INDICES)
def test_microfacet_fresnel_equals_q_in_the_specular_direction(n, k):
    mirror = bj.Directions.from_angles(TI, PI, TI, PI + np.pi)
    np.testing.assert_allclose(np.asarray(fresnel_microfacet(n, mirror, k)), np.asarray(q_factor(n, mirror, k)), rtol=1e-9)
    # ... and the whole specular term is then the same for both options
    spec = {f: Specular(dist.GGX(0.2), 0.7, n, k, shadowing="smith", fresnel=f) for f in ("q_factor", "microfacet")}
    np.testing.assert_allclose(np.asarray(spec["microfacet"](mirror, 5e-7)), np.asarray(spec["q_factor"](mirror, 5e-7)),
                               rtol=1e-9)


def test_microfacet_fresnel_term_is_reciprocal_and_differs_off_specular():
    lobes = {"spike": Lobe(dist.Beckmann(0.05), 0.6), "halo": Lobe(dist.GGX(0.3), 0.2)}
    for norm in ("seed", "torrance_sparrow"):
        term = MultiLobeSpecular(lobes, n=1.37, k=7.62, shadowing="smith", normalisation=norm, fresnel="microfacet")
        np.testing.assert_allclose(np.asarray(term(DIRS, 5e-7)), np.asarray(term(SWAP, 5e-7)), rtol=1e-10)
    q = MultiLobeSpecular(lobes, n=0.2, k=3.0, shadowing="smith", fresnel="q_factor")
    f = MultiLobeSpecular(lobes, n=0.2, k=3.0, shadowing="smith", fresnel="microfacet")
    ratio = np.asarray(f(DIRS, 5e-7)) / np.asarray(q(DIRS, 5e-7))
    assert np.nanmax(np.abs(np.log(ratio))) > 0.05  # off the mirror direction the two factors are not the same


def test_microfacet_fresnel_gradients_are_finite_at_normal_incidence_and_the_mirror():
    dirs = bj.Directions.from_angles(np.array([0.0, 0.3, 0.0, 1.2]), 0.0, np.array([0.0, 0.3, 0.4, 1.3]),
                                     np.array([np.pi, np.pi, 0.0, 2.0]))

    def loss(p):
        term = Specular(dist.GGX(p[0]), p[1], p[2], p[3], shadowing="smith", fresnel="microfacet")
        return jnp.sum(jnp.log(term(dirs, 5e-7)))

    g = jax.jit(jax.grad(loss))(jnp.array([0.2, 0.5, 1.37, 7.62]))
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g)[2:] != 0)


def test_fresnel_option_in_configs():
    body = {"terms": {"spec": {"kind": "multi_lobe", "lobes": {"a": "ggx"}, "fresnel": "microfacet", "shadowing": "smith",
                               "params": {"n": 1.37, "k": 7.62, "a": {"alpha": 0.1, "rho_s": 0.5}}}}}
    model = build_model("job.toml", ModelConfig.model_validate(body))
    assert model.terms["spec"].fresnel == "microfacet"
    expect = MultiLobeSpecular({"a": Lobe(dist.GGX(0.1), 0.5)}, n=1.37, k=7.62, shadowing="smith", fresnel="microfacet")
    np.testing.assert_allclose(np.asarray(model(DIRS, 5e-7)), np.asarray(expect(DIRS, 5e-7)), rtol=1e-12)
    # the diagnosis's config writer keeps it
    from brdfjax.diagnose.engine import model_terms_config

    terms, _ = model_terms_config(model)
    assert terms["spec"]["fresnel"] == "microfacet"
    bad = {"terms": {"s": {"kind": "specular", "distribution": "ggx", "fresnel": "schlick",
                           "params": {"alpha": 0.1, "rho_s": 1.0, "n": 1.5}}}}
    with pytest.raises((ConfigError, ValueError), match=r"unknown fresnel .schlick.; known: microfacet, q_factor"):
        build_model("job.toml", ModelConfig.model_validate(bad))
    with pytest.raises(ValueError, match=r"specular: unknown fresnel 'x'; known: q_factor, microfacet"):
        Specular(dist.GGX(0.1), 1.0, 1.5, fresnel="x")
