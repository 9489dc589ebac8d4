"""Multi-lobe specular, ABg and Phong terms: values against the oracle, normalisation, reciprocity,
gradients, parameter names and the registry/config round trip."""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax import distributions as dist, reference as ref
from brdfjax.config import ConfigError
from brdfjax.config.model import ModelConfig, build_model, describe_model
from brdfjax.core import registry
from brdfjax.core.terms import ABg, Lobe, MultiLobeSpecular, Phong, Specular

jax.config.update("jax_enable_x64", True)

RNG = np.random.default_rng(7)
TI, TS = RNG.uniform(0, 1.45, 25), RNG.uniform(0, 1.45, 25)
PI, PS = RNG.uniform(0, 2 * np.pi, 25), RNG.uniform(0, 2 * np.pi, 25)
SWAP = bj.Directions.from_angles(np.r_[TI, TS], np.r_[PI, PS], np.r_[TS, TI], np.r_[PS, PI])


def _spike_halo(shadowing="smith", normalisation="torrance_sparrow"):
    lobes = {"spike": Lobe(dist.Beckmann(0.05), 0.6), "halo": Lobe(dist.GGX(0.3), 0.2)}
    return MultiLobeSpecular(lobes, n=1.5, k=0.1, shadowing=shadowing, normalisation=normalisation)


def test_multi_lobe_is_the_sum_of_its_lobes_sharing_the_index():
    ml = _spike_halo()
    parts = [Specular(dist.Beckmann(0.05), 0.6, 1.5, 0.1, shadowing="smith", normalisation="torrance_sparrow"),
             Specular(dist.GGX(0.3), 0.2, 1.5, 0.1, shadowing="smith", normalisation="torrance_sparrow")]
    np.testing.assert_allclose(np.asarray(ml(SWAP, 5e-7)), sum(np.asarray(p(SWAP, 5e-7)) for p in parts), rtol=1e-12)
    f = np.asarray(ml(SWAP, 5e-7))
    np.testing.assert_allclose(f[:25], f[25:], rtol=1e-9)  # reciprocity
    model = bj.Model(terms={"spec": ml, "diffuse": bj.Lambertian(0.1)})
    assert model.parameter_units() == {
        "spec.spike.m": "1", "spec.spike.rho_s": "1", "spec.halo.alpha": "1", "spec.halo.rho_s": "1",
        "spec.n": "1", "spec.k": "1", "diffuse.rho_d": "1",
    }
    moved = model.with_params({"spec.halo.alpha": 0.4, "spec.n": 1.7})
    assert float(moved.params()["spec.halo.alpha"]) == 0.4 and float(moved.terms["spec"].n) == 1.7


def test_abg_and_phong_match_the_oracle_and_are_reciprocal():
    abg, phong = ABg(A=2.0, B=0.01, g=1.7), Phong(rho=0.8, k=40.0)
    np.testing.assert_allclose(np.asarray(abg(SWAP, 5e-7))[:25], ref.abg(TI, PI, TS, PS, 2.0, 0.01, 1.7), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(phong(SWAP, 5e-7))[:25], ref.phong(TI, PI, TS, PS, 0.8, 40.0), rtol=1e-9, atol=1e-300)
    for term in (abg, phong):
        f = np.asarray(term(SWAP, 5e-7))
        np.testing.assert_allclose(f[:25], f[25:], rtol=1e-12)
    # ABg: A / B in the mirror direction, A / (B + 1) one unit of |beta - beta0| away (theta_i = 0, theta_s = 90 deg)
    mirror = bj.Directions.from_angles(0.4, 0.0, 0.4, np.pi)
    assert float(abg(mirror, 5e-7)) == pytest.approx(200.0, rel=1e-12)
    side = bj.Directions.from_angles(0.0, 0.0, np.pi / 2 - 1e-9, np.pi)
    assert float(abg(side, 5e-7)) == pytest.approx(2.0 / 1.01, rel=1e-6)


def test_phong_is_normalised_at_normal_incidence():
    # albedo integral f cos ts dw at theta_i = 0 is rho exactly (the lobe is a function of theta_s there)
    for k in (5.0, 60.0):
        t = np.linspace(0, np.pi / 2, 20001)
        f = np.asarray(Phong(rho=0.7, k=k)(bj.Directions.from_angles(0.0, 0.0, t, np.pi), 5e-7))
        albedo = np.trapezoid(f * np.cos(t) * np.sin(t), t) * 2 * np.pi
        assert albedo == pytest.approx(0.7, rel=1e-6)


def test_gradients_are_finite_at_the_mirror_direction():
    mirror = bj.Directions.from_angles(np.array([0.3, 0.0]), 0.0, np.array([0.3, 0.0]), np.pi)

    @jax.jit
    def loss(p):
        m = bj.Model(terms={"a": ABg(p[0], p[1], p[2]), "p": Phong(p[3], p[4]), "s": _spike_halo()})
        return jnp.sum(jnp.log(m(mirror, 5e-7)))

    g = jax.jit(jax.grad(loss))(jnp.array([2.0, 0.01, 1.5, 0.5, 30.0]))
    assert np.all(np.isfinite(np.asarray(g)))


def test_bad_parameters_name_the_term():
    with pytest.raises(ValueError, match=r"abg: parameter 'B' = 0.0 is invalid; expected B > 0"):
        ABg(A=1.0, B=0.0, g=2.0)
    with pytest.raises(ValueError, match=r"multi_lobe: unknown shadowing 'smit' \(did you mean 'smith'\?\); known: none, smith, v_cavity"):
        MultiLobeSpecular({"a": Lobe(dist.GGX(0.1), 1.0)}, n=1.5, shadowing="smit")
    with pytest.raises(KeyError, match=r"unknown term 'abgg' \(did you mean 'abg'\?\); known: abg, binomial, diffraction, lambertian, multi_lobe"):
        registry.lookup("term", "abgg")


def _model_config(text: str) -> ModelConfig:
    import tomllib  # function-local: only this helper parses TOML

    return ModelConfig.model_validate(tomllib.loads(textwrap.dedent(text))["model"])


def test_config_round_trip_of_the_new_terms_and_options():
    cfg = _model_config(
        """
        [model.terms.spec]
        kind = "multi_lobe"
        lobes = { spike = "beckmann", halo = "ggx" }
        shadowing = "smith"
        normalisation = "torrance_sparrow"
        params = { spike = { m = 0.05, rho_s = 0.6 }, halo = { alpha = 0.3, rho_s = 0.2 }, n = 1.5, k = 0.1 }
        [model.terms.glint]
        kind = "specular"
        distribution = "cosine_lobe"
        shadowing = "v_cavity"
        params = { k = 30.0, rho_s = 0.1, n = 1.5 }
        [model.terms.stray]
        kind = "abg"
        params = { A = 2.0, B = 0.01, g = 1.7 }
        [model.terms.phong]
        kind = "phong"
        params = { rho = 0.8, k = 40.0 }
        """
    )
    model = build_model("job.toml", cfg)
    expect = bj.Model(terms={
        "spec": _spike_halo(),
        "glint": Specular(dist.CosineLobe(30.0), 0.1, 1.5, shadowing="v_cavity"),
        "stray": ABg(2.0, 0.01, 1.7),
        "phong": Phong(0.8, 40.0),
    })
    np.testing.assert_allclose(np.asarray(model(SWAP, 5e-7)), np.asarray(expect(SWAP, 5e-7)), rtol=1e-12)
    assert model.terms["spec"].shadowing == "smith" and model.terms["glint"].normalisation == "torrance_sparrow"  # the default
    text = describe_model(cfg)
    assert "spec: multi_lobe(" in text and "shadowing=smith" in text and "normalisation=torrance_sparrow" in text


@pytest.mark.parametrize(
    "body, where, message",
    [
        ('kind = "specular"\ndistribution = "ggx"\nshadowing = "smit"\nparams = { alpha = 0.1, rho_s = 1, n = 1.5 }',
         "model.terms.x.shadowing", "unknown shadowing 'smit' (did you mean 'smith'?); known: none, smith, smith_mixture, v_cavity"),
        ('kind = "lambertian"\nshadowing = "smith"\nparams = { rho_d = 0.1 }',
         "model.terms.x", "'shadowing', 'normalisation' and 'fresnel' apply only to microfacet terms (specular, offset_specular, multi_lobe)"),
        ('kind = "multi_lobe"\nparams = { n = 1.5 }', "model.terms.x", "a 'multi_lobe' term needs 'lobes'"),
        ('kind = "multi_lobe"\nlobes = { a = "ggx" }\nparams = { n = 1.5, a = { alpha = 0.1 } }',
         "model.terms.x.params", "missing parameter 'a.rho_s'"),
        ('kind = "abg"\nparams = { A = 1.0, B = 0.01 }', "model.terms.x.params", "missing parameter 'g' for a 'abg' term"),
    ],
    ids=["unknown-shadowing", "shadowing-on-lambertian", "lobes-missing", "lobe-param-missing", "abg-param-missing"],
)
def test_config_errors_name_the_key(body, where, message):
    with pytest.raises((ConfigError, ValueError)) as e:
        build_model("job.toml", _model_config("[model.terms.x]\n" + body))
    msg = str(e.value)
    # ConfigError names the dotted key; pydantic's own errors name it without the 'model.' table
    assert (where in msg or where.removeprefix("model.") in msg) and message in msg, msg


def test_diagnosis_config_writer_keeps_lobes_shadowing_and_normalisation():
    # the final model of a diagnosis (e.g. after its shadowing step) must rebuild from final_model.toml as it was
    from brdfjax.diagnose.engine import model_terms_config

    model = bj.Model(terms={"spec": _spike_halo(), "glint": Specular(dist.GGX(0.1), 0.3, 1.5, shadowing="smith"),
                            "d": bj.Lambertian(0.1)})
    terms, _ = model_terms_config(model)
    assert terms["spec"]["lobes"] == {"spike": "beckmann", "halo": "ggx"} and terms["glint"]["shadowing"] == "smith"
    assert terms["spec"]["normalisation"] == "torrance_sparrow" and "shadowing" not in terms["d"]
    again = build_model("final_model.toml", ModelConfig.model_validate({"terms": terms}))
    np.testing.assert_allclose(np.asarray(again(SWAP, 5e-7)), np.asarray(model(SWAP, 5e-7)), rtol=1e-12)
