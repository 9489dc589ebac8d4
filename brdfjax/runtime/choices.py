"""One checker for every name a user picks (a distribution, a solver, an effect, a parameter), with did-you-mean.

Configs, the command line and the Python API all check names through :func:`check_choice` (one name) or
:func:`check_choices` (a list of names), so that a typo gets the same message everywhere: what was asked,
the closest known name, and the known names, e.g. ``unknown effect(s) ['difraction'] (did you mean
'diffraction'?); known: ...``.  The close match is :func:`difflib.get_close_matches`' (ratio >= 0.6).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from typing import Literal, TypeVar

__all__ = ["did_you_mean", "closest", "unknown_message", "check_choice", "check_choices", "quoted_choices"]

T = TypeVar("T")


def quoted_choices(choices: Iterable[str]) -> str:
    """``'a', 'b' or 'c'``."""
    q = [f"'{c}'" for c in choices]
    return q[0] if len(q) == 1 else ", ".join(q[:-1]) + " or " + q[-1]


def closest(name: str, choices: Iterable[str]) -> str | None:
    """The known name closest to ``name`` (``None`` when none is close)."""
    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1)
    return close[0] if close else None


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``choices``, or ``""``."""
    c = closest(name, choices)
    return f" (did you mean '{c}'?)" if c is not None else ""


def unknown_message(what: str, value: object, choices: Iterable[str], *, listing: Literal["known", "expected"] = "known",
                    sort: bool = False) -> str:
    """``unknown <what> 'value' (did you mean 'x'?); known: a, b, c`` (``listing="expected"``:
    ``...; expected 'a', 'b' or 'c'``)."""
    names = [str(c) for c in choices]
    shown = sorted(names) if sort else names
    hint = did_you_mean(str(value), names)
    if listing == "expected":
        return f"unknown {what} {value!r}{hint}; expected {quoted_choices(shown)}"
    return f"unknown {what} '{value}'{hint}; known: {', '.join(shown)}"


def check_choice(what: str, value: T, choices: Iterable[str], *, error: type[Exception] = ValueError,
                 listing: Literal["known", "expected"] = "known", sort: bool = False, prefix: str = "") -> T:
    """``value`` if it is one of ``choices``; else ``error(prefix + unknown_message(...))``."""
    names = list(choices)
    if value not in names:
        raise error(prefix + unknown_message(what, value, names, listing=listing, sort=sort))
    return value


def check_choices(what: str, values: Sequence[str], choices: Iterable[str], *, error: type[Exception] = ValueError,
                  sort: bool = False, prefix: str = "") -> list[str]:
    """Every one of ``values`` known, else ``error``: ``unknown <what>(s) ['x', 'y'] (did you mean 'z'?, ...); known: ...``."""
    names = list(choices)
    unknown = [v for v in values if v not in names]
    if unknown:
        matches = [(u, c) for u in unknown if (c := closest(u, names)) is not None]
        if len(unknown) == 1 and matches:
            hint = f" (did you mean '{matches[0][1]}'?)"
        elif matches:
            hint = " (did you mean " + ", ".join(f"'{c}' for '{u}'" for u, c in matches) + "?)"
        else:
            hint = ""
        shown = sorted(names) if sort else names
        raise error(f"{prefix}unknown {what}(s) {unknown}{hint}; known: {', '.join(shown)}")
    return list(values)
