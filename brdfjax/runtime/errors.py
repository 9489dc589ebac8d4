"""The exit-code contract of every ``brdfjax`` command and the one error class that carries it.

=====  ==================================================================
exit   meaning
=====  ==================================================================
0      the command ran (a fit that did not converge also ran: its output
       says so)
2      bad input or a refusal: a bad config, key, value or file, a resume
       of another problem, an interlock or device refusal, an output
       folder that is a file or cannot be written; the message (one line
       on stderr, no traceback) names the file, key or value and what was
       expected
130    interrupted (Ctrl-C); what was saved is kept and, where a command
       is resumable, ``--resume`` continues it
1      an internal error, i.e. a bug in brdfjax: the traceback is printed
       with where to report it
=====  ==================================================================

:class:`InputError` is the base class of every error brdfjax raises on
purpose (a config, a file in the wrong format, a chain or capture that
belongs to another problem, a device or interlock refusal); its
:attr:`~InputError.exit_code` is 2.  It is a :class:`ValueError`, so code
that caught ``ValueError`` before keeps working.  :func:`run_command` is the
contract: every subcommand runs through it (``brdfjax.cli.main`` wraps each
one), and a new subcommand gets the same codes by doing nothing more.
"""

from __future__ import annotations

import sys
import traceback
from collections.abc import Callable

__all__ = [
    "EXIT_INTERNAL",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_REFUSED",
    "REPORT_TO",
    "FitInputError",
    "InputError",
    "run_command",
]

EXIT_OK, EXIT_INTERNAL, EXIT_REFUSED, EXIT_INTERRUPTED = 0, 1, 2, 130
#: Where an internal error is to be reported (printed with its traceback).
REPORT_TO = (
    "the brdfjax issue tracker (the project's repository, 'issues'): include the command line, "
    "`brdfjax --version` and this traceback"
)


class InputError(ValueError):
    """Bad input to brdfjax (a config, a file, an argument) or a refusal; the message says what and where.

    Every subclass exits the command line with :attr:`exit_code` (2).
    """

    exit_code: int = EXIT_REFUSED


class FitInputError(InputError):
    """Bad fit input (parameter specification, data, solver settings); the message says what to change."""


def run_command(prog: str, run: Callable[[], int | None], *, stderr=None) -> int:
    """Run one command under the exit-code contract (module docstring); returns the exit code.

    ``run()`` returns its own code (``None`` is 0; a command may return 130
    after saving an interrupted run itself).  :class:`InputError` -> its
    message and 2; ``KeyboardInterrupt`` -> 130; ``OSError`` (an output folder
    that is a file, a read-only or missing place, a full disk) -> its message
    and 2: it is the environment, not brdfjax; anything else -> the traceback,
    where to report it, and 1.
    """
    err = stderr if stderr is not None else sys.stderr
    try:
        code = run()
    except InputError as e:
        err.write(f"{prog}: error: {e}\n")
        return e.exit_code
    except KeyboardInterrupt:
        err.write(f"{prog}: interrupted (Ctrl-C); files already written are complete and kept\n")
        return EXIT_INTERRUPTED
    except OSError as e:
        where = f" ({e.filename})" if getattr(e, "filename", None) and str(e.filename) not in str(e) else ""
        err.write(f"{prog}: error: cannot read or write a file{where}: {e}\n")
        return EXIT_REFUSED
    except Exception:  # noqa: BLE001 -- the contract: anything unexpected is a bug, reported as one
        err.write(traceback.format_exc())
        err.write(f"{prog}: internal error (a bug in brdfjax, not in your input); please report it to {REPORT_TO}\n")
        return EXIT_INTERNAL
    return EXIT_OK if code is None else int(code)
