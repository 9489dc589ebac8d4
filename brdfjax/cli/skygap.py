"""``brdfjax skygap CONFIG --out DIR``: diagnose where, why and how far a facet model misses observed magnitudes.

See :mod:`brdfjax.lightcurve.skygap_config` for the config (it names an
observe config: facets, models, observation sets) and
:mod:`brdfjax.lightcurve.skygap` for the diagnosis.  Writes ``skygap.json``
(the path with held-out figures per step, the effects named, the failed
refits), ``report.md`` (the headline, the path, where each step changed the
residuals), ``residuals_by_step.png`` (residuals against phase angle before
and after each step), ``predictions.csv`` and ``skygap_model.toml``: the final
model as an observe config, which ``brdfjax observe`` reruns to the same
magnitudes (the run checks this and records the largest difference).  Exit
codes: the contract of :func:`brdfjax.runtime.errors.run_command` (0 ran; 2 a
bad config or observation file, naming the file and key; 130 interrupted; 1
an internal error).
"""

from __future__ import annotations

import argparse
import sys

from ..io import check_output_dir
from ..lightcurve.skygap_config import load_skygap_config, run_skygap
from ..runtime.cli_args import CONFIG, DIR, add_no_figures

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar=CONFIG, help="skygap TOML config (see configs/skygap_v2mini_slingshot.toml)")
    p.add_argument("--out", required=True, metavar=DIR, help="output folder (created if needed)")
    add_no_figures(p, "write the JSON, report, model and CSV only (no residuals_by_step.png)")
    p.add_argument("--no-progress", action="store_true", help="no per-step progress lines (status lines still print)")


def run(args: argparse.Namespace) -> int:
    prog = "brdfjax skygap"
    cfg = load_skygap_config(args.config)
    check_output_dir(args.out)
    quiet = getattr(args, "quiet", False)
    log = (lambda s: None) if quiet else (lambda s: sys.stderr.write(f"{prog}: {s}\n"))
    progress = None if (quiet or args.no_progress) else log
    run_skygap(cfg, args.out, log=log, figures=False if args.no_figures else None, progress=progress)
    return 0
