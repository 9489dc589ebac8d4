"""Fitting machinery on small problems: reparametrisation, specification errors, losses, solvers, covariance.

The fits here use a Lambertian table, for which the weighted least-squares
answer is closed form (the oracle): with ``r_j = (log(rho/pi) - log d_j) /
s``, ``rho = pi exp(mean log d)`` and ``sigma(rho) = rho s / sqrt(N)``.
"""

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import (
    LOSSES,
    SOLVERS,
    FitInputError,
    Param,
    TableData,
    covariance,
    fit,
    get_solver,
    irls_weights,
    robust_residuals,
)
from brdfjax.fit._params import derivative, forward, inverse

TRANSFORM_CASES = [
    ("identity", -math.inf, math.inf, [-3.0, 0.0, 0.25, 7.5]),
    ("log", 0.0, math.inf, [2e-4, 1.0, 3.6, 300.0]),
    ("log", 1.0, math.inf, [1.0001, 1.4, 6.0]),
    ("neglog", -math.inf, math.pi / 2, [-1.0, 0.3, 1.5]),
    ("logit", 0.0, math.pi / 2, [1e-6, 0.349, 1.047, math.pi / 2 - 1e-6]),
    ("logit", 1e-6, 4e-5, [2e-6, 1e-5, 3.9e-5]),
]


@pytest.mark.parametrize("kind, lo, hi, xs", TRANSFORM_CASES, ids=[c[0] for c in TRANSFORM_CASES])
def test_reparametrisation_round_trips_and_derivative(kind, lo, hi, xs):
    for x in xs:
        u = inverse(kind, x, lo, hi)
        back = float(forward(kind, jnp.asarray(u), lo, hi))
        assert back == pytest.approx(x, rel=1e-12, abs=1e-15)
        # derivative against jax.grad and central differences
        g = float(jax.grad(lambda t: forward(kind, t, lo, hi))(jnp.asarray(u)))
        assert float(derivative(kind, np.float64(u), lo, hi)) == pytest.approx(g, rel=1e-12)
        h = 1e-6
        fd = (float(forward(kind, jnp.asarray(u + h), lo, hi)) - float(forward(kind, jnp.asarray(u - h), lo, hi))) / (2 * h)
        assert g == pytest.approx(fd, rel=1e-6, abs=1e-15 * (1 + abs(x)) / h)


def test_bounded_transforms_stay_inside_for_any_u():
    u = jnp.linspace(-40.0, 40.0, 81)
    for kind, lo, hi, _ in TRANSFORM_CASES[1:]:
        x = np.asarray(forward(kind, u, lo, hi))
        assert np.all(x >= lo) and np.all(x <= hi)


# --- a Lambertian table with a closed-form answer -------------------------------------------


def _lambertian_table(n=400, rho=0.3, s=0.05, seed=0, sigma=True):
    rng = np.random.default_rng(seed)
    ti = rng.uniform(0.1, 1.2, n)
    ts = rng.uniform(0.0, 1.3, n)
    ps = rng.uniform(0.0, 2 * np.pi, n)
    d = rho / np.pi * np.exp(s * rng.standard_normal(n))
    return TableData(ti, np.zeros(n), ts, ps, d, np.full(n, s) if sigma else None, name="lamb")


LAMB = bj.Model(terms={"diffuse": bj.Lambertian(0.1)})


@pytest.mark.parametrize("solver", sorted(SOLVERS))
def test_lambertian_fit_matches_closed_form(solver):
    tab = _lambertian_table()
    res = fit(LAMB, tab, {"diffuse.rho_d": 0.1}, solver=solver)
    d = np.asarray(tab.brdf)
    rho_hat = np.pi * np.exp(np.mean(np.log(d)))
    assert res.converged, res.message
    assert res.value("diffuse.rho_d") == pytest.approx(rho_hat, rel=1e-6)
    assert res.sigma("diffuse.rho_d") == pytest.approx(rho_hat * 0.05 / np.sqrt(d.size), rel=1e-4)
    assert res.chi2 == pytest.approx(np.sum((np.log(rho_hat / np.pi) - np.log(d)) ** 2) / 0.05**2, rel=1e-8)
    assert res.dof == d.size - 1
    assert res.covariance_absolute


def test_float32_precision():
    tab = _lambertian_table()
    res = fit(LAMB, tab, {"diffuse.rho_d": 0.1}, precision="float32")
    assert res.precision == "float32" and res.converged, res.message
    rho_hat = np.pi * np.exp(np.mean(np.log(np.asarray(tab.brdf))))
    assert res.value("diffuse.rho_d") == pytest.approx(rho_hat, rel=1e-5)


def test_table_without_uncertainty_scales_covariance_by_the_estimated_noise():
    tab = _lambertian_table(sigma=False)
    res = fit(LAMB, tab, {"diffuse.rho_d": 0.1})
    d = np.asarray(tab.brdf)
    rho_hat = np.pi * np.exp(np.mean(np.log(d)))
    resid = np.log(rho_hat / np.pi) - np.log(d)
    s2 = np.sum(resid**2) / d.size  # the profile likelihood's estimate RSS / N
    assert not res.covariance_absolute and res.sigma_estimated
    assert res.noise["sigma_ln"] == pytest.approx(np.sqrt(s2), rel=1e-6)
    assert res.chi2 == pytest.approx(d.size, rel=1e-6)  # residuals in units of the estimate
    assert res.m2ll == pytest.approx(d.size * np.log(s2) + d.size, rel=1e-6)
    assert res.sigma("diffuse.rho_d") == pytest.approx(rho_hat * np.sqrt(s2 / d.size), rel=1e-4)
    grp = res.blocks[0]
    assert grp.log_rms == pytest.approx(np.sqrt(np.mean(resid**2)), rel=1e-8)


def test_result_json_follows_the_output_contract(tmp_path):
    tab = _lambertian_table()
    res = fit(LAMB, tab, {"diffuse.rho_d": Param(0.1, lower=0.0, upper=1.0)})
    out = json.loads(res.to_json(tmp_path / "result.json"))
    assert json.loads((tmp_path / "result.json").read_text()) == out
    for key in ("parameters", "chi2", "chi2_reduced", "dof", "converged", "message", "n_iterations", "wall_s"):
        assert key in out
    p = out["parameters"]["diffuse.rho_d"]
    assert set(p) >= {"value", "sigma", "unit", "free"} and p["free"] is True and p["unit"] == "1"
    assert out["converged"] is True and isinstance(out["n_iterations"], int)
    assert out["instrument_function"]["convolved"] is False
    assert out["versions"]["optimistix"] and out["versions"]["jax"]
    assert out["correlation"]["names"] == ["diffuse.rho_d"]


# --- specification errors -------------------------------------------------------------------


def test_unknown_parameter_name_lists_the_known_ones():
    with pytest.raises(FitInputError, match=r"unknown parameter 'rho_x'; known: .*diffuse\.rho_d.*phi_ref.*theta_i"):
        fit(LAMB, _lambertian_table(), {"rho_x": 0.1})


def test_lower_above_upper_is_an_error():
    with pytest.raises(FitInputError, match=r"'diffuse.rho_d': lower bound 1\.0 > upper bound 0\.5; swap them"):
        fit(LAMB, _lambertian_table(), {"diffuse.rho_d": Param(0.1, lower=1.0, upper=0.5)})


@pytest.mark.parametrize(
    "spec, message",
    [
        (Param(2.0, lower=0.0, upper=1.0), r"start value 2\.0 is outside its bounds \[0\.0, 1\.0\]"),
        (Param(-0.5), r"start value -0\.5 is outside its bounds \[0\.0, inf\]"),  # the unit's default bound
        (Param(0.0), r"lies on a bound .* must start strictly inside its bounds"),
        (Param(0.1, lower=0.5, upper=0.5), r"lower == upper == 0\.5 leaves nothing to fit"),
        (Param([0.1, 0.2]), r"2 values given for a parameter shared by all frames"),
        (Param(0.1, scale=-1.0), r"scale must be a positive number"),
        (Param(0.1, lower=float("nan")), r"expected a number \(inf allowed\), got nan"),
        (Param("start"), r"value 'start' is not a number or 'auto'"),
        (Param(float("inf"), lower=0.0), r"start value inf is not finite"),
        ("loose", r"unknown specification 'loose'"),
        ({"value": 0.1, "bound": 1}, r"unknown key\(s\) \['bound'\]"),
        (Param("auto"), r"'auto' but the automatic initialisation gives no value|need an initializer"),
    ],
)
def test_bad_parameter_specifications(spec, message):
    with pytest.raises(FitInputError, match=message):
        fit(LAMB, _lambertian_table(), {"diffuse.rho_d": spec})


def test_frame_parameters_need_frames():
    with pytest.raises(FitInputError, match=r"'phi_ref' belongs to detector frames"):
        fit(LAMB, _lambertian_table(), {"phi_ref": 0.0})


def test_unknown_solver_loss_and_options():
    with pytest.raises(FitInputError, match=r"unknown solver 'newton'; known: l-bfgs-b, lbfgsb, levenberg_marquardt, lm"):
        get_solver("newton")
    with pytest.raises(FitInputError, match=r"solver 'levenberg_marquardt': unknown option\(s\) \['tol'\]; known: rtol, atol, max_steps"):
        get_solver("lm", tol=1e-3)
    with pytest.raises(FitInputError, match=r"unknown loss 'l1'; known: linear, huber, cauchy"):
        fit(LAMB, _lambertian_table(), {"diffuse.rho_d": 0.1}, loss="l1")
    with pytest.raises(FitInputError, match=r"unknown first_stage 'x'"):
        fit(LAMB, _lambertian_table(), {"diffuse.rho_d": 0.1}, first_stage="x")


def test_non_convergence_is_reported_not_raised():
    tab = _lambertian_table()
    res = fit(LAMB, tab, {"diffuse.rho_d": 1e-6}, solver_options={"max_steps": 1}, first_stage=None)
    assert not res.converged
    assert res.status == "max_steps_reached"
    assert "max_steps=1 reached; increase max_steps" in res.message
    assert res.to_dict()["converged"] is False  # and it still has numbers
    assert np.isfinite(res.value("diffuse.rho_d"))


def test_undetermined_parameters_get_infinite_sigma_and_a_warning():
    # two Lambertian terms: only their sum is determined
    model = bj.Model(terms={"a": bj.Lambertian(0.1), "b": bj.Lambertian(0.1)})
    res = fit(model, _lambertian_table(), {"a.rho_d": 0.1, "b.rho_d": 0.2})
    assert res.converged
    assert np.isinf(res.sigma("a.rho_d")) and np.isinf(res.sigma("b.rho_d"))
    assert any("do not determine a.rho_d, b.rho_d" in w for w in res.warnings)
    assert res.to_dict()["parameters"]["a.rho_d"]["sigma"] is None  # JSON has no inf


# --- robust losses ------------------------------------------------------------------------


@pytest.mark.parametrize("loss", LOSSES)
def test_robust_residuals_square_to_twice_rho(loss):
    k = 1.5
    r = jnp.linspace(-20.0, 20.0, 401)
    rt = robust_residuals(loss, r, k)
    a = np.abs(np.asarray(r))
    if loss == "linear":
        rho = a**2 / 2
    elif loss == "huber":
        rho = np.where(a <= k, a**2 / 2, k * a - k**2 / 2)
    else:
        rho = k**2 / 2 * np.log1p((a / k) ** 2)
    np.testing.assert_allclose(np.asarray(rt) ** 2 / 2, rho, rtol=1e-12, atol=1e-15)
    assert np.all(np.sign(np.asarray(rt)) == np.sign(np.asarray(r)))
    g = jax.vmap(jax.grad(lambda x: robust_residuals(loss, x, k)))(jnp.array([0.0, 1e-9, 0.5, 5.0]))
    assert np.all(np.isfinite(np.asarray(g)))
    w = np.asarray(irls_weights(loss, r, k))
    assert np.all((w > 0) & (w <= 1))
    if loss != "linear":
        assert w[0] < 0.3 and w[200] == 1.0  # |r| = 20 down-weighted, r = 0 not


def test_robust_loss_downweights_outliers_on_a_table():
    tab = _lambertian_table(n=400, s=0.05, seed=5)
    d = np.array(tab.brdf)
    d[::20] *= 20.0  # 5% stray-light outliers, factor 20 (60 sigma in log)
    bad = TableData(tab.theta_i, tab.phi_i, tab.theta_s, tab.phi_s, d, tab.sigma_rel, name="outliers")
    truth = 0.3
    lin = fit(LAMB, bad, {"diffuse.rho_d": 0.1})
    for loss in ("huber", "cauchy"):
        rob = fit(LAMB, bad, {"diffuse.rho_d": 0.1}, loss=loss)
        assert rob.converged
        assert abs(rob.value("diffuse.rho_d") / truth - 1) < 0.25 * abs(lin.value("diffuse.rho_d") / truth - 1)
        w = rob.weights[0]
        assert np.all(w[::20] < 0.2) and np.median(w) > 0.9
        assert rob.n_downweighted >= 20
    assert abs(lin.value("diffuse.rho_d") / truth - 1) > 0.1  # the linear loss is pulled off


def test_covariance_oracle_linear_model():
    rng = np.random.default_rng(0)
    J = rng.standard_normal((50, 3))
    cov = covariance(J, np.array([1.0, 2.0, 0.5]), chi2_reduced=4.0, absolute=True)
    expect = np.linalg.inv(J.T @ J) * np.outer([1.0, 2.0, 0.5], [1.0, 2.0, 0.5])
    np.testing.assert_allclose(cov.matrix, expect, rtol=1e-10)
    np.testing.assert_allclose(np.diag(cov.correlation), 1.0)
    scaled = covariance(J, np.ones(3), chi2_reduced=4.0, absolute=False)
    np.testing.assert_allclose(scaled.matrix, 4.0 * np.linalg.inv(J.T @ J), rtol=1e-10)
    # a transform that overflowed at the solution (dx/dv = inf): that parameter's sigma is infinite, the others
    # keep theirs (no NaN spread across the matrix, no RuntimeWarning)
    import warnings as _w

    with _w.catch_warnings():
        _w.simplefilter("error")
        sat = covariance(J, np.array([1.0, np.inf, 0.5]), chi2_reduced=4.0, absolute=True)
    assert sat.saturated == (1,) and sat.sigma[1] == np.inf and np.isnan(sat.correlation[0, 1])
    np.testing.assert_allclose(sat.sigma[[0, 2]], np.sqrt(np.diag(expect))[[0, 2]], rtol=1e-10)
    assert sat.correlation[0, 0] == 1.0 and np.isnan(sat.correlation[1, 1])
    with _w.catch_warnings():
        _w.simplefilter("error")
        huge = covariance(J, np.array([1.0, 1e200, 0.5]), chi2_reduced=4.0, absolute=True)  # overflows to inf
    assert huge.saturated == (1,) and huge.sigma[1] == np.inf
    np.testing.assert_allclose(huge.sigma[[0, 2]], np.sqrt(np.diag(expect))[[0, 2]], rtol=1e-10)


def test_residual_jacobian_matches_finite_differences():
    """The solvers' residual function carries a custom JVP (one materialised Jacobian); check it."""
    from brdfjax.fit._problem import residuals, with_scale
    from brdfjax.fit.internal import prepare_problem as prepare

    model = bj.Model(terms={"s": bj.Specular(bj.GGX(0.2), rho_s=0.5, n=1.5), "d": bj.Lambertian(0.05)})
    rng = np.random.default_rng(1)
    n = 60
    ti, ts, ps = rng.uniform(0.1, 1.0, n), rng.uniform(0.0, 1.2, n), rng.uniform(0, 2 * np.pi, n)
    f = np.asarray(model(bj.Directions.from_angles(ti, np.zeros(n), ts, ps), 633e-9)) * np.exp(0.1 * rng.standard_normal(n))
    tab = TableData(ti, np.zeros(n), ts, ps, f, 0.1)
    prep = prepare(model, tab, {"s.alpha": 0.3, "s.rho_s": Param(0.4, lower=0.0, upper=2.0), "d.rho_d": 0.1}, solver=get_solver())
    problem = with_scale(prep.problem, prep.layout.u0(), np.array([0.5, 2.0, 1.0]))
    v = jnp.array([0.1, -0.2, 0.3])
    from brdfjax.fit._problem import half_sum_squares

    res = eqx.filter_jit(residuals)
    J = np.asarray(eqx.filter_jit(jax.jacfwd(residuals))(v, problem))
    h = 1e-6
    fd = np.stack([(np.asarray(res(v + h * e, problem)) - np.asarray(res(v - h * e, problem))) / (2 * h) for e in jnp.eye(3)], -1)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    # and the gradient of the objective (reverse mode through the rule) is J^T r
    g = np.asarray(eqx.filter_jit(jax.grad(half_sum_squares))(v, problem))
    np.testing.assert_allclose(g, J.T @ np.asarray(res(v, problem)), rtol=1e-10)
