"""One exit-code contract for every command (issue 16, :mod:`brdfjax.runtime.errors`).

0 ran, 2 bad input or refused (the message on stderr, no traceback), 130
interrupted, 1 only for an internal error (the traceback and where to report
it).  ``BAD_INPUTS`` lists the bad-input cases, command by command (the
issue's: a sample file given as the beam, ``--nd abc``, an interlock refusal,
a resume of another problem, a rerun into a finished capture, ``--out``
pointing at a file or an unwritable place); each runs in-process through
``brdfjax.cli.main`` and must exit 2 with its message and no traceback.
"""

from __future__ import annotations

import dataclasses
import io
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import write_config

from brdfjax.cli import COMMANDS, main
from brdfjax.runtime.errors import REPORT_TO, InputError, run_command

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parents[1] / "data"
FIT_CFG = ROOT / "configs" / "fit_synthetic_solar_cell.toml"  # only read as far as each case needs
OBSERVE_CFG = ROOT / "configs" / "observe_v2mini_slingshot.toml"
SKYGAP_CFG = ROOT / "configs" / "skygap_v2mini_slingshot.toml"

FIT = """
precision = "float64"
[data]
frames = ["{frame}"]
footprint_w_px = 0.0
sigma = "noise"
{data_extra}
[model]
preset = "solar_cell"
[params]
m1 = {{ value = 2.0e-4, lower = 1e-5, upper = 1e-3 }}
rho_s1 = 0.015
{params_extra}
[output]
figures = false
{sample}
{diagnose}
"""
SAMPLE = """[sample]
n_walkers = 32  # the frame came through the instrument: 2 parameters + its nuisance parameters
n_steps = 3
fit_result = "start.json"
predictive_draws = 0
"""
START = '{"parameters": {"m1": {"value": 2e-4, "sigma": 2e-7, "unit": "1", "free": true}, ' \
        '"rho_s1": {"value": 0.015, "sigma": 5e-5, "unit": "1", "free": true}}}'

CAPTURE = """
seed = 7
[instrument]
kind = "simulated"
bin = 8
shape = [48, 64]
camera_seed = 3
[model]
preset = "solar_cell"
[exposure]
exposures_ms = [1, 10, 100, 1000]
n_frames = 8
[beam]
nd = "{beam_nd}"
[[measurements]]
name = "ti20"
theta_i_deg = 20.0
nd = "{nd}"
[capture]
live = "off"
"""


@pytest.fixture(scope="module")
def w(tmp_path_factory):
    """A workspace: a plain file, the example set and variants of it, a reduced frame, fit/capture configs."""
    from brdfjax.instrument.reduce import reduce_measurement_set
    from brdfjax.io.raw import read_raw_exr, write_raw_exr

    root = tmp_path_factory.mktemp("exit")
    (root / "a_file.txt").write_text("not a folder")
    shutil.copytree(DATA / "example_set", root / "set")
    # the sample's file given as the beam
    shutil.copytree(DATA / "example_set", root / "beam_is_sample")
    m = root / "beam_is_sample" / "manifest.toml"
    m.write_text(m.read_text().replace('file = "beam.exr"', 'file = "solar_cell_20deg.exr"'))
    # a manifest naming a missing file
    shutil.copytree(DATA / "example_set", root / "missing")
    (root / "missing" / "solar_cell_20deg_background.exr").unlink()
    # every exposure of the sample saturated everywhere
    shutil.copytree(DATA / "example_set", root / "saturated")
    p = root / "saturated" / "solar_cell_20deg.exr"
    st = read_raw_exr(p)
    fs = st.attrs.full_scale
    write_raw_exr(p, st.attrs, [dataclasses.replace(e, counts=np.full_like(e.counts, fs)) for e in st.exposures])
    (frame,) = reduce_measurement_set(root / "set" / "manifest.toml", root / "reduced", correct_nonlinearity=True)
    (root / "start.json").write_text(START)

    def fit_cfg(name: str, data_extra="", params_extra="", sample=None, diagnose="", frame=frame) -> str:
        return str(write_config(root, FIT, name, frame=Path(frame).as_posix(), data_extra=data_extra,
                                params_extra=params_extra, sample="" if sample is None else SAMPLE + sample,
                                diagnose=diagnose))

    def capture_cfg(name: str, beam_nd="auto", nd="auto") -> str:
        return str(write_config(root, CAPTURE, name, beam_nd=beam_nd, nd=nd))

    fit_cfg("fit.toml")
    fit_cfg("fit_badkey.toml", data_extra="sigma_flor = 0.01")
    fit_cfg("fit_nofile.toml", frame=root / "nope.exr")
    fit_cfg("fit_bounds.toml", params_extra="n1 = { value = 3.6, lower = 5.0, upper = 2.0 }")
    fit_cfg("diag_heldout.toml", diagnose='[diagnose]\nheldout = ["ti99"]')
    fit_cfg("samp.toml", sample="")
    fit_cfg("sample_prior.toml", sample='[sample.priors]\nbogus = { kind = "uniform", lower = 0.0, upper = 1.0 }')
    fit_cfg("sample_fixed.toml", sample='[sample.priors]\nm2 = { kind = "uniform", lower = 0.0, upper = 1.0 }')
    capture_cfg("cap.toml")
    capture_cfg("cap_interlock.toml", beam_nd="1.0")
    capture_cfg("cap_nd.toml", nd="abc")
    (root / "sim_bad.toml").write_text("[grid]\nstepp = 2\n")
    (root / "inst_bad.toml").write_text("[camera]\nbogus = 1\n")
    (root / "garbage_chain").mkdir()
    (root / "garbage_chain" / "chain.h5").write_bytes(b"garbage" * 100)
    (root / "finished").mkdir()
    assert main(["capture", str(root / "cap.toml"), "--out", str(root / "finished"), "--no-progress", "--quiet"]) == 0
    return root


#: (command, arguments with {w} for the workspace, a piece of the expected message).  Every case exits 2.
BAD_INPUTS = [
    # simulate
    ("simulate", ["{w}/no_such.toml", "--out", "{w}/o"], "no_such.toml"),
    ("simulate", ["{w}/sim_bad.toml", "--out", "{w}/o"], "stepp"),
    ("simulate", ["--out", "{w}/a_file.txt", "--no-figures"], "is a file, not a folder"),
    ("simulate", ["--out", "/proc/x", "--no-figures"], "cannot create anything in /proc"),
    ("simulate", ["--out", "{w}/a_file.txt/sub", "--no-figures"], "is a file, so the folder cannot be created"),
    ("simulate", ["--out", "{w}/o", "--step", "0"], "argument --step: must be a positive integer, got 0"),
    ("simulate", ["--out", "{w}/o", "--precision", "float16"], "invalid choice: 'float16'"),
    # synthesize
    ("synthesize", ["--out", "{w}/syn", "--nd", "abc"], "--nd 'abc'"),
    ("synthesize", ["--out", "{w}/syn", "--without", "bogus"], "unknown effect(s) ['bogus']"),
    ("synthesize", ["--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("synthesize", ["--out", "/proc/x"], "cannot create anything in /proc"),
    ("synthesize", ["--out", "{w}/syn", "--instrument", "{w}/no_such.toml"], "no_such.toml"),
    ("synthesize", ["--out", "{w}/syn", "--instrument", "{w}/inst_bad.toml"], "camera: unknown key"),
    ("synthesize", ["--out", "{w}/syn", "--seed", "x"], "invalid int value: 'x'"),
    # reduce
    ("reduce", ["{w}/no_such_set", "--out", "{w}/r"], "no_such_set: no such manifest or folder"),
    ("reduce", ["{w}/set", "--out", "{w}/r", "--step", "0"], "argument --step: must be a positive integer, got 0"),
    ("reduce", ["{w}/set", "--out", "{w}/r", "--merge", "replacement", "--correct-nonlinearity"], "needs --merge weighted"),
    ("reduce", ["{w}/set", "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("reduce", ["{w}/set", "--out", "/proc/x"], "cannot create anything in /proc"),
    ("reduce", ["{w}/beam_is_sample", "--out", "{w}/r_bs"], "solar_cell_20deg.exr"),
    ("reduce", ["{w}/missing", "--out", "{w}/r_m"], "solar_cell_20deg_background.exr"),
    ("reduce", ["{w}/saturated", "--out", "{w}/r_sat", "--no-figures"], "saturated in every exposure"),
    ("reduce", ["{w}/set", "--out", "{w}/set"], "would overwrite an input"),
    # fit
    ("fit", ["{w}/no_such.toml", "--out", "{w}/f"], "no_such.toml"),
    ("fit", ["{w}/fit_badkey.toml", "--out", "{w}/f"], "sigma_flor"),
    ("fit", ["{w}/fit_nofile.toml", "--out", "{w}/f"], "nope.exr"),
    ("fit", ["{w}/fit_bounds.toml", "--out", "{w}/f"], "n1"),
    ("fit", [str(FIT_CFG), "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("fit", [str(FIT_CFG), "--out", "/proc/x"], "cannot create anything in /proc"),
    # diagnose
    ("diagnose", ["{w}/fit.toml", "--out", "{w}/d", "--effects", "bogus"], "unknown effect(s) ['bogus']"),
    ("diagnose", ["{w}/diag_heldout.toml", "--out", "{w}/d"], "diagnose.heldout"),
    ("diagnose", ["{w}/no_such.toml", "--out", "{w}/d"], "no_such.toml"),
    ("diagnose", ["{w}/fit.toml", "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("diagnose", ["{w}/fit.toml", "--out", "/proc/x"], "cannot create anything in /proc"),
    # sample
    ("sample", ["{w}/samp.toml", "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("sample", ["{w}/samp.toml", "--out", "/proc/x"], "cannot create anything in /proc"),
    ("sample", ["{w}/samp.toml", "--out", "{w}/s1", "--walkers", "3"], "n_walkers = 3 is fewer than twice"),
    ("sample", ["{w}/samp.toml", "--out", "{w}/s2", "--steps", "0"], "argument --steps: must be a positive integer"),
    ("sample", ["{w}/samp.toml", "--out", "{w}/s3", "--resume"], "there is no chain to resume"),
    ("sample", ["{w}/sample_prior.toml", "--out", "{w}/s4"], "prior on unknown parameter"),
    ("sample", ["{w}/sample_fixed.toml", "--out", "{w}/s5"], "prior on 'm2', which is held fixed"),
    ("sample", ["{w}/samp.toml", "--out", "{w}/garbage_chain", "--resume"], "the chain file cannot be read"),
    # observe
    ("observe", ["{w}/no_such.toml", "--out", "{w}/o"], "no_such.toml: observe config not found"),
    ("observe", [str(OBSERVE_CFG), "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("observe", [str(OBSERVE_CFG), "--out", "/proc/x"], "cannot create anything in /proc"),
    # skygap
    ("skygap", ["{w}/no_such.toml", "--out", "{w}/o"], "no_such.toml: skygap config not found"),
    ("skygap", [str(SKYGAP_CFG), "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("skygap", [str(SKYGAP_CFG), "--out", "/proc/x"], "cannot create anything in /proc"),
    # capture
    ("capture", ["{w}/no_such.toml", "--out", "{w}/c"], "no_such.toml"),
    ("capture", ["{w}/cap_nd.toml", "--out", "{w}/c"], "measurements[0].nd"),
    ("capture", ["{w}/cap_interlock.toml", "--out", "{w}/c_il"], "interlock: refusing the beam measurement"),
    ("capture", ["{w}/cap.toml", "--out", "{w}/c_empty", "--resume"], "there is no capture to resume"),
    ("capture", ["{w}/cap.toml", "--out", "{w}/finished"], "exists: pass --resume"),
    ("capture", ["{w}/cap.toml", "--out", "{w}/a_file.txt"], "is a file, not a folder"),
    ("capture", ["{w}/cap.toml", "--out", "/proc/x"], "cannot create anything in /proc"),
]


def _run(argv: list[str], capsys) -> tuple[int, str]:
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse's usage errors
        rc = e.code
    return rc, capsys.readouterr().err


def test_the_suite_covers_every_command_with_enough_cases():
    assert len(BAD_INPUTS) >= 40
    assert {c for c, _, _ in BAD_INPUTS} >= set(COMMANDS) - {"lightcurve", "batch"}


@pytest.mark.parametrize("command", sorted({c for c, _, _ in BAD_INPUTS}))
def test_bad_inputs_exit_2_with_the_message_and_no_traceback(command, w, capsys):
    failures = []
    for cmd, args, expected in BAD_INPUTS:
        if cmd != command:
            continue
        argv = [cmd, *[a.replace("{w}", str(w)) for a in args]]
        rc, err = _run(argv, capsys)
        if rc != 2 or expected not in err or "Traceback" in err:
            failures.append(f"{' '.join(argv)}: exit {rc}, expected 2 and {expected!r}; stderr: {err[-600:]}")
    assert not failures, "\n".join(failures)


def test_nothing_is_written_by_refused_runs(w):
    for folder in ("o", "syn", "r", "r_bs", "r_m", "f", "d", "s1", "s2", "s3", "s4", "s5", "c", "c_il", "c_empty"):
        p = w / folder
        assert not p.exists() or not any(f.suffix in (".exr", ".h5", ".json", ".png") for f in p.rglob("*")), folder
    # the saturated set: no frame, no summary, no staging file left
    assert not (w / "r_sat").exists() or not list((w / "r_sat").iterdir())


def test_synthesize_bad_nd_fails_fast_with_nothing_written(tmp_path, capsys):
    t0 = time.perf_counter()
    rc, err = _run(["synthesize", "--out", str(tmp_path / "syn"), "--nd", "abc"], capsys)
    dt = time.perf_counter() - t0
    assert rc == 2 and "'abc' is not an optical density" in err
    assert dt < 1.0, dt
    assert not (tmp_path / "syn").exists()


def test_interrupt_is_130_and_an_internal_error_is_1_with_where_to_report(capsys):
    def interrupted():
        raise KeyboardInterrupt

    def bug():
        raise ZeroDivisionError("a bug")

    def refused():
        raise InputError("bad.toml: key 'x': expected a number")

    err = io.StringIO()
    assert run_command("brdfjax x", interrupted, stderr=err) == 130 and "interrupted" in err.getvalue()
    err = io.StringIO()
    assert run_command("brdfjax x", bug, stderr=err) == 1
    text = err.getvalue()
    assert "Traceback" in text and "ZeroDivisionError: a bug" in text and "internal error" in text and REPORT_TO in text
    err = io.StringIO()
    assert run_command("brdfjax x", refused, stderr=err) == 2
    assert err.getvalue() == "brdfjax x: error: bad.toml: key 'x': expected a number\n"
    assert run_command("brdfjax x", lambda: None) == 0
    # through main: a subcommand interrupted mid-run exits 130
    import brdfjax.cli as cli

    original = cli.COMMANDS["simulate"]
    try:
        cli.COMMANDS["simulate"] = dataclasses.replace(original, run=lambda args: interrupted())
        assert main(["simulate", "--out", "unused"]) == 130
    finally:
        cli.COMMANDS["simulate"] = original
    assert "brdfjax simulate: interrupted" in capsys.readouterr().err


def test_partial_saturation_is_counted_and_reported(w, capsys):
    import json

    out = w / "r_ok"
    assert main(["reduce", str(w / "set"), "--out", str(out), "--no-figures"]) == 0
    err = capsys.readouterr().err
    (fr,) = json.loads((out / "summary.json").read_text())["frames"]
    assert fr["saturated_pixels"] >= 0 and fr["partly_saturated_pixels"] > 0
    assert f"{fr['partly_saturated_pixels']} pixel(s) saturated in some exposures" in err
    assert fr["warnings"] and fr["usable_pixels"] > 0


def test_sample_refuses_too_few_walkers_before_reading_any_data(w, capsys):
    # the config's free parameters bound the sampled ones from below: refused before the out folder or the data
    rc, err = _run(["sample", str(w / "samp.toml"), "--out", str(w / "s_early"), "--walkers", "2"], capsys)
    assert rc == 2 and "n_walkers = 2 is fewer than twice the 2 free parameters" in err
    assert not (w / "s_early").exists()
