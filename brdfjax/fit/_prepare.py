"""The fit problem built from NumPy inputs: data blocks checked, footprint boxes planned, the traced
:class:`~brdfjax.fit._problem.Problem` and its parameter :class:`~brdfjax.fit._params.Layout` made
(:func:`prepare`, what :func:`brdfjax.fit.fit` solves and the samplers evaluate).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..core.fft import fast_len
from ..core.geometry import Directions
from ..core.render import Conditions, cast, resolve_dtype
from ..core.terms import Model
from ..io.blocks import FrameData, TableData
from ._auto_init import get_initializer
from ._common import FRAME_PARAMETERS, FitInputError
from ._nuisance import NuisanceOptions, NuisanceSpec, NuisanceTerms, build_nuisance
from ._params import FreeEntry, Layout, as_param, build_layout
from ._problem import (
    FrameBlock,
    Problem,
    TableBlock,
    build_targets,
    can_stack,
    frame_for_block,
    stack_frames,
    template_for_block,
)
from ._residuals import DEFAULT_LOSS_SCALE, LOSSES, loss_id
from ._solvers import AbstractSolver

__all__ = ["Prepared", "prepare", "block_names"]

Data = FrameData | TableData


def _as_blocks(data: Data | Sequence[Data]) -> list[Data]:
    blocks = [data] if isinstance(data, FrameData | TableData) else list(data)
    if not blocks:
        raise FitInputError("no data: give at least one FrameData or TableData")
    for i, b in enumerate(blocks):
        if not isinstance(b, FrameData | TableData):
            raise FitInputError(f"data[{i}] is a {type(b).__name__}; expected FrameData or TableData")
    return blocks


def block_names(blocks: Sequence[Data]) -> tuple[str, ...]:
    names = [b.name for b in blocks]
    if len(set(names)) == len(names):
        return tuple(names)
    return tuple(f"{n}{i}" for i, n in enumerate(names))


def _leaves(detector) -> tuple[Any, list[np.ndarray]]:
    leaves, treedef = jax.tree_util.tree_flatten(detector, is_leaf=lambda x: x is None)
    return treedef, [None if x is None else np.asarray(x) for x in leaves]


def _check_detectors(blocks: Sequence[Data], names: Sequence[str], allow: bool) -> None:
    frames = [(n, b) for n, b in zip(names, blocks) if isinstance(b, FrameData)]
    if len(frames) < 2 or allow:
        return
    (n0, b0), rest = frames[0], frames[1:]
    t0, l0 = _leaves(b0.detector)
    for n, b in rest:
        t, lv = _leaves(b.detector)
        same = b.detector.shape == b0.detector.shape and t == t0 and all(
            (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y)) for x, y in zip(l0, lv)
        )
        if not same:
            raise FitInputError(
                f"frames '{n0}' and '{n}' were taken with different detectors; a joint fit of different "
                "detectors must say so: pass allow_different_detectors=True"
            )


def _resolve_precision(precision: str | None) -> tuple[str, Any]:
    """Default to the process's JAX precision; the checks (and messages) are render's."""
    if precision is None:
        precision = "float64" if jax.config.jax_enable_x64 else "float32"
    try:
        dtype = resolve_dtype(precision)
    except ValueError as e:
        raise FitInputError(str(e)) from None
    return np.dtype(dtype).name, dtype


def _floor(block: Data, usable: np.ndarray, floor: float | str) -> float:
    if isinstance(floor, str):
        if floor != "auto":
            raise FitInputError(f"floor must be a number (sr^-1) or 'auto', got {floor!r}")
        return 1e-6 * float(np.min(np.asarray(block.brdf, float)[usable]))
    floor = float(floor)
    if not (floor >= 0 and math.isfinite(floor)):
        raise FitInputError(f"floor must be a non-negative number (sr^-1), got {floor!r}")
    return floor


#: With a footprint, the model is evaluated only at the grid points within the kernel's reach of a
#: usable point when they are fewer than this fraction of the grid (else on the whole grid).
SUPPORT_FRACTION = 0.7


def _dilate(mask: np.ndarray, r: int, c: int) -> np.ndarray:
    """``mask`` dilated by a ``(2r+1) x (2c+1)`` rectangle (the kernel's reach)."""
    m = np.pad(np.asarray(mask, bool), ((r, r), (0, 0)))
    m = sliding_window_view(m, 2 * r + 1, axis=0).any(-1)
    m = np.pad(m, ((0, 0), (c, c)))
    return sliding_window_view(m, 2 * c + 1, axis=1).any(-1)


#: The scatter directions of a frame's evaluation points are computed once per problem (they depend on
#: no fitted parameter when theta_i is fixed) up to this many points per frame (9 floats a point).
DIRS_MAX_POINTS = 4_000_000


def _box_need(usable: np.ndarray, kshape: tuple[int, int]) -> tuple[int, int]:
    """Rows and columns a circular convolution needs so that no wrap-around reaches a usable point."""
    rows, cols = np.nonzero(usable)
    return (int(rows.max() - rows.min() + kshape[0]), int(cols.max() - cols.min() + kshape[1]))


def _box(usable: np.ndarray, reach: np.ndarray, k: np.ndarray, shape: tuple[int, int]) -> dict[str, Any]:
    """The footprint on a ``shape`` FFT box whose origin is the usable points' corner less the kernel's half-size.

    The model is zero outside the support (the usable points dilated by the kernel), so a circular
    convolution of at least the usable span plus the kernel's size equals the zero-padded linear one at
    every usable point.
    """
    r, c = k.shape[0] // 2, k.shape[1] // 2
    ur, uc = np.nonzero(usable)
    r0, c0 = int(ur.min()) - r, int(uc.min()) - c
    nr, nc = shape
    sr, sc = np.nonzero(reach)
    kc = np.zeros(shape)
    jj, ii = np.meshgrid(np.arange(k.shape[0]) - r, np.arange(k.shape[1]) - c, indexing="ij")
    kc[jj % nr, ii % nc] = k
    kf = np.fft.rfft2(kc)
    return dict(
        box_support=(sr - r0) * nc + (sc - c0),
        box_points=(ur - r0) * nc + (uc - c0),
        kernel_fft=np.stack([kf.real, kf.imag]),
        box_shape=(int(nr), int(nc)),
    )


#: A kernel is taken as separable when its second singular value is below this fraction of the first.
SEPARABLE_RTOL = 1e-12
#: The direct separable convolution is used up to this many gathered points (index entries) per frame.
SEPARABLE_MAX_ENTRIES = 50_000_000


def _separable(usable: np.ndarray, reach: np.ndarray, k: np.ndarray) -> dict[str, Any] | None:
    """The footprint as two one-dimensional passes at the points the usable ones need (None: not separable).

    ``K = outer(kv, kh)`` to rounding (the Gaussian beam footprint is): the model convolved at a usable
    point is ``sum_i kh[i] T[row, col - i + c]`` with ``T[row, col] = sum_j kv[j] f[row - j + r, col]``,
    and ``T`` is needed only at the usable points dilated along the rows by ``c``.  Index -1 is a zero.
    """
    u, s, vt = np.linalg.svd(k)
    if s.size < 2 or not s[1] <= SEPARABLE_RTOL * s[0]:
        return None
    kv, kh = u[:, 0] * np.sqrt(s[0]), vt[0] * np.sqrt(s[0])
    if kv.sum() < 0:
        kv, kh = -kv, -kh
    r, c = k.shape[0] // 2, k.shape[1] // 2
    shape = usable.shape
    mid = _dilate(usable, 0, c)
    if mid.sum() * k.shape[0] + usable.sum() * k.shape[1] > SEPARABLE_MAX_ENTRIES:
        return None
    support_of = np.full(shape[0] * shape[1] + 1, -1, np.int64)  # grid pixel -> support point (last: outside)
    support_of[np.flatnonzero(reach.ravel())] = np.arange(int(reach.sum()))
    mid_of = np.full(shape[0] * shape[1] + 1, -1, np.int64)
    mid_of[np.flatnonzero(mid.ravel())] = np.arange(int(mid.sum()))
    outside = shape[0] * shape[1]

    def index(rows, cols, lookup):
        ok = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
        return lookup[np.where(ok, rows * shape[1] + cols, outside)]

    mr, mc = np.nonzero(mid)
    sep_rows = index(mr[:, None] - np.arange(k.shape[0])[None, :] + r, mc[:, None], support_of)
    ur, uc = np.nonzero(usable)
    sep_cols = index(ur[:, None], uc[:, None] - np.arange(k.shape[1])[None, :] + c, mid_of)
    return dict(sep_rows=sep_rows.astype(np.int32), sep_cols=sep_cols.astype(np.int32), kernel_v=kv, kernel_h=kh)


def _directions(detector, theta_i: float, n_h: np.ndarray, n_v: np.ndarray) -> Directions:
    d = detector.directions(jnp.asarray(n_h), jnp.asarray(n_v), jnp.asarray(np.float64(theta_i)))
    # the incident direction stays one per frame (scalar components): terms compute its factors once
    w_i = tuple(np.asarray(c, np.float64) for c in d.i)
    return Directions(w_i, *(np.asarray(a).reshape(-1, 3) for a in (d.w_s, d.w_sum)))


def _frame_block(b: FrameData, usable: np.ndarray, template: Model, frame: Conditions, floor: float, use_footprint: bool,
                 box_shape: tuple[int, int] | None = None, fixed_theta_i: bool = False, plain: bool = False):
    brdf = np.asarray(b.brdf, np.float64)
    sigma = np.broadcast_to(np.asarray(b.sigma_rel, np.float64), brdf.shape)
    data = brdf[usable]
    inv_sigma = 1.0 / sigma[usable]
    soft = float(np.median(data))
    detector = b.arm_detector()
    theta_i = float(np.asarray(frame.theta_i))
    if plain:  # nothing precomputed from the detector or the kernel (see the caller)
        fixed_theta_i, box_shape = False, None
    if b.footprint is not None and use_footprint:
        k = np.asarray(b.footprint, np.float64)
        n_h, n_v = np.asarray(b.grid.n_h, np.float64), np.asarray(b.grid.n_v, np.float64)
        reach = _dilate(usable, k.shape[0] // 2, k.shape[1] // 2)
        extra: dict[str, Any] = {}
        if reach.sum() < SUPPORT_FRACTION * reach.size:  # evaluate the model only where the convolution looks
            rows, cols = np.nonzero(reach)
            extra = dict(support_index=np.flatnonzero(reach.ravel()), support_h=n_h[cols], support_v=n_v[rows])
            sep = None if plain else _separable(usable, reach, k / k.sum())
            if sep is not None:
                extra.update(sep)
            elif box_shape is not None:
                extra.update(_box(usable, reach, k / k.sum(), box_shape))
            if fixed_theta_i and rows.size <= DIRS_MAX_POINTS:
                extra["dirs"] = _directions(detector, theta_i, n_h[cols], n_v[rows])
        elif fixed_theta_i and reach.size <= DIRS_MAX_POINTS:
            extra["dirs"] = _directions(detector, theta_i, n_h[None, :], n_v[:, None])
        return FrameBlock(
            template, frame, detector, n_h, n_v,
            data, inv_sigma, np.float64(floor), np.float64(soft), k / k.sum(), np.flatnonzero(usable.ravel()),
            **extra,
        )
    rows, cols = np.nonzero(usable)
    n_h, n_v = np.asarray(b.grid.n_h, np.float64)[cols], np.asarray(b.grid.n_v, np.float64)[rows]
    dirs = _directions(detector, theta_i, n_h, n_v) if fixed_theta_i and rows.size <= DIRS_MAX_POINTS else None
    return FrameBlock(
        template, frame, detector, n_h, n_v,
        data, inv_sigma, np.float64(floor), np.float64(soft), dirs=dirs,
    )


def _table_block(b: TableData, usable: np.ndarray, template: Model, floor: float):
    sel = usable
    ti, pi_, ts, ps = (np.asarray(getattr(b, f), np.float64)[sel] for f in ("theta_i", "phi_i", "theta_s", "phi_s"))
    dirs = Directions.from_angles(ti, pi_, ts, ps)
    wl = np.broadcast_to(np.asarray(b.wavelength, np.float64), usable.shape)[sel]
    brdf = np.asarray(b.brdf, np.float64)[sel]
    inv_sigma = np.ones_like(brdf) if b.sigma_rel is None else 1.0 / np.broadcast_to(np.asarray(b.sigma_rel, np.float64), usable.shape)[sel]
    return TableBlock(template, dirs, wl, brdf, inv_sigma, np.float64(floor), np.float64(np.median(brdf)))


def _wants_auto(spec: Mapping[str, Any]) -> bool:
    return any(isinstance(p.value, str) and p.value == "auto" for p in (as_param(k, v) for k, v in spec.items()))


@dataclass(frozen=True, eq=False)
class Prepared:
    """A validated fit problem and what the result needs to know about its blocks."""

    problem: Problem
    layout: Layout
    blocks: list[Data]
    names: tuple[str, ...]
    auto: dict[str, Any]
    warnings: list[str]
    inv_sigma: tuple[np.ndarray, ...]  # per block, at the usable points
    convolved: tuple[bool, ...]
    init_s: float  # time spent in the automatic initialisation
    nuisance: NuisanceSpec | None = None  # the systematic errors' nuisance parameters (last free entries)


def prepare(
    model: Model,
    data: Data | Sequence[Data],
    params: Mapping[str, Any] | None = None,
    *,
    solver: AbstractSolver,
    loss: str = "linear",
    loss_scale: float | None = None,
    initializer: str | Callable | None = None,
    init_options: Mapping[str, Any] | None = None,
    floor: float | str = "auto",
    precision: str | None = None,
    allow_different_detectors: bool = False,
    use_footprint: bool = True,
    nuisance: NuisanceOptions | Mapping[str, Any] | bool | None = None,
) -> "Prepared":
    """Validate the inputs and build the :class:`Problem` (unscaled) and its :class:`Layout`."""
    if not isinstance(model, Model):
        raise FitInputError(f"model must be a brdfjax Model (a named sum of terms), got {type(model).__name__}")
    spec = dict(params or {})
    if loss not in LOSSES:
        raise FitInputError(f"unknown loss '{loss}'; known: {', '.join(LOSSES)}")
    k = DEFAULT_LOSS_SCALE if loss_scale is None else float(loss_scale)
    if not (k > 0 and math.isfinite(k)):
        raise FitInputError(f"loss_scale must be a positive number (in sigma), got {loss_scale!r}")
    blocks = _as_blocks(data)
    names = block_names(blocks)
    _check_detectors(blocks, names, allow_different_detectors)
    usable = [b.check_usable() for b in blocks]
    precision, dtype = _resolve_precision(precision)
    warnings: list[str] = []

    auto: dict[str, Any] | None = None
    t0 = time.perf_counter()
    if _wants_auto(spec):
        init = get_initializer(initializer, model)
        auto = dict(init(model, blocks, **dict(init_options or {})))
    elif initializer is not None:
        get_initializer(initializer, model)  # validate the name even when unused
    init_s = time.perf_counter() - t0

    frame_values = {
        name: [float(getattr(b, name)) if isinstance(b, FrameData) else None for b in blocks] for name in FRAME_PARAMETERS
    }
    model_values = {k_: float(np.asarray(v)) for k_, v in model.params().items()}
    layout = build_layout(
        spec, model_values, model.parameter_units(), names, frame_values, auto, solver.box_bounds
    )
    spec_n = _nuisance_spec(blocks, names, nuisance)
    # A free instrument quantity (footprint width, misalignment) moves each frame's geometry and kernel on every
    # call: its blocks keep the plain path (directions from the detector, the footprint from the kernel itself)
    # instead of the precomputed directions and convolution plans, which hold them constant.
    moving = spec_n is not None and any(spec_n.geometry_of(j) for j in range(len(spec_n.names)))
    built = []
    # one FFT box for every frame with a footprint of one kernel shape (so that they stack)
    needs: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for b, u in zip(blocks, usable):
        if isinstance(b, FrameData) and b.footprint is not None and use_footprint:
            kshape = tuple(np.shape(b.footprint))
            needs.setdefault(kshape, []).append(_box_need(u, kshape))
    boxes = {ks: (fast_len(max(n[0] for n in v)), fast_len(max(n[1] for n in v))) for ks, v in needs.items()}
    for i, (b, u) in enumerate(zip(blocks, usable)):
        template = template_for_block(model, layout, i)
        fl = _floor(b, u, floor)
        if isinstance(b, FrameData):
            frame = frame_for_block(Conditions(b.theta_i, b.phi_ref, b.wavelength), layout, i)
            fixed = not any(e.base == "theta_i" and i in e.blocks for e in layout.free)
            box = boxes.get(tuple(np.shape(b.footprint))) if b.footprint is not None else None
            built.append(_frame_block(b, u, template, frame, fl, use_footprint, box, fixed, plain=moving))
        else:
            built.append(_table_block(b, u, template, fl))
    if spec_n is not None:
        layout = _with_nuisance(layout, spec_n)
    n_free = len(layout.free)
    lo, hi = layout.bounds()
    stacked = can_stack(built)
    problem = Problem(
        blocks=() if stacked else tuple(built),
        stack=stack_frames(built) if stacked else None,
        u0=layout.u0(),
        scale=np.ones(n_free),
        lower=lo,
        upper=hi,
        loss_index=np.int32(loss_id(loss)),
        loss_scale=np.float64(k),
        soften=np.float64(0.0),
        transform_ids=layout.transform_ids(),
        targets=build_targets(layout),
        counts=tuple(int(b.data.shape[0]) for b in built),
        nuisance=None if spec_n is None else NuisanceTerms.build(
            spec_n, n_free - spec_n.size, [int(b.data.shape[0]) for b in built], [np.asarray(b.inv_sigma) for b in built]
        ),
    )
    return Prepared(
        cast(problem, dtype), layout, blocks, names, auto or {}, warnings,
        tuple(np.asarray(b.inv_sigma, np.float64) for b in built),
        tuple(isinstance(b, FrameBlock) and b.kernel is not None for b in built),
        init_s,
        spec_n,
    )


def _nuisance_spec(blocks: Sequence[Data], names: Sequence[str], nuisance: Any) -> NuisanceSpec | None:
    """The nuisance parameters asked for (``None``/``False``: none; ``True``: the defaults; options or a spec)."""
    if nuisance is None or nuisance is False:
        return None
    if isinstance(nuisance, NuisanceSpec):
        if nuisance.design.shape[0] != len(blocks):
            raise FitInputError(f"the nuisance design has {nuisance.design.shape[0]} rows for {len(blocks)} data blocks")
        return nuisance
    if nuisance is True:
        opts = NuisanceOptions()
    elif isinstance(nuisance, NuisanceOptions):
        opts = nuisance
    elif isinstance(nuisance, Mapping):
        try:
            opts = NuisanceOptions(**nuisance)
        except ValueError as e:
            raise FitInputError(f"nuisance options: {e}") from None
    else:
        raise FitInputError(f"nuisance must be None, a bool, NuisanceOptions or a dict of them, got {type(nuisance).__name__}")
    return build_nuisance(blocks, names, opts)


def _with_nuisance(layout: Layout, spec: NuisanceSpec) -> Layout:
    """The layout with the nuisance parameters appended as free, unbounded entries starting at 0."""
    taken = set(layout.order)
    extra = []
    for j, (name, s) in enumerate(zip(spec.names, spec.prior_sigma)):
        if name in taken:
            raise FitInputError(f"nuisance parameter '{name}' clashes with a parameter of the model")
        g = spec.geometry_of(j)
        base = f"nuisance:{g}" if g else name  # an instrument quantity: applied to the frames (Problem._block_values)
        extra.append(FreeEntry(name, base, "nuisance", spec.blocks_of(j), "identity", -math.inf, math.inf,
                               spec.stored_unit(j), 0.0, float(s)))
    return Layout(layout.free + tuple(extra), layout.fixed, layout.block_names, layout.order + tuple(spec.names))
