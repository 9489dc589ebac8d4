"""``brdfjax observe CONFIG --out DIR``: predict real satellite observations from facet BRDF models.

See :mod:`brdfjax.lightcurve.observe_config` for the config and
:mod:`brdfjax.lightcurve.observe` for what is computed.  Writes, per
observation set, ``predictions_<set>.csv`` (each kept row: observed and
predicted magnitude, the predictive band, per facet magnitude, angles and
lab-coverage flags), the figures ``residuals_vs_phase_<set>.png`` and
``facet_contribution_<set>.png``, and ``observe.json`` (metrics overall and
split by the flag, dropped rows, the families drawn).  Exit codes: the
contract of :func:`brdfjax.runtime.errors.run_command` (0 ran; 2 a bad config,
observation file or band, with the message naming the file, line or key; 130
interrupted; 1 an internal error).
"""

from __future__ import annotations

import argparse
import sys

import jax

from ..io import check_output_dir
from ..lightcurve.observe_config import load_observe_config, run_observe

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="observe TOML config (see configs/observe_v2mini_slingshot.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument("--no-plot", action="store_true", help="write the CSV and JSON only")


def run(args: argparse.Namespace) -> int:
    prog = "brdfjax observe"
    cfg = load_observe_config(args.config)
    check_output_dir(args.out)
    if cfg.precision == "float64":
        jax.config.update("jax_enable_x64", True)
    run_observe(cfg, args.out, log=lambda s: sys.stderr.write(f"{prog}: {s}\n"), figures=False if args.no_plot else None)
    return 0
