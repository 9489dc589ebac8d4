"""``brdfjax diagnose CONFIG --out DIR``: the diagnosis from a fit config with a ``[diagnose]`` table.

The table and the run: :mod:`brdfjax.diagnose.config` (:func:`~brdfjax.diagnose.config.run_diagnose`).
Each refit of a candidate prints ``i/n`` of its step and an estimate of the time left.
"""

from __future__ import annotations

import argparse
import re
import threading
import time
from pathlib import Path
from typing import Any

from ..diagnose.config import run_diagnose
from ..fit.config import enable_config_precision
from ..io import check_output_dir
from ..runtime.cli_args import CONFIG, DIR, add_no_figures
from ..runtime.errors import EXIT_OK
from ..runtime.progress import make_console

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar=CONFIG, help="fit config (TOML) with a [diagnose] table; the [model] is the base model")
    p.add_argument("--out", required=True, metavar=DIR, help="output folder: diagnosis.json, report.md, report.html")
    p.add_argument("--effects", default=None, metavar="EFFECTS",
                   help="comma-separated candidate effects (overrides [diagnose] effects)")
    add_no_figures(p, "report.html without figures (faster)")


_SAME_MOMENT_S = 0.05  # refits started together (a parallel step's first ones): no interval between them
_REFIT = re.compile(r"^step (\d+): refitting with (\S+) \((\d+)/(\d+)")


class _CandidateProgress:
    """The engine's progress lines, each refit with ``i/n`` of its step and an estimate of the time left.

    The estimate is the mean wall time between the starts of the refits so
    far (over every step; refits run side by side start as others finish, so
    this is the time per refit the run achieves) times the refits left in this
    step; starts at the same moment (the first refits of a parallel step) are
    not intervals.  Later steps, whose candidates are not known yet, are not
    in it (the line says so).
    """

    def __init__(self, console: Any):
        self.console = console
        self.t_refits: list[float] = []
        self._t_last: float | None = None
        self._lock = threading.Lock()

    def __call__(self, msg: str) -> None:
        with self._lock:  # refits side by side ([diagnose] workers) report from their own threads
            self._say(msg)

    def _say(self, msg: str) -> None:
        now = time.perf_counter()
        m = _REFIT.match(msg)
        if self._t_last is not None:
            if now - self._t_last > _SAME_MOMENT_S:
                self.t_refits.append(now - self._t_last)
            self._t_last = None
        if m is not None:
            i, n = int(m.group(3)), int(m.group(4))
            if self.t_refits:
                per = sum(self.t_refits) / len(self.t_refits)
                msg += f"; ~{(n - i + 1) * per:.0f} s left in this step (a refit every {per:.0f} s)"
            self._t_last = now
        self.console.print(msg, markup=False)


def run(args: argparse.Namespace) -> int:
    console = make_console(args.quiet, args.no_progress)
    effects = None if args.effects is None else [e.strip() for e in args.effects.split(",") if e.strip()]
    t0 = time.perf_counter()
    enable_config_precision(args.config)  # the command line, not the library, turns 64-bit JAX on
    check_output_dir(args.out)
    # errors: brdfjax.runtime.errors.run_command (cli.main) gives them their exit code and message
    d = run_diagnose(
        args.config, args.out, effects=effects, figures=False if args.no_figures else None,
        progress=_CandidateProgress(console),
    )
    console.print(d.summary(), markup=False)
    console.print(f"wrote {Path(args.out) / 'diagnosis.json'}, report.md, report.html ({time.perf_counter() - t0:.1f} s)", markup=False)
    return EXIT_OK
