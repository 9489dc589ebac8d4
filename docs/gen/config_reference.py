"""The config-key reference, generated from the pydantic models of every config brdfjax reads.

``python docs/gen/config_reference.py`` prints the page; the mkdocs hook renders
it at build time as ``reference/config.md``.  Every key is listed with its
unit (from the key's unit suffix, ``theta_i_deg`` -> deg), its default and its
description; :func:`undocumented` lists the keys without a description
(``tests/project/test_docs.py`` fails on any).
"""

from __future__ import annotations

import sys
import types
import typing
from typing import Any

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

#: Unit suffixes of config keys (the project's convention: keys carry their units).
UNITS = {
    "_deg": "deg", "_rad": "rad", "_nm": "nm", "_um": "µm", "_mm": "mm", "_m": "m", "_km": "km",
    "_px": "px", "_s": "s", "_ms": "ms", "_us": "µs", "_hz": "Hz", "_sr": "sr", "_k": "K", "_w": "W",
    "_arcsec": "arcsec", "_days": "days", "_pct": "%", "_percent": "%", "_cps": "counts/s",
}


def unit(key: str) -> str:
    """The unit a key's suffix names, or ``-`` (a number without unit, a name or a switch)."""
    for suffix in sorted(UNITS, key=len, reverse=True):
        if key.lower().endswith(suffix):
            return UNITS[suffix]
    return "-"


def _roots() -> list[tuple[str, str, list[tuple[str, type[BaseModel]]]]]:
    """``(section title, what reads it, [(key prefix, model)])`` for every config file kind."""
    from brdfjax.batch import Study
    from brdfjax.config import SimulateConfig
    from brdfjax.devices.config import CaptureConfig
    from brdfjax.diagnose.config import DiagnoseSection
    from brdfjax.fit.config import FitConfig
    from brdfjax.instrument.synthetic import InstrumentConfig
    from brdfjax.lightcurve.config import LightcurveConfig
    from brdfjax.lightcurve.skygap_config import SkygapConfig
    from brdfjax.sample.config import SampleSection

    return [
        ("Simulate configs", "`brdfjax simulate`, `brdfjax synthesize`", [("", SimulateConfig)]),
        ("Fit configs", "`brdfjax fit`, `brdfjax sample`, `brdfjax diagnose`",
         [("", FitConfig), ("sample", SampleSection), ("diagnose", DiagnoseSection)]),
        ("Instrument configs", "`brdfjax synthesize --instrument`, `[data.synthetic]`", [("", InstrumentConfig)]),
        ("Capture configs", "`brdfjax capture`", [("", CaptureConfig)]),
        ("Light-curve configs", "`brdfjax lightcurve`", [("", LightcurveConfig)]),
        ("Sky gap configs", "`brdfjax skygap`", [("", SkygapConfig)]),
        ("Study files", "`brdfjax batch`", [("", Study)]),
    ]


def _models_in(annotation: Any) -> list[tuple[str, type[BaseModel]]]:
    """Nested models of a field's type, each with how it nests: ``""`` (a table), ``"[]"`` (an array of
    tables) or ``".<name>"`` (a table of named tables)."""
    origin = typing.get_origin(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [("", annotation)]
    if origin in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(annotation) for m in _models_in(a)]
    if origin in (list, tuple):
        return [("[]", m) for _, m in (x for a in typing.get_args(annotation) for x in _models_in(a))]
    if origin is dict:
        args = typing.get_args(annotation)
        return [(".<name>", m) for _, m in _models_in(args[1])] if len(args) == 2 else []
    return []


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " or ".join(repr(a) for a in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(annotation))
    text = getattr(annotation, "__name__", None) if typing.get_origin(annotation) is None else None
    text = text or str(annotation).replace("typing.", "")
    for mod in ("brdfjax.", "pathlib."):
        while mod in text:  # strip module paths of nested models
            i = text.index(mod)
            j = text.find(".", i + len(mod))
            while j != -1 and text[j + 1 : j + 2].islower():
                j = text.find(".", j + 1)
            text = text[:i] + text[j + 1 :] if j != -1 else text[:i] + text[i + len(mod):]
    return text.replace("NoneType", "None")


def _default(field: Any) -> str:
    if field.is_required():
        return "required"
    if field.default_factory is not None:
        try:
            value = field.default_factory()
        except TypeError:
            return "(computed)"
        if isinstance(value, BaseModel):
            return "(table)"
        return f"`{value!r}`" if value not in ({}, []) else "empty"
    if field.default is PydanticUndefined:
        return ""
    return f"`{field.default!r}`" if field.default is not None else "unset"


def rows(prefix: str, model: type[BaseModel], seen: tuple = ()) -> list[tuple[str, str, str, str, str]]:
    """``(dotted key, type, unit, default, description)`` of ``model``'s fields and those of nested tables."""
    out = []
    for name, field in model.model_fields.items():
        key = f"{prefix}.{name}" if prefix else name
        nested = [(how, m) for how, m in _models_in(field.annotation) if m not in seen]
        desc = " ".join((field.description or "").split()).replace("|", "\\|")
        if nested:
            # a table without its own description is described by its model's docstring
            desc = desc or " ".join(((nested[0][1].__doc__ or "").strip().split("\n\n")[0]).split()).replace("|", "\\|")
            out.append((key, "table", "-", _default(field), desc))
            for how, m in nested:
                out += rows(key + how, m, (*seen, model, m))
        else:
            out.append((key, _type_name(field.annotation), unit(name), _default(field), desc))
    return out


def undocumented() -> list[str]:
    """Every ``section: key`` without a description."""
    return [f"{title}: {key}" for title, _, roots in _roots() for prefix, m in roots
            for key, _, _, _, desc in rows(prefix, m) if not desc.strip()]


def page() -> str:
    """The Markdown of ``reference/config.md``."""
    lines = [
        "# Config keys",
        "",
        "Every key of every TOML file brdfjax reads, generated from the config models (`docs/gen/config_reference.py`). "
        "Keys carry their units: `theta_i_deg` is in degrees, `wavelength_nm` in nanometres, `distance_m` in metres; "
        "inside, everything is SI and radians. Unknown keys are errors that list the allowed ones.",
        "",
        "`a.b` is key `b` of table `[a]`; `a[]` is an array of tables `[[a]]`; `a.<name>` a table of named tables "
        "(`[model.terms.center]`).  A model's parameters (`[model.params]`, `[params]`, a term's `params`) are the "
        "model's own: see the [equation table](../physics/equations.md) for each term's parameters and units.",
        "",
    ]
    for title, readers, roots in _roots():
        lines += [f"## {title}", "", f"Read by {readers}.", "", "| key | type | unit | default | meaning |",
                  "| --- | --- | --- | --- | --- |"]
        for prefix, m in roots:
            for key, typ, u, default, desc in rows(prefix, m):
                typ = typ.replace(" | ", " or ").replace("|", "or")
                lines.append(f"| `{key}` | `{typ}` | {u} | {default} | {desc} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(page())
