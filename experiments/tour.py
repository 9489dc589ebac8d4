"""The README's tour, run cold: every command a newcomer runs first, timed one after the other.

Each step runs as its own ``python -m brdfjax`` process, as a user types it, with an empty compilation
and export cache (``BRDFJAX_CACHE_DIR`` set to a new folder for the whole tour, so later steps may reuse
what earlier ones compiled, as they do on a user's machine) and into a new output folder.  Prints each
step's wall time and exit code and the total, and writes ``experiments/results/tour_cold.json``.

    python3 experiments/tour.py [--out DIR] [--json PATH]

The target is the whole tour in under 5 minutes on an idle 2-core CPU.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

#: (name, arguments after ``python -m brdfjax``), ``{out}`` the tour's output folder
STEPS = [
    ("simulate", ["simulate", "--out", "{out}/default"]),
    ("fit", ["fit", "configs/fit_synthetic_solar_cell.toml", "--out", "{out}/fit"]),
    ("sample", ["sample", "configs/sample_synthetic_solar_cell.toml", "--out", "{out}/sample"]),
    ("diagnose", ["diagnose", "configs/diagnose_withheld_diffraction.toml", "--out", "{out}/diagnose"]),
    # the README's paths: configs/fit_captured.toml reads runs/cap/reduced
    ("capture", ["capture", "configs/capture_simulated.toml", "--out", "runs/cap"]),
    ("reduce", ["reduce", "runs/cap/manifest.toml", "--out", "runs/cap/reduced", "--correct-nonlinearity"]),
    ("fit_captured", ["fit", "configs/fit_captured.toml", "--out", "{out}/cap/fit"]),
    ("lightcurve", ["lightcurve", "configs/lightcurve_box_wing.toml", "--out", "{out}/lightcurve"]),
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="output folder (default: a new temporary folder)")
    ap.add_argument("--json", default=str(ROOT / "experiments" / "results" / "tour_cold.json"))
    ap.add_argument("--only", default=None, help="comma-separated step names to run (default: all)")
    args = ap.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="brdfjax-tour-"))
    cache = Path(tempfile.mkdtemp(prefix="brdfjax-tour-cache-"))
    env = {**os.environ, "BRDFJAX_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT)}
    only = None if args.only is None else set(args.only.split(","))
    cap = ROOT / "runs" / "cap"
    if cap.exists():  # a capture there already: kept aside, never overwritten
        aside = cap.with_name(f"cap.before-tour-{int(time.time())}")
        cap.rename(aside)
        print(f"moved the existing {cap} to {aside}")
    rows = []
    t_all = time.perf_counter()
    for name, words in STEPS:
        if only is not None and name not in only:
            continue
        cmd = [sys.executable, "-m", "brdfjax", *(w.format(out=out) for w in words), "--quiet"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        rows.append({"step": name, "command": " ".join(["brdfjax", *words]), "wall_s": round(wall, 2),
                     "exit": proc.returncode, "stderr_tail": proc.stderr[-400:] if proc.returncode else ""})
        print(f"{name:<14s} {wall:7.1f} s  exit {proc.returncode}", flush=True)
        if proc.returncode:
            print(proc.stderr[-2000:], file=sys.stderr)
    total = time.perf_counter() - t_all
    load = os.getloadavg()
    print(f"{'total':<14s} {total:7.1f} s  (target < 300 s; load average {load[0]:.1f})")
    write_json_atomic(Path(args.json), {"steps": rows, "total_s": round(total, 2), "target_s": 300,
                                        "load_average_1min": load[0], "cpu_count": os.cpu_count(),
                                        "caches": "empty at the start of the tour (one folder for every step)"})
    return 0 if all(r["exit"] == 0 for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
