"""``brdfjax batch``: a study of tiny fits through the process pool and a local Ray instance, resumed after a kill."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import write_config

from brdfjax.batch import StudyError, load_study, run_study
from brdfjax.cli import main
from brdfjax.instrument.reduce import reduce_measurement_set
from brdfjax.io.fingerprint import FingerprintMismatch

DATA = Path(__file__).resolve().parents[1] / "data"

FIT = """
precision = "float64"
[data]
frames = ["{frame}"]
step = 2
footprint_w_px = 3.125
sigma = "noise"
sigma_floor = 0.0068
max_sigma_rel = 0.1
[model]
preset = "solar_cell"
[params]
m1 = {{ value = {m1}, lower = 1e-5, upper = 1e-3 }}
rho_s1 = 0.02
[fit]
first_stage = "none"
[output]
figures = false
"""


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    d = tmp_path_factory.mktemp("study")
    (frame,) = reduce_measurement_set(DATA / "example_set" / "manifest.toml", d / "reduced", correct_nonlinearity=True)
    jobs = []
    for i, m1 in enumerate((1.8e-4, 2.3e-4, 2.6e-4)):
        write_config(d, FIT, f"fit{i}.toml", frame=Path(frame).as_posix(), m1=m1)
        jobs.append(f'[[jobs]]\nname = "fit{i}"\ncommand = "fit"\nconfig = "fit{i}.toml"\nargs = ["--no-figures"]\n')
    path = d / "study.toml"
    path.write_text('[batch]\nbackend = "process"\nworkers = 2\n\n' + "\n".join(jobs))
    return path


@pytest.fixture
def warm_cache(monkeypatch, tmp_path_factory):
    # the jobs are fresh processes: let them share a compilation cache (the first compiles, the rest load)
    monkeypatch.delenv("BRDFJAX_NO_CACHE", raising=False)
    monkeypatch.setenv("BRDFJAX_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "jax-cache"))


def _results(out: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in (out / "jobs").glob("*.json")}


def test_study_through_the_process_pool_then_resumes_only_unfinished_jobs(study, tmp_path, warm_cache):
    out = tmp_path / "run"
    report = run_study(study, out, progress=False)
    assert report.backend == "process" and sorted(report.ran) == ["fit0", "fit1", "fit2"] and not report.failed
    results = _results(out)
    fits = {n: json.loads((out / n / "result.json").read_text()) for n in results}
    for n, r in fits.items():
        assert r["converged"], n
        # the same data from three starts: one answer
        assert r["parameters"]["m1"]["value"] == pytest.approx(fits["fit0"]["parameters"]["m1"]["value"], rel=1e-4)
    # a killed study: one job's result never written, another left half-done (a failed record)
    (out / "jobs" / "fit1.json").unlink()
    rec = results["fit2"] | {"ok": False, "exit_code": -9}
    (out / "jobs" / "fit2.json").write_text(json.dumps(rec))
    mtime0 = (out / "fit0" / "result.json").stat().st_mtime_ns
    again = run_study(study, out, backend="serial", progress=False)
    assert again.skipped == ["fit0"] and sorted(again.ran) == ["fit1", "fit2"]
    assert (out / "fit0" / "result.json").stat().st_mtime_ns == mtime0  # not redone
    assert all(r["ok"] for r in _results(out).values())
    summary = json.loads((out / "study.json").read_text())
    assert summary["skipped"] == ["fit0"] and summary["failed"] == []
    # a finished job whose config changed since: refused, naming the job and the file, nothing rerun
    cfg = study.parent / "fit0.toml"
    original = cfg.read_text()
    cfg.write_text(original.replace("rho_s1 = 0.02", "rho_s1 = 0.021"))
    try:
        with pytest.raises(FingerprintMismatch, match=r"fit0\.json belongs to another problem .*config_file.*Job 'fit0'"):
            run_study(study, out, backend="serial", progress=False)
    finally:
        cfg.write_text(original)
    assert (out / "fit0" / "result.json").stat().st_mtime_ns == mtime0


def test_bad_study_names_file_and_key(tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_text('[[jobs]]\nname = "a"\ncommand = "fitt"\n')
    with pytest.raises(StudyError, match=r"s\.toml: jobs\[0\]\.command: unknown command 'fitt' \(did you mean 'fit'\?\); expected 'fit'"):
        load_study(p)
    p.write_text('[batch]\nworkerz = 2\n[[jobs]]\nname = "a"\ncommand = "fit"\n')
    with pytest.raises(StudyError, match=r"s\.toml: batch\.workerz: unknown key \(did you mean 'workers'\?\)"):
        load_study(p)
    p.write_text('[[jobs]]\nname = "a"\ncommand = "fit"\nconfig = "nope.toml"\n')
    assert main(["batch", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "jobs[0].config: no such file" in capsys.readouterr().err


def test_study_through_ray_killed_then_resumed(study, tmp_path, warm_cache):
    """A local Ray instance of 2 CPUs; the study's process group is SIGKILLed once a job has finished, and the
    rerun skips exactly the jobs whose records were written, runs the rest and agrees with them."""
    pytest.importorskip("ray")
    out = tmp_path / "ray"
    cmd = [sys.executable, "-m", "brdfjax", "batch", str(study), "--out", str(out), "--backend", "ray", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not list((out / "jobs").glob("*.json")):
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done = sorted(n for n, r in _results(out).items() if r["ok"])
    assert done, "no job finished before the kill"
    mtimes = {n: (out / n / "result.json").stat().st_mtime_ns for n in done}
    again = run_study(study, out, backend="ray", workers=2, progress=False)
    assert again.backend == "ray" and sorted(again.skipped) == done and not again.failed
    assert sorted(again.ran) == sorted({"fit0", "fit1", "fit2"} - set(done))
    assert {n: (out / n / "result.json").stat().st_mtime_ns for n in done} == mtimes  # not redone
    m1 = [json.loads((out / n / "result.json").read_text())["parameters"]["m1"]["value"] for n in ("fit0", "fit1", "fit2")]
    assert m1 == pytest.approx([m1[0]] * 3, rel=1e-4)


def test_shipped_example_study_runs_and_logs_plain_progress(tmp_path, warm_cache):
    """configs/batch_example.toml: two fits of the Cornell Krylon table; progress as plain lines in a log."""
    import io

    from rich.console import Console

    log = io.StringIO()
    console = Console(file=log, force_terminal=False, width=120)
    example = Path(__file__).resolve().parents[2] / "configs" / "batch_example.toml"
    report = run_study(example, tmp_path / "run", console=console, figures=False)
    assert sorted(report.ran) == ["krylon_beckmann", "krylon_ggx"] and not report.failed
    for name in report.ran:
        r = json.loads((tmp_path / "run" / name / "result.json").read_text())
        assert r["converged"], name
        assert r["blocks"][0]["log_rms"] < 0.45, (name, r["blocks"][0]["log_rms"])  # 0.385 (GGX), 0.381 (Beckmann)
        assert "--no-figures" in json.loads((tmp_path / "run" / "jobs" / f"{name}.json").read_text())["argv"]
    text = log.getvalue()
    assert "\r" not in text and "study (process): 2/2 jobs" in text, text
