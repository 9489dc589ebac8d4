"""The fit's Jacobian built from its structure instead of ``jax.jacfwd`` through the whole residual.

``jacfwd`` of :func:`brdfjax.fit._problem.residuals` pushes every free
parameter's tangent through every step of every frame: the directions of each
pixel (which no parameter touches), every term of the model (each parameter
touches one), and the footprint's FFT (linear).  Here the same derivative is
assembled from its pieces:

1. **Pointwise, per term.**  At the evaluation points (the usable points, or
   the footprint's support) each term ``t`` of the :class:`~brdfjax.Model` is
   differentiated in forward mode only with respect to the free parameters
   that reach it: its own model parameters and the frame's ``phi_ref``
   (which turns the directions).  A parameter that scales a term (``rho_s``
   of a specular term, ``rho`` of the diffraction term, ... :data:`SCALES`)
   gets its column analytically: the term is evaluated with the scale at 1,
   ``f_t = s f1_t`` and ``df_t/ds = f1_t``.  The directions of the points in
   the scatter frame are computed once per problem (``FrameBlock.dirs``).
   ``phi_ref`` is not differentiated through a term it cannot turn (:func:`_turn_invariant`), and an
   :class:`~brdfjax.OffsetNormal` takes its ``dphi0`` column for it.  The common terms' columns are
   written by hand (:mod:`._analytic`); the rest go through batched forward mode.
2. **The footprint, once for all columns.**  The convolution is linear, so the
   Jacobian of the convolved model is the convolution of the pointwise
   Jacobian: every column goes through one batched FFT on the small FFT box
   (``FrameBlock.convolve``), together with the scaled terms' values, which
   give the convolved model itself (``g = sum_t s_t conv(f1_t) + ...``), compiled apart from the
   pointwise work (:func:`_isolated`).
3. **The rest is elementwise.**  The log residuals, the nuisance offsets, the
   robust loss and the reparametrisation ``x = g(u)`` are small functions of
   the convolved model and the parameters: their derivatives are forward-mode
   products of the columns (``jax.jvp``, batched).

Stacked frames (``FrameStack``) are done under one ``vmap`` (one copy of the
program for every frame).  Problems this does not cover (a free ``theta_i``,
directions not precomputed, a template that is not a ``Model``, stacked
frames whose free parameters differ in kind) fall back to ``jacfwd``:
:func:`supports` says which.  ``tests/fit/test_fit_jacobian.py`` checks the result
against ``jax.jacfwd`` to 1e-10 (float64) with and without a footprint.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..core.geometry import Rz
from ..core.terms import ABg, Diffraction, Lambertian, Model, OffsetNormal, Oriented, Phong, Specular
from ._analytic import PHI, term_columns
from ._residuals import block_log_residuals

__all__ = ["SCALES", "supports", "residuals_and_jacobian"]

#: Term classes that are linear in one of their parameters: ``f(s) = s f(1)``.
SCALES: dict[type, str] = {Specular: "rho_s", Diffraction: "rho", Lambertian: "rho_d", ABg: "A", Phong: "rho"}
#: Wrappers whose value is linear in the wrapped term's value (a scale of the wrapped term scales them).
_WRAPPERS: dict[type, str] = {OffsetNormal: "term", Oriented: "term"}


def _scale_path(term: Any) -> tuple[str, ...] | None:
    """Attribute path (inside the term) of the parameter that scales the term, if any."""
    cls = type(term)
    if cls in SCALES:
        return (SCALES[cls],)
    if cls in _WRAPPERS:
        inner = _scale_path(getattr(term, _WRAPPERS[cls]))
        return None if inner is None else (_WRAPPERS[cls],) + inner
    return None


def _local(problem, k: int) -> list[tuple[int, str, str]]:
    """The free parameters of block ``k`` (global index, base name, kind), nuisance ones left out."""
    return [(i, base, kind) for i, (base, kind, blocks) in enumerate(problem.targets) if k in blocks and kind != "nuisance"]


def _block_ok(block: Any, local: list[tuple[int, str, str]]) -> bool:
    # exactly a Model (a sum of named terms): a subclass such as the diagnosis's InstrumentResponse applies a
    # response to the sum, which per-term columns do not see
    if type(block.template) is not Model or getattr(block, "dirs", None) is None:
        return False
    return all(kind == "model" or base == "phi_ref" for _, base, kind in local)


def supports(problem) -> bool:
    """Whether :func:`residuals_and_jacobian` covers ``problem`` (else ``jax.jacfwd`` is the way)."""
    if any(base.startswith("nuisance:") for base, _, _ in problem.targets):
        # an instrument nuisance parameter (footprint width, misalignment) moves the frame's geometry or its
        # footprint kernel, which the per-term columns take as constants
        return False
    locals_ = [_local(problem, k) for k in range(problem.n_blocks)]
    if problem.stack is not None:
        kinds = {tuple((b, kd) for _, b, kd in loc) for loc in locals_}
        return len(kinds) == 1 and _block_ok(problem.stack.blocks, locals_[0])
    return all(_block_ok(b, loc) for b, loc in zip(problem.blocks, locals_))


class _Plan(eqx.Module):
    """How one block's free parameters reach its model's terms (static)."""

    names: tuple[tuple[str, str], ...] = eqx.field(static=True)  # (base, kind) of each local parameter
    # per term: (term name, indices of the local parameters it is differentiated by, local index of its scale or
    # -1, (j, i) pairs: the term's column for local parameter j is its column for i, not differentiated again)
    terms: tuple[tuple[str, tuple[int, ...], int, tuple[tuple[int, int], ...]], ...] = eqx.field(static=True)


def _turn_invariant(term: Any) -> bool:
    """Whether the term is unchanged when both directions turn about the normal (``phi_ref`` does not reach it).

    A :class:`Specular` term on an isotropic distribution (one with an anisotropic partner: a function of
    ``tan^2 theta_h``) depends on the zenith angles, ``tan^2 theta_h``, ``cos^2 dphi`` and ``w_i . w_h``
    only, whatever its options: Smith's Lambda of an isotropic distribution is a function of the zenith
    angle, the V-cavity factor and the microfacet Fresnel factor of dot products; a :class:`Lambertian`
    on nothing.
    """
    if type(term) is Lambertian:
        return True
    return type(term) is Specular and type(term.distribution).anisotropic is not None


def _plan(template: Model, names: tuple[tuple[str, str], ...]) -> _Plan:
    paths = template._paths()
    per: dict[str, tuple[list[int], int]] = {t: ([], -1) for t in template.terms}
    flat_of = {j: template._resolve(base) for j, (base, kind) in enumerate(names) if kind == "model"}
    alias: dict[str, list[tuple[int, int]]] = {t: [] for t in template.terms}
    for j, (_, kind) in enumerate(names):
        if kind == "frame":  # phi_ref turns the directions every term sees
            for t in per:
                term = template.terms[t]
                if _turn_invariant(term):
                    continue  # its column is 0
                # an OffsetNormal turns the directions by Rz(-dphi0) after Rz(-phi_ref): both columns are one
                dphi0 = next((i for i, f in flat_of.items() if f == f"{t}.dphi0"), None) if type(term) is OffsetNormal else None
                if dphi0 is not None and paths[f"{t}.dphi0"][0] == ("terms", t, "dphi0"):
                    alias[t].append((j, dphi0))
                else:
                    per[t][0].append(j)
            continue
        flat = flat_of[j]
        t = flat.split(".", 1)[0]
        scale = _scale_path(template.terms[t])
        if scale is not None and paths[flat][0] == ("terms", t) + scale:
            per[t] = (per[t][0], j)
        else:
            per[t][0].append(j)
    return _Plan(names, tuple((t, tuple(js), s, tuple(alias[t])) for t, (js, s) in per.items()))


def _isolated(fn, x: Array, gate: Array) -> Array:
    """``fn(x)``, compiled as a computation of its own: both branches of a ``lax.cond`` on ``gate``.

    XLA on CPU drops ``optimization_barrier`` and merges the pointwise columns with the footprint's
    gathers into one program that runs 3x slower than the two parts one after the other (measured on
    the synthetic solar-cell problem: 86 ms per frame against 31 ms isolated).  ``gate`` is any traced
    scalar boolean not batched under ``vmap`` (then the cond stays a cond); its value does not matter.
    """
    return jax.lax.cond(gate, fn, fn, x)  # fn: a plain function (a bound method of a Module is hashed)


def _columns(block: Any, plan: _Plan, xs: Array, gate: Array) -> tuple[Array, Array]:
    """Convolved model ``g`` (n,) and its derivatives (n, p) w.r.t. the block's local parameters ``xs`` (p,)."""
    model_flat = {base: xs[j] for j, (base, kind) in enumerate(plan.names) if kind == "model"}
    frame = block.frame
    wl = None if frame is None else frame.wavelength
    p = xs.shape[0]
    phi_j = next((j for j, (base, kind) in enumerate(plan.names) if kind == "frame"), None)
    base_dirs = block.dirs
    if frame is None:  # a table: the model's own wavelengths
        wl = block.wavelength
    rows: list[Array] = []  # what goes through the footprint: fixed terms' sum, scaled terms' f1, then columns
    fixed_sum = None
    scaled: list[tuple[int, int]] = []  # (row of f1_t, local index of the scale)
    cols: list[Array | None] = [None] * p
    template = block.template
    paths = template._paths()
    for tname, js, s, alias in plan.terms:

        def value(theta, tname=tname, js=js, s=s):
            vals = dict(model_flat)
            for j, th in zip(js, theta):
                if plan.names[j][1] == "model":
                    vals[plan.names[j][0]] = th
            if s >= 0:
                vals[plan.names[s][0]] = jnp.ones_like(xs[s])
            vals = {k_: vals[k_] for k_ in vals if template._resolve(k_).split(".", 1)[0] == tname}
            term = template.with_params(vals).terms[tname] if vals else template.terms[tname]
            if frame is None:
                dirs = base_dirs
            else:
                # a free phi_ref at its current value, also where it is not differentiated (_plan)
                phi = frame.phi_ref if phi_j is None else xs[phi_j]
                if phi_j is not None and phi_j in js:
                    phi = theta[js.index(phi_j)]
                dirs = base_dirs.rotated(Rz(-phi))
            return term(dirs, wl)

        theta = jnp.stack([xs[j] for j in js]) if js else jnp.zeros(0, xs.dtype)
        hand = None
        if frame is not None:  # columns written by hand for the common terms (._analytic)
            vals = dict(model_flat)
            if s >= 0:
                vals[plan.names[s][0]] = jnp.ones_like(xs[s])
            vals = {k_: vals[k_] for k_ in vals if template._resolve(k_).split(".", 1)[0] == tname}
            term = template.with_params(vals).terms[tname] if vals else template.terms[tname]
            phi = frame.phi_ref if phi_j is None else xs[phi_j]
            wanted = [PHI if plan.names[j][1] == "frame" else paths[template._resolve(plan.names[j][0])][0][2:] for j in js]
            hand = term_columns(term, base_dirs.rotated(Rz(-phi)), wl, wanted)
        if hand is not None:
            f1 = hand[0]
            df1 = jnp.stack(hand[1], axis=1) if js else None
        elif js:
            basis = jnp.eye(len(js), dtype=xs.dtype)
            f1, df1 = jax.vmap(lambda t, value=value, theta=theta: jax.jvp(value, (theta,), (t,)), out_axes=(None, 1))(basis)
        else:
            f1, df1 = value(theta), None
        scale = xs[s] if s >= 0 else None
        if s >= 0:
            scaled.append((len(rows), s))
            rows.append(f1)
        else:
            fixed_sum = f1 if fixed_sum is None else fixed_sum + f1
        own = {}
        for q, j in enumerate(js):
            own[j] = df1[:, q] if scale is None else scale * df1[:, q]
        for j, i in alias:
            own[j] = own[i]
        for j, c in own.items():
            cols[j] = c if cols[j] is None else cols[j] + c
    n_fixed = 0
    if fixed_sum is not None:
        rows.insert(0, fixed_sum)
        n_fixed = 1
        scaled = [(r + 1, s) for r, s in scaled]
    first_col = len(rows)
    live = [j for j, c in enumerate(cols) if c is not None]  # a scale's own column is its term's f1 (a row)
    rows.extend(cols[j] for j in live)
    stacked = jnp.stack(rows, axis=1)
    conv = _isolated(lambda a: block.convolve(a), stacked, gate)  # (n, rows): the points first (the fast layout)
    g = conv[:, 0] if n_fixed else jnp.zeros(conv.shape[0], conv.dtype)
    for r, s in scaled:
        g = g + xs[s] * conv[:, r]
    out = [None] * p
    for q, j in enumerate(live):
        out[j] = conv[:, first_col + q]
    for r, s in scaled:
        out[s] = conv[:, r] if out[s] is None else out[s] + conv[:, r]
    zero = jnp.zeros(conv.shape[0], conv.dtype)
    dg = jnp.stack([zero if c is None else c for c in out], axis=1)
    return g, dg


def _block_residuals(block: Any, plan: _Plan, xs: Array, soften: Array, gate: Array) -> tuple[Array, Array]:
    """Log residuals (n,) of a block and their derivatives (p, n)."""
    g, dg = _columns(block, plan, xs, gate)
    r, dr = jax.vmap(
        lambda t: jax.jvp(lambda f: block_log_residuals(f, block, soften), (g,), (t,)), in_axes=1, out_axes=(None, 0)
    )(dg)
    return r, dr


def residuals_and_jacobian(v: Array, problem) -> tuple[Array, Array]:
    """``problem.residuals(v)`` and its Jacobian ``d r / d v`` (n_rows, n_free), from the structure.

    Only for problems :func:`supports` accepts.
    """
    n_free = problem.u0.shape[0]
    dtype = problem.u0.dtype
    x = problem.natural(v)
    gate = jnp.isfinite(problem.soften)  # traced, never batched: see _isolated
    locals_ = [_local(problem, k) for k in range(problem.n_blocks)]
    if problem.stack is not None:
        stack = problem.stack
        names = tuple((b, kd) for _, b, kd in locals_[0])
        plan = _plan(stack.blocks.template, names)
        idx = np.array([[i for i, _, _ in loc] for loc in locals_], dtype=np.int32).reshape(problem.n_blocks, len(names))
        xs = x[idx]
        r, dr = jax.vmap(lambda b, xk: _block_residuals(b, plan, xk, problem.soften, gate))(stack.blocks, xs)
        # (frames, p, n_pad) -> (frames, n_pad, n_free) on the global columns
        sel = np.zeros((problem.n_blocks, len(names), n_free))
        for k in range(problem.n_blocks):
            sel[k, np.arange(len(names)), idx[k]] = 1.0
        J = jnp.einsum("fpn,fpq->fnq", dr, jnp.asarray(sel, dr.dtype))
        r_all = r.ravel()[stack.valid]
        J_all = J.reshape((-1, n_free))[stack.valid]
    else:
        rs, Js = [], []
        for k, block in enumerate(problem.blocks):
            loc = locals_[k]
            plan = _plan(block.template, tuple((b, kd) for _, b, kd in loc))
            ids = np.array([i for i, _, _ in loc], dtype=np.int32)
            r, dr = _block_residuals(block, plan, x[ids] if ids.size else jnp.zeros(0, dtype), problem.soften, gate)
            rs.append(r)
            Jk = jnp.zeros((r.shape[0], n_free), dr.dtype)
            Js.append(Jk.at[:, ids].set(dr.T) if ids.size else Jk)
        r_all, J_all = jnp.concatenate(rs), jnp.concatenate(Js)
    # nuisance offsets and the robust loss: elementwise in the block residuals, simple in x
    basis = jnp.eye(n_free, dtype=x.dtype)
    out, d_out = jax.vmap(
        lambda jr, e: jax.jvp(problem.finish, (r_all, x), (jr.astype(r_all.dtype), e)), in_axes=(1, 0), out_axes=(None, 0)
    )(J_all, basis)
    dx_dv = jax.vmap(lambda e: jax.jvp(problem.natural, (v,), (e,))[1], out_axes=1)(jnp.eye(n_free, dtype=v.dtype))
    return out, d_out.T @ dx_dv.astype(d_out.dtype)
