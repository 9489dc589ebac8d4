"""The equation table, generated from the terms and distributions of :mod:`brdfjax.core`.

Each row is a registry name (what a config's ``kind`` or ``distribution`` says),
the class, its ``equation`` tag (the seed dissertation's equation number; terms
without a tag show the equation numbers their docstring cites, or the source
they implement), the formula line of its docstring and its parameters with
units (the ``param`` metadata of each field).
"""

from __future__ import annotations

import dataclasses
import re
import sys

_EQ = re.compile(r"Eq\s*\d+(?:\s*[-,]\s*\d+)*")
_SOURCE = re.compile(r"\(([A-Z][A-Za-z-]+(?: (?:et al\.|and [A-Z][a-z]+))? \d{4}[^)]*)\)")


def _first_paragraph(cls: type) -> str:
    return " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())


def equation_tag(cls: type) -> str:
    """The class's ``equation`` tag, else the equation numbers or sources its docstring cites."""
    tag = getattr(cls, "equation", None)
    if tag:
        return str(tag)
    doc = _first_paragraph(cls)
    eqs = _EQ.findall(doc)
    if eqs:
        return ", ".join(dict.fromkeys(e.replace("  ", " ") for e in eqs))
    src = _SOURCE.findall(doc)
    return src[0] if src else "-"


def parameters(cls: type) -> list[tuple[str, str, str]]:
    """``(name, unit, meaning)`` of the class's parameter fields."""
    out = []
    for f in dataclasses.fields(cls):
        if "unit" in f.metadata:
            out.append((f.name, f.metadata["unit"], f.metadata.get("doc", "")))
    return out


def _row(name: str, cls: type) -> str:
    params = "<br>".join(f"`{n}` [{u}]: {d}" for n, u, d in parameters(cls)).replace("|", "\\|") or "-"
    doc = _first_paragraph(cls).replace("|", "\\|")
    return f"| `{name}` | `{cls.__name__}` | {equation_tag(cls)} | {doc} | {params} |"


def page() -> str:
    from brdfjax.core.registry import DISTRIBUTIONS, TERMS

    head = ["| name | class | equation | form | parameters [unit] |", "| --- | --- | --- | --- | --- |"]
    lines = [
        "# Equation table",
        "",
        "Generated from the classes of `brdfjax.core.terms` and `brdfjax.core.distributions` "
        "(`docs/gen/equations.py`): each row is what a config names, the class, the equation it implements "
        "(numbers are those of the seed dissertation, [Small 2021](../references.md)), the form its docstring "
        "gives and its parameters with units. Conventions: [conventions](conventions.md).",
        "",
        "## Terms",
        "",
        "A model is a sum of named terms (`[model.terms.<name>] kind = ...`).",
        "",
        *head,
    ]
    lines += [_row(k, c) for k, c in TERMS.items()]
    lines += ["", "## Microfacet distributions", "",
              "The `distribution` of a `specular`, `offset_specular` or `multi_lobe` term. Every distribution is "
              "normalised (Eq 54: the projected area integrates to 1; tested numerically).", "", *head]
    seen = set()
    for k, c in DISTRIBUTIONS.items():
        if c in seen:
            continue
        seen.add(c)
        aliases = [a for a, d in DISTRIBUTIONS.items() if d is c and a != k]
        row = _row(k, c)
        if aliases:
            row = row.replace(f"| `{k}` |", f"| `{k}` (also {', '.join(f'`{a}`' for a in aliases)}) |", 1)
        lines.append(row)
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(page())
