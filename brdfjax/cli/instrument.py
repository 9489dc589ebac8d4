"""What ``brdfjax simulate``, ``synthesize`` and ``reduce`` run (imported by :mod:`brdfjax.cli` when one runs).

Kept apart from the argument declarations in :mod:`brdfjax.cli` so that
parsing a command line imports nothing but argparse, and running one command
imports only its own stack.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..config import load_simulate_config
from ..core.detector import PixelGrid
from ..io import check_output_dir, detector_from_attrs, frame_from_attrs, write_json_atomic
from ..plotting import plot_frame
from ..runtime.choices import check_choices
from ..runtime.errors import EXIT_OK, InputError
from ..runtime.progress import ProgressLine, make_console
from ..simulate import run_simulate

__all__ = ["run_reduce_command", "run_simulate_command", "run_synthesize_command"]


def run_simulate_command(args: argparse.Namespace) -> int:


    cfg = load_simulate_config(args.config)
    if args.step is not None or args.precision is not None:
        cfg = cfg.with_overrides(step=args.step, precision=args.precision)
    check_output_dir(args.out)
    if cfg.precision == "float64":
        # An edge may flip the process-wide switch; the library never does.
        jax.config.update("jax_enable_x64", True)

    console = make_console(args.quiet, args.no_progress)
    grid_note = f"every {cfg.grid.step}th pixel" if cfg.grid.step > 1 else "every pixel"
    console.print(
        f"brdfjax simulate: {cfg.source} -> {args.out}: {len(cfg.frames)} frame(s), {grid_note}"
        + (f" of roi {cfg.roi}" if cfg.roi else "")
        + f", {cfg.precision}",
        markup=False,
    )
    summary = run_simulate(cfg, args.out, plot=not args.no_figures, console=console)
    console.print(f"wrote {Path(args.out) / 'summary.json'} ({summary['wall_s']:.1f} s)", markup=False)
    return EXIT_OK


def _reduced_summary(path: Path, frame: Any) -> dict[str, Any]:
    mask = np.asarray(frame.extra["mask"]) > 0
    sig = np.asarray(frame.extra["sigma_rel"])
    b = np.asarray(frame.brdf)
    keys = (
        "theta_i", "phi_ref", "nd_sample", "od_sample", "incident_flux_sdc", "noise_equivalent_brdf",
        "max_measurable_brdf", "dynamic_range_decades", "usable_fraction", "merge", "saturated_pixels",
        "partly_saturated_pixels",
    )
    out = {k: frame.attrs[k] for k in keys if k in frame.attrs}
    out.update(
        file=path.name,
        shape=list(b.shape),
        usable_pixels=int(mask.sum()),
        max_brdf=float(np.max(np.where(mask, b, -np.inf))) if mask.any() else None,
        median_sigma_rel=float(np.median(sig[mask])) if mask.any() else None,
    )
    warnings = []
    if out.get("saturated_pixels"):
        warnings.append(
            f"{out['saturated_pixels']} pixel(s) saturated in every exposure, the shortest too: excluded "
            "(mask 0, flag 1); a denser ND filter or a shorter exposure would keep them"
        )
    if out.get("partly_saturated_pixels"):
        warnings.append(
            f"{out['partly_saturated_pixels']} pixel(s) saturated in some exposures: merged from the unsaturated ones only"
        )
    out["warnings"] = warnings
    return out


def run_reduce_command(args: argparse.Namespace) -> int:
    # the instrument stack loads only for the commands that use it (not for simulate)
    from ..instrument.reduce import read_reduced_frame, reduce_measurement_set  # noqa: PLC0415

    if args.step < 1:
        raise InputError(f"--step must be a positive integer, got {args.step}")
    if args.correct_nonlinearity and args.merge != "weighted":
        raise InputError("--correct-nonlinearity needs --merge weighted (the replacement scheme is the seed's, §3.6)")
    if not Path(args.manifest).exists():
        raise InputError(f"{args.manifest}: no such manifest or folder (give a measurement set's manifest.toml)")
    check_output_dir(args.out)
    console = make_console(args.quiet, args.no_progress)
    console.print(f"brdfjax reduce: {args.manifest} -> {args.out} ({args.merge} merge)", markup=False)
    t0 = time.perf_counter()
    with ProgressLine(console, "reduce", None, unit="sample(s)", min_interval_s=0.0) as bar:
        paths = reduce_measurement_set(
            args.manifest, args.out, merge=args.merge, step=args.step, correct_nonlinearity=args.correct_nonlinearity,
            progress=lambda done, total, name: bar.update(done, f"reduced {name}", total=total),
        )
    frames = []
    for path in paths:
        frame = read_reduced_frame(path)
        entry = _reduced_summary(path, frame)
        if not args.no_figures:
            a = frame.attrs
            h0, h1, v0, v1 = a["roi"]
            det = detector_from_attrs(a, (v1 - v0 + 1, h1 - h0 + 1), follow_peak=False)
            grid = PixelGrid(np.arange(h0, h1 + 1, a["step"]), np.arange(v0, v1 + 1, a["step"]))
            shown = np.where(np.asarray(frame.extra["mask"]) > 0, frame.brdf, np.nan)
            png = plot_frame(
                shown, grid, det, frame_from_attrs(a), path.with_suffix(".png"),
                title=f"{path.stem} (reduced, masked pixels blank)",
            )
            entry["png"] = png.name
        frames.append(entry)
        console.print(
            f"done {path.stem}: {entry['usable_pixels']} usable px, median sigma_rel "
            f"{entry['median_sigma_rel']:.3g}, noise-equivalent BRDF "
            f"{entry.get('noise_equivalent_brdf', float('nan')):.3g} sr^-1 -> {path.name}",
            markup=False,
        )
        for w in entry["warnings"]:
            console.print(f"warning: {path.stem}: {w}", markup=False)
    summary = {"manifest": str(args.manifest), "merge": args.merge, "step": args.step,
               "frames": frames, "wall_s": time.perf_counter() - t0}
    write_json_atomic(Path(args.out) / "summary.json", summary)
    console.print(f"wrote {Path(args.out) / 'summary.json'} ({summary['wall_s']:.1f} s)", markup=False)
    return EXIT_OK


def run_synthesize_command(args: argparse.Namespace) -> int:
    # the instrument stack loads only for the commands that use it (not for simulate)
    from ..instrument.nd import parse_nd_filters  # noqa: PLC0415
    from ..instrument.synthetic import EFFECTS, SyntheticInstrument, load_instrument_config  # noqa: PLC0415


    # Everything that can be checked is checked before any frame is rendered or written.
    cfg = load_simulate_config(args.config)
    inst_cfg = load_instrument_config(args.instrument, args.camera_seed)
    off = [x.strip() for x in args.without.split(",") if x.strip()]
    check_choices("effect", sorted(set(off)), EFFECTS, error=InputError, prefix="--without: ")
    if cfg.grid.step != 1 or cfg.roi:
        raise InputError(f"{cfg.source}: grid.step/grid.roi do not apply: the synthetic camera reads the whole array")
    if args.nd is not None:
        try:
            parse_nd_filters(args.nd)
        except ValueError as e:
            raise InputError(f"--nd {args.nd!r}: {e}") from None
    check_output_dir(args.out)
    console = make_console(args.quiet, args.no_progress)
    detector = cfg.build_detector()
    # The seed instrument's beam footprint and stray-light offsets are sizes on the array: scale
    # them to this detector's pixels (a no-op on the seed camera).
    inst_cfg = inst_cfg.without(*off)
    inst_cfg = inst_cfg.for_pixel_pitch(float(detector.pixel_pitch))
    instrument = SyntheticInstrument(detector, inst_cfg, seed=args.seed)
    model = cfg.build_model()
    t0 = time.perf_counter()
    frames = dict(cfg.build_frames())
    console.print(
        f"brdfjax synthesize: {cfg.source} -> {args.out}: {len(frames)} sample(s), "
        f"effects on: {', '.join(inst_cfg.enabled_effects())}",
        markup=False,
    )
    with ProgressLine(console, "synthesize", None, unit="step(s)", min_interval_s=0.0) as bar:
        manifest = instrument.measure_set(
            args.out, model, frames, nd_filters=args.nd, log=lambda line: console.print(line, markup=False),
            progress=lambda done, total, what: bar.update(done, what, total=total),
        )
    console.print(f"wrote {manifest} ({time.perf_counter() - t0:.1f} s)", markup=False)
    return EXIT_OK
