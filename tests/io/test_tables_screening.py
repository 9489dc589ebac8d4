"""Row screening of goniometer tables on real data: isolated floor placeholders, min_brdf in the result, and
lumos-sat's own header.

Real tables: ``tests/data/satellites/starlink_v2mini_lab`` (Starlink V2 Mini lab BRDFs, Kandula 2025, MIT;
see tests/data/satellites/README.md) and ``tests/data/real`` (MERL aluminium, Cornell paints)."""

from __future__ import annotations

import json
import math
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from brdfjax.cli import main
from brdfjax.fit import FitInputError, Screen, read_cornell_brdf, read_merl_inplane

DATA = Path(__file__).resolve().parents[1] / "data"
V2MINI = DATA / "satellites" / "starlink_v2mini_lab"
MIRROR = V2MINI / "gen2_dialectric_mirror.csv"
REAL = DATA / "real"

#: rows kept by the screening in each V2 Mini table (rows at theta = 90 deg and BRDF = 0 dropped, nothing else)
V2MINI_KEPT = {"A700": 478, "LRB50XL2": 590, "black_c138": 659, "chassis_bare": 464, "gen2_dialectric_mirror": 527}


def _floored(path: Path, out: Path, n: int = 6, value: str = "0.0001") -> list[int]:
    """A copy of a lumos-sat table with ``n`` isolated grazing-angle rows (|phi_o| >= 60 deg, one or more rows
    apart, spread over the slices) replaced by a provider's floor ``value``; returns their line numbers."""
    lines = path.read_text().splitlines()
    cand = []
    for k, line in enumerate(lines):
        tok = line.split()
        if len(tok) == 5 and not line.startswith(("#", "phi")) and 60.0 <= abs(float(tok[2])) < 89.5 and float(tok[4]) > 0:
            cand.append(k)
    chosen = [cand[int(i)] for i in np.linspace(0, len(cand) - 1, n)]
    assert all(b - a > 1 for a, b in zip(chosen, chosen[1:]))  # isolated: no two adjacent
    for k in chosen:
        tok = lines[k].split()
        lines[k] = " ".join(tok[:4] + [value])
    out.write_text("\n".join(lines) + "\n")
    return [k + 1 for k in chosen]


def test_lumos_sat_header_is_read_without_a_mapping():
    t = read_merl_inplane(MIRROR)  # header "phi_i theta_i phi_o theta_o brdf": phi = zenith
    assert sorted(np.round(np.degrees(np.unique(t.theta_i)), 6)) == [5.0, 41.4, 60.0, 75.0]
    assert t.screening["n_rows"] == 605 and len(t) == 527
    assert t.screening["mirror_check"]["off_mirror"] == 0 and t.screening["mirror_check"]["slices_with_a_clear_peak"] == 4
    five = t.select(np.abs(t.theta_i - math.radians(5.0)) < 1e-9)
    k = int(np.argmax(five.brdf))  # the film's glint: phi_o = +7 deg, on the mirror side (brdfjax's phi_s = 180)
    assert np.degrees(five.theta_s[k]) == pytest.approx(7.0) and np.degrees(five.phi_s[k]) == pytest.approx(180.0)
    assert five.brdf[k] == 1040.0
    # a "#phi_i theta_i ..." comment line is the header too (LRB50XL2.csv)
    assert len(read_merl_inplane(V2MINI / "LRB50XL2.csv")) == V2MINI_KEPT["LRB50XL2"]


def test_lumos_sat_layout_without_header_and_an_unknown_header(tmp_path):
    body = [ln for ln in MIRROR.read_text().splitlines() if not ln.startswith("phi")]
    (tmp_path / "bare.txt").write_text("\n".join(body) + "\n")
    bare, named = read_merl_inplane(tmp_path / "bare.txt"), read_merl_inplane(MIRROR)
    np.testing.assert_array_equal(bare.brdf, named.brdf)
    np.testing.assert_array_equal(bare.theta_s, named.theta_s)
    (tmp_path / "odd.txt").write_text("zen_in az_in zen_out az_out f\n" + "\n".join(body) + "\n")
    with pytest.raises(FitInputError, match=r"odd.txt: the header \(zen_in, az_in, zen_out, az_out, f\) is neither "
                                            r"MERL's \(phi_in theta_in phi_out theta_out brdf\) nor lumos-sat's"):
        read_merl_inplane(tmp_path / "odd.txt")


def test_real_tables_have_no_floor_placeholders():
    """No false positives: the shipped real tables lose no row to the floor check.

    The V2 Mini mirror film repeats its lowest value (0.000113, once per slice) and Cornell Cayman at 550 nm,
    printed to 6 fixed decimals, repeats 1e-06 sixteen times: both are written to the same last digit as the
    values around them, so they are noise floors, not placeholders."""
    for stem, kept in V2MINI_KEPT.items():
        t = read_merl_inplane(V2MINI / f"{stem}.csv")
        assert "placeholder_floor" not in t.screening["dropped"] and len(t) == kept, stem
    mirror = read_merl_inplane(MIRROR)
    assert float(np.min(mirror.brdf)) == 0.000113 and int(np.sum(mirror.brdf == 0.000113)) == 4
    merl = read_merl_inplane(REAL / "merl_aluminium_inplane.txt")
    assert merl.screening["dropped"] == {} and len(merl) == 1785
    for name, wls, mean_kept in (("cornell_cayman_metallic", (400.0, 550.0, 700.0), 1415),
                                 ("cornell_krylon_blue", (400.0, 550.0, 700.0), 1437)):
        assert len(read_cornell_brdf(REAL / f"{name}.brdf")) == mean_kept
        for wl in wls:
            t = read_cornell_brdf(REAL / f"{name}.brdf", wl)
            assert set(t.screening["dropped"]) <= {"non_positive"}, (name, wl, t.screening["dropped"])
    cayman = read_cornell_brdf(REAL / "cornell_cayman_metallic.brdf", 550.0)
    assert int(np.sum(cayman.brdf == 1e-6)) == 16 and float(np.min(cayman.brdf)) == 1e-6


def test_isolated_floor_placeholders_are_dropped_and_named(tmp_path):
    f = tmp_path / "mirror_floored.csv"
    rows = _floored(MIRROR, f)
    t = read_merl_inplane(f)
    d = t.screening["dropped"]
    assert d["placeholder_floor"] == {"count": 6, "lines": rows, "values": [0.0001]}
    assert "placeholder" not in d  # no run: each is alone between measured values
    assert len(t) == V2MINI_KEPT["gen2_dialectric_mirror"] - 6 and not np.any(t.brdf == 1e-4)
    # the same value written to the table's own precision is a measurement at the floor, not a placeholder
    g = tmp_path / "mirror_quantised.csv"
    _floored(MIRROR, g, value="0.000101")
    assert len(read_merl_inplane(g)) == V2MINI_KEPT["gen2_dialectric_mirror"]
    # refused with the rows named under on_bad_rows = "error"; kept with floor_repeats = 0
    with pytest.raises(FitInputError, match=r"floor placeholder value\(s\) 0.0001 .*lines " + ", ".join(map(str, rows))):
        read_merl_inplane(f, screen=Screen(on_bad_rows="error"))
    assert len(read_merl_inplane(f, screen=Screen(floor_repeats=0))) == V2MINI_KEPT["gen2_dialectric_mirror"]
    # two rows are not a repeated floor (floor_repeats = 3)
    h = tmp_path / "mirror_two.csv"
    _floored(MIRROR, h, n=2)
    assert len(read_merl_inplane(h)) == V2MINI_KEPT["gen2_dialectric_mirror"]


def test_min_brdf_and_floor_rows_appear_under_screening_in_result_json(tmp_path, capsys):
    f = tmp_path / "mirror_floored.csv"
    rows = _floored(MIRROR, f)
    cfg = tmp_path / "fit.toml"
    cfg.write_text(textwrap.dedent("""
        [[data.tables]]
        path = "mirror_floored.csv"
        format = "lumos-sat"
        theta_i_deg = [41.4]
        min_brdf = 0.00015
        [model.terms.d]
        kind = "lambertian"
        params = { rho_d = 0.001 }
        [params]
        "d.rho_d" = "free"
    """))
    out = tmp_path / "out"
    assert main(["fit", str(cfg), "--out", str(out), "--no-figures"]) == 0, capsys.readouterr().err
    printed = capsys.readouterr()
    doc = json.loads((out / "result.json").read_text())
    scr = doc["data"][0]["screening"]
    table = np.loadtxt(f, skiprows=1)
    sel = (table[:, 0] == 41.4) & (np.abs(table[:, 2]) < 90) & (table[:, 4] > 0) & (table[:, 4] != 1e-4)
    low = sel & (table[:, 4] < 0.00015)
    assert scr["dropped"]["min_brdf"]["count"] == int(low.sum()) > 10
    assert scr["dropped"]["min_brdf"]["min_brdf"] == 0.00015
    assert scr["dropped"]["min_brdf"]["lines"] == (np.flatnonzero(low) + 2).tolist()[:50]  # +1 header, +1 from 1
    assert scr["dropped"]["placeholder_floor"]["lines"] == rows
    assert doc["data"][0]["n_usable"] == int((sel & ~low).sum())
    assert scr["n_kept"] == scr["n_rows"] - sum(v["count"] for v in scr["dropped"].values())
    text = printed.out + printed.err
    assert f"{int(low.sum())} min_brdf" in text and "6 placeholder_floor" in text


def test_format_lumos_sat_config_reads_the_real_file(tmp_path):
    """``format = "lumos-sat"`` on lumos-sat's own file: no columns mapping needed (a subprocess, as users run it)."""
    import subprocess

    cfg = tmp_path / "fit.toml"
    cfg.write_text(textwrap.dedent(f"""
        [[data.tables]]
        path = "{MIRROR.as_posix()}"
        format = "lumos-sat"
        theta_i_deg = [60.0]
        [model.terms.d]
        kind = "lambertian"
        params = {{ rho_d = 0.001 }}
        [params]
        "d.rho_d" = "free"
    """))
    r = subprocess.run([sys.executable, "-m", "brdfjax", "fit", str(cfg), "--out", str(tmp_path / "out"), "--no-figures"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert doc["data"][0]["screening"]["n_kept"] == V2MINI_KEPT["gen2_dialectric_mirror"]
