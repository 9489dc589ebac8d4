"""The exception every bad input raises: :class:`InputError`.

A config with a bad key, a file in the wrong format, a table without the
columns it needs, a chain that belongs to another problem: each raises a
subclass of :class:`InputError` whose message names the file, key or value
and what was expected.  Every ``brdfjax`` subcommand catches
:class:`InputError` and exits with status 2 and that message; anything else is
a failure while running (status 1), and so are, by choice, an ``ExrError`` while
``simulate`` writes and a ``ReductionError`` in ``reduce`` (a set that cannot be
reduced, e.g. a refused overwrite).  ``InputError`` is a :class:`ValueError`,
so code that caught ``ValueError`` before keeps working.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad input to brdfjax (a config, a file, an argument); the message says what and where."""
