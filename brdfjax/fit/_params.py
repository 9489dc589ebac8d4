"""Parameter specification of a fit and the reparametrisation that enforces bounds.

A fit's parameters are the model's public parameters (``model.params()``:
``m1``, ``center.m``, ...) and the frame parameters ``theta_i`` and
``phi_ref`` of detector frames.  Each is described by a :class:`Param`:

- ``value``: the start in stored units (radians, metres, 1, sr^-1); ``None``
  takes the model's (or the data's) value, ``"auto"`` the automatic
  initialisation, a sequence one value per frame;
- ``lower``, ``upper``: bounds in stored units; ``None`` means the natural
  domain of the unit (``>= 0`` for lengths, dimensionless and sr^-1
  parameters, ``[0, pi/2)`` for ``theta_i``, unbounded for other angles);
  pass ``-inf`` / ``inf`` to drop a default bound;
- ``free``: fitted or held fixed;
- ``per_frame``: one value per frame (the default for frame parameters) or
  one value shared by every frame (the default for model parameters);
- ``scale``: for unbounded parameters, the largest step (stored units) the
  solver's unit step may take; default 1.

Bounds are enforced by reparametrisation, ``x = g(u)`` with ``u``
unconstrained (:data:`TRANSFORMS`):

============  ==============================  =============================
kind          x = g(u)                        used when
============  ==============================  =============================
``identity``  ``u``                           no bound
``log``       ``lower + exp(u)``              a lower bound only
``neglog``    ``upper - exp(-u)``             an upper bound only
``logit``     ``lower + (upper-lower) s(u)``  both bounds (s: the sigmoid)
============  ==============================  =============================

A solver with native box bounds (L-BFGS-B) keeps two-sided bounds as a box
on ``identity`` parameters instead of the ``logit``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.choices import check_choice
from ._common import FRAME_PARAMETERS, FitInputError

__all__ = [
    "Param",
    "TRANSFORMS",
    "forward",
    "forward_by_id",
    "inverse",
    "derivative",
    "derivative_by_id",
    "transform_id",
    "Layout",
    "FreeEntry",
    "FixedEntry",
    "build_layout",
    "SPEC_KEYS",
    "param_problems",
    "check_param",
]

TRANSFORMS = ("identity", "log", "neglog", "logit")

_POSITIVE_UNITS = ("1", "m", "sr^-1")


@dataclass(frozen=True)
class Param:
    """How one parameter enters a fit (values and bounds in stored units: rad, m, 1, sr^-1)."""

    value: float | Sequence[float] | Literal["auto"] | None = None
    lower: float | None = None
    upper: float | None = None
    free: bool = True
    per_frame: bool | None = None
    scale: float | None = None

    @classmethod
    def fixed(cls, value: float | Sequence[float] | None = None, per_frame: bool | None = None) -> "Param":
        """A parameter held at ``value`` (``None``: the model's or the data's value)."""
        return cls(value=value, free=False, per_frame=per_frame)

    @classmethod
    def auto(cls, **kwargs: Any) -> "Param":
        """A free parameter started from the automatic initialisation."""
        return cls(value="auto", **kwargs)


#: The keys of a specification table: the fields of :class:`Param`.
SPEC_KEYS = ("value", "lower", "upper", "free", "per_frame", "scale")


def _is_nan(x: Any) -> bool:
    return isinstance(x, float | int | np.floating | np.integer) and math.isnan(x)


def param_problems(p: Param, show: Callable[[float], str] = repr) -> list[tuple[str, str]]:
    """The rules of one specification that need no data, as ``(field, message)`` pairs.

    This is the one place these rules are written: the Python API
    (:func:`check_param`, from :func:`build_layout`) and the TOML fit config
    (``brdfjax.fit.config``, which reports them at the config's key in the
    key's own unit through ``show``) both call it.  ``field`` is ``""`` for
    the whole specification, else ``"value"``, ``"lower"``, ``"upper"``,
    ``"scale"`` or ``"per_frame"``.  Rules that need the data (a start from
    the automatic initialisation or from the model inside the bounds, one
    value per frame) stay in :func:`build_layout`.
    """
    problems: list[tuple[str, str]] = []
    for field in ("lower", "upper"):
        if _is_nan(getattr(p, field)):
            problems.append((field, "expected a number (inf allowed), got nan"))
    if problems:
        return problems
    lo, hi = p.lower, p.upper
    if lo is not None and hi is not None:
        if lo > hi:
            problems.append(("", f"lower bound {show(lo)} > upper bound {show(hi)}; swap them"))
            return problems
        if lo == hi and p.free:
            problems.append(("", f"lower == upper == {show(lo)} leaves nothing to fit; fix it with free=False"))
            return problems
    if p.scale is not None and not (p.scale > 0 and math.isfinite(p.scale)):
        problems.append(("scale", f"scale must be a positive number, got {p.scale!r}"))
    v = p.value
    if isinstance(v, str):
        if v != "auto":
            problems.append(("value", f"value {v!r} is not a number or 'auto'"))
        return problems
    if v is None:
        return problems
    values = [float(x) for x in np.asarray(v, dtype=np.float64).ravel()]
    if np.ndim(v) and p.per_frame is False:
        problems.append(("value", "a list of values needs per_frame = true"))
    for x in values:
        if not math.isfinite(x):
            problems.append(("value", f"start value {show(x)} is not finite"))
        elif (lo is not None and x < lo) or (hi is not None and x > hi):
            bounds = f"[{show(lo) if lo is not None else '-inf'}, {show(hi) if hi is not None else 'inf'}]"
            problems.append(("value", f"start value {show(x)} is outside its bounds {bounds}"))
    return problems


def check_param(name: str, p: Param) -> Param:
    """Raise :class:`FitInputError` for the first problem :func:`param_problems` finds in ``p``."""
    problems = param_problems(p)
    if problems:
        raise FitInputError(f"parameter '{name}': {problems[0][1]}")
    return p


def as_param(name: str, spec: Any) -> Param:
    """Normalise the shorthands of a spec entry: a Param, a number, 'auto', 'free' or 'fixed'."""
    if isinstance(spec, Param):
        return spec
    if isinstance(spec, str):
        if spec == "auto":
            return Param(value="auto")
        if spec == "free":
            return Param()
        if spec == "fixed":
            return Param.fixed()
        raise FitInputError(
            f"parameter '{name}': unknown specification {spec!r}; give a Param, a number, 'auto', 'free' or 'fixed'"
        )
    if isinstance(spec, int | float | np.floating | np.integer):
        return Param(value=float(spec))
    if isinstance(spec, Mapping):
        unknown = set(spec) - set(SPEC_KEYS)
        if unknown:
            raise FitInputError(
                f"parameter '{name}': unknown key(s) {sorted(unknown)}; known: {', '.join(sorted(SPEC_KEYS))}"
            )
        return Param(**spec)
    raise FitInputError(
        f"parameter '{name}': cannot use {type(spec).__name__} as a specification; give a Param, a number, "
        "'auto', 'free' or 'fixed'"
    )


# --- transforms ---------------------------------------------------------------------------


def _namespace(*arrays: Any):
    return jnp if any(isinstance(a, jax.Array | jax.core.Tracer) for a in arrays) else np


def forward_by_id(ids: Any, u: Any, lower: Any, upper: Any) -> Any:
    """``x = g(u)`` element-wise, the transform of each element given by its index into :data:`TRANSFORMS`.

    NumPy in, NumPy out (float64 for reports); JAX in, JAX out (differentiable;
    unused branches see finite inputs, so no NaN leaks into gradients).  The
    transform kinds are data, not structure: changing a bound does not
    recompile a fit.
    """
    xp = _namespace(ids, u, lower, upper)
    lo = xp.where(xp.isfinite(lower), lower, 0.0)
    hi = xp.where(xp.isfinite(upper), upper, 0.0)
    is_id, is_log, is_neg = ids == 0, ids == 1, ids == 2
    u_log = xp.where(is_log, u, 0.0)
    u_neg = xp.where(is_neg, u, 0.0)
    u_sig = xp.where(ids == 3, u, 0.0)
    sig = 1.0 / (1.0 + xp.exp(-u_sig))
    return xp.where(
        is_id, u, xp.where(is_log, lo + xp.exp(u_log), xp.where(is_neg, hi - xp.exp(-u_neg), lo + (hi - lo) * sig))
    )


def derivative_by_id(ids: Any, u: Any, lower: Any, upper: Any) -> Any:
    """``dx/du`` element-wise (see :func:`forward_by_id`)."""
    xp = _namespace(ids, u, lower, upper)
    lo = xp.where(xp.isfinite(lower), lower, 0.0)
    hi = xp.where(xp.isfinite(upper), upper, 0.0)
    is_id, is_log, is_neg = ids == 0, ids == 1, ids == 2
    e_log = xp.exp(xp.where(is_log, u, 0.0))
    e_neg = xp.exp(-xp.where(is_neg, u, 0.0))
    sig = 1.0 / (1.0 + xp.exp(-xp.where(ids == 3, u, 0.0)))
    return xp.where(is_id, 1.0, xp.where(is_log, e_log, xp.where(is_neg, e_neg, (hi - lo) * sig * (1.0 - sig))))


def transform_id(kind: str) -> int:
    if kind not in TRANSFORMS:
        raise ValueError(f"unknown transform '{kind}'; known: {', '.join(TRANSFORMS)}")
    return TRANSFORMS.index(kind)


def forward(kind: str, u: Any, lower: Any, upper: Any) -> Any:
    """``x = g(u)`` for one transform kind (NumPy or JAX, differentiable)."""
    xp = _namespace(u, lower, upper)
    return forward_by_id(xp.full(xp.shape(u), transform_id(kind)), u, xp.asarray(lower, float), xp.asarray(upper, float))


def derivative(kind: str, u: Any, lower: Any, upper: Any) -> Any:
    """``dx/du`` for one transform kind (NumPy or JAX)."""
    xp = _namespace(u, lower, upper)
    return derivative_by_id(xp.full(xp.shape(u), transform_id(kind)), u, xp.asarray(lower, float), xp.asarray(upper, float))


def inverse(kind: str, x: float, lower: float, upper: float) -> float:
    """``u = g^-1(x)`` in float64 NumPy; ``x`` must lie strictly inside the bounds."""
    if kind == "identity":
        return float(x)
    if kind == "log":
        return math.log(x - lower)
    if kind == "neglog":
        return -math.log(upper - x)
    if kind == "logit":
        t = (x - lower) / (upper - lower)
        return math.log(t) - math.log1p(-t)
    raise ValueError(f"unknown transform '{kind}'; known: {', '.join(TRANSFORMS)}")


def _transform_for(lower: float, upper: float, box: bool) -> str:
    lo, hi = math.isfinite(lower), math.isfinite(upper)
    if lo and hi:
        return "identity" if box else "logit"
    if lo:
        return "log"
    if hi:
        return "neglog"
    return "identity"


# --- layout -------------------------------------------------------------------------------


@dataclass(frozen=True)
class FreeEntry:
    """One fitted scalar: ``name`` as reported, ``base`` the model/frame parameter it sets."""

    name: str
    base: str
    kind: Literal["model", "frame"]
    blocks: tuple[int, ...]
    transform: str
    lower: float
    upper: float
    unit: str
    x0: float
    scale_max: float

    @property
    def u0(self) -> float:
        return inverse(self.transform, self.x0, self.lower, self.upper)


@dataclass(frozen=True)
class FixedEntry:
    """One held scalar, for reporting and for setting up the per-frame models and frames."""

    name: str
    base: str
    kind: Literal["model", "frame"]
    blocks: tuple[int, ...]
    value: float
    unit: str


@dataclass(frozen=True)
class Layout:
    """Every parameter of a fit, free and fixed, in the order they are reported."""

    free: tuple[FreeEntry, ...]
    fixed: tuple[FixedEntry, ...]
    block_names: tuple[str, ...]
    order: tuple[str, ...]

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.free)

    def u0(self) -> np.ndarray:
        return np.array([e.u0 for e in self.free], dtype=np.float64)

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower/upper bounds of the unconstrained vector (finite only for box-bounded identity entries)."""
        lo = np.array([e.lower if e.transform == "identity" else -np.inf for e in self.free])
        hi = np.array([e.upper if e.transform == "identity" else np.inf for e in self.free])
        return lo, hi

    def transform_ids(self) -> np.ndarray:
        return np.array([transform_id(e.transform) for e in self.free], dtype=np.int32)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([e.lower for e in self.free], np.float64), np.array([e.upper for e in self.free], np.float64)

    def natural(self, u: np.ndarray) -> np.ndarray:
        """Stored-unit values of the free entries at unconstrained ``u`` (NumPy float64)."""
        return np.asarray(forward_by_id(self.transform_ids(), np.asarray(u, np.float64), *self.bounds()), np.float64)

    def jacobian_diag(self, u: np.ndarray) -> np.ndarray:
        """``dx/du`` of every free entry at ``u`` (float64)."""
        return np.asarray(derivative_by_id(self.transform_ids(), np.asarray(u, np.float64), *self.bounds()), np.float64)


def _default_bounds(unit: str, base: str, kind: str) -> tuple[float, float]:
    if kind == "frame" and base == "theta_i":
        return 0.0, math.pi / 2
    if unit in _POSITIVE_UNITS:
        return 0.0, math.inf
    return -math.inf, math.inf


def _values_for_blocks(name: str, value: Any, n_blocks: int, per_frame: bool, block_names: Sequence[str]) -> list[float]:
    if np.ndim(value) == 0:
        v = float(value)
        return [v] * (n_blocks if per_frame else 1)
    vals = [float(x) for x in np.asarray(value, dtype=np.float64).ravel()]
    if not per_frame:
        if len(set(vals)) == 1:
            return vals[:1]
        raise FitInputError(
            f"parameter '{name}': {len(vals)} values given for a parameter shared by all frames; "
            "give one value, or set per_frame=True"
        )
    if len(vals) != n_blocks:
        raise FitInputError(
            f"parameter '{name}': {len(vals)} values given for {n_blocks} frames ({', '.join(block_names)}); "
            "give one value per frame, or one value for all"
        )
    return vals


def _shared_start(name: str, values: Sequence[float], unit: str) -> float:
    """One start value from per-frame values (circular mean for angles)."""
    v = np.asarray(values, dtype=np.float64)
    if unit == "rad" and name != "theta_i":
        return float(np.arctan2(np.mean(np.sin(v)), np.mean(np.cos(v))))
    return float(np.mean(v))


def build_layout(
    spec: Mapping[str, Any],
    model_values: Mapping[str, float],
    model_units: Mapping[str, str],
    block_names: Sequence[str],
    frame_values: Mapping[str, Sequence[float | None]],
    auto: Mapping[str, Any] | None,
    box: bool,
) -> Layout:
    """Resolve a specification against a model and the data blocks.

    ``model_values``/``model_units``: the model's public parameters;
    ``frame_values``: per-block nominal ``theta_i``/``phi_ref`` (``None`` for
    blocks without them, tables); ``auto``: the automatic initial values
    (name -> value or per-block list), or ``None`` when none were computed.
    Model parameters the spec does not mention are held at the model's value;
    frame parameters at the data's.
    """
    n_blocks = len(block_names)
    known = list(model_units) + [k for k in FRAME_PARAMETERS if k not in model_units]
    for name in spec:
        check_choice("parameter", name, known, error=FitInputError, sort=True)
    free: list[FreeEntry] = []
    fixed: list[FixedEntry] = []
    order: list[str] = []
    for name in known:
        kind = "frame" if name in FRAME_PARAMETERS and name not in model_units else "model"
        unit = model_units[name] if kind == "model" else FRAME_PARAMETERS[name]
        if kind == "frame":
            blocks_with = tuple(i for i, v in enumerate(frame_values[name]) if v is not None)
            if not blocks_with:
                if name in spec:
                    raise FitInputError(
                        f"parameter '{name}' belongs to detector frames, and this fit has none "
                        "(tables carry their own angles)"
                    )
                continue
        else:
            blocks_with = tuple(range(n_blocks))
        p = check_param(name, as_param(name, spec.get(name, Param.fixed())))
        per_frame = p.per_frame if p.per_frame is not None else (kind == "frame")
        d_lo, d_hi = _default_bounds(unit, name, kind)
        lower = d_lo if p.lower is None else float(p.lower)
        upper = d_hi if p.upper is None else float(p.upper)
        if lower > upper:  # a given bound against the unit's default one (given ones: param_problems)
            raise FitInputError(f"parameter '{name}': lower bound {lower!r} > upper bound {upper!r}; swap them")
        # start values
        if isinstance(p.value, str):
            if auto is None or name not in auto:
                have = ", ".join(sorted(auto)) if auto else "none (no initialiser ran)"
                raise FitInputError(
                    f"parameter '{name}': 'auto' but the automatic initialisation gives no value for it "
                    f"(it gives: {have}); give a start value"
                )
            raw = auto[name]
            if np.ndim(raw):
                if len(raw) != n_blocks:
                    raise FitInputError(
                        f"parameter '{name}': the automatic initialisation gave {len(raw)} values for "
                        f"{n_blocks} data blocks"
                    )
                raw = [raw[i] for i in blocks_with]
                if not per_frame:
                    raw = _shared_start(name, raw, unit)
        elif p.value is None:
            if kind == "model":
                raw = model_values[name]
            else:
                nominal = [frame_values[name][i] for i in blocks_with]
                raw = nominal if per_frame else _shared_start(name, nominal, unit)
        else:
            raw = p.value
        targets: list[tuple[str, tuple[int, ...]]]
        if per_frame:
            values = _values_for_blocks(name, raw, len(blocks_with), True, [block_names[i] for i in blocks_with])
            targets = [(f"{name}[{block_names[i]}]", (i,)) for i in blocks_with]
        else:
            values = _values_for_blocks(name, raw, len(blocks_with), False, block_names)
            targets = [(name, blocks_with)]
        for (pname, blocks), x0 in zip(targets, values):
            order.append(pname)
            if not math.isfinite(x0):
                raise FitInputError(f"parameter '{pname}': start value {x0!r} is not finite")
            if not p.free:
                fixed.append(FixedEntry(pname, name, kind, blocks, x0, unit))
                continue
            if not (lower <= x0 <= upper):
                raise FitInputError(
                    f"parameter '{pname}': start value {x0!r} is outside its bounds [{lower!r}, {upper!r}]"
                )
            transform = _transform_for(lower, upper, box)
            if transform != "identity" and (x0 == lower or x0 == upper):
                raise FitInputError(
                    f"parameter '{pname}': start value {x0!r} lies on a bound of [{lower!r}, {upper!r}]; "
                    "a free parameter must start strictly inside its bounds (move the start, or fix it with "
                    "free=False)"
                )
            scale_max = 1.0 if transform != "identity" else float(p.scale if p.scale is not None else 1.0)
            if transform == "identity" and math.isfinite(lower) and math.isfinite(upper):
                scale_max = min(scale_max, upper - lower)
            free.append(FreeEntry(pname, name, kind, blocks, transform, lower, upper, unit, x0, scale_max))
    return Layout(tuple(free), tuple(fixed), tuple(block_names), tuple(order))
