"""Progress of long work on stderr: a rich bar on a terminal, plain lines when not, nothing with ``--quiet``.

Every ``brdfjax`` subcommand takes ``--quiet`` (no progress and no status
lines; errors are still printed) and ``--no-progress`` (no progress; status lines still print).  :func:`make_console` is the console a
command prints through; :class:`ProgressLine` reports ``done / total`` of a
long loop (the fit's solver steps with their chi^2, the diagnosis's
candidates, synthesis, reduction) with the elapsed time and an estimate of
the time left: on a terminal as one rich bar, otherwise (a log file, a pipe,
CI) as plain lines, at most one every ``min_interval_s`` seconds plus the
last.  The estimate is the mean time per item so far times the items left.
"""

from __future__ import annotations

import time
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

__all__ = ["ProgressLine", "make_console"]


def make_console(quiet: bool = False, no_progress: bool = False) -> Console:
    """The stderr console of a command (``quiet``: prints nothing; ``no_progress``: no :class:`ProgressLine`)."""
    console = Console(stderr=True, highlight=False, soft_wrap=True, quiet=bool(quiet))
    console.brdfjax_no_progress = bool(no_progress)  # read by ProgressLine (rich's Console takes attributes)
    return console


def _fmt_s(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"


class ProgressLine:
    """``done / total`` of a loop on ``console`` (see the module docstring); a context manager.

    ``total=None``: a count without a total (no estimate), e.g. solver steps.
    """

    def __init__(self, console: Any, what: str, total: int | None, *, unit: str = "", min_interval_s: float = 5.0):
        self.console = console
        self.what = what
        self.total = total
        self.unit = unit
        self.min_interval_s = float(min_interval_s)
        self.t0 = time.perf_counter()
        self._last = -float("inf")
        self._bar = None
        self.lines: list[str] = []  # the plain lines printed (for tests and logs)
        quiet = console is None or getattr(console, "quiet", False) or getattr(console, "brdfjax_no_progress", False)
        self.enabled = not quiet
        if self.enabled and getattr(console, "is_terminal", False):
            cols: list[Any] = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                               TextColumn("left"), TimeRemainingColumn()]  # rich shows '?' while the total is unknown
            self._bar = Progress(*cols, console=console, transient=False)
            self._bar.start()
            self._task = self._bar.add_task(what, total=total)

    def estimate_left_s(self, done: int) -> float | None:
        """Seconds left: the mean time per item so far times the items left (``None`` before the first)."""
        if self.total is None or done <= 0:
            return None
        return (time.perf_counter() - self.t0) / done * max(self.total - done, 0)

    def update(self, done: int, note: str = "", *, total: int | None = None) -> None:
        """``done`` items so far (``total``: the total, when it becomes known only now)."""
        if total is not None:
            self.total = int(total)
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.update(self._task, completed=done, total=self.total,
                             description=f"{self.what}" + (f": {note}" if note else ""))
            return
        now = time.perf_counter()
        last = self.total is not None and done >= self.total
        if now - self._last < self.min_interval_s and not last:
            return
        self._last = now
        count = f"{done}/{self.total}" if self.total is not None else f"{done}"
        left = self.estimate_left_s(done)
        est = f", ~{_fmt_s(left)} left" if left is not None and not last else ""
        line = f"{self.what}: {count}{(' ' + self.unit) if self.unit else ''} ({_fmt_s(now - self.t0)}{est})"
        line += f"; {note}" if note else ""
        self.lines.append(line)
        self.console.print(line, markup=False)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None

    def __enter__(self) -> ProgressLine:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
