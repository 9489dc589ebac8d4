"""Benchmark: one full solar-cell frame with the jit-compiled JAX core vs the NumPy float64 oracle.

What is timed
    ``bj.render(bj.solar_cell(), bj.Conditions.from_degrees(theta_i), bj.Detector.seed())``
    -- the seed's three-term solar-cell model (Chapter VI, §6.4 parameters) on
    every pixel of the seed's 3296 x 2472 detector (``--step k`` keeps every
    k-th pixel for quick runs) -- against
    ``brdfjax.reference.solar_cell_frame(theta_i)``, the plain vectorised
    NumPy float64 implementation (128 rows at a time).

How
    Each configuration runs in its own subprocess (``--path jax`` /
    ``--path numpy``, driven by the parent) so that peak-memory figures do not
    mix and each JAX precision gets a fresh process (float64 is enabled there
    with ``jax.config.update("jax_enable_x64", True)``; brdfjax never flips it).

    * JAX: the first call (trace + compile + run) is timed separately; the
      steady state is the median of ``--repeats`` further calls, each ended by
      ``block_until_ready()``.
    * NumPy: median of ``--numpy-repeats`` calls.
    * Peak RSS: increase of the process's resident-set high-water mark over
      all its calls (for JAX the first call, i.e. tracing and XLA compilation,
      included) over the RSS just before the first call (imports done, model,
      frame and detector built), from ``VmHWM`` / ``VmRSS`` in
      ``/proc/self/status`` with the high-water mark reset (``clear_refs``) at
      that point.  Where that is unavailable: ``ru_maxrss`` minus the RSS
      baseline.  It counts the output frame (31 MiB in float32, 62 MiB in
      float64), temporaries and, for JAX, the compiler's memory; it is noisy
      at the 10-50 MiB level (allocator caching).  On an
      accelerator the host RSS is not the memory that matters, so the
      device's own ``peak_bytes_in_use`` is printed too when the backend
      reports it (GPU does, CPU does not).
    * XLA buffers: output + temporary buffer sizes of the compiled program,
      from ``jax.jit(...).lower().compile().memory_analysis()`` -- the exact
      steady-state working set of one call, reported the same way on every
      backend (one extra, untimed compilation).
    * Accuracy: ``max |f_jax - f_numpy| / f_numpy`` over the pixels where the
      NumPy frame exceeds 1e-3 of its maximum.

    * Fused numba kernel (when ``numba`` is installed, ``pip install
      "brdfjax[bench]"``): ``experiments/fused_numba.py``, the same formulas
      in float32 as one ``numba.njit(parallel=True)`` loop over the pixels.
      One worker process alternates ``brdfjax.core.render`` (float32, default
      chunk) and the numba kernel, both warm, ``--duel-repeats`` times;
      medians (and minima) are compared.
    * Bare Beckmann lobe against Mitsuba 3 (when ``mitsuba`` 3.x imports with
      its LLVM backend; otherwise the section says why it is skipped): the
      8,146,112 direction pairs of the seed frame at theta_i = 20 deg (the
      detector's scatter directions, one incident direction), float32.
      brdfjax evaluates ``Specular(Beckmann(m), rho_s=1, n, k,
      shadowing="smith", normalisation="torrance_sparrow")`` times
      ``cos theta_s`` -- the microfacet form of Mitsuba's ``roughconductor``
      (``D G F / (4 cos theta_i)``, which its ``eval`` returns) -- and the
      seed's bare Eq 70 lobe (no shadowing); Mitsuba the ``roughconductor``
      plugin (``distribution = "beckmann"``, ``alpha = m``, the same complex
      index, variant ``llvm_ad_mono``), ``bsdf.eval`` on the same direction
      arrays with the result evaluated (``dr.eval``).  Alternating calls in
      one process, ``--duel-repeats`` times; the values are compared at the
      peak.  Mitsuba's LLVM backend needs an LLVM >= 17:
      ``DRJIT_LIBLLVM_PATH`` is pointed at one found on the system when it
      is not set (the system's LLVM 15 aborts).

Nothing here is CPU-specific: the same command runs on a GPU machine.

Usage::

    python experiments/benchmark_frame.py                 # full frame, ~2 min on 2 CPU cores
    python experiments/benchmark_frame.py --step 8        # quick check
    python experiments/benchmark_frame.py --json out/benchmark.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RELATIVE_FLOOR = 1e-3  # compare where BRDF > RELATIVE_FLOOR * max


def render_default_chunk() -> int:
    """``brdfjax.render``'s default ``chunk_pixels``, read from its signature so the table cannot drift."""
    import inspect

    from brdfjax.core.render import render

    return int(inspect.signature(render).parameters["chunk_pixels"].default)


# --- memory helpers (worker side) -----------------------------------------------------------


def _status_kib(key: str) -> int | None:
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    m = re.search(rf"^{key}:\s+(\d+)\s+kB", text, re.MULTILINE)
    return int(m.group(1)) if m else None


def _reset_high_water_mark() -> bool:
    """Reset VmHWM to the current RSS (Linux >= 4.0); False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


class PeakRSS:
    """RSS high-water-mark increase (MiB) over the RSS at the last ``start()``."""

    def __init__(self) -> None:
        self.can_reset = _status_kib("VmHWM") is not None and _reset_high_water_mark()
        self.method = (
            "VmHWM - VmRSS (/proc/self/status, reset via clear_refs)"
            if self.can_reset
            else "ru_maxrss - RSS baseline (not resettable: includes the first call)"
        )
        self.base_kib = 0

    def start(self) -> None:
        if self.can_reset:
            _reset_high_water_mark()
            self.base_kib = _status_kib("VmRSS") or 0
        elif not self.base_kib:
            rss = _status_kib("VmRSS")
            self.base_kib = rss if rss is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    def peak_mib(self) -> float:
        hwm = _status_kib("VmHWM") if self.can_reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return max(0, hwm - self.base_kib) / 1024.0


# --- workers ---------------------------------------------------------------------------------


def _worker_numpy(args) -> dict:
    from brdfjax import reference

    theta_i = np.deg2rad(args.theta_i)
    mem = PeakRSS()
    mem.start()
    times, peaks = [], []
    out = None
    for _ in range(args.numpy_repeats):
        out = None
        t0 = time.perf_counter()
        out = reference.solar_cell_frame(theta_i, step=args.step)
        times.append(time.perf_counter() - t0)
        peaks.append(mem.peak_mib())
    if args.save:
        np.save(args.save, out)
    return {
        "path": "numpy",
        "precision": "float64",
        "chunk": "128 rows",
        "shape": list(out.shape),
        "times_s": times,
        "steady_s": float(np.median(times)),
        "min_s": float(np.min(times)),
        "peak_rss_mib": float(max(peaks)),
        "memory_method": mem.method,
        "max_brdf": float(out.max()),
    }


def _worker_jax(args) -> dict:
    import jax

    if args.precision == "float64":
        jax.config.update("jax_enable_x64", True)
    import brdfjax as bj

    if args.chunk_pixels is None:
        args.chunk_pixels = render_default_chunk()
    model = bj.solar_cell()
    frame = bj.Conditions.from_degrees(args.theta_i)
    detector = bj.Detector.seed()

    def run():
        return bj.render(
            model, frame, detector, step=args.step, precision=args.precision, chunk_pixels=args.chunk_pixels
        ).block_until_ready()

    mem = PeakRSS()
    mem.start()
    t0 = time.perf_counter()
    out = run()
    first = time.perf_counter() - t0

    times = []
    for _ in range(args.repeats):
        out = None
        t0 = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t0)
    peak = mem.peak_mib()

    device = out.devices().pop()
    stats = device.memory_stats() or {}
    host = np.asarray(out)
    del out
    xla_mib = _xla_buffer_mib(lambda: bj.render(
        model, frame, detector, step=args.step, precision=args.precision, chunk_pixels=args.chunk_pixels
    ))
    if args.save:
        np.save(args.save, host)
    return {
        "path": "jax",
        "precision": args.precision,
        "chunk": args.chunk_pixels,
        "shape": list(host.shape),
        "first_call_s": first,
        "times_s": times,
        "steady_s": float(np.median(times)),
        "min_s": float(np.min(times)),
        "peak_rss_mib": peak,
        "device_peak_mib": stats["peak_bytes_in_use"] / 2**20 if "peak_bytes_in_use" in stats else None,
        "xla_output_temp_mib": xla_mib,
        "memory_method": mem.method,
        "max_brdf": float(host.max()),
        "jax_version": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
        "device_kind": device.device_kind,
        "platform": device.platform,
    }


def _timed_alternating(fns: dict, repeats: int) -> dict[str, list[float]]:
    """Call each function once (warm-up), then all of them in turn ``repeats`` times; the times of each."""
    for f in fns.values():
        f()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return times


def _worker_duel(args) -> dict:
    """brdfjax.core.render (float32) and the fused numba kernel, alternating in one process."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import fused_numba  # noqa: PLC0415 -- the sibling module, only in this worker

    import brdfjax as bj

    model, frame, detector = bj.solar_cell(), bj.Conditions.from_degrees(args.theta_i), bj.Detector.seed()
    theta_i = np.deg2rad(args.theta_i)
    out = np.empty(tuple(-(-n // args.step) for n in detector.shape), np.float32)
    t0 = time.perf_counter()
    fused_numba.solar_cell_frame(theta_i, step=args.step, out=out)
    numba_first = time.perf_counter() - t0
    fns = {
        "jax": lambda: bj.render(model, frame, detector, step=args.step).block_until_ready(),
        "numba": lambda: fused_numba.solar_cell_frame(theta_i, step=args.step, out=out),
    }
    times = _timed_alternating(fns, args.duel_repeats)
    if args.save:
        np.save(args.save, out)
        np.save(args.save.replace(".npy", "_jax.npy"), np.asarray(fns["jax"]()))
    import numba  # noqa: PLC0415 -- version only

    return {
        "path": "duel",
        "numba_version": numba.__version__,
        "numba_threads": numba.get_num_threads(),
        "numba_first_call_s": numba_first,
        "times_s": times,
        "median_s": {k: float(np.median(v)) for k, v in times.items()},
        "min_s": {k: float(np.min(v)) for k, v in times.items()},
    }


def _llvm_for_drjit() -> str | None:
    """An LLVM >= 17 shared library for Dr.Jit's LLVM backend, or None."""
    import glob  # noqa: PLC0415 -- only here

    for pattern in ("/usr/lib/x86_64-linux-gnu/libLLVM-{v}.so", "/usr/lib/llvm-{v}/lib/libLLVM-{v}.so",
                    "/usr/lib/llvm-{v}/lib/libLLVM.so", "/usr/lib/x86_64-linux-gnu/libLLVM.so.{v}*"):
        for v in (21, 20, 19, 18, 17):
            hits = sorted(glob.glob(pattern.format(v=v)))
            if hits:
                return hits[0]
    return None


def _worker_lobe(args) -> dict:
    """The bare Beckmann lobe over the seed frame's direction pairs: brdfjax and Mitsuba 3, alternating."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import brdfjax as bj

    m, n, k = args.lobe_m, 1.5, 0.0
    detector = bj.Detector.seed()
    grid = detector.grid(args.step)
    theta_i = np.float32(np.deg2rad(args.theta_i))
    dirs = detector.directions(
        jnp.asarray(grid.n_h, jnp.float32)[None, :], jnp.asarray(grid.n_v, jnp.float32)[:, None], theta_i
    )
    w_s = [np.ascontiguousarray(np.broadcast_to(np.asarray(c, np.float32), grid.shape).ravel()) for c in dirs.s]
    w_i = [float(np.asarray(c)) for c in dirs.i]
    n_pairs = w_s[0].size
    terms = {
        "brdfjax_ts_smith": bj.Specular(bj.Beckmann(m), rho_s=1.0, n=n, k=k, shadowing="smith",
                                        normalisation="torrance_sparrow", fresnel="q_factor"),
        "brdfjax_seed": bj.Specular(bj.Beckmann(m), rho_s=1.0, n=n, k=k, **bj.SEED_FORM),
    }
    ws_dev = [jnp.asarray(c) for c in w_s]

    @eqx.filter_jit
    def lobe(term, sx, sy, sz):
        ix, iy, iz = (jnp.float32(c) for c in w_i)
        d = bj.Directions((ix, iy, iz), (sx, sy, sz), (ix + sx, iy + sy, iz + sz))
        return term(d, 632.8e-9) * sz  # f cos(theta_s), what Mitsuba's eval returns

    fns = {name: (lambda t=t: lobe(t, *ws_dev).block_until_ready()) for name, t in terms.items()}
    res = {"path": "lobe", "n_pairs": n_pairs, "m": m, "n": n, "k": k, "jax_version": jax.__version__}
    peak = {name: np.asarray(lobe(t, *ws_dev)) for name, t in terms.items()}

    # the memory floor of any evaluator handed the three direction arrays: read them, write one array
    @jax.jit
    def floor(sx, sy, sz):
        return sx * sy + sz

    fns["memory_floor"] = lambda: floor(*ws_dev).block_until_ready()
    try:
        import drjit as dr  # noqa: PLC0415 -- optional baseline
        import mitsuba as mi  # noqa: PLC0415

        mi.set_variant("llvm_ad_mono")
        bsdf = mi.load_dict({"type": "roughconductor", "distribution": "beckmann", "alpha": m, "eta": n, "k": k,
                             "sample_visible": False})
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*w_i)
        si.n = mi.Normal3f(0.0, 0.0, 1.0)
        si.sh_frame = mi.Frame3f(si.n)
        ctx = mi.BSDFContext()
        wo = mi.Vector3f(*w_s)

        def mitsuba_eval():
            v = bsdf.eval(ctx, si, wo)
            dr.eval(v)
            dr.sync_thread()
            return v

        fns["mitsuba"] = mitsuba_eval
        peak["mitsuba"] = np.asarray(mitsuba_eval()[0], np.float32).ravel()
        res["mitsuba_version"] = mi.__version__
        res["mitsuba_variant"] = "llvm_ad_mono"
    except Exception as e:  # noqa: BLE001 - any failure to load the optional baseline skips it, with the reason
        res["mitsuba_skipped"] = f"{type(e).__name__}: {e}".splitlines()[0][:200]
    times = _timed_alternating(fns, args.duel_repeats)
    i_peak = int(np.argmax(peak["brdfjax_ts_smith"]))
    res.update({
        "times_s": times,
        "median_s": {k: float(np.median(v)) for k, v in times.items()},
        "min_s": {k: float(np.min(v)) for k, v in times.items()},
        "peak_values": {k: float(np.ravel(v)[i_peak]) for k, v in peak.items()},
        "sum_values": {k: float(np.sum(np.ravel(v), dtype=np.float64)) for k, v in peak.items()},
    })
    return res


def _xla_buffer_mib(fn) -> float | None:
    """Output + temporary buffer size (MiB) of ``fn`` compiled by XLA (``Compiled.memory_analysis``).

    Exact for the compiled program and the same on every backend; compiles
    ``fn`` once more (not timed).  None where the backend does not report it.
    """
    import jax

    try:
        stats = jax.jit(fn).lower().compile().memory_analysis()
    except Exception:  # noqa: BLE001 - a missing analysis must not fail the benchmark
        return None
    if stats is None:
        return None
    return (stats.output_size_in_bytes + stats.temp_size_in_bytes) / 2**20


# --- parent ----------------------------------------------------------------------------------


def _spawn(argv: list[str], tmp: Path, tag: str, env: dict | None = None) -> dict:
    result = tmp / f"{tag}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), *argv, "--worker-json", str(result)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0 or not result.exists():
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"benchmark worker '{tag}' failed (exit {proc.returncode}); its output is above")
    return json.loads(result.read_text())


def _max_rel_diff(test: np.ndarray, ref: np.ndarray) -> float:
    mask = ref > RELATIVE_FLOOR * ref.max()
    return float(np.max(np.abs(test[mask].astype(np.float64) - ref[mask]) / ref[mask]))


def _chunk_label(chunk) -> str:
    if isinstance(chunk, int):
        e = int(np.log2(chunk))
        return f"2^{e}" if 1 << e == chunk else str(chunk)
    return str(chunk)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _table(rows: list[dict], n_pixels: int) -> str:
    head = ["path", "precision", "chunk_pixels", "compile+1st [s]", "steady [s]", "Mpix/s",
            "XLA out+temp [MiB]", "peak RSS [MiB]", "device peak [MiB]", "max rel diff", "NumPy/JAX"]
    body = []
    for r in rows:
        body.append([
            "NumPy oracle" if r["path"] == "numpy" else "JAX jit",
            r["precision"],
            _chunk_label(r["chunk"]),
            f"{r['first_call_s']:.2f}" if "first_call_s" in r else "-",
            f"{r['steady_s']:.3f}",
            f"{n_pixels / r['steady_s'] / 1e6:.1f}",
            f"{r['xla_output_temp_mib']:.1f}" if r.get("xla_output_temp_mib") is not None else "-",
            f"{r['peak_rss_mib']:.0f}",
            f"{r['device_peak_mib']:.0f}" if r.get("device_peak_mib") is not None else "-",
            f"{r['max_rel_diff']:.1e}" if r.get("max_rel_diff") is not None else "-",
            f"{r['speedup']:.1f}x" if r.get("speedup") is not None else "-",
        ])
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(head)]
    fmt = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    lines = [fmt(head), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += [fmt(b) for b in body]
    return "\n".join(lines)


def _parent(args) -> dict:
    default_chunk = render_default_chunk()
    chunks = sorted({*args.chunks, default_chunk})
    configs = [("float32", default_chunk), ("float64", default_chunk)]
    configs += [("float32", c) for c in chunks if c != default_chunk]
    common = ["--theta-i", str(args.theta_i), "--step", str(args.step)]

    with tempfile.TemporaryDirectory(prefix="brdfjax_bench_") as tmpdir:
        tmp = Path(tmpdir)
        rows = []
        ref = None
        if not args.skip_numpy:
            print("running NumPy float64 oracle ...", file=sys.stderr, flush=True)
            r = _spawn(["--path", "numpy", "--numpy-repeats", str(args.numpy_repeats), *common,
                        "--save", str(tmp / "numpy.npy")], tmp, "numpy")
            ref = np.load(tmp / "numpy.npy")
            rows.append(r)
        for precision, chunk in configs:
            tag = f"jax_{precision}_{chunk}"
            print(f"running JAX {precision}, chunk_pixels={_chunk_label(chunk)} ...", file=sys.stderr, flush=True)
            r = _spawn(["--path", "jax", "--precision", precision, "--chunk-pixels", str(chunk),
                        "--repeats", str(args.repeats), *common, "--save", str(tmp / f"{tag}.npy")], tmp, tag)
            if ref is not None:
                r["max_rel_diff"] = _max_rel_diff(np.load(tmp / f"{tag}.npy"), ref)
            rows.append(r)
        # float64 again at the fastest float32 chunk size, if that is not the default.
        best = min((r for r in rows if r["path"] == "jax" and r["precision"] == "float32"), key=lambda r: r["steady_s"])
        if best["chunk"] != default_chunk:
            chunk = best["chunk"]
            tag = f"jax_float64_{chunk}"
            print(f"running JAX float64, chunk_pixels={_chunk_label(chunk)} ...", file=sys.stderr, flush=True)
            r = _spawn(["--path", "jax", "--precision", "float64", "--chunk-pixels", str(chunk),
                        "--repeats", str(args.repeats), *common, "--save", str(tmp / f"{tag}.npy")], tmp, tag)
            if ref is not None:
                r["max_rel_diff"] = _max_rel_diff(np.load(tmp / f"{tag}.npy"), ref)
            rows.append(r)

        duel = lobe = None
        if not args.skip_duel:
            try:
                import numba  # noqa: F401, PLC0415 -- presence check only
            except ImportError:
                duel = {"skipped": "numba is not installed (pip install 'brdfjax[bench]')"}
            else:
                print("running JAX float32 vs the fused numba kernel, alternating ...", file=sys.stderr, flush=True)
                duel = _spawn(["--path", "duel", "--duel-repeats", str(args.duel_repeats), *common,
                               "--save", str(tmp / "numba.npy")], tmp, "duel")
                if ref is not None:
                    duel["numba_max_rel_diff"] = _max_rel_diff(np.load(tmp / "numba.npy"), ref)
                    duel["jax_max_rel_diff"] = _max_rel_diff(np.load(tmp / "numba_jax.npy"), ref)
            print("running the bare Beckmann lobe: brdfjax vs Mitsuba 3, alternating ...", file=sys.stderr, flush=True)
            env = dict(os.environ)
            if "DRJIT_LIBLLVM_PATH" not in env and _llvm_for_drjit():
                env["DRJIT_LIBLLVM_PATH"] = _llvm_for_drjit()
            lobe = _spawn(["--path", "lobe", "--duel-repeats", str(args.duel_repeats), *common], tmp, "lobe", env=env)
            lobe["drjit_libllvm"] = env.get("DRJIT_LIBLLVM_PATH")

    numpy_s = rows[0]["steady_s"] if ref is not None else None
    for r in rows:
        r["speedup"] = numpy_s / r["steady_s"] if numpy_s is not None else None
    shape = rows[-1]["shape"]
    jax_row = next(r for r in rows if r["path"] == "jax")
    return {
        "model": "solar_cell() seed §6.4 parameters",
        "theta_i_deg": args.theta_i,
        "phi_ref_deg": 0.0,
        "step": args.step,
        "shape": shape,
        "n_pixels": int(np.prod(shape)),
        "repeats": args.repeats,
        "numpy_repeats": args.numpy_repeats,
        "relative_floor": RELATIVE_FLOOR,
        "jax_version": jax_row["jax_version"],
        "devices": jax_row["devices"],
        "device_kind": jax_row["device_kind"],
        "host_cpu": _cpu_name(),
        "host_cpu_count": os.cpu_count(),
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "memory_method": jax_row["memory_method"],
        "default_chunk_pixels": default_chunk,
        "rows": rows,
        "duel": duel,
        "lobe": lobe,
    }


def _report(res: dict) -> str:
    n = res["n_pixels"]
    rows_sorted = res["rows"]
    lines = [
        f"brdfjax frame benchmark: solar_cell() (seed §6.4), theta_i = {res['theta_i_deg']:g} deg, phi_ref = 0, "
        f"{res['shape'][1]} x {res['shape'][0]} = {n:,} pixels (step {res['step']})",
        f"JAX {res['jax_version']} devices: {', '.join(res['devices'])} ({res['device_kind']}); host: "
        f"{res['host_cpu']}, {res['host_cpu_count']} CPUs, load average "
        + (", ".join(f"{x:.1f}" for x in res["load_average"]) if res["load_average"] else "n/a"),
        f"steady = median of {res['repeats']} JAX calls after the first / {res['numpy_repeats']} NumPy calls; "
        f"max rel diff over pixels with BRDF > {res['relative_floor']:g} x max",
        f"peak RSS = process high-water-mark increase over the RSS before the first call, over all calls "
        f"(JAX: compilation included) [{res['memory_method']}]",
        "XLA out+temp = output + temporary buffers of the compiled program (Compiled.memory_analysis); "
        "device peak = the accelerator's peak_bytes_in_use where the backend reports it (not on CPU)",
        "",
        _table(rows_sorted, n),
    ]
    if res["rows"][0]["path"] == "numpy":
        best = min((r for r in res["rows"] if r["path"] == "jax"), key=lambda r: r["steady_s"])
        default_chunk = res["default_chunk_pixels"]
        default = next(r for r in res["rows"] if r["path"] == "jax" and r["chunk"] == default_chunk)
        lines += [
            "",
            f"NumPy/JAX (float32, render's default chunk_pixels {_chunk_label(default_chunk)}): {default['speedup']:.1f}x; "
            f"best: {best['speedup']:.1f}x ({best['precision']}, chunk_pixels {_chunk_label(best['chunk'])}); "
            f"fastest single calls: NumPy {res['rows'][0]['min_s']:.3f} s, JAX {default['min_s']:.3f} s "
            f"({res['rows'][0]['min_s'] / default['min_s']:.1f}x, a guide on a busy machine)",
        ]
    lines += _duel_report(res.get("duel"), n) + _lobe_report(res.get("lobe"))
    return "\n".join(lines)


def _paired(times: dict, num: str, den: str) -> float:
    """Median over the alternation rounds of ``time[num] / time[den]`` (each pair ran back to back)."""
    return float(np.median(np.asarray(times[num]) / np.asarray(times[den])))


def _duel_report(duel: dict | None, n: int) -> list[str]:
    if duel is None:
        return []
    if "skipped" in duel:
        return ["", f"fused numba kernel: skipped ({duel['skipped']})"]
    med, mn = duel["median_s"], duel["min_s"]
    acc = (f"; max rel diff vs the NumPy oracle: numba {duel['numba_max_rel_diff']:.1e}, "
           f"JAX {duel['jax_max_rel_diff']:.1e}" if "numba_max_rel_diff" in duel else "")
    return [
        "",
        f"float32 frame, brdfjax.core.render vs the fused numba kernel (experiments/fused_numba.py, numba "
        f"{duel['numba_version']}, {duel['numba_threads']} threads), alternating in one process, "
        f"{len(duel['times_s']['jax'])} calls each{acc}",
        "| kernel | median [s] | min [s] | Mpix/s (median) |",
        "| --- | --- | --- | --- |",
        f"| brdfjax.core.render float32 | {med['jax']:.3f} | {mn['jax']:.3f} | {n / med['jax'] / 1e6:.1f} |",
        f"| fused numba | {med['numba']:.3f} | {mn['numba']:.3f} | {n / med['numba'] / 1e6:.1f} |",
        f"brdfjax / numba time: {med['jax'] / med['numba']:.2f}x (medians), {mn['jax'] / mn['numba']:.2f}x (minima), "
        f"{_paired(duel['times_s'], 'jax', 'numba'):.2f}x (median of the back-to-back pairs); target <= 1.2x",
    ]


def _lobe_report(lobe: dict | None) -> list[str]:
    if lobe is None:
        return []
    med, mn, peak = lobe["median_s"], lobe["min_s"], lobe["peak_values"]
    labels = {
        "brdfjax_ts_smith": "brdfjax Specular(Beckmann), Torrance-Sparrow + Smith G2, x cos_s",
        "brdfjax_seed": "brdfjax Specular(Beckmann), the seed's Eq 70 (no G), x cos_s",
        "mitsuba": f"Mitsuba {lobe.get('mitsuba_version', '')} roughconductor beckmann, {lobe.get('mitsuba_variant', '')}",
        "memory_floor": "memory floor: read the three direction arrays, write one (sx * sy + sz)",
    }
    lines = [
        "",
        f"bare Beckmann lobe, m = {lobe['m']:g}, n = {lobe['n']:g} + {lobe['k']:g}i, over {lobe['n_pairs']:,} direction "
        f"pairs (the seed frame's), float32, alternating in one process, {len(lobe['times_s']['brdfjax_seed'])} calls each",
        "| evaluator | median [s] | min [s] | M pairs/s (median) | value at the peak |",
        "| --- | --- | --- | --- | --- |",
    ]
    for key in ("brdfjax_ts_smith", "brdfjax_seed", "mitsuba", "memory_floor"):
        if key in med:
            value = f"{peak[key]:.6g}" if key in peak else "-"
            lines.append(f"| {labels[key]} | {med[key]:.4f} | {mn[key]:.4f} | {lobe['n_pairs'] / med[key] / 1e6:.0f} | {value} |")
    if "mitsuba" in med:
        lines.append(
            f"Mitsuba / brdfjax time (>= 1: brdfjax at or above Mitsuba's rate): like-for-like (TS + Smith) "
            f"{med['mitsuba'] / med['brdfjax_ts_smith']:.2f}x medians, {mn['mitsuba'] / mn['brdfjax_ts_smith']:.2f}x minima, "
            f"{_paired(lobe['times_s'], 'mitsuba', 'brdfjax_ts_smith'):.2f}x median of pairs; seed lobe "
            f"{med['mitsuba'] / med['brdfjax_seed']:.2f}x medians, {mn['mitsuba'] / mn['brdfjax_seed']:.2f}x minima, "
            f"{_paired(lobe['times_s'], 'mitsuba', 'brdfjax_seed'):.2f}x median of pairs; peak value brdfjax / Mitsuba "
            f"{peak['brdfjax_ts_smith'] / peak['mitsuba']:.5f}"
        )
        lines.append(f"memory floor / Mitsuba {mn['memory_floor'] / mn['mitsuba']:.2f} (minima: how close an evaluator "
                     f"handed the three arrays can get)")
    else:
        lines.append(f"Mitsuba 3: skipped ({lobe.get('mitsuba_skipped')})")
    return lines


def _parse_chunks(text: str) -> list[int]:
    """'2**18,2**20,1048576' -> [262144, 1048576, 1048576]."""
    out = []
    for item in text.split(","):
        base, _, exp = item.strip().partition("**")
        try:
            value = int(base) ** int(exp) if exp else int(base)
        except ValueError:
            raise argparse.ArgumentTypeError(f"chunk_pixels must be integers or powers like 2**20, got {item!r}") from None
        if value < 1:
            raise argparse.ArgumentTypeError(f"chunk_pixels must be positive, got {item!r}")
        out.append(value)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--step", type=int, default=1, help="evaluate every STEP-th pixel (1: full 3296 x 2472 frame)")
    p.add_argument("--theta-i", type=float, default=20.0, help="incidence angle in degrees (default 20)")
    p.add_argument("--repeats", type=int, default=3, help="steady-state JAX calls after the first, median taken (default 3)")
    p.add_argument("--numpy-repeats", type=int, default=2, help="NumPy calls, median taken (default 2)")
    p.add_argument("--chunks", type=_parse_chunks,
                   default=[1 << 12, 1 << 14, 1 << 16, 1 << 18, 1 << 20, 1 << 22],
                   help="comma-separated chunk_pixels values for the float32 sweep, e.g. '2**18,2**20,2**22'")
    p.add_argument("--skip-numpy", action="store_true", help="JAX rows only (no speed-up or accuracy columns)")
    p.add_argument("--skip-duel", action="store_true", help="no numba and Mitsuba comparisons")
    p.add_argument("--duel-repeats", type=int, default=9,
                   help="alternating calls of each side in the numba and Mitsuba comparisons (default 9)")
    p.add_argument("--lobe-m", type=float, default=2e-4, help=argparse.SUPPRESS)
    p.add_argument("--json", type=Path, help="also write all figures to this JSON file")
    # internal: worker modes driven by the parent
    p.add_argument("--path", choices=["jax", "numpy", "duel", "lobe"], help=argparse.SUPPRESS)
    p.add_argument("--precision", choices=["float32", "float64"], default="float32", help=argparse.SUPPRESS)
    p.add_argument("--chunk-pixels", type=int, help=argparse.SUPPRESS)
    p.add_argument("--save", help=argparse.SUPPRESS)
    p.add_argument("--worker-json", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.step < 1 or args.repeats < 1 or args.numpy_repeats < 1 or args.duel_repeats < 1:
        p.error("--step, --repeats, --numpy-repeats and --duel-repeats must be positive integers")

    if args.path is not None:
        workers = {"jax": _worker_jax, "numpy": _worker_numpy, "duel": _worker_duel, "lobe": _worker_lobe}
        res = workers[args.path](args)
        Path(args.worker_json).write_text(json.dumps(res))
        return 0

    res = _parent(args)
    print(_report(res))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
