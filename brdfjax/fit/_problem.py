"""The fit problem as one pure-JAX pytree: data blocks, per-block models and the parameter map.

:class:`Problem` holds everything the residual function needs as arrays
(data, uncertainties, pixel indices or directions, the per-block template
models and frames, the start point and scales of the parameters) and the
structure as static fields.  The residual function is the module-level
:func:`residuals` ``(v, problem) -> r``: solvers receive the problem through
``args``, so a new data set of the same shapes reuses the compiled program.

Solver coordinates: ``v`` with ``u = u0 + scale * v`` and ``x = g(u)``
(:mod:`brdfjax.fit._params`); ``scale`` makes every column of the Jacobian
at the start about unit norm (capped so that a unit step in ``v`` changes a
log-parametrised quantity by at most a factor e), the scaling Marquardt's
method applies and a trust region in ``v`` needs.

Two things keep compile times down (XLA on CPU compiles the derivative of
the solar-cell model slowly, ~7 s per copy):

- Detector frames of the same structure are **stacked**: their usable pixels
  are padded to one length (a multiple of :data:`PAD_MULTIPLE`, zero weight
  on the padding) and the model is evaluated under ``vmap`` over frames, so
  one copy of the model serves every frame and data sets whose point counts
  round to the same length reuse the compiled program.  Frames with a
  footprint stack too (same grid and kernel shapes); the model is evaluated
  only on the grid points within the kernel's reach of a usable point.
- :func:`residuals` carries a **custom JVP** that materialises the Jacobian
  once (forward mode) and applies it as a matrix: optimistix uses the
  derivative several times per step (the QR of the damped system, the
  gradient, the predicted reduction), and with the rule they share one
  Jacobian.  The JVP is exact; only second derivatives through it are not
  available (no solver here needs them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..core.detector import Detector
from ..core.geometry import Directions, Rz
from ..core.render import Conditions, evaluate_pixels
from ..core.terms import AbstractTerm, Model
from ..runtime.export_cache import exportable
from ._jacobian import residuals_and_jacobian as structured_residuals_and_jacobian, supports as structured_supports
from ._nuisance import NuisanceTerms
from ._params import Layout, forward_by_id
from ._residuals import block_log_residuals, convolve_same, robust_residuals_by_id

__all__ = ["FrameBlock", "FrameStack", "TableBlock", "Problem", "residuals", "PAD_MULTIPLE"]

#: Stacked frames are padded to a multiple of this many points.
PAD_MULTIPLE = 256

Values = dict[str, Array]


def _apply(template: AbstractTerm, frame: Conditions | None, model_values: Values, frame_values: Values):
    model = template.with_params(model_values) if model_values else template
    if frame is not None:
        if "theta_i" in frame_values:
            frame = eqx.tree_at(lambda f: f.theta_i, frame, frame_values["theta_i"])
        if "phi_ref" in frame_values:
            frame = eqx.tree_at(lambda f: f.phi_ref, frame, frame_values["phi_ref"])
    return model, frame


#: Detector fields a nuisance parameter may offset (brdfjax.fit._nuisance: misalignment, Eq 105).
_DETECTOR_FIELDS = ("roll", "yaw", "pitch", "m_h", "m_v", "distance")


def _with_instrument(block: "FrameBlock | TableBlock", fv: Values) -> "FrameBlock | TableBlock":
    """The block with the instrument's nuisance offsets of ``fv`` applied: detector fields offset from nominal,
    the footprint's width scaled by ``exp(s)`` (``K -> K^(exp(-2 s))``, renormalised: a Gaussian's width)."""
    if not isinstance(block, FrameBlock):
        return block
    fields = [f for f in _DETECTOR_FIELDS if f in fv]
    if fields:
        det = block.detector
        det = eqx.tree_at(lambda d: tuple(getattr(d, f) for f in fields), det,
                          tuple(getattr(det, f) + fv[f].astype(jnp.result_type(getattr(det, f))) for f in fields))
        block = eqx.tree_at(lambda b: b.detector, block, det)
    if "footprint" in fv and block.kernel is not None:
        block = eqx.tree_at(lambda b: b.kernel, block, scale_footprint(block.kernel, fv["footprint"]))
    return block


def scale_footprint(kernel: Array, s: Array) -> Array:
    """A Gaussian footprint kernel of width ``w`` -> the one of width ``w exp(s)``: ``K^(exp(-2 s))``, renormalised.

    Exact for a sampled Gaussian; for the pixel-integrated one of Eq 73 it
    scales the pixel's share of the variance too (1/12 px^2 against
    ``w^2 / 4``: 0.1 % of a 25 px footprint).
    """
    k = jnp.asarray(kernel)
    power = jnp.exp(-2.0 * s).astype(k.dtype)
    scaled = jnp.where(k > 0, jnp.exp(jnp.log(jnp.where(k > 0, k, 1.0)) * power), 0.0)
    return scaled / jnp.sum(scaled)


class FrameBlock(eqx.Module):
    """One detector frame: the usable pixels (or the whole grid when a footprint is convolved)."""

    template: AbstractTerm
    frame: Conditions
    detector: Detector
    n_h: Array  # (n,) pixel columns of the points, or (cols,) of the grid with a footprint
    n_v: Array  # (n,) pixel rows of the points, or (rows,) of the grid with a footprint
    data: Array  # (n,) BRDF, sr^-1
    inv_sigma: Array  # (n,) 1 / sigma_rel
    floor: Array  # scalar, sr^-1: the log(0) guard
    soft_level: Array  # scalar, sr^-1: the softening level of a first stage
    kernel: Array | None = None  # normalised footprint on the grid spacing
    flat_index: Array | None = None  # (n,) indices of the points in the raveled grid
    # With a footprint, the grid points within the kernel's reach of a usable point (the only ones
    # the convolution at the usable points sees): the model is evaluated there and zero elsewhere.
    # None: the whole grid.
    support_index: Array | None = None  # (m,) indices in the raveled grid
    support_h: Array | None = None  # (m,) their pixel columns
    support_v: Array | None = None  # (m,) their pixel rows
    # Parameter-independent work done once per problem (brdfjax.fit._jacobian):
    # the scatter-frame directions at the evaluation points (the points, or the support with a
    # footprint), when theta_i is not fitted; None: computed from the pixel indices on every call.
    dirs: Directions | None = None
    # With a support, the footprint as a circular convolution on a small FFT box (the usable points'
    # span plus the kernel's, rounded up to a 2-3-5 size) instead of the whole grid zero-padded:
    # flat indices of the support points and of the usable points in the box, and the rfft2 of the
    # kernel centred at the box's origin (real and imaginary parts: every leaf stays real).
    box_support: Array | None = None  # (m,)
    box_points: Array | None = None  # (n,)
    kernel_fft: Array | None = None  # (2, box rows, box cols // 2 + 1)
    box_shape: tuple[int, int] | None = eqx.field(static=True, default=None)
    # A separable kernel (K = outer(kernel_v, kernel_h), the Gaussian beam footprint) with a support:
    # the convolution done directly, in two one-dimensional passes, only where the usable points need
    # it.  sep_rows (q, kr): for each point of the first pass (the usable points dilated along the
    # rows by the kernel's half-width), the support points it sums along its column (-1: none, zero);
    # sep_cols (n, kc): for each usable point, the first-pass points it sums along its row.
    sep_rows: Array | None = None
    sep_cols: Array | None = None
    kernel_v: Array | None = None  # (kr,)
    kernel_h: Array | None = None  # (kc,)

    def point_values(self, model: AbstractTerm, frame: Conditions) -> Array:
        """The model at the evaluation points: the usable points, or the support (or grid) with a footprint."""
        if self.dirs is not None:
            return model(self.dirs.rotated(Rz(-frame.phi_ref)), frame.wavelength)
        if self.kernel is None:
            return evaluate_pixels(model, frame, self.detector, self.n_h, self.n_v)
        if self.support_index is None:
            return evaluate_pixels(model, frame, self.detector, self.n_h[None, :], self.n_v[:, None]).ravel()
        return evaluate_pixels(model, frame, self.detector, self.support_h, self.support_v)

    def convolve(self, values: Array) -> Array:
        """Point values ``(m,)`` or ``(m, k)`` to the footprint-convolved model at the usable points, ``(n,)`` or ``(n, k)``.

        Linear: the Jacobian's columns go through it together (the trailing axis).
        """
        if self.kernel is None:
            return values
        cols = values.reshape((values.shape[0], -1))  # (m, k)
        if self.sep_rows is not None:
            zero = jnp.zeros((1, cols.shape[1]), values.dtype)
            ext = jnp.concatenate([cols, zero])  # index -1: outside the support
            mid = sum(self.kernel_v[j] * ext[self.sep_rows[:, j]] for j in range(self.sep_rows.shape[1]))
            ext = jnp.concatenate([mid, zero])
            out = sum(self.kernel_h[i] * ext[self.sep_cols[:, i]] for i in range(self.sep_cols.shape[1]))
        elif self.box_shape is not None:
            nr, nc = self.box_shape
            kf = jax.lax.complex(self.kernel_fft[0], self.kernel_fft[1])

            def one(col):
                image = jnp.zeros(nr * nc, values.dtype).at[self.box_support].set(col).reshape((nr, nc))
                return jnp.fft.irfft2(jnp.fft.rfft2(image) * kf, s=(nr, nc)).ravel()[self.box_points]

            out = jax.lax.map(one, cols.T).T  # one column at a time: faster than a batched FFT on CPU
        else:
            shape = (self.n_v.shape[0], self.n_h.shape[0])

            def one(col):
                if self.support_index is None:
                    image = col.reshape(shape)
                else:
                    image = jnp.zeros(shape[0] * shape[1], values.dtype).at[self.support_index].set(col).reshape(shape)
                return convolve_same(image, self.kernel).ravel()[self.flat_index]

            out = jax.lax.map(one, cols.T).T
        return out.reshape(out.shape[:1] + values.shape[1:]).astype(values.dtype)

    def model_values(self, model: AbstractTerm, frame: Conditions) -> Array:
        return self.convolve(self.point_values(model, frame))

    def residuals(self, model: AbstractTerm, frame: Conditions, soften: Array) -> Array:
        return _log_residuals(self.model_values(model, frame), self, soften)


_log_residuals = block_log_residuals  # (moved to ._residuals: ._jacobian needs it too)


class TableBlock(eqx.Module):
    """One goniometer table: the usable rows."""

    template: AbstractTerm
    dirs: Directions
    wavelength: Array
    data: Array
    inv_sigma: Array
    floor: Array
    soft_level: Array

    @property
    def frame(self) -> None:
        return None

    def point_values(self, model: AbstractTerm, frame: None) -> Array:
        return model(self.dirs, self.wavelength)

    def convolve(self, values: Array) -> Array:
        return values

    def model_values(self, model: AbstractTerm, frame: None) -> Array:
        return model(self.dirs, self.wavelength)

    def residuals(self, model: AbstractTerm, frame: None, soften: Array) -> Array:
        return _log_residuals(self.model_values(model, frame), self, soften)


class FrameStack(eqx.Module):
    """Detector frames of one structure, stacked along a leading axis (usable points padded)."""

    blocks: FrameBlock  # every array leaf has a leading (n_frames,) axis
    valid: Array  # (n_points,) flat indices of the real points in the (n_frames * n_pad) residuals

    def residuals(self, model_values: Values, frame_values: Values, soften: Array) -> Array:
        def one(block, mv, fv):
            block = _with_instrument(block, fv)
            model, frame = _apply(block.template, block.frame, mv, fv)
            return block.residuals(model, frame, soften)

        r = jax.vmap(one)(self.blocks, model_values, frame_values)
        return r.ravel()[self.valid]


def _pad_to(n: int) -> int:
    return -(-n // PAD_MULTIPLE) * PAD_MULTIPLE


def stack_frames(blocks: list[FrameBlock]) -> FrameStack:
    """Stack frame blocks, their usable points padded to a common multiple of :data:`PAD_MULTIPLE`.

    Padding points carry zero weight.  Blocks with a footprint (same grid shape and kernel shape) also
    pad their support (the grid points the model is evaluated at) by repeating its first point, which
    writes the same value twice.
    """
    n = [int(b.data.shape[0]) for b in blocks]
    n_pad = _pad_to(max(n))
    with_support = blocks[0].support_index is not None
    m_pad = _pad_to(max(int(b.support_index.shape[0]) for b in blocks)) if with_support else 0
    separable = blocks[0].sep_rows is not None
    q_pad = _pad_to(max(int(b.sep_rows.shape[0]) for b in blocks)) if separable else 0

    def ext(a, k, fill):
        a = np.asarray(a)
        return np.concatenate([a, np.full(k - a.shape[0], fill, a.dtype)])

    def rep(a, k):  # pad along the first axis by repeating the first entry
        a = np.asarray(a)
        return np.concatenate([a, np.repeat(a[:1], k - a.shape[0], axis=0)])

    def pad_dirs(d: Directions | None, k: int) -> Directions | None:
        if d is None:
            return None
        # a frame's one incident direction stays one (scalar components): the terms' per-frame factors
        # (the Q factor's A(theta_i), ...) are then computed once, not at every point
        w_i = d.i if all(np.ndim(c) == 0 for c in d.i) else rep(d.w_i, k)
        return Directions(w_i, rep(d.w_s, k), rep(d.w_sum, k))

    def pad(b: FrameBlock, k: int) -> FrameBlock:
        if b.kernel is None:
            return eqx.tree_at(
                lambda x: (x.n_h, x.n_v, x.data, x.inv_sigma, x.dirs),
                b,
                (ext(b.n_h, n_pad, np.asarray(b.n_h)[0]), ext(b.n_v, n_pad, np.asarray(b.n_v)[0]),
                 ext(b.data, n_pad, 1.0), ext(b.inv_sigma, n_pad, 0.0), pad_dirs(b.dirs, n_pad)),
                is_leaf=lambda x: x is None,
            )
        b = eqx.tree_at(
            lambda x: (x.flat_index, x.data, x.inv_sigma, x.box_points, x.sep_cols, x.sep_rows),
            b,
            (ext(b.flat_index, n_pad, np.asarray(b.flat_index)[0]), ext(b.data, n_pad, 1.0), ext(b.inv_sigma, n_pad, 0.0),
             None if b.box_points is None else rep(b.box_points, n_pad),
             None if b.sep_cols is None else rep(b.sep_cols, n_pad),
             None if b.sep_rows is None else rep(b.sep_rows, q_pad)),
            is_leaf=lambda x: x is None,
        )
        if with_support:
            b = eqx.tree_at(
                lambda x: (x.support_index, x.support_h, x.support_v, x.box_support, x.dirs),
                b,
                tuple(rep(a, m_pad) for a in (b.support_index, b.support_h, b.support_v))
                + (None if b.box_support is None else rep(b.box_support, m_pad), pad_dirs(b.dirs, m_pad)),
                is_leaf=lambda x: x is None,
            )
        return b

    padded = [pad(b, k) for b, k in zip(blocks, n)]
    stacked = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *padded)
    valid = np.concatenate([i * n_pad + np.arange(k) for i, k in enumerate(n)])
    return FrameStack(stacked, valid)


def can_stack(blocks: list[Any]) -> bool:
    """Frames of one structure: all without a footprint, or all with one on grids and kernels of one shape."""
    if len(blocks) < 2 or not all(isinstance(b, FrameBlock) for b in blocks):
        return False
    s0 = jax.tree_util.tree_structure(blocks[0])
    if not all(jax.tree_util.tree_structure(b) == s0 for b in blocks[1:]):
        return False
    if blocks[0].kernel is None:
        return True

    def shapes(b):
        return (np.shape(b.n_h), np.shape(b.n_v), np.shape(b.kernel))

    return all(shapes(b) == shapes(blocks[0]) for b in blocks[1:])


class Problem(eqx.Module):
    """Data blocks and the map from solver coordinates ``v`` to each block's model and frame."""

    blocks: tuple[FrameBlock | TableBlock, ...]  # evaluated one by one (empty when stacked)
    stack: FrameStack | None  # all blocks, stacked (None when evaluated one by one)
    u0: Array
    scale: Array
    lower: Array
    upper: Array
    loss_index: Array  # index into LOSSES (traced: changing the loss does not recompile)
    loss_scale: Array
    soften: Array  # 0: plain log residuals; 1: softened at each block's soft_level (traced)
    transform_ids: Array  # (n_free,) indices into TRANSFORMS (traced: bounds and kinds do not recompile)
    targets: tuple[tuple[str, str, tuple[int, ...]], ...] = eqx.field(static=True)  # (base, kind, blocks)
    counts: tuple[int, ...] = eqx.field(static=True)  # usable points per block
    # Systematic errors as nuisance parameters (the last free entries): offsets of every point's log
    # model and their prior rows after the data's residuals (brdfjax.fit._nuisance).  None: none.
    nuisance: NuisanceTerms | None = None
    # Whether the residual function reports each evaluation to report_evaluations' listeners (static:
    # the solvers set it from whether anyone listens, so that a quiet solve carries no host callback).
    report: bool = eqx.field(static=True, default=True)

    @property
    def n_blocks(self) -> int:
        return len(self.counts)

    def unconstrained(self, v: Array) -> Array:
        # The solver may work in float64 while the model is evaluated in float32 (``precision``).
        return self.u0 + self.scale * jnp.asarray(v, self.u0.dtype)

    def natural(self, v: Array) -> Array:
        """Stored-unit values of the free parameters."""
        return forward_by_id(self.transform_ids, self.unconstrained(v), self.lower, self.upper)

    def _block_values(self, x: Array, k: int) -> tuple[Values, Values]:
        mv: Values = {}
        fv: Values = {}
        for i, (base, kind, blocks) in enumerate(self.targets):
            if k not in blocks:
                continue
            if kind == "nuisance":
                # an instrument nuisance parameter (footprint, misalignment) goes with the frame's values
                # under its quantity ("nuisance:<field>"); the log-scale ones act in NuisanceTerms
                if base.startswith("nuisance:"):
                    g = base.split(":", 1)[1]
                    fv[g] = fv[g] + x[i] if g in fv else x[i]
                continue
            (mv if kind == "model" else fv)[base] = x[i]
        return mv, fv

    def _stacked_values(self, x: Array) -> tuple[Values, Values]:
        per = [self._block_values(x, k) for k in range(self.n_blocks)]
        mv = {name: jnp.stack([p[0][name] for p in per]) for name in per[0][0]}
        # an instrument offset that acts on some frames only is 0 on the others
        names = list(dict.fromkeys(n for p in per for n in p[1]))
        fv = {name: jnp.stack([jnp.asarray(p[1].get(name, 0.0), x.dtype) for p in per]) for name in names}
        return mv, fv

    def block_inputs(self, v: Array) -> list[tuple[AbstractTerm, Conditions | None]]:
        """Each block's model and frame with the free parameters at ``v``."""
        x = self.natural(v)
        out = []
        for k in range(self.n_blocks):
            mv, fv = self._block_values(x, k)
            if self.stack is not None:
                block = jax.tree_util.tree_map(lambda a, k=k: a[k], self.stack.blocks)
            else:
                block = self.blocks[k]
            out.append(_apply(block.template, block.frame, mv, fv))
        return out

    def block_list(self) -> list[FrameBlock | TableBlock]:
        """The blocks one by one (unstacked views when stacked; padding included)."""
        if self.stack is None:
            return list(self.blocks)
        return [jax.tree_util.tree_map(lambda a, k=k: a[k], self.stack.blocks) for k in range(self.n_blocks)]

    def block_residuals(self, x: Array) -> Array:
        """The blocks' log residuals at the natural parameter values ``x``, blocks in order (no nuisance rows)."""
        if self.stack is not None:
            return self.stack.residuals(*self._stacked_values(x), self.soften)
        out = []
        for k, block in enumerate(self.blocks):
            mv, fv = self._block_values(x, k)
            block = _with_instrument(block, fv)
            model, frame = _apply(block.template, block.frame, mv, fv)
            out.append(block.residuals(model, frame, self.soften))
        return jnp.concatenate(out)

    def weighted_residuals(self, v: Array) -> Array:
        """``(log(f + floor) - log d) / sigma_rel`` at every usable point (softened in a first stage), blocks in order."""
        x = self.natural(v)
        return self.with_nuisance(self.block_residuals(x), x)

    def with_nuisance(self, r: Array, x: Array) -> Array:
        return r if self.nuisance is None else self.nuisance.apply(r, x)

    def robust(self, r: Array) -> Array:
        if self.nuisance is None:
            return robust_residuals_by_id(self.loss_index, r, self.loss_scale)
        n = r.shape[0] - self.nuisance.size  # the prior rows stay quadratic
        return jnp.concatenate([robust_residuals_by_id(self.loss_index, r[:n], self.loss_scale), r[n:]])

    def finish(self, r_blocks: Array, x: Array) -> Array:
        """The solver's residuals from the blocks' log residuals: nuisance offsets and rows, then the robust loss."""
        return self.robust(self.with_nuisance(r_blocks, x))

    def residuals(self, v: Array) -> Array:
        return self.robust(self.weighted_residuals(v))


def _plain_residuals(v: Array, problem: Problem) -> Array:
    return problem.residuals(v)


_BIG = 1e8  # stands in for a non-finite residual at a solver's trial point

#: Who hears of each residual evaluation of a solve (:func:`report_evaluations`).  A module-level
#: list, not an argument: the callback below must be the same function in every compiled solve, so
#: that listening does not recompile (one program serves fits with and without progress).
_LISTENERS: list[Callable[[float], None]] = []


def _emit(chi2: Any) -> None:
    if _LISTENERS:
        value = float(np.min(np.asarray(chi2)))  # vmapped solves report their best member
        for listener in list(_LISTENERS):
            listener(value)


def listening() -> bool:
    """Whether anyone listens to residual evaluations now (:func:`report_evaluations`)."""
    return bool(_LISTENERS)


def _announce(r: Array, problem: "Problem") -> None:
    # A program with a host callback never comes from JAX's persistent compilation cache in another
    # process (the cache key holds the callback's address): a solve nobody listens to goes without.
    if problem.report:
        jax.debug.callback(_emit, jnp.sum(jnp.square(r)))


@contextmanager
def report_evaluations(listener: Callable[[float], None] | None) -> Iterator[None]:
    """While inside, ``listener(sum of squared residuals)`` hears of every residual evaluation of a solver.

    Levenberg-Marquardt evaluates (and linearises) the residuals once per
    step, so this is the chi^2 (the robust cost, for a robust loss) step by
    step; the fit's progress line is built on it.
    """
    if listener is None:
        yield
        return
    _LISTENERS.append(listener)
    try:
        yield
    finally:
        _LISTENERS.remove(listener)


@jax.custom_jvp
def residuals(v: Array, problem: Problem) -> Array:
    """The residual function handed to solvers (one object, so compiled programs are reused)."""
    r = problem.robust(_shared(_weighted_residuals_program, v, problem)).astype(jnp.result_type(v))
    r = jnp.where(jnp.isfinite(r), r, _BIG)
    _announce(r, problem)
    return r


@residuals.defjvp
def _residuals_jvp(primals, tangents):
    v, problem = primals
    t_v, _ = tangents  # the data are not differentiated
    r, J = _shared(_residuals_and_jacobian_program, v, problem)
    r, J = r.astype(jnp.result_type(v)), J.astype(jnp.result_type(v))
    # Far from the data (a trial step of the solver) a derivative can be 0 * inf; the solver must
    # see finite numbers to reject the step rather than fail.
    r = jnp.where(jnp.isfinite(r), r, _BIG)
    J = jnp.where(jnp.isfinite(J), J, 0.0)
    _announce(r, problem)
    return r, J @ t_v


def half_sum_squares(v: Array, problem: Problem) -> Array:
    """``sum rho(r)``: the objective of minimisers (L-BFGS-B)."""
    return 0.5 * jnp.sum(jnp.square(residuals(v, problem)))


def _residuals_and_jacobian(v: Array, problem: Problem) -> tuple[Array, Array]:
    """Residuals and Jacobian: from the problem's structure where it allows (:mod:`._jacobian`), else jacfwd."""
    if STRUCTURED_JACOBIAN and structured_supports(problem):
        return structured_residuals_and_jacobian(v, problem)
    return problem.residuals(v), jax.jacfwd(_plain_residuals)(v, problem)


#: Use the structured Jacobian (:mod:`brdfjax.fit._jacobian`) where a problem allows it; False: always jacfwd.
STRUCTURED_JACOBIAN = True


@eqx.filter_jit
def _residuals_and_jacobian_program(v: Array, problem: Problem) -> tuple[Array, Array]:
    """One traced program of the residuals and Jacobian, shared by the solver's linearisations and the
    covariance where the solver did not return its Jacobian (each caller goes through :func:`_shared`, so they
    hit one trace); the step scales come from differences of the residuals (``_fit._difference_columns``)."""
    return _residuals_and_jacobian(v, problem)


@eqx.filter_jit
def _weighted_residuals_program(v: Array, problem: Problem) -> Array:
    """``problem.weighted_residuals(v)`` as one traced program, shared by the solvers and :func:`evaluate`."""
    return problem.weighted_residuals(v)


def _solver_context():
    """One tracing context for every call of the shared programs above (an empty abstract mesh).

    JAX keys its trace cache on the context, and the callers run in different ones: inside
    ``optx.least_squares`` the residuals' linearisation runs under an empty abstract mesh, its closure
    conversion and a top-level call (the step scales, the covariance, the stepped solver's ``init``) under
    none (``jax_explain_cache_misses``: "abstract_mesh_context_manager differs: now AbstractMesh((),
    axis_types=()) and before None").  Without one context a cold fit traced the structured Jacobian twice
    or three times, about 1.5 s a trace on the synthetic solar-cell fit.  Where a JAX version lacks the API
    (it is new in the 0.10 series), nothing is entered: a trace more, the same numbers."""
    try:
        return jax.sharding.use_abstract_mesh(jax.sharding.AbstractMesh((), ()))
    except (AttributeError, TypeError):
        return nullcontext()


def _shared(program, v: Array, problem: Problem):
    """``program(v, problem)`` as every caller must call a shared program to hit its one trace: in
    :func:`_solver_context`, and with ``report`` (static, so part of the trace's key) off; the callers
    announce the evaluation themselves."""
    with _solver_context():
        return program(v, dataclasses.replace(problem, report=False))


@eqx.filter_jit
def jacobian(v: Array, problem: Problem) -> Array:
    """d r~ / d v, (n_points, n_free): from the problem's structure where it allows, else ``jax.jacfwd``."""
    return _shared(_residuals_and_jacobian_program, v, problem)[1]


@eqx.filter_jit
def jacobian_jacfwd(v: Array, problem: Problem) -> Array:
    """d r~ / d v by ``jax.jacfwd`` through the whole residual function (the reference)."""
    return jax.jacfwd(_plain_residuals)(v, problem)


@eqx.filter_jit
def evaluate(v: Array, problem: Problem) -> tuple[Array, Array]:
    """Raw and robust residuals at ``v``."""
    r = _shared(_weighted_residuals_program, v, problem)
    return r, robust_residuals_by_id(problem.loss_index, r, problem.loss_scale)


def switches() -> tuple:
    """The module switches that a fit's programs read while they are traced (part of an exported program's key)."""
    return (("STRUCTURED_JACOBIAN", bool(STRUCTURED_JACOBIAN)),)


#: :func:`jacobian` and :func:`evaluate` through their exported programs when :mod:`brdfjax.runtime.export_cache` is on
jacobian_call = exportable("jacobian", jacobian, switches)
evaluate_call = exportable("evaluate", evaluate, switches)


def with_loss(problem: Problem, index: int, scale: float, soften: float = 0.0) -> Problem:
    """The same problem with another loss and softening (no recompilation: all are arrays)."""
    dtype = problem.loss_scale.dtype
    return eqx.tree_at(
        lambda p: (p.loss_index, p.loss_scale, p.soften),
        problem,
        (jnp.asarray(index, jnp.int32), jnp.asarray(scale, dtype), jnp.asarray(soften, dtype)),
    )


def with_scale(problem: Problem, u0: np.ndarray, scale: np.ndarray) -> Problem:
    dtype = problem.u0.dtype
    return eqx.tree_at(lambda p: (p.u0, p.scale), problem, (jnp.asarray(u0, dtype), jnp.asarray(scale, dtype)))


def build_targets(layout: Layout) -> tuple[tuple[str, str, tuple[int, ...]], ...]:
    return tuple((e.base, e.kind, e.blocks) for e in layout.free)


def template_for_block(model: Model, layout: Layout, k: int) -> Model:
    """The model of block ``k`` with the fixed values of the layout applied (the free ones set at start)."""
    values: dict[str, Any] = {}
    for e in layout.fixed:
        if e.kind == "model" and k in e.blocks:
            values[e.base] = np.float64(e.value)
    for e in layout.free:
        if e.kind == "model" and k in e.blocks:
            values[e.base] = np.float64(e.x0)
    return model.with_params(values) if values else model


def frame_for_block(frame: Conditions, layout: Layout, k: int) -> Conditions:
    entries = [(e.base, e.kind, e.blocks, e.value) for e in layout.fixed]
    entries += [(e.base, e.kind, e.blocks, e.x0) for e in layout.free]
    for base, kind, blocks, x in entries:
        if kind == "frame" and k in blocks:
            value = np.float64(x)
            if base == "theta_i":
                frame = eqx.tree_at(lambda f: f.theta_i, frame, value)
            else:
                frame = eqx.tree_at(lambda f: f.phi_ref, frame, value)
    return frame
