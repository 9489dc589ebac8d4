"""The pieces every config of brdfjax builds on: the strict base, TOML reading, error messages.

- :class:`StrictModel`: the one pydantic base of every config table (frozen,
  unknown keys rejected, no type coercion, no inf/NaN unless a field allows it);
- :func:`read_toml`: read a TOML file, file and syntax errors as
  :class:`ConfigError` naming the file;
- :func:`validate`: a parsed mapping into a config model, pydantic errors as
  :class:`ConfigError` naming the file and the dotted key
  (:func:`describe_validation_error`);
- :func:`check_choice` / :func:`quoted_choices`: a name checked against the
  registry that owns the choices (the message lists them);
- :func:`unknown_key_message`: the message for an unknown parameter key, with
  the unit-suffix hint (``dtheta`` -> ``dtheta_deg``).
"""

from __future__ import annotations

import tomllib
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError, model_validator

from ..runtime.choices import check_choice as _check_choice, did_you_mean, quoted_choices, unknown_message
from ..runtime.errors import InputError

__all__ = [
    "ConfigError",
    "StrictModel",
    "read_toml",
    "validate",
    "describe_validation_error",
    "check_choice",
    "quoted_choices",
    "unknown_key_message",
]

M = TypeVar("M", bound=BaseModel)


class ConfigError(InputError):
    """A config that cannot be used; the message names the file and the key.

    ``source`` is the file (or ``"<string>"``), ``problems`` a list of
    ``(dotted key, message)`` pairs.
    """

    def __init__(self, source: str, problems: list[tuple[str, str]]):
        self.source = source
        self.problems = list(problems)
        lines = [f"{source}: {key}: {msg}" if key else f"{source}: {msg}" for key, msg in self.problems]
        super().__init__("\n".join(lines))


def _tuples(x: Any) -> Any:
    return tuple(_tuples(v) for v in x) if isinstance(x, list) else x


def _has_tuple(annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    if origin is tuple:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_has_tuple(a) for a in typing.get_args(annotation))
    return False


class StrictModel(BaseModel):
    """The base of every config table: frozen, unknown keys are errors, no coercion, no inf/NaN.

    A field that takes inf says so itself (``Field(allow_inf_nan=True)``).  TOML
    has no tuples, so a TOML array given for a tuple-typed field is taken as a
    tuple (the only conversion; element types stay strict).
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _toml_arrays_as_tuples(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            fields = cls.model_fields
            if any(isinstance(v, list) and k in fields and _has_tuple(fields[k].annotation) for k, v in data.items()):
                data = {
                    k: _tuples(v) if isinstance(v, list) and k in fields and _has_tuple(fields[k].annotation) else v
                    for k, v in data.items()
                }
        return data


def read_toml(path: str | Path, what: str = "config file") -> dict[str, Any]:
    """The parsed TOML file at ``path``; a missing, unreadable or malformed file raises :class:`ConfigError`."""
    path = Path(path)
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(source, [("", f"{what} not found")]) from None
    except IsADirectoryError:
        raise ConfigError(source, [("", f"is a directory, not a TOML {what}")]) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(source, [("", f"cannot read {what}: {e}")]) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(source, [("", f"not valid TOML: {e}")]) from None


def validate(model: type[M], data: Any, source: str) -> M:
    """``model.model_validate(data)``; every pydantic error as one ``(dotted key, message)`` of a :class:`ConfigError`."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ConfigError(source, [describe_validation_error(model, err) for err in e.errors()]) from None


# --- choices from registries ------------------------------------------------------------------


def check_choice(what: str, value: str, choices: Iterable[str]) -> str:
    """``value`` if it is one of ``choices`` (a config choice); else a ValueError quoting them, with did-you-mean
    (:func:`brdfjax.runtime.choices.check_choice`)."""
    return _check_choice(what, value, choices, listing="expected")


def unknown_key_message(key: str, known: Mapping[str, Any], what: str) -> str:
    """``unknown parameter 'key' for <what> (did you mean ...); known: ...`` for a parameter key."""
    msg = f"unknown parameter '{key}' for {what}"
    stem = key.removesuffix("_deg").removesuffix("_m").removesuffix("_px")
    hint = [k for k in known if k.removesuffix("_deg").removesuffix("_m").removesuffix("_px") == stem]
    if hint:
        msg += f" (did you mean '{hint[0]}'? angles are given in degrees as <name>_deg, lengths in metres as <name>_m)"
    else:
        msg += did_you_mean(key, known)
    return msg + f"; known: {', '.join(known)}"


def raise_unknown(what: str, name: str, table: Mapping[str, Any]) -> typing.NoReturn:
    """A ValueError for a name not in a registry table (sorted names listed, close match suggested)."""
    raise ValueError(unknown_message(what, name, table, sort=True))


# --- pydantic errors as (dotted key, message) -----------------------------------------------------


def _dotted(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _inner_model(annotation: Any) -> tuple[type[BaseModel] | None, bool]:
    """The config model inside an annotation, and whether it sits in a dict (keys in the path)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation, False
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is dict:
        inner, _ = _inner_model(args[1])
        return inner, True
    if origin in (list, tuple, typing.Union, types.UnionType):
        for a in args:
            inner, in_dict = _inner_model(a)
            if inner is not None:
                return inner, in_dict
    return None, False


def _walk(root: type[BaseModel], loc: tuple[Any, ...]) -> tuple[Any, type[BaseModel] | None]:
    """The field info at ``loc`` under the config model ``root``, and the config model it leads into."""
    cls: type[BaseModel] | None = root
    info = None
    dict_key_next = False
    for part in loc:
        if isinstance(part, int):
            continue
        if dict_key_next:
            dict_key_next = False
            continue
        if cls is None or part not in cls.model_fields:
            # a union member's tag (pydantic puts e.g. 'list[float]' in the path)
            continue
        info = cls.model_fields[part]
        cls, dict_key_next = _inner_model(info.annotation)
    return info, cls


def describe_validation_error(
    root: type[BaseModel], err: Mapping[str, Any], prefix: tuple[Any, ...] = ()
) -> tuple[str, str]:
    """One pydantic error of a config model as ``(dotted key, message)``: unknown keys get the allowed
    keys (and a close match), other errors the value given and the field's description.  Used by every
    config of the package (simulate, fit, sample, diagnose, capture, instrument)."""
    loc = tuple(x for x in err["loc"] if not (isinstance(x, str) and ("[" in x or x in ("str", "int", "float", "bool"))))
    kind = err["type"]
    full = prefix + loc
    if kind == "extra_forbidden":
        _, owner = _walk(root, loc[:-1])
        allowed = list(owner.model_fields) if owner is not None else []
        key = str(loc[-1])
        msg = "unknown key"
        msg += did_you_mean(key, allowed)
        if allowed:
            where = _dotted(full[:-1]) or "the top level"
            msg += f"; allowed keys in {where}: {', '.join(allowed)}"
        return _dotted(full), msg
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    if kind not in ("missing", "value_error") and "input" in err and not isinstance(err["input"], Mapping | list):
        msg += f" (got {err['input']!r})"
    info, _ = _walk(root, loc)
    if info is not None and info.description and kind != "value_error":
        msg += f"; expected {info.description}"
    return _dotted(full), msg
