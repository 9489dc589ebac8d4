"""experiments/device_check.py: its smallest part runs here and writes the JSON it promises (the whole --small is slow)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "experiments" / "device_check.py"


def _run(tmp_path, *args, timeout=600):
    out = tmp_path / "dc.json"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--small", "--out", str(out), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(out.read_text())


def test_render_and_memory_sections(tmp_path):
    doc = _run(tmp_path, "--only", "render,memory", "--step", "128", "--ref-step", "1", "--repeats", "1")
    assert doc["platform"] == "cpu" and doc["small"] is True and doc["devices"][0].lower().startswith("cpu")
    assert set(doc["sections"]) == {"render", "memory"}
    r = doc["sections"]["render"]
    assert r["status"] == "ok" and r["step"] == 128 and r["reference"]["pixels_compared"] > 10
    # the NumPy oracle on the same pixels: float64 to ~1e-10, float32 to its rounding
    assert r["float64"]["max_rel_err_vs_numpy"] < 1e-9 and r["float64"]["dtype"] == "float64"
    assert r["float32"]["max_rel_err_vs_numpy"] < 1e-4 and r["float32"]["dtype"] == "float32"
    assert r["float32"]["shape"] == [-(-2472 // 128), -(-3296 // 128)] and r["float32"]["finite"]
    assert r["float32"]["first_call_s"] > 0 and r["float32"]["steady_s"] > 0
    m = doc["sections"]["memory"]
    assert m["status"] == "ok" and m["host_peak_rss_mib"] > 50 and m["devices"][0]["peak_bytes_in_use"] is None


def test_unknown_section_is_refused(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPT), "--only", "render,gpu"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "--only: unknown section(s) gpu" in proc.stderr


@pytest.mark.slow
def test_small_run_writes_every_section(tmp_path):
    doc = _run(tmp_path, timeout=900)
    assert set(doc["sections"]) == {"tests", "render", "sharded", "fit", "memory"}
    assert all(s["status"] == "ok" for s in doc["sections"].values()), doc["sections"]
    t = doc["sections"]["tests"]
    assert t["failed"] == 0 and t["errors"] == 0 and t["passed"] > 5
    s = doc["sections"]["sharded"]
    assert s["n_devices"] >= 1 and s["max_abs_diff_vs_render_rel_to_max"] < 1e-5
    f = doc["sections"]["fit"]
    assert f["bin"] == 8 and f["converged"] and 0.5 < f["chi2_reduced"] < 2.0
    assert doc["total_s"] < 480
