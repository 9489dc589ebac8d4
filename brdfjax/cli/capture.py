"""``brdfjax capture CONFIG --out DIR [--resume]``: run a capture plan on the simulated bench or lab hardware.

The config is :mod:`brdfjax.devices.config`; the runner :func:`brdfjax.devices.capture.run_capture`.
Errors and their exit codes: :func:`brdfjax.runtime.errors.run_command`, 2 for every refusal.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from ..devices.capture import run_capture
from ..devices.config import CaptureError, load_capture_config
from ..devices.liveview import LiveView
from ..io import check_output_dir
from ..runtime.errors import EXIT_OK
from ..runtime.progress import make_console

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="capture config (TOML), e.g. configs/capture_simulated.toml")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: the raw measurement set + manifest.toml")
    p.add_argument("--resume", action="store_true", help="continue an interrupted capture in DIR from its manifest")
    p.add_argument("--seed", type=int, default=None, metavar="N", help="noise seed of the simulated instrument (overrides seed)")
    p.add_argument("--live", choices=("auto", "window", "png", "off"), default=None,
                   help="live view: a matplotlib window, a PNG + HTML page in DIR/live/, or none (overrides capture.live)")
    p.add_argument("--override-interlock", action="store_true",
                   help="allow direct-beam steps below the safe OD (logged in the manifest); only if the array can take it")
    p.add_argument("--no-progress", action="store_true", help="no progress bar or progress lines")


def run(args: argparse.Namespace) -> int:
    # Errors and their exit codes: brdfjax.runtime.errors.run_command (cli.main), 2 for every refusal.
    cfg = load_capture_config(args.config)
    check_output_dir(args.out)
    updates: dict[str, Any] = {}
    if args.seed is not None:
        updates["seed"] = args.seed
    cap = {}
    if args.live is not None:
        cap["live"] = args.live
    if getattr(args, "no_figures", False):  # the shared --no-figures: no live PNG preview either
        cap["live"] = "off"
    if args.override_interlock:
        cap["override_interlock"] = True
    if cap:
        updates["capture"] = cfg.capture.model_copy(update=cap)
    if updates:
        src = cfg.source
        cfg = cfg.model_copy(update=updates)
        cfg._source = src
    console = make_console(args.quiet, args.no_progress)
    log = lambda s: console.print(s, markup=False)  # noqa: E731
    live = None
    if cfg.capture.live != "off":
        live = LiveView(Path(args.out) / "live", mode=cfg.capture.live, min_interval_s=cfg.capture.live_interval_s)
    t0 = time.perf_counter()
    try:
        manifest = run_capture(cfg, args.out, resume=args.resume, log=log, live=live,
                               progress=not (args.no_progress or args.quiet))
    except FileExistsError as e:  # a rerun into a started or finished capture: a refusal (exit 2)
        raise CaptureError(str(e)) from None
    finally:
        if live is not None:
            live.close()
    log(f"wrote {manifest} ({time.perf_counter() - t0:.1f} s); reduce it with: brdfjax reduce {manifest} --out DIR")
    return EXIT_OK
