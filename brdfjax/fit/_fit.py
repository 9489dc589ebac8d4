"""``fit``: fit a brdfjax model to detector frames and/or goniometer tables.

The numerical work is pure JAX (:mod:`brdfjax.fit._problem`); this module sets
it up from NumPy inputs, runs the solver and turns the solution into a
:class:`~brdfjax.fit.FitResult`.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import math
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..core.fft import fast_len
from ..core.geometry import Directions
from ..core.render import Frame, cast, resolve_dtype
from ..core.terms import Model
from ..io.blocks import FrameData, TableData
from ._auto_init import get_initializer
from ._common import FRAME_PARAMETERS, FitInputError, natural_unit, to_natural
from ._covariance import covariance
from ._likelihood import LIKELIHOOD_OPTIONS, Likelihood
from ._nuisance import NuisanceOptions, NuisanceSpec, NuisanceTerms, build_nuisance, conditional_sigma
from ._params import FreeEntry, Layout, as_param, build_layout
from ._problem import (
    FrameBlock,
    Problem,
    TableBlock,
    build_targets,
    can_stack,
    evaluate_call as evaluate,
    frame_for_block,
    jacobian_call as jacobian,
    report_evaluations,
    stack_frames,
    template_for_block,
    with_loss,
    with_scale,
)
from ._residuals import DEFAULT_LOSS_SCALE, LOSSES, irls_weights, loss_id
from ._resolution import check_resolution
from ._result import BlockSummary, FitResult, ParameterEstimate
from ._solvers import AbstractSolver, SolveOutcome, SolveStatus, get_solver

__all__ = ["fit", "prepare", "versions", "FIRST_STAGES"]

#: First stages of a fit (``fit(first_stage=...)``): ``soft`` softens the log residuals below each
#: block's median datum; a loss name runs that robust loss first.
FIRST_STAGES = ("soft", "huber", "cauchy")

Data = FrameData | TableData


def versions() -> dict[str, str]:
    """Versions of Python and the packages a fit depends on."""
    out = {"python": platform.python_version()}
    for pkg in ("brdfjax", "jax", "jaxlib", "equinox", "optimistix", "lineax", "jaxopt", "numpy"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


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


def _frame_block(b: FrameData, usable: np.ndarray, template: Model, frame: Frame, floor: float, use_footprint: bool,
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
            frame = frame_for_block(Frame(b.theta_i, b.phi_ref, b.wavelength), layout, i)
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


def _scales(problem: Problem, layout: Layout, warnings: list[str]) -> np.ndarray:
    """Per-parameter step scale: 1 / (Jacobian column norm) at the start, capped by ``scale_max``."""
    n = len(layout.free)
    if n == 0:
        return np.ones(0)
    J = np.asarray(jacobian(jnp.zeros(n, problem.u0.dtype), problem), np.float64)
    norms = np.linalg.norm(J, axis=0)
    caps = np.array([e.scale_max for e in layout.free])
    scale = np.empty(n)
    for i, e in enumerate(layout.free):
        if not np.isfinite(norms[i]):
            raise FitInputError(
                f"parameter '{e.name}': the Jacobian at the start is not finite; check the start values and data"
            )
        if norms[i] == 0:
            warnings.append(
                f"parameter '{e.name}' does not change the residuals at the start (zero Jacobian column): "
                "the data do not see it there; give a better start or fix it"
            )
            scale[i] = caps[i]
        else:
            scale[i] = min(1.0 / norms[i], caps[i])
    return scale


def _solve_stage(
    problem: Problem, layout: Layout, solver: AbstractSolver, u_start: np.ndarray, warnings: list[str]
) -> tuple[Problem, SolveOutcome]:
    """One solve from ``u_start``, with the step scales recomputed there."""
    n = len(layout.free)
    problem = with_scale(problem, u_start, np.ones(n))
    scale = _scales(problem, layout, warnings)
    problem = with_scale(problem, u_start, scale)
    box = None
    if solver.box_bounds:
        lo, hi = layout.box()
        with np.errstate(invalid="ignore"):
            box = ((lo - u_start) / scale, (hi - u_start) / scale)
    # The solver's coordinates are float64 whenever 64-bit JAX is on (optimistix keeps its own scalars in
    # the default float type); the model is still evaluated at the requested precision.
    outcome = solver.solve(problem, jnp.zeros(n, jnp.result_type(float)), box)
    return problem, outcome


def _segments(counts: Sequence[int]) -> list[tuple[int, int, int]]:
    """``(offset, count, block)`` of each block's points in the concatenated residuals."""
    offs = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    return [(int(offs[k]), int(c), k) for k, c in enumerate(counts)]


def _est_rss(problem: Problem, v: np.ndarray, est: Sequence[int]) -> tuple[float, int]:
    """Sum of squared ln residuals and their number over the blocks whose noise is estimated."""
    r = np.asarray(evaluate(jnp.asarray(v), problem)[0], np.float64)
    rss, n = 0.0, 0
    for o, c, k in _segments(problem.counts):
        if k in est:
            rk = r[o : o + c] / np.asarray(problem.blocks[k].inv_sigma, np.float64)
            rss += float(np.sum(rk**2))
            n += c
    return rss, n


def _estimate_noise(
    problem: Problem, layout: Layout, solver: AbstractSolver, outcome: SolveOutcome, est: Sequence[int],
    robust: bool, prep: "Prepared",
) -> tuple[Problem, SolveOutcome, dict[str, Any]]:
    """The log-normal scatter of tables without uncertainties, profiled out of the likelihood.

    Model: ``ln d = ln f + e``, ``e ~ N(0, s^2)`` with one unknown ``s`` shared by the blocks ``est``.
    Profiling ``s`` out gives ``-2 ln L = chi2_rest + N ln(RSS/N) + N`` at ``s^2 = RSS/N``; its optimum
    is a fixed point of "weight those blocks by 1/s, solve, re-estimate s", which is iterated here when
    it matters (other blocks with their own sigma, or a robust loss whose scale is in sigma); with the
    linear loss and only such blocks the unweighted solve is already the optimum.  The blocks'
    weights are left at ``1/s``, so residuals, zones and the covariance are in units of the estimate.
    """
    dtype = problem.u0.dtype
    base = {k: np.asarray(prep.inv_sigma[k], np.float64) for k in est}
    iterate = robust or len(est) < problem.n_blocks
    s, extra, n_iter = 1.0, 0, 0
    while n_iter < 8:
        n_iter += 1
        rss, n = _est_rss(problem, outcome.v, est)
        s_new = math.sqrt(rss / max(n, 1)) if rss > 0 else 1.0
        problem = eqx.tree_at(
            lambda p: tuple(p.blocks[k].inv_sigma for k in est), problem,
            tuple(jnp.asarray(base[k] / s_new, dtype) for k in est),
        )
        done = abs(s_new / s - 1.0) < 1e-3
        s = s_new
        if not iterate or done or not len(layout.free) or not np.all(np.isfinite(outcome.v)):
            break
        u_start = np.asarray(problem.u0, np.float64) + np.asarray(problem.scale, np.float64) * np.asarray(outcome.v)
        problem, new = _solve_stage(problem, layout, solver, u_start, [])
        extra += new.n_steps
        outcome = SolveOutcome(new.v, new.converged, new.status, new.message, outcome.n_steps + new.n_steps)
    rss, n = _est_rss(problem, outcome.v, est)
    return problem, outcome, {
        "estimated": True,
        "sigma_ln": s,
        "n_points": n,
        "rss_ln": rss,
        "blocks": [prep.names[k] for k in est],
        "iterations": n_iter,
        "method": "profile likelihood: -2 ln L = chi2_other + N ln(RSS/N) + N, s^2 = RSS/N (log-normal scatter of ln BRDF)",
        "extra_steps": extra,
    }


def _group_stats(b: TableData, usable: np.ndarray, r: np.ndarray, log_res: np.ndarray) -> tuple[dict[str, Any], ...]:
    ti = np.asarray(b.theta_i, float)[usable]
    key = np.round(np.degrees(ti), 4)
    out = []
    for t in np.unique(key):
        sel = key == t
        out.append(
            {
                "theta_i_deg": float(t),
                "n_points": int(sel.sum()),
                "chi2": float(np.sum(r[sel] ** 2)),
                "log_rms": float(np.sqrt(np.mean(log_res[sel] ** 2))),
            }
        )
    return tuple(out)


def _is_default(value: Any, default: Any) -> bool:
    return value is default or (type(value) is type(default) and value == default)


def fit(
    model: Model | Likelihood,
    data: Data | Sequence[Data] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    solver: str | AbstractSolver = "levenberg_marquardt",
    solver_options: Mapping[str, Any] | None = None,
    loss: str = "linear",
    loss_scale: float | None = None,
    first_stage: str | None = "soft",
    initializer: str | Callable | None = None,
    init_options: Mapping[str, Any] | None = None,
    floor: float | str = "auto",
    precision: str | None = None,
    absolute_sigma: bool | None = None,
    allow_different_detectors: bool = False,
    use_footprint: bool = True,
    resolution_check: bool = True,
    progress: Callable[[int, float], None] | None = None,
    nuisance: NuisanceOptions | Mapping[str, Any] | bool | None = None,
) -> FitResult:
    """Fit ``model`` to one or several data blocks (detector frames and/or goniometer tables).

    ``fit(likelihood, solver=...)`` fits a :class:`~brdfjax.fit.Likelihood` built by
    :func:`brdfjax.fit.prepare` (the data, params and likelihood options are then the likelihood's);
    ``fit(model, data, params, **options)`` builds it in place.

    ``params`` maps parameter names (the model's public names, ``theta_i``,
    ``phi_ref``) to a :class:`~brdfjax.fit.Param`, a start value (free),
    ``"auto"``, ``"free"`` or ``"fixed"``; parameters not named are held at
    the model's (or the data's) values.  Values and bounds are in stored units
    (radians, metres); the result reports angles in degrees.

    ``solver``: a name from :data:`~brdfjax.fit.SOLVERS` with
    ``solver_options``, or a solver object.  ``loss``: ``linear``, ``huber`` or
    ``cauchy`` with ``loss_scale`` in sigma (default 3).  ``initializer``: the
    automatic initialisation for ``"auto"`` starts (a name from
    :data:`~brdfjax.fit.INITIALIZERS` or a callable ``(model, blocks, **options)
    -> {name: value}``; default: chosen from the model), with
    ``init_options`` (e.g. index priors ``n1``, ``n2``).  ``floor``: the
    underflow guard of the log model (sr^-1, or ``"auto"``).  ``precision``:
    ``float32``/``float64`` (default: float64 when 64-bit JAX is on).
    ``absolute_sigma``: take the data's uncertainties at face value
    (default: yes when every block has ``sigma_rel``).  Frames from different
    detectors need ``allow_different_detectors=True``.  A footprint on a frame
    is convolved with the model unless ``use_footprint=False``.
    ``progress(k, chi2)`` hears of every residual evaluation of the solver
    (about one per step) with the sum of squared residuals there.

    ``nuisance``: the systematic errors of frames that came through the
    instrument as nuisance parameters of the likelihood
    (:mod:`brdfjax.fit._nuisance`; ``True`` or options; default none); the
    result then reports each parameter's sigma with them (marginal) and
    without (conditional) in ``FitResult.nuisance``.

    A fit that does not converge returns normally with ``converged=False``
    and a message that says why; bad inputs raise
    :class:`~brdfjax.fit.FitInputError`.
    """
    call = {
        "loss": loss, "loss_scale": loss_scale, "floor": floor, "precision": precision, "absolute_sigma": absolute_sigma,
        "use_footprint": use_footprint, "nuisance": nuisance, "initializer": initializer, "init_options": init_options,
        "allow_different_detectors": allow_different_detectors, "resolution_check": resolution_check,
    }
    if isinstance(model, Likelihood):
        clash = [k for k, v in call.items() if not _is_default(v, LIKELIHOOD_OPTIONS[k])]
        clash += [k for k, v in (("data", data), ("params", params)) if v is not None]
        if clash:
            raise FitInputError(
                f"fit(likelihood) takes {', '.join(clash)} from the likelihood; set them with "
                "brdfjax.fit.prepare(...) or likelihood.replace(...)"
            )
        return fit(model.model, model.blocks, model.params, solver=solver, solver_options=solver_options,
                   first_stage=first_stage, progress=progress, **model.options())
    if data is None:
        raise FitInputError("fit(model, data, params): data is missing (a FrameData, a TableData or a list of them)")
    t_start = time.perf_counter()
    opts = dict(solver_options or {})
    solver_obj = get_solver(solver, **opts)
    if first_stage is not None and first_stage not in FIRST_STAGES:
        raise FitInputError(f"unknown first_stage '{first_stage}'; known: {', '.join(FIRST_STAGES)} or None")
    prep = prepare(
        model, data, params, solver=solver_obj, loss=loss, loss_scale=loss_scale, initializer=initializer,
        init_options=init_options, floor=floor, precision=precision,
        allow_different_detectors=allow_different_detectors, use_footprint=use_footprint, nuisance=nuisance,
    )
    problem, layout, blocks, auto, warnings = prep.problem, prep.layout, prep.blocks, prep.auto, prep.warnings
    precision_name = "float64" if problem.u0.dtype == jnp.float64 else "float32"
    t_setup = time.perf_counter()
    n_free = len(layout.free)
    u0 = layout.u0()
    k_final = float(np.asarray(problem.loss_scale))
    stages = [(loss_id(loss), k_final, 0.0)]
    if first_stage == "soft":
        stages.insert(0, (loss_id(loss), k_final, 1.0))
    elif first_stage is not None:
        stages.insert(0, (loss_id(first_stage), DEFAULT_LOSS_SCALE, 0.0))
    notes, total_steps = [], 0
    if not n_free:
        problem = with_scale(problem, u0, np.ones(0))
        outcome = SolveOutcome(np.zeros(0), True, "successful", "nothing to fit: every parameter is fixed", 0)
    else:
        u_start = u0
        n_eval = 0

        def heard(chi2: float) -> None:
            nonlocal n_eval
            n_eval += 1
            progress(n_eval, chi2)

        for i, (index, k_stage, soften) in enumerate(stages):
            with report_evaluations(heard if progress is not None else None):
                problem, outcome = _solve_stage(
                    with_loss(problem, index, k_stage, soften), layout, solver_obj, u_start, warnings if i == 0 else []
                )
            total_steps += outcome.n_steps
            if i < len(stages) - 1:
                notes.append(f"first stage ({first_stage}): {outcome.n_steps} steps, {outcome.status}")
                if np.all(np.isfinite(outcome.v)):
                    u_start = np.asarray(problem.u0, np.float64) + np.asarray(problem.scale, np.float64) * outcome.v
        if notes:
            outcome = SolveOutcome(
                outcome.v, outcome.converged, outcome.status, f"{outcome.message} [{'; '.join(notes)}]", total_steps
            )
    est = [k for k, b in enumerate(blocks) if isinstance(b, TableData) and b.sigma_rel is None]
    noise: dict[str, Any] = {"estimated": False}
    inv_eff = list(prep.inv_sigma)
    if est:
        problem, outcome, noise = _estimate_noise(problem, layout, solver_obj, outcome, est, loss != "linear", prep)
        total_steps += noise.pop("extra_steps")
        for kk in est:
            inv_eff[kk] = prep.inv_sigma[kk] / noise["sigma_ln"]
    u0 = np.asarray(problem.u0, np.float64)
    scale = np.asarray(problem.scale, np.float64)
    t_solve = time.perf_counter()

    v = outcome.v
    converged, status, message = outcome.converged, outcome.status, outcome.message
    r_blocks_all, r_tilde = evaluate(jnp.asarray(v), problem)
    r = np.asarray(r_blocks_all, np.float64)
    rt = np.asarray(r_tilde, np.float64)
    if not np.all(np.isfinite(r)) and converged:
        converged, status = False, SolveStatus.failed
        message = "not converged: residuals at the solution are not finite"
    q = 0 if prep.nuisance is None else prep.nuisance.size
    r_prior = r[r.size - q :]  # the nuisance parameters' prior rows (each balances its parameter in the dof)
    r = r[: r.size - q]
    n_points = int(r.size)
    dof = n_points - (n_free - q)
    chi2 = float(np.sum(r**2))
    chi2_red = chi2 / dof if dof > 0 else math.nan
    if dof <= 0:
        warnings.append(f"{n_points} points for {n_free} free parameters: no degrees of freedom left")
    # With estimated noise the residuals are already in units of the estimate: the covariance takes them at
    # face value (the profile likelihood's curvature), which is the old "scale by the residual variance" with
    # RSS / N in place of RSS / dof.
    absolute = True if absolute_sigma is None else bool(absolute_sigma)
    neg2_ll = chi2
    if noise["estimated"]:
        n_e = noise["n_points"]
        chi2_e = float(sum(np.sum(r[o : o + c] ** 2) for o, c, kk in _segments(problem.counts) if kk in est))
        neg2_ll = chi2 - chi2_e + n_e * math.log(noise["rss_ln"] / n_e) + n_e
        warnings.append(
            f"the noise was estimated from the residuals (sigma of ln BRDF = {noise['sigma_ln']:.4g}, the data give "
            "none): chi2_reduced is ~1 by construction and says nothing about the goodness of fit; set sigma_rel "
            "for a known uncertainty"
        )
    u = u0 + scale * v
    if n_free:
        J = np.asarray(jacobian(jnp.asarray(v), problem), np.float64)
        cov = covariance(J, scale * layout.jacobian_diag(u), chi2_red, absolute)
        if cov.undetermined:
            warnings.append(
                "the data do not determine "
                + ", ".join(layout.free[i].name for i in cov.undetermined)
                + f" (Jacobian rank {cov.rank} < {n_free}): their sigmas are infinite; fix some of them"
            )
        if cov.saturated:
            warnings.append(
                "the sigmas of " + ", ".join(layout.free[i].name for i in cov.saturated)
                + " are infinite: their transform's derivative is not finite at the solution (the parameter ran to "
                "an extreme of its stored form); fix it, bound it, or give a better start"
            )
    else:
        cov = covariance(np.zeros((n_points, 0)), np.zeros(0), chi2_red, absolute)
    nuisance_report: dict[str, Any] = {}
    if prep.nuisance is not None and n_free:
        n_phys = n_free - prep.nuisance.size
        cond = conditional_sigma(J, scale * layout.jacobian_diag(u), range(n_phys), cov.factor)
        nuisance_report = {
            "parameters": prep.nuisance.describe(),
            "sigma_conditional": {layout.free[i].name: float(cond[i]) for i in range(n_phys)},
            "chi2_prior": float(np.sum(r_prior**2)),
            "note": "sigma (marginal) includes the systematic errors; sigma_conditional holds the nuisance "
            "parameters at the optimum (the data's own uncertainty)",
        }
    t_cov = time.perf_counter()
    x = layout.natural(u)
    for i, e in enumerate(layout.free):
        for bound in (e.lower, e.upper):
            if math.isfinite(bound) and abs(x[i] - bound) <= 1e-6 * abs(e.x0 - bound):
                # in the unit a config gives the key in (degrees for angles: '<name>_deg'), radians beside
                u_name = natural_unit(e.unit)
                shown = f"{bound * to_natural(e.unit):.6g}" + ("" if u_name in ("", "1") else f" {u_name}")
                if e.unit == "rad":
                    shown += f" ({bound:.6g} rad; config key '{e.name}_deg')"
                warnings.append(
                    f"parameter '{e.name}' ended on its bound {shown}; its sigma is not meaningful "
                    "(widen the bound, or fix the parameter)"
                )

    estimates: dict[str, ParameterEstimate] = {}
    free_index = {e.name: i for i, e in enumerate(layout.free)}
    fixed_by_name = {e.name: e for e in layout.fixed}
    for name in layout.order:
        if name in free_index:
            i = free_index[name]
            e = layout.free[i]
            estimates[name] = ParameterEstimate(float(x[i]), float(cov.sigma[i]), e.unit, True, e.x0)
        else:
            f = fixed_by_name[name]
            estimates[name] = ParameterEstimate(f.value, None, f.unit, False, f.value)

    # per-block statistics
    summaries = []
    res_blocks, w_blocks = [], []
    offset = 0
    k = float(np.asarray(problem.loss_scale))
    for name, b, n, inv_sigma, conv in zip(prep.names, blocks, problem.counts, inv_eff, prep.convolved):
        rb = r[offset : offset + n]
        offset += n
        log_res = rb / inv_sigma
        res_blocks.append(rb)
        w_blocks.append(np.asarray(irls_weights(loss, jnp.asarray(rb), k)))
        groups = _group_stats(b, b.usable(), rb, log_res) if isinstance(b, TableData) else ()
        summaries.append(
            BlockSummary(
                name, "frame" if isinstance(b, FrameData) else "table", n, float(np.sum(rb**2)),
                float(np.sqrt(np.mean(log_res**2))), conv, groups,
            )
        )
    n_down = int(np.sum(np.abs(r) > k)) if loss != "linear" else 0
    fitted = problem.block_inputs(jnp.asarray(v))
    t_end = time.perf_counter()
    result = FitResult(
        parameters=estimates,
        free_names=layout.free_names,
        covariance=cov.matrix,
        correlation=cov.correlation,
        chi2=chi2,
        dof=dof,
        n_points=n_points,
        converged=bool(converged),
        status=status,
        message=message,
        n_iterations=int(outcome.n_steps),
        wall_s=t_end - t_start,
        solver=solver_obj.name,
        loss=loss,
        loss_scale=k,
        cost=float(np.sum(rt**2)),
        n_downweighted=n_down,
        covariance_absolute=absolute and not (noise["estimated"] and absolute_sigma is None),
        noise=noise,
        neg2_log_likelihood=neg2_ll,
        precision=precision_name,
        blocks=tuple(summaries),
        warnings=tuple(warnings),
        versions=versions(),
        timings={
            "setup_s": t_setup - t_start,
            "auto_init_s": prep.init_s,
            "solve_s": t_solve - t_setup,
            "covariance_s": t_cov - t_solve,
            "total_s": t_end - t_start,
        },
        models=tuple(m for m, _ in fitted),
        frames=tuple(f for _, f in fitted),
        residuals=tuple(res_blocks),
        weights=tuple(w_blocks),
        auto_init={kk: (np.asarray(vv).tolist()) for kk, vv in auto.items()},
        nuisance=nuisance_report,
    )
    if resolution_check and converged and any(isinstance(b, TableData) for b in blocks):
        kwargs = dict(
            solver=solver, solver_options=solver_options, loss=loss, loss_scale=loss_scale, first_stage=first_stage,
            floor=floor, precision=precision, absolute_sigma=absolute_sigma,
            allow_different_detectors=allow_different_detectors, use_footprint=use_footprint, resolution_check=False,
        )
        result = _mark_unresolved(result, model, blocks, dict(params or {}), kwargs)
    return result


def _mark_unresolved(result: FitResult, model: Model, blocks: list[Data], params: dict[str, Any], kwargs: dict) -> FitResult:
    """The result with an unresolved lobe's width and weight reported as not determined (:mod:`._resolution`)."""
    found = check_resolution(model, blocks, params, result, lambda m, spec: fit(m, blocks, spec, **kwargs))
    notes = found.pop("_notes", [])
    if notes:
        result = dataclasses.replace(result, warnings=tuple(result.warnings) + tuple(notes))
    if not found:
        return result
    estimates = dict(result.parameters)
    undetermined = {}
    for name, rec in found.items():
        p = estimates[name]
        f = to_natural(p.unit)
        lo, hi = rec["range"]
        rec = {**rec, "range": [lo * f, hi * f], "unit": natural_unit(p.unit)}
        rec["range_text"] = (f"< {hi * f:.3g}" if rec.get("open_below") else f"{lo * f:.3g} .. {hi * f:.3g}") + (
            f" {rec['unit']}" if rec["unit"] not in ("1", "") else ""
        )
        undetermined[name] = rec
        estimates[name] = dataclasses.replace(p, sigma=math.nan)
    warns = list(result.warnings) + [
        f"{name} is NOT determined: {rec['reason']}; the data allow {rec['range_text']} "
        "(profile -2 ln L within 1 of the best); its sigma is not given" for name, rec in undetermined.items()
    ]
    return dataclasses.replace(result, parameters=estimates, undetermined=undetermined, warnings=tuple(warns))
