"""The ``brdfjax`` command line: ``brdfjax <subcommand> ...``.

A leaf: it parses arguments and dispatches to library code; nothing in
brdfjax imports it.  Subcommands are entries of :data:`COMMANDS` (a name, a
help line, a function adding its arguments and a function running it); the
fit, diagnose, sample and capture commands live beside their packages
(:mod:`brdfjax.fit.cli_fit`, :mod:`brdfjax.diagnose.cli`,
:mod:`brdfjax.sample.cli`, :mod:`brdfjax.devices.capture`).

``brdfjax simulate [CONFIG] --out DIR [--step K] [--precision P] [--no-plot]``
renders every frame of a TOML config (see :mod:`brdfjax.config`; without
CONFIG the packaged default job) and writes, per frame, ``<name>.exr``
(BRDF, theta_s, phi_s, solid angle; see :mod:`brdfjax.io.exr`) and
``<name>.png`` (see :mod:`brdfjax.plotting`), plus ``summary.json``.

Exit codes (every subcommand, :func:`brdfjax.errors.run_command`): 0 ran,
2 bad input or a refusal (the message names the file, key or value), 130
interrupted, 1 an internal error (a bug: the traceback and where to report it).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .compile_cache import enable_compilation_cache
from .errors import EXIT_OK, EXIT_REFUSED, InputError, run_command
from .progress import ProgressLine, make_console

# Each subcommand imports what it runs when it runs (a lazy entry below, or imports inside its
# runner): `brdfjax simulate` does not pay for the fit, sampling, device and instrument stacks
# (emcee, scipy.stats, ...), which were most of its start-up time.

__all__ = ["COMMANDS", "Command", "build_parser", "main"]

EXIT_USAGE = EXIT_REFUSED


# --- subcommands -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """A subcommand: ``add_arguments(parser)`` declares its options, ``run(args) -> exit code`` runs it."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config",
        nargs="?",
        default=None,
        metavar="CONFIG",
        help="TOML config (default: the packaged default job, brdfjax/data/default.toml)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument("--step", type=int, default=None, metavar="K", help="evaluate every K-th pixel (overrides grid.step)")
    p.add_argument(
        "--precision", choices=("float32", "float64"), default=None, help="floating-point precision (overrides precision)"
    )
    p.add_argument("--no-plot", action="store_true", help="write the EXR files and summary only, no PNG figures")


def _run_simulate(args: argparse.Namespace) -> int:
    import jax  # noqa: PLC0415 -- see the note on imports at the top

    from .config import load_simulate_config  # noqa: PLC0415
    from .io import check_output_dir  # noqa: PLC0415
    from .simulate import run_simulate  # noqa: PLC0415

    cfg = load_simulate_config(args.config)
    if args.step is not None or args.precision is not None:
        cfg = cfg.with_overrides(step=args.step, precision=args.precision)
    check_output_dir(args.out)
    if cfg.precision == "float64":
        # An edge may flip the process-wide switch; the library never does.
        jax.config.update("jax_enable_x64", True)

    console = make_console(args.quiet)
    grid_note = f"every {cfg.grid.step}th pixel" if cfg.grid.step > 1 else "every pixel"
    console.print(
        f"brdfjax simulate: {cfg.source} -> {args.out}: {len(cfg.frames)} frame(s), {grid_note}"
        + (f" of roi {cfg.roi}" if cfg.roi else "")
        + f", {cfg.precision}",
        markup=False,
    )
    summary = run_simulate(cfg, args.out, plot=not args.no_plot, console=console)
    console.print(f"wrote {Path(args.out) / 'summary.json'} ({summary['wall_s']:.1f} s)", markup=False)
    return EXIT_OK


def _reduce_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("manifest", metavar="MANIFEST", help="a measurement set's manifest.toml (or its folder)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument(
        "--merge",
        choices=("weighted", "replacement"),
        default="weighted",
        help="HDR merge: inverse-variance weighted (default) or the seed's replacement scheme (§3.6)",
    )
    p.add_argument("--step", type=int, default=1, metavar="K", help="keep every K-th pixel of the output frames")
    p.add_argument(
        "--correct-nonlinearity",
        action="store_true",
        help="correct the readings by the camera's response curve (manifest [calibration] nonlinearity_curve, "
        "else the seed's typical 1.72%% curve) before the weighted merge: removes the exposure-switch seams",
    )
    p.add_argument("--no-plot", action="store_true", help="write the EXR files and summary only, no PNG figures")


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


def _run_reduce(args: argparse.Namespace) -> int:
    from .detector import PixelGrid  # noqa: PLC0415 -- see the note on imports at the top
    from .instrument.reduce import read_reduced_frame, reduce_measurement_set  # noqa: PLC0415
    from .io import check_output_dir, detector_from_attrs, frame_from_attrs, write_json_atomic  # noqa: PLC0415
    from .plotting import plot_frame  # noqa: PLC0415

    if args.step < 1:
        raise InputError(f"--step must be a positive integer, got {args.step}")
    if args.correct_nonlinearity and args.merge != "weighted":
        raise InputError("--correct-nonlinearity needs --merge weighted (the replacement scheme is the seed's, §3.6)")
    if not Path(args.manifest).exists():
        raise InputError(f"{args.manifest}: no such manifest or folder (give a measurement set's manifest.toml)")
    check_output_dir(args.out)
    console = make_console(args.quiet)
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
        if not args.no_plot:
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


def _synthesize_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config", nargs="?", default=None, metavar="CONFIG",
        help="a simulate config naming the detector, model and frames (default: the packaged default job)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder for the measurement set")
    p.add_argument("--seed", type=int, default=0, help="noise seed (the same seed gives the same files)")
    p.add_argument(
        "--camera-seed", type=int, default=None, help="seed of the camera's fixed per-pixel maps (overrides the config)"
    )
    p.add_argument("--nd", default=None, metavar="STACK", help='sample ND filters, e.g. "3.0" (default: chosen by the seed\'s rule)')
    p.add_argument(
        "--instrument", default=None, metavar="TOML",
        help="instrument config: every effect's switch and parameters (see configs/instrument_seed.toml); "
        "default: the seed's instrument",
    )
    p.add_argument(
        "--without", default="", metavar="EFFECTS",
        help="comma-separated instrument effects to switch off (e.g. stray_light,ambient)",
    )


def _run_synthesize(args: argparse.Namespace) -> int:
    from .config import load_simulate_config  # noqa: PLC0415 -- see the note on imports at the top
    from .instrument.nd import parse_nd_filters  # noqa: PLC0415
    from .instrument.synthetic import EFFECTS, SyntheticInstrument, load_instrument_config  # noqa: PLC0415
    from .io import check_output_dir  # noqa: PLC0415

    # Everything that can be checked is checked before any frame is rendered or written.
    cfg = load_simulate_config(args.config)
    inst_cfg = load_instrument_config(args.instrument, args.camera_seed)
    off = [x.strip() for x in args.without.split(",") if x.strip()]
    unknown = sorted(set(off) - set(EFFECTS))
    if unknown:
        raise InputError(f"--without: unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")
    if cfg.grid.step != 1 or cfg.roi:
        raise InputError(f"{cfg.source}: grid.step/grid.roi do not apply: the synthetic camera reads the whole array")
    if args.nd is not None:
        try:
            parse_nd_filters(args.nd)
        except ValueError as e:
            raise InputError(f"--nd {args.nd!r}: {e}") from None
    check_output_dir(args.out)
    console = make_console(args.quiet)
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


def _lazy(module: str, name: str) -> Callable[..., Any]:
    """``module.name``, imported on first call (the subcommand's stack loads only when it is used)."""

    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(importlib.import_module(module, __package__), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = f"{module.lstrip('.')}.{name}"
    return call


#: Subcommands by name: each is a name, a help line, its argument declarations and its runner.
COMMANDS: dict[str, Command] = {
    "simulate": Command(
        "simulate",
        "render the frames of a config to OpenEXR + PNG + summary.json",
        _simulate_arguments,
        _run_simulate,
    ),
    "synthesize": Command(
        "synthesize",
        "measure a config's model with the synthetic instrument: raw OpenEXR stacks + manifest.toml",
        _synthesize_arguments,
        _run_synthesize,
    ),
    "reduce": Command(
        "reduce",
        "reduce a raw measurement set (manifest.toml) to calibrated BRDF frames with per-pixel uncertainty",
        _reduce_arguments,
        _run_reduce,
    ),
    "fit": Command(
        "fit",
        "fit a model to frames/tables from a TOML fit config: result.json (parameters, uncertainties, chi2) + figures",
        _lazy(".fit.cli_fit", "add_arguments"),
        _lazy(".fit.cli_fit", "run"),
    ),
    "diagnose": Command(
        "diagnose",
        "diagnose the gap between a base model and measured frames: where, which effect, how far it shrinks",
        _lazy(".diagnose.cli", "add_arguments"),
        _lazy(".diagnose.cli", "run"),
    ),
    "capture": Command(
        "capture",
        "run a capture plan (beam signature, alignment, samples) on the simulated bench or lab hardware: raw set",
        _lazy(".devices.capture", "capture_arguments"),
        _lazy(".devices.capture", "run_capture_command"),
    ),
    "batch": Command(
        "batch",
        "run a study: many fit/sample/diagnose/synthesize jobs on Ray or a process pool, one result file each, resumable",
        _lazy(".batch", "add_arguments"),
        _lazy(".batch", "run"),
    ),
    "sample": Command(
        "sample",
        "parameter posteriors with emcee from a fit config ([sample] table): chain.h5, posterior.json, corner/trace plots",
        _lazy(".sample.cli", "add_arguments"),
        _lazy(".sample.cli", "run"),
    ),
    "lightcurve": Command(
        "lightcurve",
        "a satellite's light curve from facets with brdfjax models along TLE passes: CSV, JSON, magnitude plot",
        _lazy(".lightcurve.cli", "add_arguments"),
        _lazy(".lightcurve.cli", "run"),
    ),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser; ``only``: declare the arguments of that subcommand alone (the others are
    listed with their help line), so that parsing one command imports only its own stack."""
    parser = argparse.ArgumentParser(
        prog="brdfjax",
        description="Differentiable near-specular BRDF models and CCD scatterometer frames in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"brdfjax {__version__}")
    parser.add_argument(
        "--no-cache", action="store_true",
        help="do not use the persistent compilation cache (default: on, in ~/.cache/brdfjax/jax; "
        "also off with BRDFJAX_NO_CACHE=1; folder: BRDFJAX_CACHE_DIR)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for cmd in COMMANDS.values():
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        if only is not None and cmd.name != only:
            continue
        cmd.add_arguments(p)
        if not any("--quiet" in a.option_strings for a in p._actions):
            p.add_argument("--quiet", action="store_true", help="no progress and no status lines (errors still print)")
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``brdfjax`` console script; returns the exit code.

    Every subcommand runs under :func:`brdfjax.errors.run_command` (0 ran, 2
    bad input or refused, 130 interrupted, 1 internal error); a usage error
    of argparse exits 2 with its message (``SystemExit``).
    """
    words = list(sys.argv[1:] if argv is None else argv)
    chosen = next((w for w in words if not w.startswith("-")), None)
    parser = build_parser(chosen if chosen in COMMANDS else None)
    args = parser.parse_args(words)
    if not args.no_cache:
        enable_compilation_cache()  # before any program is compiled: the second run on this machine starts warm
    return run_command(f"brdfjax {args.command}", lambda: args._run(args))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
