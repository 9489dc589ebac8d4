"""``brdfjax simulate`` end to end on small decimated grids."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import brdfjax as bj
from brdfjax import __version__
from brdfjax.cli import COMMANDS, main
from brdfjax.io import CHANNELS, read_frame_exr

ROOT = Path(__file__).resolve().parents[2]

# Every 16th pixel of a 321 x 321 window about the alignment pixel (0, 0), which is on the
# grid; the offset peak (near (731, 684) at 20 deg) lies outside, so the maximum is the
# centre peak of Fig 33.
SMALL = """
precision = "float32"
[grid]
step = 16
roi = [-160, 160, -160, 160]
[model]
preset = "solar_cell"
[[frames]]
name = "ti20"
theta_i_deg = 20.0
[[frames]]
name = "ti60"
theta_i_deg = 60.0
"""


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    config = root / "small.toml"
    config.write_text(SMALL)
    out = root / "out"
    rc = main(["simulate", str(config), "--out", str(out)])
    return rc, config, out


def test_simulate_writes_exr_png_summary(small_run):
    rc, _, out = small_run
    assert rc == 0
    assert sorted(os.listdir(out)) == ["summary.json", "ti20.exr", "ti20.png", "ti60.exr", "ti60.png"]
    for stem in ("ti20", "ti60"):
        assert (out / f"{stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_summary_times_are_wall_spans_within_the_total(small_run):
    _, _, out = small_run
    s = json.loads((out / "summary.json").read_text())
    for f in s["frames"]:
        # the EXR and PNG are written in parallel threads: the frame's times are spans, not sums
        assert f["wall_s"] <= s["wall_s"] + 1e-3 and f["write_s"] <= f["wall_s"] + 1e-3
        assert set(f["file_s"]) == {"exr", "png"} and max(f["file_s"].values()) <= f["write_s"] + 1e-3


def test_term_labels_name_what_a_frame_shows():
    from brdfjax.plotting import term_labels

    assert term_labels(bj.solar_cell()) == {"center": "centre peak (center)", "offset": "offset peak (offset)",
                                            "bars": "diffraction bars (bars)"}


def test_exr_channels_and_attributes(small_run):
    _, _, out = small_run
    data = read_frame_exr(out / "ti20.exr")
    for name in CHANNELS:
        arr = getattr(data, name)
        assert arr.dtype == np.float32 and arr.shape == (21, 21)
    a = data.attrs
    assert a["theta_i"] == np.deg2rad(20.0) and a["theta_c"] == np.deg2rad(20.0)  # exact doubles
    assert a["phi_ref"] == 0.0 and a["wavelength"] == pytest.approx(632.8e-9, rel=1e-15)
    assert a["R"] == 0.325 and a["pixel_pitch"] == pytest.approx(5.5e-6, rel=1e-15)
    assert a["step"] == 16 and a["roi"] == (-160, 160, -160, 160)
    assert a["model"] == "preset solar_cell" and a["brdfjax_version"] == __version__
    # Geometry at the centre pixel (row 10, column 10): theta_s = theta_i, phi_s = 180 deg, Table 3 solid angle.
    assert np.rad2deg(data.theta_s[10, 10]) == pytest.approx(20.0, abs=1e-4)
    assert np.rad2deg(data.phi_s[10, 10]) == pytest.approx(180.0, abs=1e-4)
    assert data.omega[10, 10] == pytest.approx(2.864e-10, rel=1e-3)
    assert np.all(data.brdf >= 0) and np.all(np.isfinite(data.brdf))


def test_summary_numbers_match_fig33(small_run):
    _, config, out = small_run
    s = json.loads((out / "summary.json").read_text())
    assert s["config"] == str(config) and s["precision"] == "float32" and s["grid_shape"] == [21, 21]
    f20, f60 = s["frames"]
    # Seed Fig 33: maximum near the centre peak 1.11e4 (20 deg) and 3.91e4 (60 deg) sr^-1.
    assert f20["max_brdf"] == pytest.approx(1.11e4, rel=0.01)
    assert f60["max_brdf"] == pytest.approx(3.91e4, rel=0.01)
    for f in (f20, f60):
        assert f["max_pixel"] == [0, 0]
        assert set(f["term_max"]) == {"center", "offset", "bars"}
        assert f["term_max"]["bars"]["value"] == pytest.approx(300.0, rel=1e-4)
        assert f["term_max"]["bars"]["pixel"] == [0, 0]
        assert f["grid_shape"] == [21, 21] and f["precision"] == "float32" and f["config"] == str(config)
        assert f["wall_s"] > 0 and f["files"] == {"exr": f"{f['name']}.exr", "png": f"{f['name']}.png"}
    assert f20["max_theta_s_deg"] == pytest.approx(20.0, abs=1e-4)
    # The max equals the EXR's max (same numbers, float32).
    data = read_frame_exr(out / "ti60.exr")
    assert float(data.brdf.max()) == pytest.approx(f60["max_brdf"], rel=1e-7)


def test_step_flag_overrides_config(small_run, tmp_path, capsys):
    _, config, _ = small_run
    out = tmp_path / "o"
    assert main(["simulate", str(config), "--out", str(out), "--step", "32", "--no-figures"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["step"] == 32 and s["grid_shape"] == [11, 11]
    assert sorted(os.listdir(out)) == ["summary.json", "ti20.exr", "ti60.exr"]
    err = capsys.readouterr().err
    assert "done ti20" in err and "done ti60" in err  # one status line per frame


@pytest.mark.parametrize(
    "text, key, expect",
    [
        (SMALL.replace('theta_i_deg = 60.0', 'theta_i_deg = 95.0'), "frames[1].theta_i_deg", "0 <= theta_i_deg < 90"),
        (SMALL.replace("step = 16", "stride = 16"), "grid.stride", "allowed keys"),
        (SMALL.replace('"solar_cell"', '"solar"'), "model.preset", "known: kapton, mirror, polished_aluminium, solar_cell"),
        (SMALL + "[model.params]\nm1 = -1.0\n", "model.params.m1", "m > 0"),
    ],
)
def test_bad_config_exits_2_naming_file_and_key(tmp_path, capsys, text, key, expect):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    rc = main(["simulate", str(config), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(config) in err and key in err and expect in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_missing_config_exits_2(tmp_path, capsys):
    rc = main(["simulate", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "nope.toml: config file not found" in err


def test_bad_flag_value_exits_2(small_run, tmp_path, capsys):
    _, config, _ = small_run
    with pytest.raises(SystemExit) as info:  # blamed on the flag, not on the config's grid.step
        main(["simulate", str(config), "--out", str(tmp_path / "o"), "--step", "0"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --step: must be a positive integer, got 0" in err and "grid.step" not in err


def test_usage_errors(capsys):
    with pytest.raises(SystemExit) as info:
        main(["simulate"])  # --out is required
    assert info.value.code == 2 and "--out" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2
    assert "simulate" in COMMANDS


def test_default_config_when_none_given(tmp_path):
    out = tmp_path / "d"
    assert main(["simulate", "--out", str(out), "--step", "128", "--no-figures"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["config"].endswith(os.path.join("brdfjax", "data", "default.toml"))
    assert [f["name"] for f in s["frames"]] == ["ti20", "ti60"]


def test_python_m_brdfjax_float64(small_run, tmp_path):
    # A fresh process: precision = float64 flips jax_enable_x64 there, not in this test session.
    _, config, _ = small_run
    out = tmp_path / "f64"
    proc = subprocess.run(
        [sys.executable, "-m", "brdfjax", "simulate", str(config), "--out", str(out), "--precision", "float64", "--no-figures"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["precision"] == "float64"
    assert s["frames"][0]["max_brdf"] == pytest.approx(1.11e4, rel=0.01)


# --- brdfjax reduce -------------------------------------------------------------------------------

EXAMPLE_SET = Path(__file__).resolve().parents[1] / "data" / "example_set"


def test_reduce_example_set_writes_frames_with_uncertainty(tmp_path, capsys):
    import hashlib

    from brdfjax.cli import main
    from brdfjax.io import read_frame_exr

    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in EXAMPLE_SET.iterdir()}
    assert main(["reduce", str(EXAMPLE_SET / "manifest.toml"), "--out", str(tmp_path)]) == 0
    after = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in EXAMPLE_SET.iterdir()}
    assert before == after  # inputs are never modified
    fd = read_frame_exr(tmp_path / "solar_cell_20deg.exr")
    assert {"sigma_rel", "mask", "u_scatter_flux", "u_incident_flux", "u_scatter_angle", "u_solid_angle"} <= set(fd.extra)
    mask = fd.extra["mask"] > 0
    assert 0 < mask.sum() < mask.size
    assert np.all(np.isfinite(fd.brdf[mask])) and np.all(fd.extra["sigma_rel"][mask] > 0)
    summary = json.loads((tmp_path / "summary.json").read_text())
    (entry,) = summary["frames"]
    assert entry["usable_pixels"] == int(mask.sum()) and entry["png"] == "solar_cell_20deg.png"
    # The example sample is the seed solar cell at 20 deg seen by a coarse camera: its peak,
    # blurred by the beam footprint, is thousands of sr^-1.
    assert 1e3 < entry["max_brdf"] < 2e4
    assert (tmp_path / "solar_cell_20deg.png").stat().st_size > 10_000


def test_reduce_bad_manifest_exit_2(tmp_path, capsys):
    from brdfjax.cli import main

    bad = tmp_path / "manifest.toml"
    bad.write_text('[beam]\nfile = "beam.exr"\n')
    assert main(["reduce", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "brdfjax reduce: error:" in err and "manifest.toml" in err and "Traceback" not in err


def test_reduce_refuses_to_overwrite_inputs(tmp_path, capsys):
    import shutil

    from brdfjax.cli import main

    work = tmp_path / "set"
    shutil.copytree(EXAMPLE_SET, work)
    assert main(["reduce", str(work), "--out", str(work), "--no-figures"]) == 2  # a refusal (brdfjax.runtime.errors)
    assert "would overwrite an input" in capsys.readouterr().err


# --- brdfjax synthesize -> brdfjax reduce ---------------------------------------------------------

SMALL_CONFIG = """
[detector]
n_h = 64
n_v = 48
pixel_pitch_um = 44.0

[model]
preset = "solar_cell"

[[frames]]
name = "ti40"
theta_i_deg = 40.0
"""


def test_synthesize_then_reduce_round_trip(tmp_path, capsys):
    from brdfjax.cli import main
    from brdfjax.instrument.reduce import read_reduced_frame
    from brdfjax.io.raw import read_manifest, read_raw_exr

    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_CONFIG)
    assert main(["synthesize", str(cfg), "--out", str(tmp_path / "set"), "--seed", "5"]) == 0
    manifest = read_manifest(tmp_path / "set")
    assert [s.name for s in manifest.samples] == ["ti40"]
    stack = read_raw_exr(manifest.samples[0].file)
    assert [e.exposure_s for e in stack.exposures] == [1e-3, 1e-2, 1e-1, 1.0]
    # ND filters chosen by the seed's rule: nothing saturates at the shortest exposure, but it would
    # with the next-smaller stack (so the OD is the smallest that works).
    from brdfjax.instrument.nd import ND_STACKS

    full = stack.attrs.full_scale
    peak = float(stack.exposures[0].counts.max())
    assert peak < 0.9 * full
    smaller = ND_STACKS[ND_STACKS.index(stack.attrs.nd_filters) - 1]
    od_gap = stack.attrs.optical_density - sum(float(x) for x in smaller.split("+") if x)
    assert (peak - stack.attrs.black_level) * 10**od_gap > 0.8 * full
    assert main(["reduce", str(tmp_path / "set"), "--out", str(tmp_path / "red"), "--no-figures"]) == 0
    red = read_reduced_frame(tmp_path / "red" / "ti40.exr")
    # Same seeds, same instrument: the noiseless expectation the reduction should recover.
    import brdfjax as bj
    from brdfjax.instrument.synthetic import InstrumentConfig, SyntheticInstrument

    det = bj.Detector.seed(shape=(48, 64), pixel_pitch=44e-6, pixel_pitch_v=44e-6)
    ins = SyntheticInstrument(det, InstrumentConfig(camera_seed=0).for_pixel_pitch(44e-6), seed=0)
    expected = ins.expected_brdf(ins.render_brdf(bj.solar_cell(), bj.Conditions.from_degrees(40)))
    mask = red.extra["mask"] > 0
    log_err = np.log(red.brdf[mask] / expected[mask])
    z = np.abs(log_err) / red.extra["sigma_rel"][mask]
    assert mask.sum() > 500 and np.mean(z < 2) >= 0.95
    # sigma_rel is dominated by the uncancelled ND filters (the 3.0 at +-0.15 OD, ~35 %); the
    # actual error of this noise-on stack is a few percent.
    assert np.median(np.abs(log_err)) < 0.03


def test_synthesize_bad_effect_name_exit_2(tmp_path, capsys):
    from brdfjax.cli import main

    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_CONFIG)
    assert main(["synthesize", str(cfg), "--out", str(tmp_path / "set"), "--without", "stray_lite"]) == 2
    assert "unknown effect(s) ['stray_lite'] (did you mean 'stray_light'?); known:" in capsys.readouterr().err


def test_reduce_correct_nonlinearity_flag(tmp_path, capsys):
    from brdfjax.cli import main
    from brdfjax.instrument.reduce import read_reduced_frame

    assert main(["reduce", str(EXAMPLE_SET), "--out", str(tmp_path / "c"), "--no-figures", "--correct-nonlinearity"]) == 0
    assert read_reduced_frame(tmp_path / "c" / "solar_cell_20deg.exr").attrs["nonlinearity_corrected"] in (1, True)
    assert main(["reduce", str(EXAMPLE_SET), "--out", str(tmp_path / "r"), "--merge", "replacement",
                 "--correct-nonlinearity"]) == 2
    assert "needs --merge weighted" in capsys.readouterr().err


def test_synthesize_instrument_config(tmp_path, capsys):
    """Every effect's switch and parameters come from an instrument TOML; bad keys are named."""
    from brdfjax.cli import main
    from brdfjax.config import ConfigError
    from brdfjax.instrument.synthetic import InstrumentConfig, load_instrument_config
    from brdfjax.io.raw import read_raw_exr

    shipped = load_instrument_config(Path(__file__).parents[2] / "configs" / "instrument_seed.toml")

    assert shipped == InstrumentConfig()  # the shipped file spells out the defaults
    inst = tmp_path / "inst.toml"
    inst.write_text("exposures_s = [0.002, 0.02]\nn_frames = 4\n[stray_light]\nenabled = false\n")
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_CONFIG)
    assert main(["synthesize", str(cfg), "--instrument", str(inst), "--out", str(tmp_path / "s")]) == 0
    st = read_raw_exr(tmp_path / "s" / "ti40.exr")
    assert [e.exposure_s for e in st.exposures] == [0.002, 0.02] and st.exposures[0].n_frames == 4
    inst.write_text("n_frames = 0\n[footprint]\nw_pix = 3\n")
    with pytest.raises(ConfigError, match=r"footprint.w_pix: unknown key \(did you mean 'w_px'\?\); allowed keys in footprint: enabled, w_px"):
        load_instrument_config(inst)
    assert main(["synthesize", str(cfg), "--instrument", str(inst), "--out", str(tmp_path / "t")]) == 2
    assert "n_frames: Input should be greater than or equal to 1" in capsys.readouterr().err


def test_commands_without_figures_do_not_import_matplotlib():
    # matplotlib costs ~0.4 s of every process that loads it; the fit, batch and diagnose stacks import it
    # only where a figure is drawn (brdfjax.plotting, brdfjax.fit._figures)
    code = (
        "import sys, brdfjax.cli, brdfjax.fit, brdfjax.fit.config, brdfjax.cli.fit, brdfjax.batch, "
        "brdfjax.diagnose, brdfjax.plotting, brdfjax.instrument.reduce; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
