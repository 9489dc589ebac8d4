"""Checks of the NumPy oracle (brdfjax.reference) against the seed's printed numbers.

The reference numbers are the seed dissertation's (Tables 3, 4, 7, 8, 9; §4.4-4.5;
§6.4 / Figure 33), as collected at the end of shared/design/physics.md.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from brdfjax import reference as ref

DEG = np.pi / 180.0
NINE_PIXELS = [
    (-1647, -1235), (0, -1235), (1648, -1235),
    (-1647, 0), (0, 0), (1648, 0),
    (-1647, 1236), (0, 1236), (1648, 1236),
]  # fmt: skip


def _tol(printed: str) -> float:
    """Half a unit in the last printed digit."""
    decimals = len(printed.split(".")[1]) if "." in printed else 0
    return 0.5 * 10.0**-decimals


# ---------------------------------------------------------------------------
# Pixel indices
# ---------------------------------------------------------------------------


def test_pixel_indices_convention():
    nh, nv = ref.pixel_indices()
    assert nh.shape == (2472, 3296) and nv.shape == (2472, 3296)
    assert (nh[0, 0], nv[0, 0]) == (-1647, -1235)
    assert (nh[-1, -1], nv[-1, -1]) == (1648, 1236)
    assert (nh[1235, 1647], nv[1235, 1647]) == (0, 0)
    assert np.all(nh[:, 0] == -1647) and np.all(nv[0, :] == -1235)
    nh4, nv4 = ref.pixel_indices(step=4)
    assert nh4.shape == (618, 824)
    assert np.array_equal(nh4, nh[::4, ::4]) and np.array_equal(nv4, nv[::4, ::4])


# ---------------------------------------------------------------------------
# Table 3: solid angles
# ---------------------------------------------------------------------------

TABLE3 = {
    (-1647, -1235): "2.859", (0, -1235): "2.862", (1648, -1235): "2.859",
    (-1647, 0): "2.861", (0, 0): "2.864", (1648, 0): "2.861",
    (-1647, 1236): "2.859", (0, 1236): "2.862", (1648, 1236): "2.859",
}  # fmt: skip


@pytest.mark.parametrize("pix", NINE_PIXELS)
def test_table3_solid_angle(pix):
    printed = TABLE3[pix]
    omega = ref.solid_angle(*pix) * 1e10
    assert abs(omega - float(printed)) <= _tol(printed)


def test_solid_angle_eq109_equals_eq86_when_aligned():
    nh, nv = ref.pixel_indices(step=7)
    d, R = 5.5e-6, 0.325
    eq86 = d * d * R / ((nh * d) ** 2 + (nv * d) ** 2 + R**2) ** 1.5
    np.testing.assert_allclose(ref.solid_angle(nh, nv), eq86, rtol=1e-13)


# ---------------------------------------------------------------------------
# Tables 4, 7, 8, 9: scatter angles at nine pixels
# ---------------------------------------------------------------------------

TABLES = {
    0: ["1.995", "36.86", "1.197", "90", "1.996", "143.2",
        "1.597", "0", "0", "180", "1.598", "180",
        "1.996", "323.1", "1.198", "270", "1.997", "216.9"],
    20: ["18.44", "176.2", "20.03", "176.5", "21.63", "176.8",
         "18.40", "180", "20", "180", "21.60", "180",
         "18.44", "183.8", "20.03", "183.5", "21.63", "183.3"],
    40: ["38.42", "178.1", "40.01", "178.1", "41.6", "178.2",
         "38.40", "180", "40", "180", "41.60", "180",
         "38.42", "181.9", "40.02", "181.9", "41.61", "181.8"],
    60: ["58.41", "178.6", "60.01", "178.6", "61.60", "178.6",
         "58.40", "180", "60", "180", "61.60", "180",
         "58.41", "181.4", "60.01", "181.4", "61.60", "181.4"],
}  # fmt: skip

# Cells where the printed value cannot be reproduced to half a unit of its last
# digit.  Table 8, pixel (0, 1236): the formulas give theta_s = 40.01493 deg
# (and 40.01491 at the mirror pixel (0, -1235), printed 40.01); the seed prints
# 40.02, off by 0.0051 deg, just over half a unit.  Checked to one unit instead.
KNOWN_OFF = {(40, (0, 1236), "theta"): 0.01}

TABLE_CASES = [
    (tc, pix, which)
    for tc in TABLES
    for pix in NINE_PIXELS
    for which in ("theta", "phi")
]


@pytest.mark.parametrize("tc,pix,which", TABLE_CASES)
def test_scatter_angle_tables(tc, pix, which):
    k = NINE_PIXELS.index(pix)
    printed = TABLES[tc][2 * k + (which == "phi")]
    theta, phi = ref.pixel_angles(pix[0], pix[1], tc * DEG)
    value = float(np.degrees(theta if which == "theta" else phi))
    tol = KNOWN_OFF.get((tc, pix, which), _tol(printed))
    assert abs(value - float(printed)) <= tol, (value, printed)
    if "." not in printed:  # symmetry values (0, 90, 180, ...) hold exactly
        assert abs(value - float(printed)) < 1e-9


def test_known_table8_discrepancy_is_as_documented():
    theta, _ = ref.pixel_angles(0, 1236, 40 * DEG)
    assert abs(np.degrees(theta) - 40.01493) < 1e-5
    assert 0.005 < 40.02 - np.degrees(theta) < 0.0052


def test_phi_range_and_eq78():
    nh, nv = ref.pixel_indices(step=13)
    for tc in (0.0, 0.3, 1.2):
        theta, phi = ref.pixel_angles(nh, nv, tc)
        assert np.all((phi >= 0) & (phi < 2 * np.pi))
        d, R = 5.5e-6, 0.325
        eq78 = np.stack(
            [nh * d * np.cos(tc) + R * np.sin(tc), nv * d + 0 * nh, R * np.cos(tc) - nh * d * np.sin(tc)],
            axis=-1,
        )
        np.testing.assert_allclose(ref.scatter_vectors(nh, nv, tc), eq78, rtol=1e-14, atol=1e-18)
        # Eq 80a with acos agrees with the atan2 form (away from theta = 0)
        acos = np.arccos(eq78[..., 2] / np.linalg.norm(eq78, axis=-1))
        np.testing.assert_allclose(theta, acos, atol=1e-7)


# ---------------------------------------------------------------------------
# §4.4-4.5 misalignment numbers (Eq 105, 109)
# ---------------------------------------------------------------------------


def _edge_and_grid_pixels():
    h = np.arange(-1647, 1649)
    v = np.arange(-1235, 1237)
    g_h, g_v = ref.pixel_indices(step=32)
    nh = np.concatenate([h, h, np.full(v.size, -1647), np.full(v.size, 1648), g_h.ravel()])
    nv = np.concatenate([np.full(h.size, -1235), np.full(h.size, 1236), v, v, g_v.ravel()])
    return nh, nv


ROT = dict(roll=0.11 * DEG, yaw=0.062 * DEG, pitch=0.025 * DEG)


def test_misaligned_solid_angle_seed_4_5():
    # seed §4.5: largest relative change 0.012% with the §4.4 angles and m = (-1, -1)
    nh, nv = _edge_and_grid_pixels()
    o0 = ref.solid_angle(nh, nv)
    o1 = ref.solid_angle(nh, nv, m_h=-1, m_v=-1, **ROT)
    assert round(100 * np.max(np.abs(o1 - o0) / o0), 3) == 0.012


@pytest.mark.parametrize(
    "tc,m_h,m_v,theta_pct,phi_pct",
    [(20, 3, 5, 0.0034, 0.012), (40, -1, -1, 0.0049, 0.0036), (60, 72, -3, 0.23, 0.0045)],
)
def test_misaligned_scatter_angles_seed_4_4(tc, m_h, m_v, theta_pct, phi_pct):
    # seed §4.4: max relative misalignment uncertainties, scaled as in Eq 99-104
    # (Delta theta * tan(theta) and Delta phi / phi), in percent.
    nh, nv = _edge_and_grid_pixels()
    t0, p0 = ref.pixel_angles(nh, nv, tc * DEG)
    t1, p1 = ref.pixel_angles(nh, nv, tc * DEG, m_h=m_h, m_v=m_v, **ROT)
    rel_t = 100 * np.max(np.abs(t1 - t0) * np.tan(t0))
    rel_p = 100 * np.max(np.abs(p1 - p0) / p0)
    assert abs(rel_t - theta_pct) <= 0.5 * 10 ** np.floor(np.log10(theta_pct) - 1)
    assert abs(rel_p - phi_pct) <= 0.5 * 10 ** np.floor(np.log10(phi_pct) - 1)


# ---------------------------------------------------------------------------
# Inverse map (Eq 82-84)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("tc_deg", [0.0, 1e-7, 1e-3, 20.0, 40.0, 60.0, 89.9, 90.0 - 1e-7, 90.0])
def test_inverse_map_round_trip(tc_deg):
    nh, nv = _edge_and_grid_pixels()
    tc = tc_deg * DEG
    ts, ps = ref.pixel_angles(nh, nv, tc)
    h, v = ref.inverse_map(ts, ps, tc)
    assert np.max(np.abs(h - nh)) < 1e-6
    assert np.max(np.abs(v - nv)) < 1e-6


def _eq82(ts, ps, tc, R=0.325, d=5.5e-6):
    cot = 1.0 / np.tan(tc)
    c = np.cos(ps - np.pi)
    nh = (R / d) * (cot * np.sin(ts) * c - np.cos(ts)) / (cot * np.cos(ts) + np.sin(ts) * c)
    nv = (R / d) * np.sin(ts) * np.sin(ps - np.pi) / (np.cos(tc) * np.cos(ts) + np.sin(tc) * np.sin(ts) * c)
    return nh, nv


def test_inverse_map_matches_eq82_and_limits():
    R, d = 0.325, 5.5e-6
    nh, nv = _edge_and_grid_pixels()
    for tc in (20 * DEG, 45 * DEG, 70 * DEG):
        ts, ps = ref.pixel_angles(nh, nv, tc)
        np.testing.assert_allclose(ref.inverse_map(ts, ps, tc), _eq82(ts, ps, tc), rtol=1e-9, atol=1e-8)
    # Eq 83 at theta_c = 0, and Eq 82 tends to it
    ts, ps = ref.pixel_angles(nh, nv, 0.0)
    eq83 = ((R / d) * np.tan(ts) * np.cos(ps - np.pi), (R / d) * np.tan(ts) * np.sin(ps - np.pi))
    np.testing.assert_allclose(ref.inverse_map(ts, ps, 0.0), eq83, rtol=1e-12, atol=1e-9)
    # (the index of a fixed direction moves by ~ (R/d) dtheta_c = 6e-5 pixel per 1e-9 rad)
    np.testing.assert_allclose(_eq82(ts, ps, 1e-9), eq83, rtol=0, atol=2e-4)
    # Eq 84 at theta_c = 90 deg, and Eq 82 tends to it
    tc = np.pi / 2
    ts, ps = ref.pixel_angles(nh, nv, tc)
    eq84 = (-(R / d) / np.tan(ts) / np.cos(ps - np.pi), (R / d) * np.tan(ps - np.pi))
    np.testing.assert_allclose(ref.inverse_map(ts, ps, tc), eq84, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(_eq82(ts, ps, tc - 1e-9), eq84, rtol=0, atol=2e-4)


# ---------------------------------------------------------------------------
# Distribution normalisation (Eq 54)
# ---------------------------------------------------------------------------

# Eq 54 with u = tan^2(th): cos(th) sin(th) dth = cos^4(th) du / 2 = du / (2 (1+u)^2),
# then v = ln u so that a uniform grid resolves widths from 1e-4 to 1 alike.
_V = np.linspace(-100.0, 60.0, 16001)
_U = np.exp(_V)
_TH = np.arctan(np.sqrt(_U))
_W = _U / (2.0 * (1.0 + _U) ** 2)
_PHI = np.linspace(0.0, 2 * np.pi, 129)[:-1]


def _norm_iso(D):
    return 2 * np.pi * np.trapezoid(D(_TH) * _W, _V)


def _norm_aniso(D):
    vals = np.trapezoid(D(_TH[None, :], _PHI[:, None]) * _W, _V, axis=1)
    return 2 * np.pi * vals.mean()  # periodic trapezoid in phi


ISO = {
    "beckmann": (lambda t: ref.beckmann(t, 2e-4), lambda t: ref.beckmann(t, 0.3)),
    "ggx": (lambda t: ref.ggx(t, 2e-4), lambda t: ref.ggx(t, 0.3)),
    "gtr_g1": (lambda t: ref.gtr(t, 2e-4, 1), lambda t: ref.gtr(t, 0.3, 1)),
    "gtr_g1.5": (lambda t: ref.gtr(t, 2e-4, 1.5), lambda t: ref.gtr(t, 0.3, 1.5)),
    "gtr_g3": (lambda t: ref.gtr(t, 2e-4, 3), lambda t: ref.gtr(t, 0.3, 3)),
    "hyper_cauchy": (lambda t: ref.hyper_cauchy(t, 2e-4, 1.5), lambda t: ref.hyper_cauchy(t, 0.3, 2.5)),
    "student_t": (lambda t: ref.student_t(t, 2e-4, 1.5), lambda t: ref.student_t(t, 0.3, 4.0)),
    "cosine_lobe": (lambda t: ref.cosine_lobe(t, 5e7), lambda t: ref.cosine_lobe(t, 22.0)),
    "beard_maxwell": (lambda t: ref.beard_maxwell(t, 2e-4), lambda t: ref.beard_maxwell(t, 0.3)),
    "beard_maxwell_s>=1": (lambda t: ref.beard_maxwell(t, 1.0), lambda t: ref.beard_maxwell(t, 3.0)),
    "ribardiere": (lambda t: ref.ribardiere(t, 1 / 2e-4**2, 2.5), lambda t: ref.ribardiere(t, 11.0, 1.7)),
}
ANISO = {
    "beckmann_aniso": (
        lambda t, p: ref.beckmann_aniso(t, p, 2e-4, 5e-4),
        lambda t, p: ref.beckmann_aniso(t, p, 0.3, 0.1),
    ),
    "ggx_aniso": (lambda t, p: ref.ggx_aniso(t, p, 2e-4, 5e-4), lambda t, p: ref.ggx_aniso(t, p, 0.3, 0.1)),
    "student_t_aniso": (
        lambda t, p: ref.student_t_aniso(t, p, 2e-4, 5e-4, 2.5),
        lambda t, p: ref.student_t_aniso(t, p, 0.3, 0.1, 1.5),
    ),
    "ashikhmin_shirley": (
        lambda t, p: ref.ashikhmin_shirley(t, p, 5e7, 1e7),
        lambda t, p: ref.ashikhmin_shirley(t, p, 22.0, 100.0),
    ),
}


@pytest.mark.parametrize("name", sorted(ISO))
@pytest.mark.parametrize("width", ["narrow", "wide"])
def test_isotropic_normalisation(name, width):
    D = ISO[name][width == "wide"]
    assert abs(_norm_iso(D) - 1.0) < 1e-3


@pytest.mark.parametrize("name", sorted(ANISO))
@pytest.mark.parametrize("width", ["narrow", "wide"])
def test_anisotropic_normalisation(name, width):
    D = ANISO[name][width == "wide"]
    assert abs(_norm_aniso(D) - 1.0) < 1e-3


@pytest.mark.parametrize("name", sorted(ISO))
def test_wide_normalisation_direct_theta(name):
    # no substitution: scipy quad straight over Eq 54 for the wide case
    D = ISO[name][1]
    val = 2 * np.pi * quad(lambda t: D(t) * np.cos(t) * np.sin(t), 0, np.pi / 2, limit=400)[0]
    assert abs(val - 1.0) < 1e-3


@pytest.mark.parametrize("s", [1e-6, 2e-4, 0.3, 0.9995, 1.0, 1.0003, 2.0, 50.0])
def test_beard_maxwell_constant_vs_quadrature(s):
    pts = [np.arctan(s)] if s < 1 else None
    i = quad(lambda t: np.sin(t) / (s * s + np.tan(t) ** 2), 0, np.pi / 2, limit=500, points=pts)[0]
    assert abs(ref.beard_maxwell_norm(s) * 2 * np.pi * i - 1.0) < 1e-8


def test_distribution_special_cases_agree():
    th = np.linspace(0, 1.4, 50)
    ph = np.linspace(0, 6.2, 50)
    np.testing.assert_allclose(ref.gtr(th, 0.3, 2), ref.ggx(th, 0.3), rtol=1e-12)
    np.testing.assert_allclose(ref.student_t(th, 0.3, 2), ref.ggx(th, 0.3), rtol=1e-12)
    np.testing.assert_allclose(ref.ggx_aniso(th, ph, 0.3, 0.3), ref.ggx(th, 0.3), rtol=1e-12)
    np.testing.assert_allclose(ref.beckmann_aniso(th, ph, 0.3, 0.3), ref.beckmann(th, 0.3), rtol=1e-12)
    np.testing.assert_allclose(ref.student_t_aniso(th, ph, 0.3, 0.3, 3.0), ref.student_t(th, 0.3, 3.0), rtol=1e-12)
    np.testing.assert_allclose(ref.ashikhmin_shirley(th, ph, 20.0, 20.0), ref.cosine_lobe(th, 20.0), rtol=1e-12)
    np.testing.assert_allclose(ref.ribardiere(th, 1 / 0.09, 3.0), ref.hyper_cauchy(th, 0.3, 3.0), rtol=1e-12)
    np.testing.assert_allclose(ref.ribardiere(th, 1 / (0.09 * 2.0), 3.0), ref.student_t(th, 0.3, 3.0), rtol=1e-12)
    # Student's t -> Beckmann as gamma -> infinity (plain form: (gamma-1)^gamma
    # overflows beyond gamma ~ 140, so gamma = 100 and an O(1/gamma) tolerance)
    th = np.linspace(0, 0.3, 20)
    np.testing.assert_allclose(ref.student_t(th, 0.3, 100.0), ref.beckmann(th, 0.3), rtol=2e-2)


# ---------------------------------------------------------------------------
# Fresnel and Q
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1.4, 3.6, 1.5 + 0.01j, 0.27 + 3.4j])
def test_q_equals_fs_plus_fp_in_specular_direction(n):
    ti = np.linspace(0.0, 89.0, 30) * DEG
    fs, fp = ref.fresnel(n, ti)
    q = ref.q_factor(n, ti, 0.0, ti, np.pi)
    np.testing.assert_allclose(q, fs + fp, rtol=1e-12)
    # general incidence azimuth: only the azimuth difference matters
    q2 = ref.q_factor(n, ti, 1.0, ti, 1.0 + np.pi)
    np.testing.assert_allclose(q2, fs + fp, rtol=1e-12)


def test_fresnel_normal_incidence():
    fs, fp = ref.fresnel(1.5, 0.0)
    assert abs(fs - 0.04) < 1e-15 and abs(fp - 0.04) < 1e-15


def test_half_vector_and_specular():
    ti, ts = 30 * DEG, 30 * DEG
    th, ph = ref.half_vector_angles(ti, 0.0, ts, np.pi)
    assert abs(th) < 1e-15
    th, ph = ref.half_vector_angles(0.0, 0.0, 0.2, 0.5)
    assert abs(th - 0.1) < 1e-14 and abs(ph - 0.5) < 1e-14
    w = ref.direction(0.3, 0.0)
    np.testing.assert_allclose(w, [-np.sin(0.3), 0.0, np.cos(0.3)], atol=1e-16)
    D = lambda t, p: ref.beckmann(t, 0.1)  # noqa: E731
    f = ref.specular(ti, 0.0, ts, np.pi, D, 0.5, 1.5) + ref.lambertian(0.2)
    fs, fp = ref.fresnel(1.5, ti)
    expect = 0.5 * (1 / (np.pi * 0.01)) * (fs + fp) / (2 * (2 * np.cos(ti)) ** 2) + 0.2 / np.pi
    assert abs(f - expect) < 1e-12 * expect


# ---------------------------------------------------------------------------
# Solar-cell model (Figure 33)
# ---------------------------------------------------------------------------


def _window(ch, cv, half):
    h = np.arange(ch - half, ch + half + 1)
    v = np.arange(cv - half, cv + half + 1)
    return np.meshgrid(h, v)


def _offset_peak_guess(ti, dtheta=0.5 * DEG, dphi0=45 * DEG, phi_ref=0.0):
    n2 = np.array(
        [np.sin(dtheta) * np.cos(dphi0 + phi_ref), np.sin(dtheta) * np.sin(dphi0 + phi_ref), np.cos(dtheta)]
    )
    wi = ref.direction(ti, 0.0)
    ws = 2 * (wi @ n2) * n2 - wi
    ts, ps = ref.zenith_azimuth(ws)
    h, v = ref.inverse_map(ts, ps, ti)
    return int(round(float(h))), int(round(float(v)))


# Figure 33 maxima printed in the seed (§6.4), 3 significant figures.  The 60 deg
# centre peak cannot be reproduced: with theta_c = theta_i and perfect
# alignment, pixel (0, 0) is exactly specular and the model gives
# 0.015 (F_s + F_p)(60 deg, n = 3.6) / (2 pi m1^2) + 300 = 3.9188e4, which rounds
# to 3.92e4, not the printed 3.91e4 (0.22 % above the printed value, 0.12 %
# beyond its rounding interval).  It is checked to 0.5 % and pinned to 3.919e4.
CENTER_KNOWN_OFF = {60: (3.9188e4, 5e-3)}


@pytest.mark.parametrize("ti_deg,center,offset", [(20, 1.11e4, 4.44e4), (60, 3.91e4, 4.19e5)])
def test_figure33_peaks_local(ti_deg, center, offset):
    ti = ti_deg * DEG
    nh, nv = _window(0, 0, 30)
    ts, ps = ref.pixel_angles(nh, nv, ti)
    f = ref.solar_cell(ti, ts, ps)
    assert np.unravel_index(np.argmax(f), f.shape) == (30, 30)  # peak at pixel (0, 0)
    if ti_deg in CENTER_KNOWN_OFF:
        ours, rtol = CENTER_KNOWN_OFF[ti_deg]
        assert abs(f.max() / center - 1) < rtol
        assert abs(f.max() - ours) < 1.0
    else:
        assert float(f"{f.max():.2e}") == center
    terms = ref.solar_cell(ti, ts, ps, terms=True)
    assert terms["diffraction"][30, 30] == pytest.approx(300.0, rel=1e-14)
    np.testing.assert_allclose(terms["center"] + terms["offset"] + terms["diffraction"], f, rtol=1e-15)

    ch, cv = _offset_peak_guess(ti)
    assert ch > 0 and cv > 0  # down and to the right of the centre peak
    nh, nv = _window(ch, cv, 40)
    ts, ps = ref.pixel_angles(nh, nv, ti)
    f = ref.solar_cell(ti, ts, ps)
    i = np.unravel_index(np.argmax(f), f.shape)
    assert 0 < i[0] < 80 and 0 < i[1] < 80  # interior maximum of the window
    assert float(f"{f.max():.2e}") == offset


@pytest.mark.parametrize("ti_deg,grating_factor,expected", [(20, True, 26), (60, True, 26), (20, False, 14), (60, False, 26)])
def test_diffraction_maxima_count(ti_deg, grating_factor, expected):
    ti = ti_deg * DEG
    nv = np.arange(0, -1236, -1)
    ts, ps = ref.pixel_angles(np.zeros_like(nv), nv, ti)
    f3 = ref.solar_cell(ti, ts, ps, terms=True, grating_factor=grating_factor)["diffraction"]
    assert f3[0] == pytest.approx(300.0)
    interior_max = (f3[1:-1] > f3[:-2]) & (f3[1:-1] >= f3[2:])
    assert int(interior_max.sum()) == expected


@pytest.mark.parametrize("ti_deg", [20, 60])
def test_diffraction_edge_peak_magnitude(ti_deg):
    # seed §6.4: simulated diffraction peaks range from 300 at the centre to 209
    # at each edge (the outermost order, maximum along its curved ridge)
    ti = ti_deg * DEG
    for rows in (np.arange(-1235, -1192), np.arange(1194, 1237)):
        nh, nv = np.meshgrid(np.arange(-200, 201), rows)
        ts, ps = ref.pixel_angles(nh, nv, ti)
        f3 = ref.solar_cell(ti, ts, ps, terms=True)["diffraction"]
        assert round(float(f3.max())) == 209


def test_solar_cell_frame_consistency():
    ti = 40 * DEG
    a = ref.solar_cell_frame(ti, phi_ref=0.3, step=16)
    b = ref.solar_cell_frame(ti, phi_ref=0.3, step=16, rows_per_chunk=5)
    assert a.shape == (155, 206) and a.dtype == np.float64
    np.testing.assert_array_equal(a, b)
    nh, nv = ref.pixel_indices(step=16)
    ts, ps = ref.pixel_angles(nh, nv, ti)
    np.testing.assert_allclose(a, ref.solar_cell(ti, ts, ps, phi_ref=0.3), rtol=1e-15)


def test_solar_cell_rotation_covariance_at_normal_incidence():
    # at theta_i = 0 turning the cell by phi_ref about the normal just turns the
    # pattern: f(ts, ps + phi_ref; phi_ref) = f(ts, ps; 0), term by term
    rng = np.random.default_rng(0)
    ts = rng.uniform(0.0, 0.03, 500)
    ps = rng.uniform(0.0, 2 * np.pi, 500)
    for phi_ref in (0.4, np.pi / 2, 2.5):
        a = ref.solar_cell(0.0, ts, ps, terms=True)
        b = ref.solar_cell(0.0, ts, np.mod(ps + phi_ref, 2 * np.pi), phi_ref=phi_ref, terms=True)
        for key in a:
            np.testing.assert_allclose(b[key], a[key], rtol=1e-7, atol=1e-9 * a[key].max())
