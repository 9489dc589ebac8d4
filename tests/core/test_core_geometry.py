"""Pixel mapping against the seed's printed tables (Tables 3, 4, 7, 8, 9) and §4.4-4.5."""

import numpy as np
import pytest

import brdfjax as bj

NINE = [(-1647, -1235), (0, -1235), (1648, -1235), (-1647, 0), (0, 0), (1648, 0), (-1647, 1236), (0, 1236), (1648, 1236)]

# (theta_s, phi_s) in degrees, as printed (physics.md reference numbers).
TABLES = {
    0: [(1.995, 36.86), (1.197, 90), (1.996, 143.2), (1.597, 0), (0, 180), (1.598, 180), (1.996, 323.1), (1.198, 270), (1.997, 216.9)],
    20: [(18.44, 176.2), (20.03, 176.5), (21.63, 176.8), (18.40, 180), (20, 180), (21.60, 180), (18.44, 183.8), (20.03, 183.5), (21.63, 183.3)],
    40: [(38.42, 178.1), (40.01, 178.1), (41.6, 178.2), (38.40, 180), (40, 180), (41.60, 180), (38.42, 181.9), (40.02, 181.9), (41.61, 181.8)],
    60: [(58.41, 178.6), (60.01, 178.6), (61.60, 178.6), (58.40, 180), (60, 180), (61.60, 180), (58.41, 181.4), (60.01, 181.4), (61.60, 181.4)],
}


def _decimals(x: float) -> int:
    s = repr(float(x))
    return 0 if "." not in s or s.endswith(".0") else len(s.split(".")[1])


@pytest.mark.parametrize("theta_c", sorted(TABLES))
def test_tables_4_7_8_9_scatter_angles(theta_c):
    det = bj.Detector.seed(theta_c=np.deg2rad(theta_c))
    nh = np.array([p[0] for p in NINE])
    nv = np.array([p[1] for p in NINE])
    th, ph = (np.rad2deg(np.asarray(a)) for a in det.angles(nh, nv))
    for k, (t_ref, p_ref) in enumerate(TABLES[theta_c]):
        # Compare to the printed digits: within half a unit of the last printed digit,
        # plus 0.1 unit of slack for the seed's double rounding (40.0149 is printed 40.02).
        # Entries like "20" or "180" are printed without decimals but are exact.
        t_tol = 0.6 * 10.0 ** -(_decimals(t_ref) or 2)
        p_tol = 0.6 * 10.0 ** -(_decimals(p_ref) or 2)
        assert abs(th[k] - t_ref) <= t_tol + 1e-12, (theta_c, NINE[k], th[k], t_ref)
        dp = (ph[k] - p_ref + 180) % 360 - 180
        assert abs(dp) <= p_tol + 1e-12, (theta_c, NINE[k], ph[k], p_ref)


def test_table_3_solid_angles():
    det = bj.Detector.seed()
    pix = {(0, 0): 2.864e-10, (-1647, -1235): 2.859e-10, (0, -1235): 2.862e-10, (-1647, 0): 2.861e-10}
    for (h, v), ref in pix.items():
        omega = float(det.solid_angle(h, v))
        assert abs(omega - ref) <= 0.5e-13, ((h, v), omega, ref)


def test_solid_angle_independent_of_arm_and_sums_to_array_extent():
    det = bj.Detector.seed()
    g = det.grid(16)
    H, V = np.meshgrid(g.n_h, g.n_v)
    omega = np.asarray(det.solid_angle(H, V))
    # Each pixel's solid angle is close to its area over R^2 (small-angle limit), never above it.
    assert np.all(omega <= 5.5e-6**2 / 0.325**2 * (1 + 1e-12))
    assert omega.min() / omega.max() > 0.998


def test_pixel_index_convention():
    det = bj.Detector.seed()
    assert det.index_range == (-1647, 1648, -1235, 1236)
    g = det.grid()
    assert g.shape == (2472, 3296)
    assert g.n_h[0] == -1647 and g.n_v[0] == -1235
    g4 = det.grid(4, roi=(-100, 100, -50, 50))
    assert g4.shape == (26, 51) and g4.n_h[0] == -100 and g4.n_h[-1] == 100


@pytest.mark.parametrize("theta_c_deg", [0.0, 1e-6, 20.0, 60.0, 89.9])
@pytest.mark.parametrize("misaligned", [False, True])
def test_inverse_map_round_trip(theta_c_deg, misaligned):
    """Eq 82 (and its Eq 83-84 limits): pixel -> (theta_s, phi_s) -> pixel."""
    if misaligned:
        det = bj.Detector.seed_misaligned_example(m_h=72, m_v=-3, theta_c=np.deg2rad(theta_c_deg))
    else:
        det = bj.Detector.seed(theta_c=np.deg2rad(theta_c_deg))
    rng = np.random.default_rng(0)
    nh = rng.integers(-1647, 1649, 200).astype(float)
    nv = rng.integers(-1235, 1237, 200).astype(float)
    th, ph = det.angles(nh, nv)
    nh2, nv2 = det.pixel_of(th, ph)
    np.testing.assert_allclose(np.asarray(nh2), nh, atol=1e-6)
    np.testing.assert_allclose(np.asarray(nv2), nv, atol=1e-6)


def test_inverse_map_is_eq_82_when_aligned():
    tc = np.deg2rad(40.0)
    det = bj.Detector.seed(theta_c=tc)
    th, ph = np.deg2rad(41.2), np.deg2rad(178.9)
    R, d = 0.325, 5.5e-6
    cot = 1 / np.tan(tc)
    c = np.cos(ph - np.pi)
    nh = (R / d) * (cot * np.sin(th) * c - np.cos(th)) / (cot * np.cos(th) + np.sin(th) * c)
    nv = (R / d) * np.sin(th) * np.sin(ph - np.pi) / (np.cos(tc) * np.cos(th) + np.sin(tc) * np.sin(th) * c)
    got = det.pixel_of(th, ph)
    np.testing.assert_allclose([float(got[0]), float(got[1])], [nh, nv], rtol=1e-10)


@pytest.mark.parametrize(
    "theta_i, m_h, m_v, theta_pct, phi_pct",
    [(20, 3, 5, 0.0034, 0.012), (40, -1, -1, 0.0049, 0.0036), (60, 72, -3, 0.23, 0.0045)],
)
def test_misalignment_examples_section_4_4(theta_i, m_h, m_v, theta_pct, phi_pct):
    """§4.4: maximum relative misalignment uncertainty (dtheta tan(theta), dphi/phi) over the array."""
    tc = np.deg2rad(theta_i)
    det = bj.Detector.seed(theta_c=tc)
    mis = bj.Detector.seed_misaligned_example(m_h=m_h, m_v=m_v, theta_c=tc)
    g = det.grid(8)
    H, V = np.meshgrid(g.n_h, g.n_v)
    t0, p0 = (np.asarray(a) for a in det.angles(H, V))
    t1, p1 = (np.asarray(a) for a in mis.angles(H, V))
    rel_theta = 100 * np.max(np.abs(t1 - t0) * np.tan(t0))
    rel_phi = 100 * np.max(np.abs(p1 - p0) / p0)
    assert float(f"{rel_theta:.2g}") == pytest.approx(theta_pct)
    assert float(f"{rel_phi:.2g}") == pytest.approx(phi_pct)


def test_misaligned_solid_angle_section_4_5():
    """§4.5: misalignment (seed angles, m = -1, -1) changes Omega_d by at most 0.012%."""
    det = bj.Detector.seed()
    mis = bj.Detector.seed_misaligned_example(m_h=-1, m_v=-1)
    g = det.grid(8)
    H, V = np.meshgrid(g.n_h, g.n_v)
    rel = np.abs(np.asarray(mis.solid_angle(H, V)) / np.asarray(det.solid_angle(H, V)) - 1)
    assert float(f"{100 * rel.max():.2g}") == pytest.approx(0.012)


def test_contours_follow_their_levels():
    det = bj.Detector.seed(theta_c=np.deg2rad(20))
    lines = det.contours()
    kinds = {ln["kind"] for ln in lines}
    assert kinds == {"theta_s", "phi_s"}
    for ln in lines:
        ok = np.isfinite(ln["n_h"])
        th, ph = det.angles(ln["n_h"][ok], ln["n_v"][ok])
        got = np.rad2deg(np.asarray(th if ln["kind"] == "theta_s" else ph))
        np.testing.assert_allclose(got, ln["level_deg"], atol=1e-6)


def test_directions_sum_matches_naive_sum_in_float64():
    det = bj.Detector.seed_misaligned_example()
    g = det.grid(64)
    H, V = np.meshgrid(g.n_h, g.n_v)
    d = det.directions(H, V, np.deg2rad(33.0))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d.w_s), axis=-1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(d.w_sum), np.asarray(d.w_i + d.w_s), atol=1e-14)


def test_bad_detector_and_grid_inputs():
    with pytest.raises(ValueError, match="pixel_pitch"):
        bj.Detector.seed(pixel_pitch=-5e-6)
    with pytest.raises(ValueError, match="shape"):
        bj.Detector(shape=(0, 10), pixel_pitch=1e-6, pixel_pitch_v=1e-6, distance=0.3)
    with pytest.raises(ValueError, match="roi"):
        bj.Detector.seed().grid(1, roi=(-5000, 0, 0, 10))
    with pytest.raises(ValueError, match="step"):
        bj.Detector.seed().grid(0)
