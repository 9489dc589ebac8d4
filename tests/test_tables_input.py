"""Goniometer table input: column mappings, wavelength checks, the mirror-angle check and row screening.

Every bad input is an exit-2 error of ``brdfjax fit`` that names the file, column or key and writes nothing."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from brdfjax.cli import main
from brdfjax.fit import FitInputError, read_astm_e1392, read_merl_inplane, read_table

REAL = Path(__file__).parent / "data" / "real"
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
    cfg = tmp_path / "fit.toml"
    cfg.write_text(textwrap.dedent(f"""
        [[data.tables]]
        {table}
        [model.terms.d]
        kind = "lambertian"
        params = {{ rho_d = 0.3 }}
        [params]
        "d.rho_d" = "free"
    """))
    return cfg


def _fails(tmp_path: Path, cfg: Path, capsys) -> str:
    out = tmp_path / "out"
    assert main(["fit", str(cfg), "--out", str(out), "--no-figures"]) == 2
    assert not out.exists()  # nothing written
    return capsys.readouterr().err


def test_merl_layout_with_other_column_names_through_a_mapping(tmp_path):
    f = _lumos(tmp_path / "scan.csv")
    with pytest.raises(FitInputError, match=r"scan.csv: no column 'phi_in' for 'theta_i'; the header has: phi_i, theta_i"):
        read_merl_inplane(f)
    t = read_merl_inplane(f, columns={"theta_i": "phi_i", "phi_i": "theta_i", "theta_s": "phi_o", "phi_s": "theta_o"},
                          wavelength=532.0)
    assert len(t) == 70 and float(t.wavelength) == pytest.approx(532e-9)
    k = int(np.argmax(t.brdf[:35]))  # the 20-deg slice peaks at the mirror direction, brdfjax's phi_s = 180 deg
    assert np.degrees(t.theta_s[k]) == pytest.approx(20.0) and np.degrees(t.phi_s[k]) == pytest.approx(180.0)
    assert t.screening["mirror_check"] == {"slices_with_a_clear_peak": 2, "off_mirror": 0}


def test_real_merl_file_passes_the_checks_and_honours_wavelength_nm():
    t = read_merl_inplane(MERL, wavelength=532.0)
    assert len(t) == 1785 and t.screening["dropped"] == {} and float(t.wavelength) == pytest.approx(532e-9)
    assert t.screening["mirror_check"] == {"slices_with_a_clear_peak": 7, "off_mirror": 0}


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
    from brdfjax.fit.config import _describe_block, build_fit_job, load_fit_config

    ts = np.arange(0.0, 91.0, 2.0)
    rows = [[30.0, t, _lobe(30.0, t)] for t in ts]
    rows[3][2] = float("nan")
    _csv(tmp_path / "bad.csv", "ti,ts,f", rows)
    cfg = _config(tmp_path, 'path = "bad.csv"\ncolumns = { theta_i = "ti", theta_s = "ts", brdf = "f" }\nsigned_inplane = true')
    job = build_fit_job(load_fit_config(cfg))
    assert any("dropped 2 of 46 rows: 1 non_finite, 1 theta_90deg" in n for n in job.notes), job.notes
    doc = _describe_block(job.blocks[0])
    assert doc["screening"]["dropped"]["non_finite"] == {"count": 1, "lines": [5]} and doc["n_rows"] == 44
