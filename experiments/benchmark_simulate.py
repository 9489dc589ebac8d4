"""Benchmark: ``brdfjax simulate`` on the seed config, whole process, against the NumPy oracle.

What is timed (each a fresh Python process, wall clock and CPU seconds of the
child, from ``resource.getrusage(RUSAGE_CHILDREN)``):

* ``brdfjax simulate configs/seed_fig33.toml --out DIR``: the seed's Fig 33
  job (solar-cell model, full 3296 x 2472 frames at theta_i = 20 and 60 deg):
  import, compile (or load from the persistent compilation cache), render,
  and write per frame an OpenEXR file (BRDF, theta_s, phi_s, solid angle) and
  a PNG figure, plus ``summary.json``.  The first run uses an empty cache
  folder (``BRDFJAX_CACHE_DIR``, cold: it compiles); the later ones find it
  filled (warm: the second process on the same machine).
* the NumPy float64 oracle on the same two frames
  (``brdfjax.reference.solar_cell_frame``, the plain vectorised NumPy
  implementation of the same formulas), saving each BRDF frame with
  ``np.save``: it computes the BRDF only, no geometry channels and no figure.

The warm brdfjax runs and the oracle runs alternate (``--repeats`` of each);
medians are compared.  On a shared machine the wall-clock ratio moves with
the load; the CPU-second ratio is printed beside it.

Also printed: the floor of a warm process (its start, the imports, two warm renders and the last frame's
EXR and PNG, each timed alone) and the oracle's time over it, the most any overlap of the pieces could give.

Usage::

    python experiments/benchmark_simulate.py [--repeats 3] [--json experiments/results/benchmark_simulate.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "seed_fig33.toml"
ORACLE = """
import sys, numpy as np
from brdfjax import reference
for name, deg in (("ti20", 20.0), ("ti60", 60.0)):
    np.save(f"{sys.argv[1]}/{name}.npy", reference.solar_cell_frame(np.deg2rad(deg)))
"""

# The floor of a warm process, piece by piece in one fresh process with the cache filled: its start and the
# simulate stack's imports, then (the program warm) one frame's render, its EXR and its PNG.  Even with every
# other piece overlapped, a process that renders two frames and writes the last one's files takes at least
# start + 2 renders + that EXR + that PNG.
FLOOR = """
import json, sys, time
t0 = time.perf_counter()
from brdfjax.runtime.compile_cache import enable_compilation_cache
enable_compilation_cache()
import numpy as np
import brdfjax as bj
from brdfjax import simulate as S
from brdfjax.cli import instrument as cli_run
from brdfjax.io import frame_attrs, write_frame_exr
t_imp = time.perf_counter() - t0
det = bj.Detector.seed()
grid = det.grid(1)
frame = bj.Conditions.from_degrees(60.0, 0.0, 632.8)
model = bj.solar_cell()
S.simulate_frame(model, frame, det, grid, "float32", "ti60")
t = time.perf_counter(); res = S.simulate_frame(model, frame, det, grid, "float32", "ti60"); t_render = time.perf_counter() - t
attrs = {**frame_attrs(det, frame, step=1, roi=det.index_range), "model": "preset solar_cell", "brdfjax_version": "x"}
t = time.perf_counter()
write_frame_exr(sys.argv[1] + "/f.exr", res.brdf, res.geometry["theta_s"], res.geometry["phi_s"], res.geometry["omega"], attrs)
t_exr = time.perf_counter() - t
S.plot_frame(res.brdf, grid, det, frame, sys.argv[1] + "/f0.png")
t = time.perf_counter(); S.plot_frame(res.brdf, grid, det, frame, sys.argv[1] + "/f1.png"); t_png = time.perf_counter() - t
print(json.dumps(dict(imports_s=t_imp, render_s=t_render, exr_s=t_exr, png_s=t_png)))
"""


def _timed(cmd: list[str], env: dict[str, str]) -> dict[str, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"benchmark_simulate: {' '.join(cmd[:4])} ... failed with exit code {proc.returncode}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3, help="warm brdfjax runs and oracle runs, alternating (default 3)")
    p.add_argument("--config", type=Path, default=CONFIG, help="simulate config (default: configs/seed_fig33.toml)")
    p.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats must be a positive integer")

    with tempfile.TemporaryDirectory(prefix="brdfjax_bench_sim_") as tmp:
        tmp = Path(tmp)
        env = {**os.environ, "BRDFJAX_CACHE_DIR": str(tmp / "cache"), "PYTHONPATH": str(ROOT)}
        env.pop("BRDFJAX_NO_CACHE", None)
        sim = [sys.executable, "-m", "brdfjax", "simulate", str(args.config), "--out", str(tmp / "out"), "--quiet"]
        (tmp / "oracle").mkdir()
        oracle = [sys.executable, "-c", ORACLE, str(tmp / "oracle")]
        print("brdfjax simulate, cold cache ...", file=sys.stderr, flush=True)
        cold = _timed(sim, env)
        warm, ref = [], []
        for k in range(args.repeats):
            print(f"round {k + 1}/{args.repeats}: NumPy oracle, brdfjax simulate (warm) ...", file=sys.stderr, flush=True)
            ref.append(_timed(oracle, env))
            warm.append(_timed(sim, env))
        # the floor: a bare interpreter's start, then the pieces (above)
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], env=env, check=True)
        t_python = time.perf_counter() - t
        proc = subprocess.run([sys.executable, "-c", FLOOR, str(tmp)], env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            sys.stderr.write(proc.stderr)
            raise SystemExit("benchmark_simulate: the floor's pieces failed")
        floor = {"python_s": t_python, **json.loads(proc.stdout.strip().splitlines()[-1])}
        floor["floor_s"] = floor["python_s"] + floor["imports_s"] + 2 * floor["render_s"] + floor["exr_s"] + floor["png_s"]
        summary = json.loads((tmp / "out" / "summary.json").read_text())
        check = {}
        for fr in summary["frames"]:
            ora = np.load(tmp / "oracle" / f"{fr['name']}.npy")
            check[fr["name"]] = {"max_brdf": fr["max_brdf"], "oracle_max_brdf": float(ora.max())}

    med = {k: float(np.median([r[k] for r in warm])) for k in ("wall_s", "cpu_s")}
    med_ref = {k: float(np.median([r[k] for r in ref])) for k in ("wall_s", "cpu_s")}
    res = {
        "config": str(args.config.relative_to(ROOT) if args.config.is_relative_to(ROOT) else args.config),
        "cold": cold,
        "warm": warm,
        "oracle": ref,
        "warm_median": med,
        "oracle_median": med_ref,
        "speedup_wall": med_ref["wall_s"] / med["wall_s"],
        "speedup_cpu": med_ref["cpu_s"] / med["cpu_s"],
        "load_average": os.getloadavg(),
        "cpu_count": os.cpu_count(),
        "frames": check,
        "floor": floor,
        "oracle_over_floor": med_ref["wall_s"] / floor["floor_s"],
    }
    la = ", ".join(f"{x:.1f}" for x in res["load_average"])
    print(f"brdfjax simulate {res['config']} (2 full frames, EXR + PNG) vs the NumPy oracle (same 2 BRDF frames), "
          f"whole processes; {os.cpu_count()} CPUs, load average at the end {la}")
    print("| run | wall [s] (median) | CPU [s] (median) | oracle / run, wall | oracle / run, CPU |")
    print("| --- | --- | --- | --- | --- |")
    print(f"| NumPy oracle ({args.repeats} runs) | {med_ref['wall_s']:.1f} | {med_ref['cpu_s']:.1f} | 1.0x | 1.0x |")
    print(f"| brdfjax simulate, cold cache | {cold['wall_s']:.1f} | {cold['cpu_s']:.1f} | "
          f"{med_ref['wall_s'] / cold['wall_s']:.1f}x | {med_ref['cpu_s'] / cold['cpu_s']:.1f}x |")
    print(f"| brdfjax simulate, warm cache ({args.repeats} runs) | {med['wall_s']:.2f} | {med['cpu_s']:.2f} | "
          f"**{res['speedup_wall']:.1f}x** | {res['speedup_cpu']:.1f}x |")
    print("warm wall times: " + ", ".join(f"{r['wall_s']:.2f}" for r in warm)
          + "; oracle: " + ", ".join(f"{r['wall_s']:.1f}" for r in ref))
    print(f"floor of a warm process: start {floor['python_s']:.2f} s + imports {floor['imports_s']:.2f} s + 2 renders x "
          f"{floor['render_s']:.2f} s + the last frame's EXR {floor['exr_s']:.2f} s + its PNG {floor['png_s']:.2f} s = "
          f"{floor['floor_s']:.2f} s: oracle / floor {res['oracle_over_floor']:.1f}x (the most any overlap could reach)")
    print("peak BRDF (simulate / oracle): " + "; ".join(
        f"{k} {v['max_brdf']:.5g} / {v['oracle_max_brdf']:.5g}" for k, v in check.items()))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp_json = args.json.with_suffix(".json.tmp")
        tmp_json.write_text(json.dumps(res, indent=2))
        tmp_json.replace(args.json)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
