"""Benchmark: the instrument layer on the full seed frame (3296 x 2472, 14 bit, four exposures).

What is timed, stage by stage, in one process:

``render``      the seed's solar-cell model on every pixel (``bj.render``, float32)
``synthesise``  the synthetic instrument (:mod:`brdfjax.instrument.synthetic`):
                beam signature + its background, the sample (footprint FFT
                convolution, Eq 45 inverted, stray light, ambient, four
                exposures with shot/dark noise, non-linearity, quantisation,
                saturation) + its background, seed defaults; one stack at a
                time (synthesise, write, drop), the times summed
``write``       each raw stack as a multi-part ZIP OpenEXR file (atomic)
``read``        reading and validating each file back (:func:`read_raw_exr`)
``reduce``      :func:`reduce_measurement_set`: stitching of beam and sample
                (inverse-variance merge), incident flux (Eq 87), Eq 45 on the
                core pixel mapping, masks, §4.2 figures, the Chapter IV
                per-pixel uncertainty, and the atomic write of the frame with
                its extra channels (the reduction re-reads the four files, so
                its time includes a second ``read``)

Peak memory: the process's resident-set high-water mark during each stage
minus the RSS at its start (``VmHWM`` reset through ``/proc/self/clear_refs``,
Linux; the largest over a stage's repetitions), and the overall high-water
mark.  The frame itself is 31 MiB in float32; a four-exposure stack with
``counts_std`` is 250 MiB.

Usage::

    python experiments/benchmark_instrument.py            # full frame
    python experiments/benchmark_instrument.py --bin 8    # quick: 412 x 309 pixels, coarse camera

Nothing here is CPU-specific; on a GPU machine only ``render`` and the
uncertainty step use the accelerator (the rest is NumPy and OpenEXR).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _status_kib(key: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


class Stage:
    """Wall time and peak RSS growth of a block of code."""

    rows: list[tuple[str, float, float | None, str]] = []

    def __init__(self, name: str, note: str = ""):
        self.name, self.note = name, note

    def __enter__(self):
        try:
            Path("/proc/self/clear_refs").write_text("5")
            self.can = True
        except OSError:
            self.can = False
        self.rss0 = _status_kib("VmRSS")
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        dt = time.perf_counter() - self.t0
        hwm = _status_kib("VmHWM") if self.can else None
        peak = (hwm - self.rss0) / 1024 if hwm is not None and self.rss0 is not None else None
        Stage.rows.append((self.name, dt, peak, self.note))
        return False


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", type=int, default=1, help="k x k binned camera for quick runs (default 1: full frame)")
    ap.add_argument("--theta-i", type=float, default=20.0, help="incidence angle, deg (default 20)")
    ap.add_argument("--nd", default="3.0", help="sample ND filter stack (default '3.0')")
    ap.add_argument("--merge", default="weighted", choices=("weighted", "replacement"))
    ap.add_argument("--keep", type=Path, default=None, help="write the set and the output here instead of a temp dir")
    args = ap.parse_args(argv)

    import jax

    import brdfjax as bj
    from brdfjax.instrument.reduce import read_reduced_frame, reduce_measurement_set
    from brdfjax.instrument.synthetic import InstrumentConfig, SyntheticInstrument
    from brdfjax.io.raw import Calibration, read_raw_exr, write_raw_exr

    k = args.bin
    shape = (2472 // k, 3296 // k)
    det = bj.Detector.seed(shape=shape, pixel_pitch=5.5e-6 * k, pixel_pitch_v=5.5e-6 * k)
    cfg = InstrumentConfig() if k == 1 else InstrumentConfig().coarse(k)
    ins = SyntheticInstrument(det, cfg, seed=2024)
    frame = bj.Conditions.from_degrees(args.theta_i)
    model = bj.solar_cell()
    base_rss = _status_kib("VmRSS")

    tmp_ctx = tempfile.TemporaryDirectory() if args.keep is None else None
    root = Path(tmp_ctx.name) if tmp_ctx else args.keep
    folder, out = root / "set", root / "out"
    folder.mkdir(parents=True, exist_ok=True)

    with Stage("render", "solar cell, float32, incl. jit compile"):
        brdf = ins.render_brdf(model, frame)
        brdf.sum()
    # One stack at a time, as SyntheticInstrument.write_set does: synthesise, write, drop.
    from brdfjax.io.raw import write_manifest

    def synth_and_write(name, make):
        with Stage("synthesise", name):
            st = make()
        with Stage("write", name):
            write_raw_exr(folder / f"{name}.exr", st.attrs, st.exposures)
        return st.attrs

    beam_attrs = synth_and_write("beam", lambda: ins.measure_beam())
    synth_and_write("beam_background", lambda: ins.measure_background(beam_attrs))
    sample_attrs = synth_and_write("solar_cell", lambda: ins.measure_sample(brdf, frame, args.nd, sample="solar_cell"))
    synth_and_write("solar_cell_background", lambda: ins.measure_background(sample_attrs))
    write_manifest(
        folder / "manifest.toml",
        ("beam.exr", "beam_background.exr"),
        [("solar_cell", "solar_cell.exr", "solar_cell_background.exr")],
        Calibration(nd_tolerances={3.0: 0.15}),
    )
    sizes = {p.name: p.stat().st_size for p in folder.glob("*.exr")}
    for p in sorted(folder.glob("*.exr")):
        with Stage("read", p.stem):
            st = read_raw_exr(p)
        del st
    with Stage("reduce", f"merge={args.merge}, incl. re-read, uncertainty, write"):
        paths = reduce_measurement_set(folder / "manifest.toml", out, merge=args.merge)

    r = read_reduced_frame(paths[0])
    total_hwm = _status_kib("VmHWM")
    print(f"# benchmark_instrument: {shape[1]} x {shape[0]} pixels ({shape[0] * shape[1] / 1e6:.2f} Mpx), "
          f"{len(cfg.exposures_s)} exposures {[t * 1e3 for t in cfg.exposures_s]} ms, {cfg.adc_bits}-bit, "
          f"n_frames={cfg.n_frames}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__} "
          f"({jax.default_backend()}), numpy {np.__version__}, python {sys.version.split()[0]}")
    print()
    print(f"| {'stage':<11} | {'time (s)':>8} | {'peak RSS growth (MiB)':>21} | detail")
    print(f"|{'-' * 13}|{'-' * 10}|{'-' * 23}|------")
    for stage in dict.fromkeys(r[0] for r in Stage.rows):
        rows = [r for r in Stage.rows if r[0] == stage]
        dt = sum(r[1] for r in rows)
        peaks = [r[2] for r in rows if r[2] is not None]
        p = f"{max(peaks):.0f}" if peaks else "n/a"
        detail = "; ".join(f"{r[3]} {r[1]:.2f} s" for r in rows) if len(rows) > 1 else rows[0][3]
        print(f"| {stage:<11} | {dt:8.2f} | {p:>21} | {detail}")
    print()
    if base_rss and total_hwm:
        print(f"process RSS before the stages: {base_rss / 1024:.0f} MiB; lifetime peak: {total_hwm / 1024:.0f} MiB")
    print("raw file sizes (MiB): " + ", ".join(f"{n} {s / 2**20:.1f}" for n, s in sorted(sizes.items())))
    a = r.attrs
    print(f"reduced: {paths[0].name} {paths[0].stat().st_size / 2**20:.1f} MiB, {len(r.extra)} extra channels; "
          f"usable fraction {a['usable_fraction']:.4f}, peak {a['peak_brdf']:.4g} sr^-1, "
          f"NEB {a['noise_equivalent_brdf']:.4g} (std {a['noise_equivalent_brdf_std']:.3g}) sr^-1, "
          f"max {a['max_measurable_brdf']:.4g} sr^-1, {a['dynamic_range_decades']:.2f} decades")
    if tmp_ctx:
        tmp_ctx.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
