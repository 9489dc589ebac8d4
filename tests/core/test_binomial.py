"""The binomial empirical term (Greynolds; lumos-sat's BINOMIAL family): lumos-sat's values to 1e-12,
reciprocity, gradients, parameter names, the registry/config round trip and a fit."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import model_config

import brdfjax as bj
from brdfjax.config import ConfigError
from brdfjax.config.model import ModelConfig, build_model, describe_model
from brdfjax.core import registry
from brdfjax.diagnose.engine import model_terms_config
from brdfjax.fit import Param, TableData, fit

jax.config.update("jax_enable_x64", True)

RNG = np.random.default_rng(11)
TI, TS = RNG.uniform(0, 1.45, 40), RNG.uniform(0, 1.45, 40)
PI, PS = RNG.uniform(0, 2 * np.pi, 40), RNG.uniform(0, 2 * np.pi, 40)
SWAP = bj.Directions.from_angles(np.r_[TI, TS], np.r_[PI, PS], np.r_[TS, TI], np.r_[PS, PI])
B = np.array([[0.5, -3.0, 1.2], [0.3, 0.2, -0.1], [0.1, 0.05, 0.02]])
C = np.array([[-1.5, 0.4], [0.2, -0.1], [0.05, 0.01]])
D_SPEC, L1 = 12.0, -1


def test_matches_lumos_sat_binomial_to_1e_12():
    lib = pytest.importorskip("lumos.brdf.library")
    term = bj.Binomial(B, C, D_SPEC, L1)
    assert term.shape == (3, 3, 2)
    f = np.asarray(term(SWAP, 5e-7))
    wi, ws = np.asarray(SWAP.w_i).T, np.asarray(SWAP.w_s).T  # lumos: the incident vector points to the source
    want = lib.BINOMIAL(B, C, D_SPEC, L1)(tuple(wi), (0.0, 0.0, 1.0), tuple(ws))
    assert np.all(want > 0)
    np.testing.assert_allclose(f, want, rtol=1e-12)
    # a one-row model (n = 1: no V dependence), l1 = 0, and below the horizon: 0 in both
    f1 = np.asarray(bj.Binomial(B[:1], C[:1], 3.0)(SWAP, 5e-7))
    np.testing.assert_allclose(f1, lib.BINOMIAL(B[:1], C[:1], 3.0, 0)(tuple(wi), (0, 0, 1), tuple(ws)), rtol=1e-12)
    below = bj.Directions.from_vectors(np.array([0.3, 0.0, -0.95]), np.array([-0.3, 0.0, 0.95]))
    assert float(term(below, 5e-7)) == 0.0


def test_reciprocal_and_parameters_named_after_lumos_matrices():
    f = np.asarray(bj.Binomial(B, C, D_SPEC, L1)(SWAP, 5e-7))
    np.testing.assert_allclose(f[:40], f[40:], rtol=1e-12)
    model = bj.Model(terms={"bn": bj.Binomial(B, C, D_SPEC, L1)})
    names = model.parameter_units()
    assert set(names) == {f"bn.b{k}_{i}" for k in range(3) for i in range(3)} | {
        f"bn.c{k}_{i}" for k in range(3) for i in range(2)} | {"bn.d"}
    assert float(model.params()["bn.b1_2"]) == B[1, 2] and float(model.params()["bn.c2_1"]) == C[2, 1]
    moved = model.with_params({"bn.b0_0": 0.7})
    # b0_0 is log10 of the mirror-direction BRDF at normal incidence (D = V = 0)
    normal = bj.Directions.from_angles(0.0, 0.0, 0.0, math.pi)
    assert float(moved(normal, 5e-7)) == pytest.approx(10**0.7, rel=1e-12)


def test_gradients_finite_at_the_mirror_direction_and_equal_to_finite_differences():
    dirs = bj.Directions.from_angles(np.array([0.3, 0.0, 0.8]), 0.0, np.array([0.3, 0.0, 0.5]), np.pi)
    base = bj.Model(terms={"bn": bj.Binomial(B, C, D_SPEC, L1)})
    names = ("bn.b0_1", "bn.c0_0", "bn.b1_0", "bn.d")

    def loss(x):
        return jnp.sum(jnp.log(base.with_params(dict(zip(names, x)))(dirs, 5e-7)))

    x0 = jnp.array([B[0, 1], C[0, 0], B[1, 0], D_SPEC])
    g = np.asarray(jax.grad(loss)(x0))
    assert np.all(np.isfinite(g))
    for i in range(4):
        e = np.zeros(4)
        e[i] = 1e-6
        fd = (float(loss(x0 + e)) - float(loss(x0 - e))) / 2e-6
        assert g[i] == pytest.approx(fd, rel=1e-5, abs=1e-8)


def test_config_round_trip_and_the_diagnosis_config_writer():
    cfg = model_config("""
        [model.terms.bn]
        kind = "binomial"
        l1 = -1
        params = { d = 12.0, b0_0 = 0.5, b0_1 = -3.0, b0_2 = 1.2, c0_0 = -1.5, c0_1 = 0.4 }
        [model.terms.d]
        kind = "lambertian"
        params = { rho_d = 0.1 }
    """)
    model = build_model("job.toml", cfg)
    want = bj.Binomial(B[:1], C[:1], D_SPEC, L1)(SWAP, 5e-7) + 0.1 / np.pi * (np.asarray(SWAP.w_s)[..., 2] > 0)
    np.testing.assert_allclose(np.asarray(model(SWAP, 5e-7)), np.asarray(want), rtol=1e-12)
    assert "bn: binomial(" in describe_model(cfg) and "l1=-1" in describe_model(cfg)
    assert registry.TERMS["binomial"] is bj.Binomial
    terms, _ = model_terms_config(model)
    assert terms["bn"]["kind"] == "binomial" and terms["bn"]["l1"] == -1 and terms["bn"]["params"]["c0_1"] == 0.4
    again = build_model("again.toml", ModelConfig.model_validate({"terms": terms}))
    np.testing.assert_allclose(np.asarray(again(SWAP, 5e-7)), np.asarray(model(SWAP, 5e-7)), rtol=1e-12)


@pytest.mark.parametrize("body, where, message", [
    ('kind = "binomial"\nparams = { d = 2.0, b0_0 = 0.1, b1_1 = 0.2 }', "model.terms.x.params",
     "binomial: missing coefficient(s) b0_1, b1_0 (a full 2 x 2 'b' matrix)"),
    ('kind = "binomial"\nparams = { b0_0 = 0.1 }', "model.terms.x.params", "missing parameter 'd'"),
    ('kind = "binomial"\nparams = { d = 0.0, b0_0 = 0.1 }', "model.terms.x.params.d", "parameter 'd' = 0.0 is invalid; expected d > 0"),
    ('kind = "binomial"\nparams = { d = 1.0, b0_0 = 0.1, bx = 1 }', "model.terms.x.params.bx", "unknown"),
    ('kind = "abg"\nl1 = 2\nparams = { A = 1.0, B = 0.01, g = 2 }', "terms.x", "'l1' applies only to a 'binomial' term"),
], ids=["missing-coefficient", "missing-d", "bad-d", "unknown-key", "l1-on-abg"])
def test_config_errors_name_the_key(body, where, message):
    with pytest.raises((ConfigError, ValueError)) as e:
        build_model("job.toml", model_config("[model.terms.x]\n" + body))
    msg = str(e.value)
    assert where.removeprefix("model.") in msg and message in msg, msg


def test_fit_recovers_the_coefficients_of_a_table():
    truth = bj.Model(terms={"bn": bj.Binomial(np.array([[0.8, -4.0]]), np.array([[-1.0]]), 30.0)})
    ts = np.radians(np.arange(-80.0, 81.0, 4.0))
    rows = [(ti, t) for ti in (20.0, 50.0) for t in ts]
    ti = np.radians([r[0] for r in rows])
    tsa = np.array([r[1] for r in rows])
    ps = np.where(tsa >= 0, math.pi, 0.0)
    dirs = bj.Directions.from_angles(ti, 0 * ti, np.abs(tsa), ps)
    f = np.asarray(truth(dirs, 632.8e-9)) * np.exp(0.02 * np.random.default_rng(3).standard_normal(ti.size))
    table = TableData(ti, 0 * ti, np.abs(tsa), ps, f, name="binomial")
    start = truth.with_params({"bn.b0_0": 0.3, "bn.b0_1": -3.0, "bn.c0_0": -0.5})
    res = fit(start, table, {"bn.b0_0": "free", "bn.b0_1": "free", "bn.c0_0": "free", "bn.d": Param(30.0, free=False)},
              first_stage=None)
    assert res.converged, res.message
    for name, want in (("bn.b0_0", 0.8), ("bn.b0_1", -4.0), ("bn.c0_0", -1.0)):
        assert res.value(name) == pytest.approx(want, abs=4 * res.sigma(name) + 1e-3), name
