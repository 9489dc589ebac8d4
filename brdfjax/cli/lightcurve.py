"""``brdfjax lightcurve CONFIG --out DIR``: a satellite's light curve from a TOML config (see :mod:`.config`).

Writes ``lightcurve.csv`` (one row per visible time step: time, elevation,
phase angle, sunlit fraction, per-facet incidence and scatter angles and
magnitudes, the total magnitude of every compared model, posterior bands),
``lightcurve.json`` (the summary: glints, comparisons, and the series) and
``lightcurve.png``.  Exit codes: the contract of :func:`brdfjax.runtime.errors.run_command`
(0 ran, 2 a bad config or an output that cannot be written, with the message
naming the file and key; 130 interrupted; 1 an internal error).
"""

from __future__ import annotations

import argparse
import sys

import jax

from ..io import check_output_dir
from ..lightcurve.config import load_lightcurve_config
from ..lightcurve.run import run_lightcurve
from ..runtime.cli_args import add_no_figures

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="light-curve TOML config (see configs/lightcurve_box_wing.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    add_no_figures(p, "write the CSV and JSON only")


def run(args: argparse.Namespace) -> int:
    prog = "brdfjax lightcurve"

    def log(s: str) -> None:
        if not args.quiet:
            sys.stderr.write(f"{prog}: {s}\n")

    # InputError (exit 2), OSError (2), interrupts (130) and bugs (1): brdfjax.runtime.errors.run_command, from cli.main
    cfg = load_lightcurve_config(args.config)
    check_output_dir(args.out)
    if cfg.precision == "float64":
        # An edge may flip the process-wide switch; the library never does.
        jax.config.update("jax_enable_x64", True)
    summary = run_lightcurve(cfg, args.out, plot=not args.no_figures, log=log)
    if args.quiet:
        return 0
    for label, g in summary["glints"].items():
        sys.stderr.write(
            f"{prog}: {label}: {g['count']} glint(s) brighter than {summary['glint_threshold_mag']:g} mag, "
            f"{g['total_duration_s']:g} s in total; brightest {summary['brightest_mag'][label]}\n"
        )
    for label, c in summary["comparisons"].items():
        if c.get("n_compared"):
            sys.stderr.write(f"{prog}: {label} vs primary: max |dm| = {c['max_abs_diff_mag']:.3f} mag at t = {c['at_s']:.0f} s; "
                             f"{100 * c['fraction_beyond_tol']:.1f} % of steps differ by more than the tolerance\n")
    return 0
