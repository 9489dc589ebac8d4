"""Problem fingerprints of resumable artefacts (issue 16): a resume of another problem is refused, naming the difference.

For ``brdfjax sample`` (chain.h5) and ``brdfjax capture`` (manifest.toml): a
changed prior, data file, grid and sigma setting (sample), a changed
measurement, exposure list, sample model and seed (capture) are each refused
with exit 2 and a message naming the component; an unchanged resume is
bit-identical to an uninterrupted run; a run that fails before its first step
leaves no chain file; ``capture --resume`` into an empty folder is refused.
"""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from helpers import write_config

from brdfjax.cli import main
from brdfjax.io.fingerprint import FingerprintMismatch, array_digest, check_resume, compare, file_digest

DATA = Path(__file__).resolve().parents[1] / "data"

TINY = """
precision = "float64"
[data]
frames = ["{frame}"]
footprint_w_px = 0.0
sigma = "noise"
sigma_floor = {floor}
max_sigma_rel = 0.1
step = {step}
[model]
preset = "solar_cell"
[params]
m1 = {{ value = 2.0e-4, lower = 1e-5, upper = 1e-3 }}
rho_s1 = 0.015
[output]
figures = false
[nuisance]
enabled = false  # two free parameters: these tests are about the fingerprint
[sample]
n_walkers = 8
n_steps = 20
seed = 4
fit_result = "start.json"
predictive_draws = 0
[sample.priors]
rho_s1 = {prior}
"""
START = {"parameters": {"m1": {"value": 2.0e-4, "sigma": 2e-7, "unit": "1", "free": True},
                        "rho_s1": {"value": 0.015, "sigma": 5e-5, "unit": "1", "free": True}}}
UNIFORM = '{ kind = "uniform", lower = 0.0, upper = 0.1 }'


def test_fingerprint_helpers_name_what_differs(tmp_path):
    a = {"priors.x": "uniform[0, 1]", "data[f].brdf": array_digest(np.ones(3)), "n": 1}
    b = {"priors.x": "normal(0, 1)", "data[f].brdf": array_digest(np.ones(3) * 2), "n": 1.0, "new": 2}
    diffs = compare(a, b)
    assert diffs == [
        f"data[f].brdf: content differs ({a['data[f].brdf']} -> {b['data[f].brdf']})",
        "new: absent from the recorded problem, now 2",
        "priors.x: 'uniform[0, 1]' -> 'normal(0, 1)'",
    ]
    with pytest.raises(FingerprintMismatch, match=r"x\.h5 belongs to another problem .*3 difference\(s\)") as e:
        check_resume("x.h5", a, b)
    assert e.value.differences == diffs and e.value.exit_code == 2
    check_resume("x.h5", a, dict(a))  # the same problem: no error
    p = tmp_path / "f.bin"
    p.write_bytes(b"abc")
    assert file_digest(p) == "sha256:ba7816bf8f01cfea"  # sha256("abc"), first 16 hex digits


@pytest.fixture(scope="module")
def frame_file(tmp_path_factory):
    from brdfjax.instrument.reduce import reduce_measurement_set

    (path,) = reduce_measurement_set(DATA / "example_set" / "manifest.toml", tmp_path_factory.mktemp("reduced"),
                                     correct_nonlinearity=True)
    return path


def _cfg(folder: Path, frame: Path, *, prior=UNIFORM, floor=0.0068, step=1) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "start.json").write_text(json.dumps(START))
    return write_config(folder, TINY, "tiny.toml", frame=frame.as_posix(), prior=prior, floor=floor, step=step)


def _chain(out: Path) -> np.ndarray:
    from brdfjax.sample import read_chain

    return read_chain(out / "chain.h5").get_chain()


def test_sample_resume_refuses_another_problem_and_names_it(tmp_path, frame_file, capsys):
    from brdfjax.instrument.reduce import read_reduced_frame, write_reduced_frame

    frame = tmp_path / "data" / frame_file.name
    frame.parent.mkdir()
    shutil.copy(frame_file, frame)
    cfg = _cfg(tmp_path / "c", frame)
    run = ["--no-progress", "--no-figures"]
    assert main(["sample", str(cfg), "--out", str(tmp_path / "full"), "--steps", "10", *run]) == 0
    assert main(["sample", str(cfg), "--out", str(tmp_path / "part"), "--steps", "4", *run]) == 0
    first = _chain(tmp_path / "part")
    capsys.readouterr()

    def refused(cfg_path: Path, *names: str) -> None:
        before = (tmp_path / "part" / "chain.h5").read_bytes()
        assert main(["sample", str(cfg_path), "--out", str(tmp_path / "part"), "--resume", *run]) == 2
        err = capsys.readouterr().err
        assert "chain.h5 belongs to another problem and cannot be resumed" in err and "Traceback" not in err
        for n in names:
            assert n in err, (n, err)
        assert (tmp_path / "part" / "chain.h5").read_bytes() == before  # left untouched

    # a changed prior (the issue's case: uniform[0, 0.1] -> normal(0.02, 1e-5))
    refused(_cfg(tmp_path / "prior", frame, prior='{ kind = "normal", mu = 0.02, sigma = 1e-5 }'),
                  "priors.rho_s1: 'uniform[0, 0.1] 1' -> 'normal(mu=0.02, sigma=1e-05) 1'")
    # a changed sigma setting: the floor, and through it every uncertainty
    refused(_cfg(tmp_path / "floor", frame, floor=0.01), "config.data.sigma_floor: 0.0068 -> 0.01",
            "data[solar_cell_20deg].sigma_rel: content differs")
    # a changed grid
    refused(_cfg(tmp_path / "grid", frame, step=2), "config.data.step: 1 -> 2", "data[solar_cell_20deg].grid:")
    # a changed data file (same name, other values)
    fr = read_reduced_frame(frame)
    fr.brdf[:] = fr.brdf * np.float32(1.01)
    write_reduced_frame(frame, fr)
    refused(cfg, f"file[{frame.as_posix()}]: content differs", "data[solar_cell_20deg].brdf: content differs")
    # the original data again: the unchanged resume continues bit-identically
    shutil.copy(frame_file, frame)
    assert main(["sample", str(cfg), "--out", str(tmp_path / "part"), "--resume", "--steps", "10", *run]) == 0
    resumed, full = _chain(tmp_path / "part"), _chain(tmp_path / "full")
    assert resumed.shape == (10, 8, 2) and np.array_equal(resumed[:4], first) and np.array_equal(resumed, full)


def test_sample_failing_before_its_first_step_leaves_no_chain(tmp_path, frame_file, capsys):
    cfg = _cfg(tmp_path / "c", frame_file, prior='{ kind = "uniform", lower = 0.5, upper = 0.6 }')
    out = tmp_path / "o"
    assert main(["sample", str(cfg), "--out", str(out), "--no-progress"]) == 2
    assert "prior excludes the starting point: 'rho_s1'" in capsys.readouterr().err
    assert not (out / "chain.h5").exists()
    # so a clean rerun with the fixed prior starts a new chain (no --resume into a 0-step chain)
    assert main(["sample", str(_cfg(tmp_path / "c", frame_file)), "--out", str(out), "--no-progress", "--no-figures",
                 "--steps", "3"]) == 0
    assert _chain(out).shape == (3, 8, 2)


CAPTURE = """
seed = {seed}
[instrument]
kind = "simulated"
bin = 8
shape = [48, 64]
camera_seed = 3
[model]
preset = "solar_cell"
{model_extra}
[exposure]
exposures_ms = {exposures}
n_frames = 8
[beam]
nd = "auto"
[[measurements]]
name = "ti20"
theta_i_deg = {theta}
[capture]
live = "off"
"""


def _capture_cfg(tmp_path: Path, name: str, *, seed=7, theta=20.0, exposures="[1, 10, 100, 1000]", model_extra="") -> Path:
    p = tmp_path / name
    p.write_text(CAPTURE.format(seed=seed, theta=theta, exposures=exposures, model_extra=model_extra))
    return p


def test_capture_resume_refuses_another_problem_and_an_empty_folder(tmp_path, capsys):
    base = _capture_cfg(tmp_path, "base.toml")
    out = tmp_path / "set"
    # --resume into an empty (or missing) folder: refused like sample's
    assert main(["capture", str(base), "--out", str(out), "--resume", "--no-progress"]) == 2
    assert "there is no capture to resume" in capsys.readouterr().err and not (out / "manifest.toml").exists()
    assert main(["capture", str(base), "--out", str(out), "--no-progress"]) == 0
    state = tomllib.loads((out / "manifest.toml").read_text())["capture"]
    assert state["fingerprint"]["measurements[0].theta_i_deg"] == 20.0 and state["status"] == "complete"
    files = {p.name: p.read_bytes() for p in out.glob("*.exr")}
    capsys.readouterr()
    # a rerun into the finished capture: refused (2), not an internal error
    assert main(["capture", str(base), "--out", str(out), "--no-progress"]) == 2
    assert "exists: pass --resume to continue that capture" in capsys.readouterr().err
    cases = {
        "theta.toml": (dict(theta=25.0), "measurements[0].theta_i_deg: 20.0 -> 25.0"),
        "exp.toml": (dict(exposures="[1, 10, 100]"), "exposure.exposures_ms: '[1.0, 10.0, 100.0, 1000.0]' -> '[1.0, 10.0, 100.0]'"),
        "seed.toml": (dict(seed=8), "seed: 7 -> 8"),
        "model.toml": (dict(model_extra="params = { m1 = 3e-4 }"), "model.params:"),
    }
    for name, (kw, named) in cases.items():
        assert main(["capture", str(_capture_cfg(tmp_path, name, **kw)), "--out", str(out), "--resume",
                     "--no-progress"]) == 2, name
        err = capsys.readouterr().err
        assert "manifest.toml belongs to another problem" in err and named in err and "Traceback" not in err, err
    # the same config: nothing to do, nothing rewritten
    assert main(["capture", str(base), "--out", str(out), "--resume", "--no-progress"]) == 0
    assert "already complete" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.glob("*.exr")} == files
