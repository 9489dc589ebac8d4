"""``brdfjax fit CONFIG --out DIR``: fit a model to data from a TOML config (see :mod:`brdfjax.fit.config`).

Writes ``DIR/result.json`` (the output contract: ``parameters``
name -> ``{value, sigma, unit, free}`` in natural units, ``chi2``,
``chi2_reduced``, ``dof``, ``converged``, ``message``, ``n_iterations``,
``wall_s``, ...) and the figures.  Exit codes: 0 when the fit ran (also when
it did not converge: the message says so and ``result.json`` holds what it
found), 2 for a bad config, unreadable data or an output folder that cannot be
written (the message names the file and the key), 130 interrupted, 1 an
internal error (:mod:`brdfjax.runtime.errors`).  The solver's progress (chi^2 per
evaluation) goes to stderr unless ``--quiet``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..fit.config import enable_config_precision
from ..fit.job import run_fit
from ..io import check_output_dir
from ..runtime.progress import make_console

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="a fit config (TOML; see configs/fit_synthetic_solar_cell.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: result.json, figures, work files")
    p.add_argument("--no-figures", action="store_true", help="write result.json only")


def run(args: argparse.Namespace) -> int:
    console = make_console(args.quiet)
    prog = "brdfjax fit"
    enable_config_precision(args.config)
    check_output_dir(args.out)
    # errors: brdfjax.runtime.errors.run_command (cli.main) gives them their exit code and message
    result = run_fit(args.config, args.out, console=console, figures=False if args.no_figures else None)
    state = "converged" if result.converged else "did NOT converge"
    console.print(
        f"{prog}: {state} ({result.message}); chi2_reduced = {result.chi2_reduced:.4g}; wrote {Path(args.out) / 'result.json'}",
        markup=False,
    )
    return 0
