"""Goniometer table input: column mappings, wavelength checks, the mirror-angle check and row screening.

Every bad input is an exit-2 error of ``brdfjax fit`` that names the file, column or key and writes nothing."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
from helpers import write_config

import brdfjax as bj
from brdfjax.cli import main
from brdfjax.fit import FitInputError, read_astm_e1392, read_merl_inplane, read_table

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
MERL = REAL / "merl_aluminium_inplane.txt"


def _lobe(ti: float, ts: np.ndarray) -> np.ndarray:
    return 0.05 * np.cos(np.radians(ts)) + 0.01 + 30.0 * np.exp(-(((ts - ti) / 5.0) ** 2))


def _csv(path: Path, header: str, rows) -> Path:
    path.write_text(header + "\n" + "\n".join(",".join(f"{v:.6g}" for v in r) for r in rows) + "\n")
    return path


def _lumos(path: Path, sign: float = 1.0) -> Path:
    """A lumos-sat/MERL-layout file with other column names: phi_i theta_i phi_o theta_o brdf (phi = zenith)."""
    ts = np.arange(-85.0, 86.0, 5.0)
    rows = [(ti, 180.0, t, 0.0, _lobe(ti, sign * t)) for ti in (20.0, 40.0) for t in ts]
    return _csv(path, "phi_i,theta_i,phi_o,theta_o,brdf", rows)


def _config(tmp_path: Path, table: str) -> Path:
    return write_config(tmp_path, """
        [[data.tables]]
        {table}
        [model.terms.d]
        kind = "lambertian"
        params = {{ rho_d = 0.3 }}
        [params]
        "d.rho_d" = "free"
    """, table=table)


def _fails(tmp_path: Path, cfg: Path, capsys) -> str:
    out = tmp_path / "out"
    assert main(["fit", str(cfg), "--out", str(out), "--no-figures"]) == 2
    assert not out.exists()  # nothing written
    return capsys.readouterr().err


def test_merl_layout_with_lumos_sat_names_and_through_a_mapping(tmp_path):
    f = _lumos(tmp_path / "scan.csv")
    direct = read_merl_inplane(f, wavelength=532.0)  # lumos-sat's own header: recognised
    t = read_merl_inplane(f, columns={"theta_i": "phi_i", "phi_i": "theta_i", "theta_s": "phi_o", "phi_s": "theta_o"},
                          wavelength=532.0)
    np.testing.assert_array_equal(direct.brdf, t.brdf)
    np.testing.assert_array_equal(direct.phi_s, t.phi_s)
    assert len(t) == 70 and float(t.wavelength) == pytest.approx(532e-9)
    k = int(np.argmax(t.brdf[:35]))  # the 20-deg slice peaks at the mirror direction, brdfjax's phi_s = 180 deg
    assert np.degrees(t.theta_s[k]) == pytest.approx(20.0) and np.degrees(t.phi_s[k]) == pytest.approx(180.0)
    assert t.screening["mirror_check"] == {"slices_with_a_clear_peak": 2, "off_mirror": 0, "forward_shifted": 0}


def test_real_merl_file_passes_the_checks_and_honours_wavelength_nm():
    t = read_merl_inplane(MERL, wavelength=532.0)
    assert len(t) == 1785 and t.screening["dropped"] == {} and float(t.wavelength) == pytest.approx(532e-9)
    assert t.screening["mirror_check"]["slices_with_a_clear_peak"] == 7
    assert t.screening["mirror_check"]["off_mirror"] == 0


def test_header_without_the_mapped_column_exits_2(tmp_path, capsys):
    _lumos(tmp_path / "scan.csv")
    err = _fails(tmp_path, _config(tmp_path, 'path = "scan.csv"\nformat = "merl"\ncolumns = { theta_i = "phi_i", phi_i = "theta_i", theta_s = "phi_out", phi_s = "theta_o" }'), capsys)
    assert "data.tables[0]: " in err and "scan.csv: no column 'phi_out' for 'theta_s'; the header has: phi_i, theta_i, phi_o" in err


def test_wrong_azimuth_convention_peaks_on_the_backscatter_side_exits_2(tmp_path, capsys):
    _lumos(tmp_path / "scan.csv", sign=-1.0)  # the file's positive angles are on the source side
    err = _fails(tmp_path, _config(tmp_path, textwrap.dedent("""
        path = "scan.csv"
        format = "merl"
        columns = { theta_i = "phi_i", phi_i = "theta_i", theta_s = "phi_o", phi_s = "theta_o" }""")), capsys)
    assert "scan.csv: the BRDF peak of 2 of 2 slices is not at the mirror direction (on the backscatter side" in err
    assert "data.tables[0].azimuth_offset (now -180.0)" in err and "data.tables[0].signed_inplane" in err


def _broad_lobe_csv(path: Path, ti: float, m: float = 0.145, sign: float = 1.0, step: float = 1.0) -> Path:
    """A signed in-plane scan of a Beckmann lobe (seed form) + Lambertian, 2 % scatter (a noise-free Lambertian floor
    would be identical rows: placeholders); sign -1 puts it on the source side."""
    model = bj.Model(terms={"s": bj.Specular(bj.Beckmann(m), rho_s=0.5, n=1.5, **bj.SEED_FORM), "d": bj.Lambertian(0.02)})
    ts = np.arange(-85.0, 86.0, step)
    t = np.full(ts.shape, math.radians(ti))
    dirs = bj.Directions.from_angles(t, 0 * t, np.radians(np.abs(ts)), np.where(ts >= 0, math.pi, 0.0))
    f = np.asarray(model(dirs, 632.8e-9)) * np.exp(0.02 * np.random.default_rng(1).standard_normal(ts.size))
    path.write_text("ti,ts,f\n" + "".join(f"{ti:g},{sign * a:g},{v:.12e}\n" for a, v in zip(ts, f)))
    return path


COLS = {"theta_i": "ti", "theta_s": "ts", "brdf": "f"}


def test_broad_lobe_forward_peak_is_not_refused_but_its_mirror_image_is(tmp_path):
    # Beckmann m = 0.145 at 60 deg peaks forward of the mirror direction (at ~70 deg, 10 deg off): its
    # half-maximum region reaches the mirror, so it is a broad lobe's off-specular peak, not a wrong convention.
    f = _broad_lobe_csv(tmp_path / "rough.csv", 60.0)
    t = read_table(f, COLS, signed_inplane=True)
    k = int(np.argmax(t.brdf))
    assert np.degrees(t.theta_s[k]) >= 69.0 and np.degrees(t.phi_s[k]) == pytest.approx(180.0)
    assert t.screening["mirror_check"] == {"slices_with_a_clear_peak": 1, "off_mirror": 0, "forward_shifted": 1}
    # the same lobe on the source side (the wrong sign convention) is still refused, naming the side and the keys
    bad = _broad_lobe_csv(tmp_path / "flipped.csv", 60.0, sign=-1.0)
    with pytest.raises(FitInputError, match=r"flipped.csv: the BRDF peak of 1 of 1 slices is not at the mirror "
                                            r"direction \(on the backscatter side.*signed_inplane \(now true\)"):
        read_table(bad, COLS, signed_inplane=True)


def test_mirror_check_over_lobe_widths_and_incidences(tmp_path):
    # Every lobe of m <= 0.2 at 20-80 deg passes in the right convention and is refused in the flipped one.
    for ti in (20.0, 40.0, 60.0, 75.0):
        for m in (0.05, 0.2):
            f = _broad_lobe_csv(tmp_path / "ok.csv", ti, m=m, step=2.0)
            assert read_table(f, COLS, signed_inplane=True).screening["mirror_check"]["off_mirror"] == 0, (ti, m)
            bad = _broad_lobe_csv(tmp_path / "flip.csv", ti, m=m, sign=-1.0, step=2.0)
            with pytest.raises(FitInputError, match="backscatter side"):
                read_table(bad, COLS, signed_inplane=True)


def test_narrow_peak_far_forward_of_the_mirror_is_refused(tmp_path):
    # A narrow peak 30 deg beyond the mirror direction (a zenith mislabelled by 30 deg) is no broad lobe's shift.
    ts = np.arange(-85.0, 86.0, 1.0)
    _csv(tmp_path / "shifted.csv", "ti,ts,f", [(30.0, a, _lobe(60.0, a)) for a in ts])
    with pytest.raises(FitInputError, match=r"shifted.csv: the BRDF peak of 1 of 1 slices is not at the mirror "
                                            r"direction: e.g. theta_i = 30 deg: peak at theta_s = 60"):
        read_table(tmp_path / "shifted.csv", COLS, signed_inplane=True)


def test_wavelength_that_disagrees_with_the_file_exits_2(tmp_path, capsys):
    ts = np.arange(0.0, 81.0, 5.0)
    _csv(tmp_path / "wl.csv", "ti,ts,f,wl", [(30.0, t, _lobe(30.0, t), 633.0) for t in ts])
    err = _fails(tmp_path, _config(tmp_path, textwrap.dedent("""
        path = "wl.csv"
        columns = { theta_i = "ti", theta_s = "ts", brdf = "f", wavelength = "wl" }
        signed_inplane = true
        wavelength_nm = 532.0""")), capsys)
    assert "wl.csv: wavelength_nm = 532 disagrees with the file (column 'wl' states 633 nm)" in err
    astm = tmp_path / "scan.txt"
    astm.write_text("Wavelength: 633 nm\nIncident angle: 30\ntheta_s BRDF\n" + "\n".join(f"{t:g} {_lobe(30, t):.6g}" for t in ts))
    with pytest.raises(FitInputError, match=r"scan.txt: wavelength_nm = 532 disagrees with the file \(its 'Wavelength:' line states 633 nm\)"):
        read_astm_e1392(astm, wavelength=532.0)
    assert float(read_astm_e1392(astm, wavelength=633.0).wavelength) == pytest.approx(633e-9)


def test_all_placeholder_slice_exits_2(tmp_path, capsys):
    ts = np.arange(0.0, 81.0, 2.0)
    rows = [(30.0, t, _lobe(30.0, t)) for t in ts] + [(50.0, t, 0.5) for t in ts]
    _csv(tmp_path / "ph.csv", "ti,ts,f", rows)
    err = _fails(tmp_path, _config(tmp_path, 'path = "ph.csv"\ncolumns = { theta_i = "ti", theta_s = "ts", brdf = "f" }\nsigned_inplane = true'), capsys)
    assert "ph.csv: the slice at theta_i = 50 deg holds only a constant placeholder value (BRDF = 0.5 in all its 41 rows, lines 43-83)" in err
    assert "theta_i_deg" in err


def test_bad_rows_are_reported_with_lines_and_dropped_or_refused(tmp_path):
    ts = np.arange(0.0, 91.0, 2.0)  # ends at theta_s = 90 deg
    rows = [[30.0, t, _lobe(30.0, t)] for t in ts]
    rows[3][2] = float("nan")
    rows[5][2] = 0.0
    rows += [[50.0, t, _lobe(50.0, t)] for t in ts]
    for r in rows[60:72]:
        r[2] = 0.25  # a run of 12 identical values inside the 50-deg slice
    f = _csv(tmp_path / "bad.csv", "ti,ts,f", rows)
    t = read_table(f, {"theta_i": "ti", "theta_s": "ts", "brdf": "f"}, signed_inplane=True)
    d = t.screening["dropped"]
    assert d["non_finite"] == {"count": 1, "lines": [5]}
    assert d["non_positive"] == {"count": 1, "lines": [7]}
    assert d["theta_90deg"]["count"] == 2 and d["placeholder"]["count"] == 12
    assert t.screening["n_rows"] == 92 and len(t) == 92 - 16
    from brdfjax.fit import Screen

    with pytest.raises(FitInputError, match=r"bad.csv: bad rows: 1 NaN/non-finite angle or BRDF \(lines 5\); 2 at theta = 90 deg"):
        read_table(f, {"theta_i": "ti", "theta_s": "ts", "brdf": "f"}, signed_inplane=True, screen=Screen(on_bad_rows="error"))


def test_dropped_rows_are_printed_and_recorded_for_result_json(tmp_path):
    from brdfjax.fit.config import load_fit_config
    from brdfjax.fit.job import _describe_block, build_fit_job

    ts = np.arange(0.0, 91.0, 2.0)
    rows = [[30.0, t, _lobe(30.0, t)] for t in ts]
    rows[3][2] = float("nan")
    _csv(tmp_path / "bad.csv", "ti,ts,f", rows)
    cfg = _config(tmp_path, 'path = "bad.csv"\ncolumns = { theta_i = "ti", theta_s = "ts", brdf = "f" }\nsigned_inplane = true')
    job = build_fit_job(load_fit_config(cfg))
    assert any("dropped 2 of 46 rows: 1 non_finite, 1 theta_90deg" in n for n in job.notes), job.notes
    doc = _describe_block(job.blocks[0])
    assert doc["screening"]["dropped"]["non_finite"] == {"count": 1, "lines": [5]} and doc["n_rows"] == 44


def test_rows_below_min_brdf_are_recorded_under_screening(tmp_path):
    from brdfjax.fit.config import load_fit_config
    from brdfjax.fit.job import _describe_block, build_fit_job

    ts = np.arange(0.0, 89.0, 2.0)
    rows = [[30.0, t, _lobe(30.0, t)] for t in ts] + [[50.0, t, _lobe(50.0, t)] for t in ts]
    rows[3][2] = float("nan")
    _csv(tmp_path / "t.csv", "ti,ts,f", rows)
    cfg = _config(tmp_path, 'path = "t.csv"\ncolumns = { theta_i = "ti", theta_s = "ts", brdf = "f" }\n'
                            'signed_inplane = true\nmin_brdf = 0.02\ntheta_i_deg = [30]')
    job = build_fit_job(load_fit_config(cfg))
    b = np.array([r[2] for r in rows])
    low = np.flatnonzero((np.arange(len(rows)) < 45) & (b < 0.02))  # the 30-deg slice only (theta_i_deg)
    assert low.size > 3
    rec = _describe_block(job.blocks[0])["screening"]
    assert rec["dropped"]["min_brdf"] == {"count": low.size, "min_brdf": 0.02, "lines": (low + 2).tolist()}
    assert rec["dropped"]["non_finite"] == {"count": 1, "lines": [5]}
    assert rec["n_rows"] == 90 and rec["n_kept"] == 90 - 1 - low.size
    assert any(f"{low.size} min_brdf" in n for n in job.notes), job.notes
