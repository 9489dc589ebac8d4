"""``brdfjax lightcurve CONFIG --out DIR``: a satellite's light curve from a TOML config (see :mod:`.config`).

Writes ``lightcurve.csv`` (one row per visible time step: time, elevation,
phase angle, sunlit fraction, per-facet incidence and scatter angles and
magnitudes, the total magnitude of every compared model, posterior bands),
``lightcurve.json`` (the summary: glints, comparisons, and the series) and
``lightcurve.png``.  Exit codes: 0 success, 1 failure while running, 2 a bad
config (the message names the file and key).
"""

from __future__ import annotations

import argparse
import sys

import jax

from ..errors import InputError
from .config import load_lightcurve_config
from .run import run_lightcurve

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="light-curve TOML config (see configs/lightcurve_box_wing.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument("--no-plot", action="store_true", help="write the CSV and JSON only")


def run(args: argparse.Namespace) -> int:
    prog = "brdfjax lightcurve"
    try:
        cfg = load_lightcurve_config(args.config)
    except InputError as e:
        sys.stderr.write(f"{prog}: error: {e}\n")
        return 2
    if cfg.precision == "float64":
        # An edge may flip the process-wide switch; the library never does.
        jax.config.update("jax_enable_x64", True)
    try:
        summary = run_lightcurve(cfg, args.out, plot=not args.no_plot, log=lambda s: sys.stderr.write(f"{prog}: {s}\n"))
    except InputError as e:
        sys.stderr.write(f"{prog}: error: {e}\n")
        return 2
    except OSError as e:
        sys.stderr.write(f"{prog}: error: {e}\n")
        return 1
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
