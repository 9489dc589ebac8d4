"""The command line's shared vocabulary: flag names, metavars and argument types every subcommand uses.

Every ``brdfjax`` subcommand takes ``--quiet``, ``--no-progress`` and ``--no-figures`` (with these names,
whatever the command does with them) and names its config ``CONFIG`` and its output folder ``DIR``.
:func:`add_shared_flags` adds the flags a command did not declare itself; the argument types below make
argparse's own error name the flag (``argument --step: must be a positive integer, got 0``), exit 2.
Imports nothing heavy: ``brdfjax --help`` builds every parser.
"""

from __future__ import annotations

import argparse

__all__ = ["SHARED_FLAGS", "CONFIG", "DIR", "add_shared_flags", "add_no_figures", "positive_int", "non_negative_int"]

#: Metavar of a command's config file and of its output folder.
CONFIG = "CONFIG"
DIR = "DIR"

#: The flags every subcommand has: name -> the help line used where the command does not give its own.
SHARED_FLAGS: dict[str, str] = {
    "--quiet": "no progress and no status lines (errors still print)",
    "--no-progress": "no progress bar or progress lines (status lines still print)",
    "--no-figures": "write no figures (PNG/HTML plots); the data files only",
}


def add_no_figures(p: argparse.ArgumentParser, help: str | None = None) -> None:
    """``--no-figures`` (dest ``no_figures``) and its deprecated, hidden alias ``--no-plot``."""
    p.add_argument("--no-figures", action="store_true", dest="no_figures", help=help or SHARED_FLAGS["--no-figures"])
    p.add_argument("--no-plot", action="store_true", dest="no_figures", help=argparse.SUPPRESS)


def add_shared_flags(p: argparse.ArgumentParser, notes: dict[str, str] | None = None) -> None:
    """Add every flag of :data:`SHARED_FLAGS` that ``p`` lacks (``notes``: a command's own help line for one)."""
    have = {s for a in p._actions for s in a.option_strings}
    notes = notes or {}
    for flag, text in SHARED_FLAGS.items():
        if flag in have:
            continue
        if flag == "--no-figures":
            add_no_figures(p, notes.get(flag, text))
        else:
            p.add_argument(flag, action="store_true", help=notes.get(flag, text))


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (argparse names the flag in its error)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {v}")
    return v


def non_negative_int(text: str) -> int:
    """An argparse type: an integer >= 0."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {v}")
    return v
