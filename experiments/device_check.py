"""One-shot device check: what brdfjax does on the accelerator it runs on, in one JSON, in under 8 minutes.

    python experiments/device_check.py            # on the GPU (or whatever jax.default_backend() is)
    python experiments/device_check.py --small    # CPU-sized (a couple of minutes), for CI

Sections (each timed; one that fails records its error and the rest still run; one that would not fit in
what is left of ``--budget-s`` is skipped with the reason):

``tests``
    The tests that touch JAX numerics (the core's geometry, terms, distributions, Fresnel and shadowing, the
    radiometry, the fit's Jacobian, the footprint kernel, the shipped models in float32), run by pytest in a child
    process on the default backend: counts of passed / failed / errors / skipped and the failed tests' names.
``render``
    The seed's solar-cell model (``bj.solar_cell()``) on the seed detector (3296 x 2472 pixels; ``--small``:
    every ``--step``-th pixel) at theta_i = 20 deg, in float32 and in float64: the first call (trace,
    compile, run) and the median of the steady calls (``block_until_ready``), and the agreement with the
    NumPy float64 oracle (:func:`brdfjax.reference.solar_cell_frame`) on every ``--ref-step``-th pixel of the
    frame: ``max |f - f_ref| / f_ref`` where ``f_ref`` exceeds 1e-3 of its maximum.
``sharded``
    :func:`brdfjax.render` with ``devices`` (float32) with the frame's rows split over every device of
    ``jax.devices()``: the device count, first and steady times, and ``max |f_sharded - f_render|`` relative
    to the frame's maximum.
``fit``
    ``brdfjax fit`` on ``configs/fit_synthetic_solar_cell.toml`` at full resolution (``[data.synthetic]
    bin = 1``: the seed camera's own pixels, the config's region of interest; ``--small``: ``bin = 8``), in
    a child process on the default backend, figures off: the process's wall time, the fit's own (the rest is
    imports, synthesis and reduction of the frames, setup), chi^2, reduced chi^2, steps, convergence.
``memory``
    Per device, ``device.memory_stats()`` (``peak_bytes_in_use``, ``bytes_limit``) where the backend reports
    it (GPU and TPU do, CPU does not: then ``null``), and the host's peak resident set.

Written to ``experiments/results/device_check_<platform>.json`` (``<platform>`` = ``jax.default_backend()``)
or ``--out``, atomically.  ``--only render,sharded`` runs a subset (the fast test in tests/ does that).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform as host_platform
import resource
import subprocess
import sys
import tempfile
import time
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = ("tests", "render", "sharded", "fit", "memory")
#: The test files whose checks run JAX numerics (on the default backend: the accelerator when there is one).
NUMERIC_TESTS = (
    "tests/core/test_core_numerics.py", "tests/core/test_core_geometry.py", "tests/core/test_core_terms.py",
    "tests/core/test_fresnel_microfacet.py", "tests/core/test_shadowing.py", "tests/core/test_shadowing_mixture.py",
    "tests/instrument/test_radiometry.py", "tests/core/test_kernel.py", "tests/fit/test_fit_jacobian.py", "tests/project/test_cases.py",
)  # not tests/core/test_sharding.py: it runs on two forced host (CPU) devices; the sharded section covers the accelerator
SMALL_TESTS = ("tests/instrument/test_radiometry.py", "tests/core/test_core_geometry.py")
FIT_CONFIG = ROOT / "configs" / "fit_synthetic_solar_cell.toml"
RELATIVE_FLOOR = 1e-3
THETA_I_DEG = 20.0
#: Each section's expected cost (seconds) for the skip decision: (full, small).
COST = {"tests": (240, 60), "render": (60, 20), "sharded": (30, 10), "fit": (240, 60), "memory": (1, 1)}


def _timed(fn, repeats: int) -> tuple[float, float]:
    """(first call, median of ``repeats`` further calls), each ended by ``block_until_ready``."""
    import jax
    import numpy as np

    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    steady = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        steady.append(time.perf_counter() - t0)
    return first, float(np.median(steady)) if steady else math.nan


def section_tests(args) -> dict:
    files = list(SMALL_TESTS if args.small else NUMERIC_TESTS)
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "junit.xml"
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), MPLBACKEND="Agg")
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={xml}", *files],
            cwd=ROOT, env=env, capture_output=True, text=True, timeout=args.tests_timeout_s,
        )
        wall = time.perf_counter() - t0
        if not xml.exists():
            raise RuntimeError(f"pytest wrote no report (exit {proc.returncode}): {proc.stdout[-1500:]}{proc.stderr[-1500:]}")
        root = ET.parse(xml).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    n = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    failed = [f"{c.get('classname')}::{c.get('name')}" for c in suite.iter("testcase")
              if c.find("failure") is not None or c.find("error") is not None]
    return {"files": files, "passed": n["tests"] - n["failures"] - n["errors"] - n["skipped"], "failed": n["failures"],
            "errors": n["errors"], "skipped": n["skipped"], "failed_tests": failed, "exit_code": proc.returncode,
            "wall_s": wall}


def section_render(args) -> dict:
    import numpy as np

    import brdfjax as bj
    from brdfjax import reference

    model, frame, det = bj.solar_cell(), bj.Conditions.from_degrees(THETA_I_DEG), bj.Detector.seed()
    k = args.ref_step  # compare on every k-th pixel of the rendered grid
    t0 = time.perf_counter()
    ref = reference.solar_cell_frame(np.deg2rad(THETA_I_DEG), step=args.step * k)
    ref_s = time.perf_counter() - t0
    mask = ref > RELATIVE_FLOOR * ref.max()
    out: dict = {"model": "solar_cell", "theta_i_deg": THETA_I_DEG, "step": args.step,
                 "pixels": int(det.grid(args.step).n_h.size * det.grid(args.step).n_v.size),
                 "reference": {"step": args.step * k, "pixels_compared": int(mask.sum()), "numpy_s": ref_s}}
    for precision in ("float32", "float64"):
        f = None

        def call(precision=precision):
            nonlocal f
            f = bj.render(model, frame, det, step=args.step, precision=precision)
            return f

        first, steady = _timed(call, args.repeats)
        sub = np.asarray(f, np.float64)[::k, ::k]
        assert sub.shape == ref.shape, (sub.shape, ref.shape)
        rel = np.abs(sub[mask] - ref[mask]) / ref[mask]
        out[precision] = {"first_call_s": first, "steady_s": steady, "dtype": str(f.dtype), "shape": list(f.shape),
                          "max_rel_err_vs_numpy": float(rel.max()), "median_rel_err_vs_numpy": float(np.median(rel)),
                          "finite": bool(np.all(np.isfinite(np.asarray(f))))}
        del f
    return out


def section_sharded(args) -> dict:
    import jax
    import numpy as np

    import brdfjax as bj

    model, frame, det = bj.solar_cell(), bj.Conditions.from_degrees(THETA_I_DEG), bj.Detector.seed()
    devices = jax.devices()
    box: dict = {}

    def sharded():
        box["f"] = bj.render(model, frame, det, step=args.step, precision="float32", devices=devices)
        return box["f"]

    first, steady = _timed(sharded, args.repeats)
    plain = np.asarray(bj.render(model, frame, det, step=args.step, precision="float32"), np.float64)
    f = np.asarray(box["f"], np.float64)
    shards = getattr(box["f"], "sharding", None)
    return {"n_devices": len(devices), "devices": [str(d) for d in devices], "step": args.step,
            "first_call_s": first, "steady_s": steady, "shape": list(f.shape),
            "max_abs_diff_vs_render_rel_to_max": float(np.max(np.abs(f - plain)) / np.max(np.abs(plain))),
            "sharding": type(shards).__name__ if shards is not None else None}


def section_fit(args) -> dict:
    cfg = FIT_CONFIG.read_text()
    bin_ = 8 if args.small else 1
    doc = tomllib.loads(cfg)
    assert doc["data"]["synthetic"]["bin"] == 4 and doc["output"]["figures"] is True  # the lines edited below
    cfg = cfg.replace("bin = 4", f"bin = {bin_}").replace("figures = true", "figures = false")
    assert tomllib.loads(cfg)["data"]["synthetic"]["bin"] == bin_
    with tempfile.TemporaryDirectory() as tmp:
        c = Path(tmp) / "fit.toml"  # the shipped config names no file relative to its folder
        c.write_text(cfg)
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
                   MPLBACKEND="Agg", BRDFJAX_NO_CACHE="1")
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "brdfjax", "fit", str(c), "--out", str(Path(tmp) / "out")],
                              cwd=ROOT, env=env, capture_output=True, text=True, timeout=args.fit_timeout_s)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"brdfjax fit exited {proc.returncode}: {proc.stderr[-2000:]}")
        res = json.loads((Path(tmp) / "out" / "result.json").read_text())
    keys = ("chi2", "chi2_reduced", "dof", "converged", "n_iterations", "message")
    fit_s = res.get("wall_s")
    return {"config": str(FIT_CONFIG.relative_to(ROOT)), "bin": bin_, "camera_pixels": [2472 // bin_, 3296 // bin_],
            "process_wall_s": wall, "fit_wall_s": fit_s,
            "synthesis_and_setup_s": wall - fit_s if isinstance(fit_s, int | float) else None,
            **{k: res.get(k) for k in keys}}


def section_memory(args) -> dict:
    import jax

    per = []
    for d in jax.devices():
        try:
            stats = d.memory_stats()
        except Exception:  # noqa: BLE001 -- a backend without the query
            stats = None
        per.append({"device": str(d), "peak_bytes_in_use": (stats or {}).get("peak_bytes_in_use"),
                    "bytes_limit": (stats or {}).get("bytes_limit")})
    ru = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return {"devices": per, "host_peak_rss_mib": ru / 1024.0,
            "note": None if any(p["peak_bytes_in_use"] is not None for p in per)
            else f"{jax.default_backend()} reports no device memory statistics"}


RUNNERS = {"tests": section_tests, "render": section_render, "sharded": section_sharded, "fit": section_fit,
           "memory": section_memory}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--small", action="store_true", help="CPU-sized run for CI: decimated frames, a binned fit, two test files")
    p.add_argument("--only", default=",".join(SECTIONS), help=f"comma-separated sections (default: all of {','.join(SECTIONS)})")
    p.add_argument("--out", type=Path, default=None, help="the JSON (default experiments/results/device_check_<platform>.json)")
    p.add_argument("--step", type=int, default=None, help="render every step-th pixel (default 1; --small 16)")
    p.add_argument("--ref-step", type=int, default=None, help="compare with NumPy on every k-th rendered pixel (default 8; --small 2)")
    p.add_argument("--repeats", type=int, default=None, help="steady-state calls per render (default 5; --small 2)")
    p.add_argument("--budget-s", type=float, default=450.0, help="skip sections that would end after this many seconds")
    p.add_argument("--tests-timeout-s", type=float, default=300.0)
    p.add_argument("--fit-timeout-s", type=float, default=300.0)
    args = p.parse_args(argv)
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(only) - set(SECTIONS))
    if unknown:
        p.error(f"--only: unknown section(s) {', '.join(unknown)}; expected some of {', '.join(SECTIONS)}")
    args.step = args.step or (16 if args.small else 1)
    args.ref_step = args.ref_step or (2 if args.small else 8)
    args.repeats = args.repeats if args.repeats is not None else (2 if args.small else 5)

    t_start = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)  # the float64 render; float32 is asked for explicitly
    from brdfjax.runtime.atomic import write_json_atomic

    backend = jax.default_backend()
    out_path = args.out or ROOT / "experiments" / "results" / f"device_check_{backend}.json"
    doc: dict = {
        "platform": backend, "small": args.small, "devices": [str(d) for d in jax.devices()],
        "device_kind": jax.devices()[0].device_kind, "jax_version": jax.__version__, "python": sys.version.split()[0],
        "host": {"machine": host_platform.machine(), "cpus": os.cpu_count()}, "sections": {},
    }
    for name in SECTIONS:
        if name not in only:
            continue
        left = args.budget_s - (time.perf_counter() - t_start)
        cost = COST[name][1 if args.small else 0]
        if left < cost:
            doc["sections"][name] = {"status": "skipped", "reason": f"{left:.0f} s left of --budget-s, it needs ~{cost} s"}
            continue
        t0 = time.perf_counter()
        try:
            res = RUNNERS[name](args)
            doc["sections"][name] = {"status": "ok", "section_s": time.perf_counter() - t0, **res}
        except Exception as e:  # noqa: BLE001 -- record it, run the other sections
            doc["sections"][name] = {"status": "error", "section_s": time.perf_counter() - t0,
                                     "error": f"{type(e).__name__}: {e}"[-3000:]}
        print(f"{name}: {doc['sections'][name]['status']} ({time.perf_counter() - t0:.1f} s)", flush=True)
    doc["total_s"] = time.perf_counter() - t_start
    write_json_atomic(out_path, doc)
    print(json.dumps(doc, indent=1)[:6000])
    print(f"wrote {out_path}")
    return 0 if all(s["status"] != "error" for s in doc["sections"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
