"""``brdfjax fit`` on the synthetic solar-cell config, whole process, twice with one persistent compile cache (issue 19).

The first process starts with an empty cache (``$BRDFJAX_CACHE_DIR`` in a fresh temporary folder) and
fills it; the second, the same command in a new process, must start warm: every program of the fit
(the Levenberg-Marquardt solve stepped from Python for the progress line, the covariance, ...) comes
from the cache, none carries a host callback.  The progress line stays on (no ``--quiet``).  The frames
are the ones ``experiments/benchmark_fit.py`` generated (``--data``), copied into the output folder.
Run::

    python3 experiments/benchmark_fit_cli.py --json experiments/results/benchmark_fit_cli.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "fit_synthetic_solar_cell.toml"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT / "runs" / "benchmark_fit_data", help="frames made by benchmark_fit.py")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if not (args.data / "synthetic").is_dir():
        print(f"{args.data / 'synthetic'}: no frames; run experiments/benchmark_fit.py first", file=sys.stderr)
        return 2
    work = Path(tempfile.mkdtemp())
    shutil.copytree(args.data / "synthetic", work / "out" / "synthetic")
    env = dict(os.environ, BRDFJAX_CACHE_DIR=str(work / "cache"))
    env.pop("BRDFJAX_NO_CACHE", None)
    runs = []
    # with the progress line the solve is stepped from Python (its state cannot be exported); --quiet runs it as
    # one program, which a later process reads back traced (brdfjax.runtime.export_cache): its first quiet run exports it
    for label, flags in (("empty cache", []), ("second process", []), ("--quiet, 1st", ["--quiet"]),
                         ("--quiet, later", ["--quiet"])):
        cmd = [sys.executable, "-m", "brdfjax", "fit", str(CONFIG), "--out", str(work / "out"), "--no-figures", *flags]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
            return 1
        result = json.loads((work / "out" / "result.json").read_text())
        runs.append(dict(run=label, wall_s=wall, chi2=result.get("chi2"), steps=result.get("n_iterations")))
        print(f"brdfjax fit, {label:15s}: {wall:7.2f} s wall, chi^2 {result.get('chi2')}, load {os.getloadavg()[0]:.1f}",
              flush=True)
    print(f"second process / first: {runs[1]['wall_s'] / runs[0]['wall_s']:.2f}; "
          f"--quiet later / first: {runs[3]['wall_s'] / runs[0]['wall_s']:.2f}")
    if args.json:
        from brdfjax.runtime.atomic import write_json_atomic  # noqa: PLC0415 -- the timed children import brdfjax, not this parent

        write_json_atomic(args.json, dict(runs=runs, load=os.getloadavg()))
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
