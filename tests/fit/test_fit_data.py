"""Fit data containers and table readers: validation messages, conventions, round trips."""

from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax.fit import (
    FitInputError,
    FrameData,
    TableData,
    export_table,
    fit,
    read_astm_e1392,
    read_cornell_brdf,
    read_merl_inplane,
    read_table,
)

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="tests/data/real is not present")

DET = bj.Detector.seed()
GRID = DET.grid(8, (-40, 40, -24, 24))


def _frame(**kw):
    shape = GRID.shape
    args = dict(brdf=np.ones(shape), sigma_rel=0.03, theta_i=0.35, detector=DET, grid=GRID, name="f")
    args.update(kw)
    return FrameData(**args)


# --- frames -------------------------------------------------------------------------------


def test_frame_data_validates_shapes_and_conditions():
    with pytest.raises(FitInputError, match=r"frame 'f': 'brdf' has shape \(3, 3\), but the grid is \(7, 11\)"):
        _frame(brdf=np.ones((3, 3)))
    with pytest.raises(FitInputError, match=r"'sigma_rel' has shape \(2,\), expected \(7, 11\)"):
        _frame(sigma_rel=np.ones(2))
    with pytest.raises(FitInputError, match=r"'theta_i' = 2\.0 is invalid; expected 0 <= theta_i < pi/2"):
        _frame(theta_i=2.0)
    with pytest.raises(FitInputError, match=r"'footprint' must be a 2-D kernel with odd sides"):
        _frame(footprint=np.ones((4, 5)))
    with pytest.raises(FitInputError, match=r"'grid' must be a PixelGrid"):
        _frame(grid=None)


def test_all_nan_frame_is_an_error():
    with pytest.raises(FitInputError, match=r"frame 'f': 'brdf' is all NaN"):
        _frame(brdf=np.full(GRID.shape, np.nan))


def test_empty_mask_is_an_error_naming_the_frame():
    model = bj.Model(terms={"d": bj.Lambertian(0.1)})
    fr = _frame(mask=np.zeros(GRID.shape, bool))
    with pytest.raises(FitInputError, match=r"frame 'f': no usable points: the mask selects none of the 77 points"):
        fit(model, fr, {"d.rho_d": 0.1})
    b = np.ones(GRID.shape)
    b[0, 0] = -1.0
    fr2 = _frame(brdf=b, mask=np.zeros(GRID.shape, bool) | (np.arange(77).reshape(GRID.shape) == 0))
    with pytest.raises(FitInputError, match=r"of the 1 points in the mask, 0 have NaN/inf brdf, 1 have brdf <= 0"):
        fit(model, fr2, {"d.rho_d": 0.1})


def test_joint_fit_of_different_detectors_must_say_so():
    model = bj.Model(terms={"d": bj.Lambertian(0.1)})
    other = bj.Detector.seed(distance=0.3)
    a = _frame(name="a")
    b = FrameData(np.ones(GRID.shape), 0.03, 0.35, other, other.grid(8, (-40, 40, -24, 24)), name="b")
    with pytest.raises(FitInputError, match=r"frames 'a' and 'b' were taken with different detectors.*allow_different_detectors=True"):
        fit(model, [a, b], {"d.rho_d": 0.1})
    res = fit(model, [a, b], {"d.rho_d": 0.1}, allow_different_detectors=True)
    assert res.converged
    assert res.value("d.rho_d") == pytest.approx(np.pi, rel=1e-6)  # brdf = 1 = rho / pi


def test_footprint_is_convolved_and_recorded_with_a_free_incidence_angle():
    # A narrow peak seen through a box footprint, the sample 0.02 deg off (the arm stays at the
    # nominal 30 deg, the incidence is 30.02 deg): the fit convolves the model with the footprint,
    # recovers the width (unconvolved, the 14-pixel box would widen it by ~5 %) and the incidence,
    # and says that it convolved.
    det = bj.Detector.seed()
    grid = det.grid(2, (-40, 40, -30, 30))
    model = bj.Model(terms={"p": bj.Specular(bj.Beckmann(1e-4), rho_s=0.02, n=1.5, **bj.SEED_FORM), "floor": bj.Lambertian(0.5)})
    truth = np.asarray(
        bj.render(model, bj.Conditions.from_degrees(30.02), det.at(np.radians(30.0)), grid=grid, precision="float64")
    )
    kernel = np.ones((7, 7)) / 49.0
    import jax.scipy.signal as jss

    blurred = np.asarray(jss.fftconvolve(truth, kernel, mode="same"))
    mask = np.zeros(truth.shape, bool)
    mask[6:-6, 6:-6] = True  # away from the zero-padded edge
    fr = FrameData(blurred, 1e-3, np.radians(30.0), det, grid, mask=mask, footprint=kernel, name="blur")
    res = fit(model, fr, {"p.m": 1.3e-4, "p.rho_s": 0.03, "theta_i": "free"})
    assert res.converged, res.message
    assert res.convolved and res.to_dict()["instrument_function"] == {"convolved": True, "blocks": ["blur"]}
    assert res.value("p.m") == pytest.approx(1e-4, rel=1e-4)
    assert np.degrees(res.value("theta_i[blur]")) == pytest.approx(30.02, abs=1e-6)
    out = res.to_dict()["parameters"]["theta_i[blur]"]
    assert out["unit"] == "deg" and out["free"] is True and out["initial"] == pytest.approx(30.0)


# --- tables -------------------------------------------------------------------------------


def test_table_data_validates():
    with pytest.raises(FitInputError, match=r"zenith angles beyond 90 deg .* are they in degrees\? give radians"):
        TableData([20.0], [0.0], [20.0], [180.0], [1.0])
    with pytest.raises(FitInputError, match=r"negative zenith angles"):
        TableData([-0.2], [0.0], [0.2], [3.1], [1.0])
    with pytest.raises(FitInputError, match=r"'wavelength' must be positive and in metres"):
        TableData([0.2], [0.0], [0.2], [3.1], [1.0], wavelength=632.8)
    with pytest.raises(FitInputError, match=r"'brdf' is all NaN"):
        TableData([0.2, 0.3], [0.0, 0.0], [0.2, 0.3], [3.1, 3.1], [np.nan, np.nan])


def test_read_table_csv_with_column_mapping_and_units(tmp_path):
    p = tmp_path / "lab.csv"
    p.write_text(
        "# my goniometer\n"
        "AOI,scatter(rad),az,value,unc\n"
        "20,0.3490658504,180,12.5,0.5\n"
        "20,0.3,180,3.0,0.2\n"
        "40,0.7,0,0.5,0.05\n"
    )
    t = read_table(p, {"theta_i": "aoi", "theta_s": "scatter", "phi_s": "az", "brdf": "value", "sigma": "unc"})
    np.testing.assert_allclose(t.theta_i, np.radians([20, 20, 40]))
    np.testing.assert_allclose(t.theta_s, [0.3490658504, 0.3, 0.7])  # the (rad) unit in the header wins
    np.testing.assert_allclose(t.phi_s, np.radians([180, 180, 0]))
    np.testing.assert_allclose(t.sigma_rel, [0.04, 0.2 / 3, 0.1])
    assert t.name == "lab" and t.source == str(p)


def test_read_table_whitespace_by_index_and_signed_inplane(tmp_path):
    p = tmp_path / "inplane.txt"
    p.write_text("30 -10 0.1\n30 30 50.0\n30 10 0.2\n")
    t = read_table(p, {"theta_i": 0, "theta_s": 1, "brdf": 2}, signed_inplane=True, wavelength=532)
    np.testing.assert_allclose(t.theta_s, np.radians([10, 30, 10]))
    np.testing.assert_allclose(t.phi_s, [0.0, np.pi, np.pi])  # negative: the source side
    assert float(np.asarray(t.wavelength)) == pytest.approx(532e-9)


@pytest.mark.parametrize(
    "text, columns, kw, message",
    [
        ("a b c\n1 2 3\n", {"theta_i": "a", "theta_s": "x", "brdf": "c", "phi_s": "b"}, {},
         r"no column 'x' for 'theta_s'; the header has: a, b, c"),
        ("1 2 3\n", {"theta_i": 0, "theta_s": 1, "brdf": 5, "phi_s": 1}, {}, r"column index 5 for 'brdf' is out of range"),
        ("1 2 3\n1 x 3\n", {"theta_i": 0, "theta_s": 1, "brdf": 2, "phi_s": 1}, {}, r":2: 'x' is not a number"),
        ("1 2 3\n1 2\n", {"theta_i": 0, "theta_s": 1, "brdf": 2, "phi_s": 1}, {}, r":2: 2 columns, but the first data row has 3"),
        ("100 2 3\n", {"theta_i": 0, "theta_s": 1, "brdf": 2, "phi_s": 1}, {}, r"column '0' \(theta_i\) has zenith angles up to 100 deg"),
        ("10 2 3\n", {"theta_i": 0, "theta_s": 1, "brdf": 2}, {}, r"no 'phi_s' column; .* signed_inplane=True"),
        ("10 2 3\n", {"theta_i": 0, "brdf": 2}, {}, r"the column mapping needs 'theta_s'"),
        ("10 2 3\n", {"theta_i": 0, "theta_s": 1, "brdf": 2, "zenith": 1}, {}, r"unknown column role\(s\) \['zenith'\]"),
        ("10 2 3\n", {"theta_i": 0, "theta_s": 1, "brdf": 2, "phi_s": 1}, {"angle_unit": "grad"}, r"angle_unit must be 'deg' or 'rad'"),
        ("# only a comment\n", {"theta_i": 0, "theta_s": 1, "brdf": 2}, {}, r"no data rows"),
    ],
)
def test_read_table_errors_name_the_file_and_column(tmp_path, text, columns, kw, message):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(FitInputError, match=str(p).replace(".", r"\.") + r".*" + message):
        read_table(p, columns, **kw)


def test_missing_file():
    with pytest.raises(FitInputError, match=r"nope\.txt: no such file"):
        read_table("nope.txt", {"theta_i": 0, "theta_s": 1, "brdf": 2})


ASTM = """# ASTM E1392-style export
Sample: test mirror
Wavelength: 632.8 nm
Angle unit: deg
Incident angle: 20
theta_s(deg)  BRDF  sigma
-10  0.010  0.001
20   1000   50
30   0.5    0.05
Incident angle: 40 deg
35   2.0    0.1
40   900    45
"""


def test_read_astm_e1392_sections_and_signed_angles(tmp_path):
    p = tmp_path / "scan.e1392"
    p.write_text(ASTM)
    t = read_astm_e1392(p)
    np.testing.assert_allclose(np.degrees(t.theta_i), [20, 20, 20, 40, 40])
    np.testing.assert_allclose(np.degrees(t.theta_s), [10, 20, 30, 35, 40])
    np.testing.assert_allclose(t.phi_s, [0.0, np.pi, np.pi, np.pi, np.pi])
    np.testing.assert_allclose(t.sigma_rel, [0.1, 0.05, 0.1, 0.05, 0.05])
    assert float(np.asarray(t.wavelength)) == pytest.approx(632.8e-9)


@pytest.mark.parametrize(
    "text, message",
    [
        (ASTM.replace("Wavelength: 632.8 nm\n", ""), r"no 'Wavelength:' line"),
        (ASTM.replace("Sample:", "Colour:"), r":2: unknown header key 'Colour'"),
        (ASTM.replace("theta_s(deg)  BRDF  sigma", "theta_s  BRDF  flux"), r":6: unknown column 'flux'"),
        (ASTM.replace("Incident angle: 20\n", ""), r"data before any 'Incident angle:' line"),
        (ASTM.replace("30   0.5    0.05", "30   0.5"), r":9: 2 values, but the header names 3 columns"),
        (ASTM.replace("Wavelength: 632.8 nm", "Wavelength: 632.8 furlong"), r"unknown wavelength unit 'furlong'"),
    ],
)
def test_read_astm_errors(tmp_path, text, message):
    p = tmp_path / "bad.e1392"
    p.write_text(text)
    with pytest.raises(FitInputError, match=message):
        read_astm_e1392(p)


@needs_real
def test_read_merl_inplane_conventions():
    t = read_merl_inplane(REAL / "merl_aluminium_inplane.txt")
    assert len(t) == 1785
    np.testing.assert_allclose(np.unique(np.round(np.degrees(np.asarray(t.theta_i)), 3)), [11.25, 22.5, 33.75, 45, 56.25, 67.5, 78.75])
    # each slice peaks in the mirror direction: theta_s = theta_i, phi_s = 180 deg
    ti, ts, ps, b = (np.asarray(x) for x in (t.theta_i, t.theta_s, t.phi_s, t.brdf))
    for a in np.unique(np.round(ti, 6)):
        sel = np.round(ti, 6) == a
        k = np.argmax(b[sel])
        assert ts[sel][k] == pytest.approx(a, abs=1e-6)
        assert ps[sel][k] == pytest.approx(np.pi)
    assert t.sigma_rel is None


@needs_real
def test_read_cornell_wavelength_choice():
    f = REAL / "cornell_krylon_blue.brdf"
    mean = read_cornell_brdf(f)
    one = read_cornell_brdf(f, wavelength_nm=450)
    # 1439 records; the reader drops (and counts) those whose BRDF is <= 0 at that wavelength
    assert mean.screening["n_rows"] == one.screening["n_rows"] == 1439
    assert (len(mean), len(one)) == (1437, 1436)
    assert mean.screening["dropped"] == {"non_positive": {"count": 2, "records": [1437, 1438]}}
    assert float(np.asarray(mean.wavelength)) == pytest.approx(550e-9)
    assert float(np.asarray(one.wavelength)) == pytest.approx(450e-9)
    assert np.all(np.asarray(mean.phi_i) == 0)
    with pytest.raises(FitInputError, match=r"no wavelength 455 nm; the file has 400, 410, .* nm or 'mean'"):
        read_cornell_brdf(f, wavelength_nm=455)


def test_export_table_round_trip(tmp_path):
    model = bj.Model(terms={"s": bj.Specular(bj.GGX(0.2), rho_s=0.5, n=1.5), "d": bj.Lambertian(0.05)})
    p = tmp_path / "model.csv"
    cols = export_table(model, [10, 40], 0, np.linspace(0, 80, 9), [0, 180], path=p)
    assert cols["brdf_per_sr"].shape == (2 * 9 * 2,)
    t = read_table(
        p,
        {"theta_i": "theta_i_deg", "phi_i": "phi_i_deg", "theta_s": "theta_s_deg", "phi_s": "phi_s_deg", "brdf": "brdf_per_sr", "wavelength": "wavelength_nm"},
    )
    direct = np.asarray(model(bj.Directions.from_angles(t.theta_i, t.phi_i, t.theta_s, t.phi_s), 632.8e-9))
    np.testing.assert_allclose(np.asarray(t.brdf), direct, rtol=1e-9)
    # the mirror direction carries the peak
    k = np.argmax(cols["brdf_per_sr"])
    assert cols["phi_s_deg"][k] == 180 and cols["theta_s_deg"][k] in (10, 40)
    with pytest.raises(FitInputError, match=r"theta_s must lie in \[0, 90\] deg"):
        export_table(model, 10, 0, 95, 180)


def test_frames_and_tables_jointly_with_a_per_frame_parameter():
    model = bj.Model(terms={"d": bj.Lambertian(0.1)})
    fr = _frame(brdf=np.full(GRID.shape, 0.2 / np.pi), name="frame")
    n = 50
    tab = TableData(np.full(n, 0.3), np.zeros(n), np.full(n, 0.4), np.full(n, 1.0), np.full(n, 0.4 / np.pi), 0.03, name="gonio")
    res = fit(model, [fr, tab], {"d.rho_d": bj.fit.Param(0.1, per_frame=True)})
    assert res.converged, res.message
    assert res.value("d.rho_d[frame]") == pytest.approx(0.2, rel=1e-5)  # the log(0) guard biases by 1e-6
    assert res.value("d.rho_d[gonio]") == pytest.approx(0.4, rel=1e-5)
    assert [b.kind for b in res.blocks] == ["frame", "table"]
