"""The command-line reference, generated from the argparse parsers of :mod:`brdfjax.cli`.

``python docs/gen/cli_reference.py`` prints the page; the mkdocs hook
(``docs/gen/hooks.py``) renders it at build time as ``reference/cli.md``.
:func:`undocumented` lists every flag without a help text (``tests/project/test_docs.py``
fails on any).
"""

from __future__ import annotations

import argparse
import sys


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    from brdfjax.cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {name: sub.choices[name] for name in COMMANDS}


def _top_parser() -> argparse.ArgumentParser:
    from brdfjax.cli import build_parser

    return build_parser()


def _rows(p: argparse.ArgumentParser) -> list[tuple[str, str, str, str]]:
    """``(argument, metavar/choices, default, help)`` for every argument but ``-h``."""
    rows = []
    for a in p._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = ", ".join(a.option_strings) if a.option_strings else (a.metavar or a.dest)
        if a.choices is not None and not isinstance(a, argparse._SubParsersAction):
            value = " \\| ".join(f"`{c}`" for c in a.choices)
        elif a.nargs == 0:
            value = "(switch)"
        else:
            value = f"`{a.metavar or a.dest.upper()}`"
        if a.nargs == 0 or a.default in (None, argparse.SUPPRESS) or a.required:
            default = "required" if a.required else ""
        else:
            default = f"`{a.default}`"
        if not a.option_strings:
            default = "optional" if a.nargs == "?" else "required"
        rows.append((f"`{name}`", value, default, (a.help or "").replace("%%", "%").replace("|", "\\|")))
    return rows


def undocumented() -> list[str]:
    """``command: flag`` for every argument without a help text (``brdfjax`` itself included)."""
    missing = [f"brdfjax: {n}" for n, _, _, h in _rows(_top_parser()) if not h.strip()]
    for name, p in _subparsers().items():
        missing += [f"{name}: {n}" for n, _, _, h in _rows(p) if not h.strip()]
    return missing


def _table(rows: list[tuple[str, str, str, str]]) -> list[str]:
    out = ["| argument | value | default | meaning |", "| --- | --- | --- | --- |"]
    out += [f"| {n} | {v} | {d} | {h} |" for n, v, d, h in rows]
    return out


def page() -> str:
    """The Markdown of ``reference/cli.md``."""
    lines = [
        "# Command line",
        "",
        "Generated from the argument parsers in `brdfjax/cli/` (`docs/gen/cli_reference.py`); "
        "`brdfjax COMMAND --help` prints the same.",
        "",
        "```text",
        "brdfjax [--version] [--no-cache] COMMAND ...",
        "```",
        "",
    ]
    lines += _table(_rows(_top_parser()))
    lines += ["", "Every command exits 0 when it ran, 2 on bad input or a refusal, 130 when interrupted and 1 on an "
              "internal error ([exit codes](exit-codes.md)).", ""]
    for name, p in _subparsers().items():
        usage = " ".join(p.format_usage().split())
        usage = usage.removeprefix("usage: ")
        lines += [f"## `brdfjax {name}`", "", p.description or "", "", "```text", usage, "```", ""]
        lines += _table(_rows(p))
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(page())
