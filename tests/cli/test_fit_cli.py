"""``brdfjax fit CONFIG --out DIR`` end to end: result.json contract, exit codes, figures, synthetic data cache,
the shipped configs (synthetic solar cell: slow-gated; a cheaper variant of it runs by default; real data)."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
from helpers import write_config

import brdfjax as bj
from brdfjax.cli import main
from brdfjax.fit.config import load_fit_config
from brdfjax.fit.job import build_fit_job, run_fit
from brdfjax.instrument.reduce import reduce_measurement_set

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parents[1] / "data"
CONFIGS = ROOT / "configs"
REAL = ROOT / "tests" / "data" / "real"
TRUTH = dict(bj.SOLAR_CELL_SEED)
slow = pytest.mark.slow
CONTRACT = ("parameters", "chi2", "chi2_reduced", "dof", "converged", "message", "n_iterations", "wall_s")


@pytest.fixture(scope="module")
def example_frame(tmp_path_factory):
    """The example set (64 x 48 coarse camera, solar cell at 20 deg, footprint w = 25/8 px) reduced."""
    (path,) = reduce_measurement_set(DATA / "example_set" / "manifest.toml", tmp_path_factory.mktemp("reduced"),
                                     correct_nonlinearity=True)
    return path


TINY = """
precision = "float64"
[data]
frames = ["{frame}"]
footprint_w_px = 3.125
sigma = "noise"
sigma_floor = 0.0068
max_sigma_rel = 0.1
[model]
preset = "solar_cell"
[params]
m1 = {{ value = 2.3e-4, lower = 1e-5, upper = 1e-3 }}
rho_s1 = 0.02
[fit]
{fit}
[output]
figures = {figures}
"""


def _tiny(tmp_path, frame, fit="", figures="true") -> Path:
    return write_config(tmp_path, TINY, "tiny.toml", frame=Path(frame).as_posix(), fit=fit, figures=figures)


def test_fit_cli_writes_the_result_contract_and_figures(tmp_path, example_frame, capsys):
    out = tmp_path / "out"
    assert main(["fit", str(_tiny(tmp_path, example_frame)), "--out", str(out)]) == 0
    doc = json.loads((out / "result.json").read_text())
    for k in CONTRACT:
        assert k in doc, k
    assert doc["converged"] is True and isinstance(doc["message"], str) and doc["n_iterations"] > 0
    assert doc["dof"] == doc["n_points"] - 2 and doc["n_free"] == 2
    assert doc["chi2_reduced"] == pytest.approx(doc["chi2"] / doc["dof"])
    m1 = doc["parameters"]["m1"]
    assert set(m1) >= {"value", "sigma", "unit", "free"} and m1["free"] is True and m1["unit"] == "1"
    assert m1["value"] == pytest.approx(TRUTH["m1"], rel=0.05)  # the truth of the example set
    assert doc["parameters"]["dtheta"] == {"value": pytest.approx(0.5), "sigma": None, "unit": "deg", "free": False,
                                           "initial": pytest.approx(0.5)}
    assert doc["instrument_function"]["convolved"] is True
    assert doc["data"][0]["name"] == "solar_cell_20deg" and doc["data"][0]["footprint"] == [21, 21]
    assert doc["wall_s"] > 0 and doc["config"].endswith("tiny.toml")
    assert (out / "fit_solar_cell_20deg.png").stat().st_size > 10_000
    assert not list(out.glob("*.tmp"))
    assert "converged" in capsys.readouterr().err


def test_a_fit_that_does_not_converge_says_so_and_exits_zero(tmp_path, capsys):
    """Two solver steps on a specular + Lambertian table: not converged, exit 0, result.json written."""
    csv = tmp_path / "gonio.csv"
    ts = np.linspace(0.0, 80.0, 41)
    f = 0.05 + 20.0 * np.exp(-(((ts - 30.0) / 4.0) ** 2))
    csv.write_text("ti,ts,f\n" + "\n".join(f"30,{t:g},{v:.6g}" for t, v in zip(ts, f)) + "\n")
    cfg = tmp_path / "tab.toml"
    cfg.write_text(textwrap.dedent("""
        [[data.tables]]
        path = "gonio.csv"
        columns = { theta_i = "ti", theta_s = "ts", brdf = "f" }
        signed_inplane = true
        [model.terms.spec]
        kind = "specular"
        distribution = "ggx"
        params = { alpha = 0.3, rho_s = 0.5, n = 1.5 }
        [model.terms.diffuse]
        kind = "lambertian"
        params = { rho_d = 0.3 }
        [params]
        "spec.alpha" = 0.3
        "spec.rho_s" = 0.5
        "diffuse.rho_d" = 0.3
        [fit]
        first_stage = "none"
        solver_options = { max_steps = 2 }
    """))
    out = tmp_path / "out"
    assert main(["fit", str(cfg), "--out", str(out)]) == 0
    doc = json.loads((out / "result.json").read_text())
    assert doc["converged"] is False and doc["n_iterations"] <= 2
    assert "max_steps" in doc["message"] or "steps" in doc["message"]
    assert doc["parameters"]["spec.alpha"]["value"] is not None
    assert "did NOT converge" in capsys.readouterr().err
    assert (out / "fit_gonio.png").stat().st_size > 5_000  # the table overlay, titled NOT CONVERGED


def test_bad_config_and_unreadable_data_exit_2(tmp_path, example_frame, capsys):
    bad = _tiny(tmp_path, example_frame)
    bad.write_text(bad.read_text().replace("rho_s1 = 0.02", "rho_s9 = 0.02"))
    assert main(["fit", str(bad), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert "brdfjax fit: error:" in err and "params.rho_s9: unknown parameter 'rho_s9'" in err
    assert not (tmp_path / "o1" / "result.json").exists()
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"\x76\x2f\x31\x01 not really")
    assert main(["fit", str(_tiny(tmp_path, junk)), "--out", str(tmp_path / "o2")]) == 2
    assert "data.frames[0]:" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "absent.toml"), "--out", str(tmp_path / "o3")]) == 2
    assert "config file not found" in capsys.readouterr().err


def _cheap_synthetic(tmp_path: Path, cache: Path) -> Path:
    """The shipped synthetic config restricted to one frame (20 deg) and the centre peak and band, started 10-15 %
    off the truth (no auto), so that it runs in seconds."""
    text = (CONFIGS / "fit_synthetic_solar_cell.toml").read_text()
    text = text.replace("theta_i_deg = [20.0, 40.0, 60.0]", "theta_i_deg = [20.0]")
    text = text.replace("roi_deg = [-0.3, 1.15, -0.6, 0.9]", "roi_deg = [-0.3, 0.3, -0.3, 0.3]")
    text = text.replace("bin = 4", f"bin = 8\ncache_dir = \"{cache.as_posix()}\"")  # 8 x 8: seconds
    head, _, _ = text.partition("[params]")
    p = tmp_path / "cheap.toml"
    p.write_text(head + textwrap.dedent("""
        [params]
        m1 = 2.3e-4
        rho_s1 = 0.017
        rho_s3 = 330.0
        c_m = 4.4e-5
        [fit]
        [output]
        figures = false
    """))
    return p


def test_synthetic_frames_are_generated_once_and_the_fit_recovers(tmp_path):
    cache = tmp_path / "cache"
    cfg = _cheap_synthetic(tmp_path, cache)
    res = run_fit(cfg, tmp_path / "a")
    stamp = json.loads((cache / "synthetic.json").read_text())
    assert stamp["frames"] == ["ti20.exr"] and stamp["footprint_w_px"] == pytest.approx(25.0 / 8)
    mtime = (cache / "reduced" / "ti20.exr").stat().st_mtime_ns
    doc = json.loads((tmp_path / "a" / "result.json").read_text())
    assert doc["truth"]["m1"]["value"] == pytest.approx(TRUTH["m1"])
    print(f"\ncheap synthetic fit: {res.message}; chi2_reduced {res.chi2_reduced:.3f}, {res.wall_s:.1f} s")
    assert res.converged, res.message
    assert 0.8 < res.chi2_reduced < 1.3
    for k in ("m1", "rho_s1", "rho_s3", "c"):
        assert abs(res.value(k) - TRUTH[k]) < 3.5 * res.sigma(k), k
    assert res.value("m1") == pytest.approx(TRUTH["m1"], rel=0.05)
    job = build_fit_job(load_fit_config(cfg), work_dir=tmp_path / "b")  # reuses the cached frames
    assert any("reused" in n for n in job.notes)
    assert (cache / "reduced" / "ti20.exr").stat().st_mtime_ns == mtime
    # a changed seed regenerates
    cfg.write_text(cfg.read_text().replace("seed = 2026", "seed = 2027"))
    job = build_fit_job(load_fit_config(cfg), work_dir=tmp_path / "c")
    assert any("generated" in n for n in job.notes)
    assert (cache / "reduced" / "ti20.exr").stat().st_mtime_ns != mtime


@pytest.mark.parametrize("n", [pytest.param(1, marks=slow)])
def test_shipped_synthetic_config_recovers_the_seed_parameters(tmp_path, n):
    """configs/fit_synthetic_solar_cell.toml through the CLI (a few minutes on a loaded 2-core box: slow-gated)."""
    out = tmp_path / "fit"
    assert main(["fit", str(CONFIGS / "fit_synthetic_solar_cell.toml"), "--out", str(out)]) == 0
    doc = json.loads((out / "result.json").read_text())
    p = doc["parameters"]
    print("\nshipped synthetic fit:", doc["message"], "chi2_reduced", doc["chi2_reduced"], "wall", doc["wall_s"])
    assert doc["converged"] and 0.8 < doc["chi2_reduced"] < 1.3
    assert p["a"]["value"] == pytest.approx(TRUTH["a"], rel=0.01)
    assert p["m1"]["value"] == pytest.approx(TRUTH["m1"], rel=0.05)
    assert p["m2"]["value"] == pytest.approx(TRUTH["m2"], rel=0.05)
    assert abs(p["dtheta"]["value"] - np.degrees(TRUTH["dtheta"])) < 0.05
    assert abs(p["dphi0"]["value"] - np.degrees(TRUTH["dphi0"])) < 0.05
    for t in (20, 40, 60):
        assert abs(p[f"phi_ref[ti{t}]"]["value"]) < 0.05
    assert len(list(out.glob("fit_ti*.png"))) == 3


#: The shipped real-data configs (the best physically based model per material of
#: experiments/real_data_fits.py, started from its fitted values) through the CLI; the Cornell Krylon fit
#: runs by default, MERL and Cayman with --slow.  Bounds: today's log-RMS of the single
#: microfacet lobe + Lambertian (1.17, 0.48, 1.32) overall, and per incident angle.
REAL_CASES = [
    pytest.param("fit_merl_aluminium.toml", 1.17, 2.0, marks=slow, id="merl_aluminium"),
    pytest.param("fit_cornell_krylon_blue.toml", 0.48, 1.5, id="cornell_krylon_blue"),
    pytest.param("fit_cornell_cayman.toml", 1.32, 3.5, marks=slow, id="cornell_cayman"),
]


@pytest.mark.parametrize("config, overall, per_angle", REAL_CASES)
def test_real_data_configs_fit_through_the_cli(tmp_path, config, overall, per_angle):
    out = tmp_path / "out"
    assert main(["fit", str(CONFIGS / config), "--out", str(out), "--no-figures"]) == 0
    doc = json.loads((out / "result.json").read_text())
    assert doc["converged"], doc["message"]
    assert doc["covariance_absolute"] is False  # no uncertainties in the files
    widths = {k: v for k, v in doc["parameters"].items() if k.endswith((".alpha", ".m", ".sigma"))}
    assert widths and all(1e-4 < w["value"] < 1.0 for w in widths.values()), widths
    (block,) = doc["blocks"]
    assert block["log_rms"] < overall
    per = {g["theta_i_deg"]: g["log_rms"] for g in block["groups"]}
    print(f"\n{config}: log-RMS {block['log_rms']:.3f}; per theta_i:", {k: round(v, 3) for k, v in per.items()})
    assert max(per.values()) < per_angle
