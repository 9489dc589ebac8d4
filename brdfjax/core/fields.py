"""Parameter fields shared by distributions and terms: conversion and checks."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np

__all__ = ["param", "check_param", "is_concrete"]


def _as_param(x: Any) -> Any:
    # Keep JAX arrays and tracers as they are (so models can be built inside
    # jit / grad); store plain numbers as float64 NumPy scalars so that no
    # precision is lost before the caller chooses float32 or float64.
    if x is None or isinstance(x, jax.Array | jax.core.Tracer):
        return x
    return np.asarray(x, dtype=np.float64)


def param(unit: str, doc: str = "", **kwargs: Any) -> Any:
    """A differentiable parameter field with its unit recorded in metadata."""
    return eqx.field(converter=_as_param, metadata={"unit": unit, "doc": doc}, **kwargs)


def is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_param(owner: str, name: str, value: Any, ok: Callable[[np.ndarray], Any], expected: str) -> None:
    """Raise ``ValueError`` if a concrete parameter value fails ``ok``.

    Traced values (inside ``jit`` or ``grad``) are not checked: the check runs
    where models are built from user input, at the edge.
    """
    if not is_concrete(value):
        return
    v = np.asarray(value)
    if not np.all(np.isfinite(v)) or not np.all(ok(v)):
        raise ValueError(f"{owner}: parameter '{name}' = {v.tolist()!r} is invalid; expected {expected}")
