"""What ``[diagnose] fast_compile`` (``brdfjax.runtime.export_cache.FAST_COMPILE_CPU``) buys and costs on the CPU.

Three measurements, each with XLA's default options and with the fast-compile ones, measured in the same run:

1. the shipped diagnosis (``configs/diagnose_withheld_diffraction.toml``), cold (an empty cache folder each),
   ``fast_compile = true`` (the default) and ``false``: wall, CPU seconds, peak RSS, path and final reduced
   chi^2 (``experiments/benchmark_diagnose.py``'s child run);
2. the compile time of every program the diagnosis exported (``<cache>/export/*.jaxexport``), compiled again in a
   fresh process with each set of options, alternating per program, summed per kind (solve, evaluate, render);
3. a full seed frame (3296 x 2472 pixels, float32) rendered through the exported render program with each set
   of options: the first call (compile + run; the trace is made before either) and the median of ``--repeats``
   calls after it.

    python3 experiments/benchmark_fast_compile.py [--out experiments/results/fast_compile_cpu.json] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from benchmark_diagnose import _config_with, _run  # noqa: E402

from brdfjax.runtime.atomic import write_json_atomic  # noqa: E402
from brdfjax.runtime.export_cache import FAST_COMPILE_CPU  # noqa: E402

COMPILE_ALL = textwrap.dedent(
    """
    import collections, glob, json, sys, time
    import jax
    jax.config.update("jax_enable_x64", True)
    from jax import export
    fast = json.loads(sys.argv[2])
    tot = {"default": collections.Counter(), "fast": collections.Counter()}
    n = collections.Counter()
    for f in sorted(glob.glob(sys.argv[1] + "/*.jaxexport")):
        exp = export.deserialize(bytearray(open(f, "rb").read()))
        args = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exp.in_avals]
        kind = f.rsplit("/", 1)[-1].split("-")[0]
        n[kind] += 1
        for tag, opts in (("default", None), ("fast", fast)):
            t = time.perf_counter()
            jax.jit(exp.call, compiler_options=opts).lower(*args).compile()
            tot[tag][kind] += time.perf_counter() - t
    print(json.dumps({"programs": dict(n), "default_s": dict(tot["default"]), "fast_s": dict(tot["fast"])}))
    """
)

RENDER = textwrap.dedent(
    """
    import json, statistics, sys, time
    import numpy as np
    from brdfjax.runtime import export_cache
    assert export_cache.activate(sys.argv[1]) is not None
    import brdfjax as bj
    fast, repeats = json.loads(sys.argv[2]), int(sys.argv[3])
    det = bj.Detector.seed()
    grid = det.grid(1)
    # the trace and the exported program first (XLA's default value written out: a program of its own), so that
    # neither measured first call includes them
    with export_cache.compiler_options({k: not v for k, v in fast.items()}):
        bj.render(bj.solar_cell(), bj.Conditions.from_degrees(20.0), det, grid=grid)
    out = {}
    for tag, opts in (("default", None), ("fast", fast)):
        with export_cache.compiler_options(opts):
            t = time.perf_counter()
            img = np.asarray(bj.render(bj.solar_cell(), bj.Conditions.from_degrees(20.0), det, grid=grid))
            first = time.perf_counter() - t
            times = []
            for _ in range(repeats):
                t = time.perf_counter()
                np.asarray(bj.render(bj.solar_cell(), bj.Conditions.from_degrees(20.0), det, grid=grid))
                times.append(time.perf_counter() - t)
        out[tag] = {"first_call_s": first, "median_s": statistics.median(times), "pixels": int(img.size),
                    "dtype": str(img.dtype), "sum": float(np.sum(img, dtype=np.float64))}
    print(json.dumps(out))
    """
)


def _child(code: str, *args: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + (os.pathsep + os.environ["PYTHONPATH"] if os.environ.get("PYTHONPATH") else ""))
    proc = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"child failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "diagnose_withheld_diffraction.toml"))
    p.add_argument("--out", default=str(ROOT / "experiments" / "results" / "fast_compile_cpu.json"))
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    fast = json.dumps(FAST_COMPILE_CPU)
    result: dict = {"options": FAST_COMPILE_CPU, "cpus": os.cpu_count(), "load_before": os.getloadavg()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        runs = {}
        for tag, value in (("fast", "true"), ("default", "false")):
            rec, _ = _run(_config_with(args.config, "fast_compile", value, tmp, tag), str(tmp / f"cache_{tag}"), tmp, tag)
            rec["cold"] = True  # a fresh cache folder of its own
            runs[tag] = rec
            print(f"diagnosis, {tag} options: wall {rec['wall_s']:.1f} s, CPU {rec['cpu_s']:.1f} s, peak RSS "
                  f"{rec['peak_rss_mb']:.0f} MB, exit {rec['exit']}, final reduced chi^2 "
                  f"{rec['path'][-1][2] if rec['exit'] == 0 else None!r}")
        result["diagnosis"] = runs
        if all(r["exit"] == 0 for r in runs.values()):
            f, d = runs["fast"], runs["default"]
            result["diagnosis_ratio_fast_to_default"] = {k: f[k] / d[k] for k in ("wall_s", "cpu_s", "peak_rss_mb")}
            result["final_chi2_reduced_relative_difference"] = abs(f["path"][-1][2] / d["path"][-1][2] - 1.0)
            print("fast / default: " + ", ".join(f"{k} x{v:.3f}" for k, v in result["diagnosis_ratio_fast_to_default"].items())
                  + f"; final reduced chi^2 differs by {result['final_chi2_reduced_relative_difference']:.2e} relative")
        comp = _child(COMPILE_ALL, str(tmp / "cache_default" / "export"), fast)
        result["compile"] = comp
        for kind, n in sorted(comp["programs"].items()):
            print(f"compile {kind}: {n} programs, {comp['default_s'][kind]:.1f} s default, {comp['fast_s'][kind]:.1f} s fast "
                  f"(x{comp['fast_s'][kind] / comp['default_s'][kind]:.3f})")
        rend = _child(RENDER, str(tmp / "render_export"), fast, str(args.repeats))
        result["render_full_frame"] = rend
        print(f"full-frame render ({rend['default']['pixels']} pixels, {rend['default']['dtype']}): first call "
              f"{rend['default']['first_call_s']:.2f} s default, {rend['fast']['first_call_s']:.2f} s fast; median after "
              f"{rend['default']['median_s']:.3f} s default, {rend['fast']['median_s']:.3f} s fast "
              f"(x{rend['fast']['median_s'] / rend['default']['median_s']:.3f}); sums agree to "
              f"{abs(rend['fast']['sum'] / rend['default']['sum'] - 1):.1e}")
    result["load_after"] = os.getloadavg()
    write_json_atomic(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
