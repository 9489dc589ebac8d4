"""The ``brdfjax`` command line: ``brdfjax <subcommand> ...``.

A leaf: it parses arguments and dispatches to library code; nothing in
brdfjax imports it.  Subcommands are entries of :data:`COMMANDS` (a name, a
help line, a function adding its arguments and a function running it); the
fit, diagnose, sample and capture commands live beside their packages
(:mod:`brdfjax.cli.fit`, :mod:`brdfjax.cli.diagnose`,
:mod:`brdfjax.cli.sample`, :mod:`brdfjax.cli.capture`).

``brdfjax simulate [CONFIG] --out DIR [--step K] [--precision P] [--no-figures]``
renders every frame of a TOML config (see :mod:`brdfjax.config`; without
CONFIG the packaged default job) and writes, per frame, ``<name>.exr``
(BRDF, theta_s, phi_s, solid angle; see :mod:`brdfjax.io.exr`) and
``<name>.png`` (see :mod:`brdfjax.plotting`), plus ``summary.json``.

Exit codes (every subcommand, :func:`brdfjax.runtime.errors.run_command`): 0 ran,
2 bad input or a refusal (the message names the file, key or value), 130
interrupted, 1 an internal error (a bug: the traceback and where to report it).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from .. import __version__
from ..runtime.cli_args import CONFIG, DIR, add_no_figures, add_shared_flags, positive_int
from ..runtime.errors import EXIT_REFUSED, run_command

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
        metavar=CONFIG,
        help="TOML config (default: the packaged default job, brdfjax/data/default.toml)",
    )
    p.add_argument("--out", required=True, metavar=DIR, help="output folder (created if needed)")
    p.add_argument("--step", type=positive_int, default=None, metavar="K",
                   help="evaluate every K-th pixel, K >= 1 (overrides grid.step)")
    p.add_argument(
        "--precision", choices=("float32", "float64"), default=None, help="floating-point precision (overrides precision)"
    )
    add_no_figures(p, "write the EXR files and summary only, no PNG figures")


def _reduce_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("manifest", metavar="MANIFEST", help="a measurement set's manifest.toml (or its folder)")
    p.add_argument("--out", required=True, metavar=DIR, help="output folder (created if needed)")
    p.add_argument(
        "--merge",
        choices=("weighted", "replacement"),
        default="weighted",
        help="HDR merge: inverse-variance weighted (default) or the seed's replacement scheme (§3.6)",
    )
    p.add_argument("--step", type=positive_int, default=1, metavar="K", help="keep every K-th pixel of the output frames")
    p.add_argument(
        "--correct-nonlinearity",
        action="store_true",
        help="correct the readings by the camera's response curve (manifest [calibration] nonlinearity_curve, "
        "else the seed's typical 1.72%% curve) before the weighted merge: removes the exposure-switch seams",
    )
    add_no_figures(p, "write the EXR files and summary only, no PNG figures")


def _synthesize_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config", nargs="?", default=None, metavar=CONFIG,
        help="a simulate config naming the detector, model and frames (default: the packaged default job)",
    )
    p.add_argument("--out", required=True, metavar=DIR, help="output folder for the measurement set")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="noise seed (the same seed gives the same files)")
    p.add_argument(
        "--camera-seed", type=int, default=None, metavar="N", help="seed of the camera's fixed per-pixel maps (overrides the config)"
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
        _lazy(".instrument", "run_simulate_command"),
    ),
    "synthesize": Command(
        "synthesize",
        "measure a config's model with the synthetic instrument: raw OpenEXR stacks + manifest.toml",
        _synthesize_arguments,
        _lazy(".instrument", "run_synthesize_command"),
    ),
    "reduce": Command(
        "reduce",
        "reduce a raw measurement set (manifest.toml) to calibrated BRDF frames with per-pixel uncertainty",
        _reduce_arguments,
        _lazy(".instrument", "run_reduce_command"),
    ),
    "fit": Command(
        "fit",
        "fit a model to frames/tables from a TOML fit config: result.json (parameters, uncertainties, chi2) + figures",
        _lazy(".fit", "add_arguments"),
        _lazy(".fit", "run"),
    ),
    "diagnose": Command(
        "diagnose",
        "diagnose the gap between a base model and measured frames: where, which effect, how far it shrinks",
        _lazy(".diagnose", "add_arguments"),
        _lazy(".diagnose", "run"),
    ),
    "capture": Command(
        "capture",
        "run a capture plan (beam signature, alignment, samples) on the simulated bench or lab hardware: raw set",
        _lazy(".capture", "add_arguments"),
        _lazy(".capture", "run"),
    ),
    "batch": Command(
        "batch",
        "run a study: many fit/sample/diagnose/synthesize jobs on Ray or a process pool, one result file each, resumable",
        _lazy("..batch", "add_arguments"),
        _lazy("..batch", "run"),
    ),
    "sample": Command(
        "sample",
        "parameter posteriors (emcee or NUTS) from a fit config ([sample] table): chain.h5, posterior.json, corner/trace plots",
        _lazy(".sample", "add_arguments"),
        _lazy(".sample", "run"),
    ),
    "lightcurve": Command(
        "lightcurve",
        "a satellite's light curve from facets with brdfjax models along TLE passes: CSV, JSON, magnitude plot",
        _lazy(".lightcurve", "add_arguments"),
        _lazy(".lightcurve", "run"),
    ),
    "observe": Command(
        "observe",
        "predict real satellite observations (alt/az or relative rows) from facet BRDF fits: bands, flags, metrics",
        _lazy(".observe", "add_arguments"),
        _lazy(".observe", "run"),
    ),
    "skygap": Command(
        "skygap",
        "diagnose the gap between a facet model and observed magnitudes: which effect, where, how far on held-out nights",
        _lazy(".skygap", "add_arguments"),
        _lazy(".skygap", "run"),
    ),
}


#: What a shared flag means for a command that has nothing of its kind (the flag is accepted everywhere, so
#: that scripts and batch jobs can pass it to any command).
SHARED_NOTES: dict[str, dict[str, str]] = {
    "synthesize": {"--no-figures": "accepted for a uniform command line: synthesize writes no figures"},
    "capture": {"--no-figures": "no live PNG preview (the same as --live off)"},
    "simulate": {"--no-progress": "no per-frame progress lines (status lines still print)"},
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser; ``only``: declare the arguments of that subcommand alone (the others are
    listed with their help line; ``""``: of none), so that parsing one command imports only its own stack."""
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
        add_shared_flags(p, SHARED_NOTES.get(cmd.name))
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``brdfjax`` console script; returns the exit code.

    Every subcommand runs under :func:`brdfjax.runtime.errors.run_command` (0 ran, 2
    bad input or refused, 130 interrupted, 1 internal error); a usage error
    of argparse exits 2 with its message (``SystemExit``).
    """
    words = list(sys.argv[1:] if argv is None else argv)
    chosen = next((w for w in words if not w.startswith("-")), None)
    # no subcommand named (`brdfjax --help`, `--version`): declare no subcommand's arguments, so that none of
    # their stacks is imported; `build_parser()` (every command's arguments) is for the docs and the tests
    parser = build_parser(chosen if chosen in COMMANDS else "")
    args = parser.parse_args(words)
    if not args.no_cache:
        from ..runtime.compile_cache import enable_compilation_cache  # imports JAX: not for --help/--version

        enable_compilation_cache()  # before any program is compiled: the second run on this machine starts warm
    return run_command(f"brdfjax {args.command}", lambda: args._run(args))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
