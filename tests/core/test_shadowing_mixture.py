"""Smith G2 of a multi-lobe surface as one surface (``shadowing = "smith_mixture"``: Lambda of the lobes' mixture)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax import distributions as dist
from brdfjax.config.model import ModelConfig, build_model
from brdfjax.core.shadowing import lambda_ggx, smith_mixture_g2_parts
from brdfjax.core.terms import Lobe, MultiLobeSpecular

jax.config.update("jax_enable_x64", True)

RNG = np.random.default_rng(5)
TI, TS = RNG.uniform(0, 1.5, 40), RNG.uniform(0, 1.5, 40)
PI, PS = RNG.uniform(0, 2 * np.pi, 40), RNG.uniform(0, 2 * np.pi, 40)
DIRS = bj.Directions.from_angles(TI, PI, TS, PS)
SWAP = bj.Directions.from_angles(TS, PS, TI, PI)


def _lobes(halo=None):
    return {"spike": Lobe(dist.GGX(0.02), 0.6), "halo": Lobe(halo or dist.GGX(0.5), 0.2)}


def test_mixture_g2_is_the_weighted_lambda_of_the_lobes():
    # GGX closed forms: Lambda_mix = 0.75 Lambda(0.02) + 0.25 Lambda(0.5); G2 = 1 / (1 + Lambda_i + Lambda_s)
    def lam(a, t):
        return np.asarray(lambda_ggx((a * np.tan(t)) ** 2))

    mix = lambda t: 0.75 * lam(0.02, t) + 0.25 * lam(0.5, t)  # noqa: E731
    g2 = 1.0 / (1.0 + mix(TI) + mix(TS))
    wi, ws = np.asarray(DIRS.w_i), np.asarray(DIRS.w_s)
    h = wi + ws
    g2 = np.where((np.sum(wi * h, -1) > 0) & (np.sum(ws * h, -1) > 0), g2, 0.0)
    num, den = smith_mixture_g2_parts([dist.GGX(0.02), dist.GGX(0.5)], [0.6, 0.2], DIRS)
    np.testing.assert_allclose(np.asarray(num / den), g2, rtol=1e-12)
    # the term: every lobe masked by the same G2
    term = MultiLobeSpecular(_lobes(), n=1.37, k=7.62, shadowing="smith_mixture", normalisation="torrance_sparrow")
    bare = MultiLobeSpecular(_lobes(), n=1.37, k=7.62, shadowing="none", normalisation="torrance_sparrow")
    np.testing.assert_allclose(np.asarray(term(DIRS, 5e-7)), np.asarray(bare(DIRS, 5e-7)) * g2, rtol=1e-10)
    # the wide lobe masks the narrow lobe's facets: at 80 deg the mixture G is below the spike's own
    own = MultiLobeSpecular(_lobes(), n=1.37, k=7.62, shadowing="smith", normalisation="torrance_sparrow")
    graze = bj.Directions.from_angles(np.radians(80.0), 0.0, np.radians(80.0), np.pi)
    assert float(term(graze, 5e-7)) < float(own(graze, 5e-7))


def test_one_lobe_mixture_is_smith_and_g2_is_at_most_one():
    one = {"a": Lobe(dist.Beckmann(0.2), 0.5)}
    a = MultiLobeSpecular(one, n=1.5, shadowing="smith_mixture")(DIRS, 5e-7)
    b = MultiLobeSpecular(one, n=1.5, shadowing="smith")(DIRS, 5e-7)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)
    s = bj.Specular(dist.GGX(0.3), 0.5, 1.5, shadowing="smith_mixture")(DIRS, 5e-7)
    np.testing.assert_allclose(np.asarray(s), np.asarray(bj.Specular(dist.GGX(0.3), 0.5, 1.5, shadowing="smith")(DIRS, 5e-7)))
    num, den = smith_mixture_g2_parts([dist.GGX(0.02), dist.Beckmann(0.4)], [0.6, 0.0], DIRS)
    g = np.asarray(num / den)
    assert np.all((g >= 0) & (g <= 1))


@pytest.mark.parametrize("halo", [dist.GGX(0.5), dist.HyperCauchy(0.4, 2.5)], ids=["ggx", "hyper_cauchy"])
def test_mixture_shadowing_is_reciprocal_with_finite_gradients(halo):
    term = MultiLobeSpecular(_lobes(halo), n=1.37, k=7.62, shadowing="smith_mixture")
    np.testing.assert_allclose(np.asarray(term(DIRS, 5e-7)), np.asarray(term(SWAP, 5e-7)), rtol=1e-9)
    dirs = bj.Directions.from_angles(np.array([0.0, 0.3, 1.3]), 0.0, np.array([0.0, 0.3, 1.4]), np.pi)

    def loss(p):
        lobes = {"spike": Lobe(dist.GGX(p[0]), p[1]), "halo": Lobe(dist.GGX(p[2]), p[3])}
        return jnp.sum(jnp.log(MultiLobeSpecular(lobes, n=1.37, k=7.62, shadowing="smith_mixture")(dirs, 5e-7)))

    g = np.asarray(jax.jit(jax.grad(loss))(jnp.array([0.02, 0.6, 0.5, 0.2])))
    assert np.all(np.isfinite(g)) and g[2] != 0  # the halo's width changes the spike's masking


def test_smith_mixture_in_configs():
    body = {"terms": {"spec": {"kind": "multi_lobe", "lobes": {"spike": "ggx", "halo": "ggx"}, "shadowing": "smith_mixture",
                               "params": {"n": 1.37, "k": 7.62, "spike": {"alpha": 0.02, "rho_s": 0.6},
                                          "halo": {"alpha": 0.5, "rho_s": 0.2}}}}}
    model = build_model("job.toml", ModelConfig.model_validate(body))
    expect = MultiLobeSpecular(_lobes(), n=1.37, k=7.62, shadowing="smith_mixture")
    np.testing.assert_allclose(np.asarray(model(DIRS, 5e-7)), np.asarray(expect(DIRS, 5e-7)), rtol=1e-12)
