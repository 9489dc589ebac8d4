"""Physics properties of the BRDF building blocks (Eq 54, 69-70, 112-115)."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import DISTRIBUTION_CASES, TERM_CASES

import brdfjax as bj
from brdfjax import distributions as D
from brdfjax.core.geometry import Directions, direction


def _normalisation(dist: D.AbstractDistribution) -> float:
    """Eq 54 integral, in slope space: cos sin dtheta = t dt / (1 + t^2)^2 with t = tan(theta_h).

    Log-spaced t from 1e-9 to 1e7 resolves a 2e-4 wide peak and the far tails.
    """
    logt = np.linspace(np.log(1e-9), np.log(1e7), 40001)
    t = np.exp(logt)
    phi = np.linspace(0.0, 2 * np.pi, 129)[:-1]  # periodic: rectangle rule is spectrally accurate
    T, P = np.meshgrid(t, phi, indexing="ij")
    val = eqx.filter_jit(lambda d, a, b: d(a, b))(dist, jnp.asarray((T * np.cos(P)) ** 2), jnp.asarray((T * np.sin(P)) ** 2))
    integrand = np.asarray(val) * T / (1 + T**2) ** 2 * T  # extra T: dt = t dlogt
    inner = integrand.mean(axis=1) * 2 * np.pi
    return float(np.trapezoid(inner, logt))




@pytest.mark.parametrize("dist", DISTRIBUTION_CASES, ids=lambda d: f"{d.name}")
def test_every_distribution_is_normalised_eq_54(dist):
    assert _normalisation(dist) == pytest.approx(1.0, abs=1e-3)


def test_distribution_registry_covers_every_class():
    from brdfjax.core.registry import DISTRIBUTIONS

    classes = {type(d) for d in DISTRIBUTION_CASES}
    assert classes == set(DISTRIBUTIONS.values())


def _slopes(n=500, scale=3e-4, seed=0):
    rng = np.random.default_rng(seed)
    tx = rng.normal(0, scale, n)
    ty = rng.normal(0, scale, n)
    return jnp.asarray(tx**2), jnp.asarray(ty**2)


@pytest.mark.parametrize(
    "aniso, iso",
    [
        (D.BeckmannAniso(3e-4, 3e-4), D.Beckmann(3e-4)),
        (D.GGXAniso(3e-4, 3e-4), D.GGX(3e-4)),
        (D.StudentTAniso(3e-4, 3e-4, 2.7), D.StudentT(3e-4, 2.7)),
        (D.AshikhminShirley(2e7, 2e7), D.CosineLobe(2e7)),
    ],
    ids=lambda d: d.name,
)
def test_anisotropic_forms_reduce_to_isotropic(aniso, iso):
    tx2, ty2 = _slopes()
    np.testing.assert_allclose(np.asarray(aniso(tx2, ty2)), np.asarray(iso(tx2, ty2)), rtol=1e-12)


@pytest.mark.parametrize(
    "special, ggx",
    [
        (D.StudentT(3e-4, 2.0), D.GGX(3e-4)),
        (D.HyperCauchy(3e-4, 2.0), D.GGX(3e-4)),
        (D.GTR(3e-4, 2.0), D.GGX(3e-4)),
        (D.Ribardiere(1 / (3e-4) ** 2, 2.0), D.GGX(3e-4)),
    ],
    ids=lambda d: d.name,
)
def test_family_members_equal_trowbridge_reitz_at_gamma_2(special, ggx):
    tx2, ty2 = _slopes()
    np.testing.assert_allclose(np.asarray(special(tx2, ty2)), np.asarray(ggx(tx2, ty2)), rtol=1e-9)


def test_student_t_tends_to_beckmann():
    tx2, ty2 = _slopes(scale=2e-4)
    b = np.asarray(D.Beckmann(2e-4)(tx2, ty2))
    s = np.asarray(D.StudentT(2e-4, 1e5)(tx2, ty2))
    keep = b > 1e-3 * b.max()
    np.testing.assert_allclose(s[keep], b[keep], rtol=1e-3)


def test_gtr_continuous_through_gamma_1():
    tx2, ty2 = _slopes(scale=0.2)
    a = np.asarray(D.GTR(0.3, 1.0)(tx2, ty2))
    b = np.asarray(D.GTR(0.3, 1.0 + 1e-5)(tx2, ty2))
    np.testing.assert_allclose(a, b, rtol=1e-4)


@pytest.mark.parametrize("n, k", [(3.6, 0.0), (1.4, 0.0), (1.2, 7.0), (0.2, 3.5)])
@pytest.mark.parametrize("theta_deg", [0.0, 20.0, 45.0, 60.0, 85.0])
def test_q_equals_fresnel_sum_in_specular_direction(n, k, theta_deg):
    th = np.deg2rad(theta_deg)
    dirs = Directions.from_angles(th, 0.0, th, np.pi)
    q = float(bj.q_factor(n, dirs, k))
    fs, fp = bj.fresnel(n, th, k)
    assert q == pytest.approx(float(fs + fp), rel=1e-12)


def test_fresnel_normal_incidence():
    fs, fp = bj.fresnel(3.6, 0.0)
    ref = ((3.6 - 1) / (3.6 + 1)) ** 2
    assert float(fs) == pytest.approx(ref, rel=1e-12) and float(fp) == pytest.approx(ref, rel=1e-12)


def _random_upper_directions(n, seed):
    rng = np.random.default_rng(seed)
    th = rng.uniform(0.0, np.deg2rad(80), n)
    ph = rng.uniform(0.0, 2 * np.pi, n)
    return direction(th, ph)




@pytest.mark.parametrize("term", TERM_CASES, ids=lambda t: type(t).__name__)
def test_helmholtz_reciprocity(term):
    w_i = _random_upper_directions(400, 1)
    w_s = _random_upper_directions(400, 2)
    f_fwd = np.asarray(term(Directions.from_vectors(w_i, w_s), 632.8e-9))
    f_rev = np.asarray(term(Directions.from_vectors(w_s, w_i), 632.8e-9))
    assert np.all(np.isfinite(f_fwd)) and f_fwd.max() > 0
    np.testing.assert_allclose(f_fwd, f_rev, rtol=1e-11, atol=1e-300)


def test_lambertian_value_and_hemisphere():
    w_i = direction(0.3, 0.0)
    f = bj.Lambertian(0.6)(Directions.from_vectors(w_i, direction(np.array([0.2, 2.0]), 1.0)), 5e-7)
    np.testing.assert_allclose(np.asarray(f), [0.6 / np.pi, 0.0])  # second direction is below the surface


def test_offset_normal_moves_the_peak_to_the_mirror_of_the_tilted_normal():
    dtheta, dphi0 = np.deg2rad(0.5), np.deg2rad(45)
    term = bj.OffsetNormal(bj.Specular(D.Beckmann(2e-4), rho_s=0.7, n=1.4), dtheta=dtheta, dphi0=dphi0)
    ti = np.deg2rad(20)
    w_i = np.array([-np.sin(ti), 0.0, np.cos(ti)])
    n2 = np.array([np.sin(dtheta) * np.cos(dphi0), np.sin(dtheta) * np.sin(dphi0), np.cos(dtheta)])
    mirror = 2 * np.dot(w_i, n2) * n2 - w_i
    f_peak = float(term(Directions.from_vectors(w_i, mirror), 632.8e-9))
    f_spec = float(term(Directions.from_vectors(w_i, np.array([np.sin(ti), 0, np.cos(ti)])), 632.8e-9))
    assert f_peak > 1e3 * max(f_spec, 1e-300)
    # "down and to the right" of the centre peak for phi_ref = 0 (seed §6.4): +x and +y.
    assert mirror[0] > np.sin(ti) and mirror[1] > 0


def test_diffraction_centre_value_and_period():
    bars = bj.Diffraction(rho=300.0, a=8e-4, b=1e-5, c=4e-5)
    ti = np.deg2rad(20)
    w_i = np.array([-np.sin(ti), 0.0, np.cos(ti)])
    w_spec = np.array([np.sin(ti), 0.0, np.cos(ti)])
    assert float(bars(Directions.from_vectors(w_i, w_spec), 632.8e-9)) == pytest.approx(300.0)
    # First maximum off the centre: 2 a h_y cos(theta_i) / lambda = 1.
    hy = 632.8e-9 / (2 * 8e-4 * np.cos(ti))
    h = np.array([0.0, hy, np.sqrt(1 - hy**2)])
    w_s = 2 * np.dot(w_i, h) * h - w_i
    d = Directions.from_vectors(w_i, w_s)
    sinc2 = np.sinc(2 * 1e-5 * hy * np.cos(ti) / 632.8e-9) ** 2
    assert float(bars(d, 632.8e-9)) == pytest.approx(300.0 * sinc2, rel=1e-9)


def test_rotating_phi_ref_rotates_the_pattern():
    """At normal incidence on a centred detector, phi_ref = 90 deg is the phi_ref = 0 frame turned by 90 deg."""
    det = bj.Detector.seed(theta_c=0.0)
    model = bj.solar_cell(dtheta=np.deg2rad(0.05))  # keep the offset peak inside a small window
    k = 120
    roi = (-k, k, -k, k)
    f0 = np.asarray(bj.render(model, bj.Conditions(0.0, 0.0), det, roi=roi, precision="float64"))
    f90 = np.asarray(bj.render(model, bj.Conditions(0.0, np.pi / 2), det, roi=roi, precision="float64"))
    assert f0.max() > 1e3
    # f90 at pixel (h, v) equals f0 at the pixel Rz(-90 deg) maps it to: (h, v) -> (v, -h).
    # Arrays are [v, h] with indices -k..k, so f90[v, h] = f0[-h, v]: a clockwise quarter turn.
    np.testing.assert_allclose(f90, np.rot90(f0, k=-1), rtol=1e-9, atol=1e-9 * f0.max())
    assert not np.allclose(f90, f0, rtol=1e-3)


def test_model_parameter_names_and_replacement():
    m = bj.solar_cell()
    p = m.params()
    for name in ["m1", "rho_s1", "n1", "m2", "rho_s2", "n2", "dtheta", "dphi0", "a", "b", "c", "rho_s3"]:
        assert name in p
    assert float(p["dphi0"]) == pytest.approx(np.deg2rad(45))
    m2 = m.with_params({"m1": 3e-4, "bars.a": 7.5e-4})
    assert float(m2.params()["m1"]) == pytest.approx(3e-4) and float(m2.params()["a"]) == pytest.approx(7.5e-4)
    assert m.parameter_units()["dtheta"] == "rad" and m.parameter_units()["a"] == "m"
    with pytest.raises(KeyError, match=r"unknown parameter 'mm1' \(did you mean 'm1'\?\); known: .*m1"):
        m.with_params({"mm1": 1.0})
    with pytest.raises(KeyError, match="unknown parameter"):
        bj.solar_cell(m3=1.0)


def test_models_are_sums_of_any_terms():
    """'Beckmann peak + offset GGX peak + diffraction + Lambertian' without new code."""
    from brdfjax.core.registry import term_from_params as build_term

    model = bj.Model(
        terms={
            "peak": build_term("specular", {"m": 2e-4, "rho_s": 0.02, "n": 3.6}, "beckmann"),
            "glint": build_term(
                "offset_specular", {"alpha": 3e-4, "rho_s": 0.5, "n": 1.4, "dtheta": 0.01, "dphi0": 0.5}, "ggx"
            ),
            "bars": build_term("diffraction", {"rho": 100.0, "a": 8e-4, "b": 1e-5, "c": 4e-5}),
            "floor": build_term("lambertian", {"rho_d": 0.05}),
        }
    )
    frame = bj.Conditions.from_degrees(30)
    det = bj.Detector.seed()
    parts = bj.render(model, frame, det, step=32, per_term=True, precision="float64")
    total = bj.render(model, frame, det, step=32, precision="float64")
    np.testing.assert_allclose(np.asarray(total), sum(np.asarray(v) for v in parts.values()), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(parts["floor"]), 0.05 / np.pi)


def test_bad_parameters_raise_clear_errors():
    with pytest.raises(ValueError, match="beckmann: parameter 'm' = -0.1 is invalid; expected m > 0"):
        D.Beckmann(-0.1)
    with pytest.raises(ValueError, match="'alpha_y'"):
        D.GGXAniso(0.1, 0.0)
    with pytest.raises(ValueError, match="gamma > 1"):
        D.StudentT(0.1, 1.0)
    with pytest.raises(ValueError, match="'b'.*metres"):
        bj.Diffraction(rho=1.0, a=1e-3, b=-1e-5, c=1e-5)
    with pytest.raises(ValueError, match="rho_s >= 0"):
        bj.Specular(D.Beckmann(0.1), rho_s=-1.0, n=1.5)
    from brdfjax.core.registry import lookup, term_from_params as build_term

    with pytest.raises(KeyError, match=r"unknown distribution 'ggxx' \(did you mean 'ggx'\?\); known: .*ggx"):
        lookup("distribution", "ggxx")
    with pytest.raises(KeyError, match="unknown term 'mirror'"):
        build_term("mirror", {})
    with pytest.raises(KeyError, match="missing parameter 'm'"):
        build_term("specular", {"rho_s": 1.0, "n": 1.5}, "beckmann")
