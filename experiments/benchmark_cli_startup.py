"""Benchmark: ``brdfjax --help`` and ``brdfjax --version`` wall time beside ``python -c "import numpy"``.

Each command runs in a fresh Python process (``sys.executable``, with this checkout first on ``PYTHONPATH``),
``--repeats`` times, alternating so that a change of load hits every command alike; the medians are
printed with their ratio to NumPy's import.  The target: ``brdfjax --help`` at most 1 s of wall time.  The
top-level help declares no subcommand's arguments, so no subcommand's stack (JAX, the fit, the sampler) is
imported; ``brdfjax fit --help`` (which imports the fit stack to list its options) is timed beside it for
scale.  ``uptime``'s load average is recorded: on a shared box the wall times move with it.

Usage::

    python experiments/benchmark_cli_startup.py [--repeats 7] [--json experiments/results/cli_startup.json]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402

COMMANDS = {
    "python -c 'import numpy'": [sys.executable, "-c", "import numpy"],
    "brdfjax --help": [sys.executable, "-m", "brdfjax", "--help"],
    "brdfjax --version": [sys.executable, "-m", "brdfjax", "--version"],
    "python -c 'import brdfjax'": [sys.executable, "-c", "import brdfjax"],
    "brdfjax fit --help": [sys.executable, "-m", "brdfjax", "fit", "--help"],
}
TARGET_S = 1.0


def _time(cmd: list[str], env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-500:]}")
    return wall


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--json", default=str(ROOT / "experiments" / "results" / "cli_startup.json"))
    args = p.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    for cmd in COMMANDS.values():  # warm the file cache once, not timed
        _time(cmd, env)
    walls: dict[str, list[float]] = {k: [] for k in COMMANDS}
    for _ in range(args.repeats):
        for name, cmd in COMMANDS.items():
            walls[name].append(_time(cmd, env))
    med = {k: statistics.median(v) for k, v in walls.items()}
    numpy_s = med["python -c 'import numpy'"]
    print(f"{'command':30s} {'median wall (s)':>16s} {'x numpy':>8s}")
    for name, m in med.items():
        print(f"{name:30s} {m:16.3f} {m / numpy_s:8.2f}")
    load = os.getloadavg()
    ok = med["brdfjax --help"] <= TARGET_S
    print(f"brdfjax --help {med['brdfjax --help']:.3f} s: {'meets' if ok else 'MISSES'} the {TARGET_S:g} s target "
          f"(load average {load[0]:.1f} on {os.cpu_count()} CPUs)")
    write_json_atomic(args.json, {
        "repeats": args.repeats, "median_wall_s": med, "walls_s": walls, "ratio_to_numpy": {k: m / numpy_s for k, m in med.items()},
        "target_s": TARGET_S, "help_meets_target": ok, "load_average": load, "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
    })
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
