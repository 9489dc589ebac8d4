"""Hand-written pointwise columns of the terms the structured Jacobian meets most (:mod:`._jacobian`).

Forward mode through a whole term with several tangents makes XLA on CPU carry every tangent through
every intermediate (half vector, Q factor, rotations).  For the terms below, the columns come instead
from the per-point quantities the value needs, with a single small forward pass where a derivative
has no cheap closed form:

- :class:`~brdfjax.Specular` without shadowing, ``f1 = D(tan^2 theta_h) QG(n, k)``, and an
  :class:`~brdfjax.OffsetNormal` around one: one forward pass per parameter, each with a single
  tangent, so that JAX knows the zero tangents (a width's inside the Q factor, the index's inside
  ``D``) and skips those parts, which a batch of tangents cannot;
- :class:`~brdfjax.Diffraction`: ``f1 = cos^2(A h_y) sinc^2(B h_y) exp(-(C h_x)^2)`` differentiated by
  hand in ``a``, ``b``, ``c`` and ``phi_ref`` (which turns the half vector: ``dh_x = h_y``,
  ``dh_y = -h_x``); only ``sinc'`` comes from a forward pass.

:func:`term_columns` returns None for anything else (the caller's generic forward mode then does it).
``tests/fit/test_fit_speed.py`` checks every column against ``jax.jacfwd`` to 1e-10 (float64).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.geometry import Directions, fast_cos, fast_sinc
from ..core.terms import Diffraction, OffsetNormal, Specular

__all__ = ["term_columns"]

PHI = ("phi_ref",)  # the path that stands for the frame's phi_ref


def _both_above(dirs: Directions):
    return (dirs.cos_theta_i > 0) & (dirs.cos_theta_s > 0)


def _one_by_one(fn, values: list, dtype) -> tuple[Any, list]:
    """``fn(values)`` and its derivative by each value, one forward pass per value (not batched).

    Each pass carries one tangent: where it is zero (the index's tangent inside the distribution, the
    width's inside the Q factor) JAX knows it and skips that part, which a batch of tangents cannot.
    """
    out, cols = None, []
    # one jitted function for all the passes: its Python is traced once and its forward-mode program
    # derived once (JAX caches both), instead of a Python trace of the term per pass
    program = jax.jit(lambda *a: fn(list(a)))
    for i in range(len(values)):
        tangents = [jnp.asarray(float(q == i), dtype) for q in range(len(values))]
        out, d = jax.jvp(program, tuple(values), tuple(tangents))
        cols.append(d)
    return out, cols


def _specular(term: Specular, dirs: Directions, wavelength: Any, wanted: list[tuple[str, ...]]):
    if type(term) is not Specular or term.shadowing != "none":
        return None
    if not all((len(w) == 2 and w[0] == "distribution") or w in (("n",), ("k",)) for w in wanted):
        return None
    if not wanted:
        return term(dirs, wavelength), []

    def value(vals):
        return eqx.tree_at(lambda t: tuple(_get(t, w) for w in wanted), term, tuple(vals))(dirs, wavelength)

    return _one_by_one(value, [_get(term, w) for w in wanted], jnp.result_type(term.n))


def _get(module: Any, path: tuple[str, ...]):
    for name in path:
        module = getattr(module, name)
    return module


def _offset(term: OffsetNormal, dirs: Directions, wavelength: Any, wanted: list[tuple[str, ...]]):
    if type(term) is not OffsetNormal or type(term.term) is not Specular or term.term.shadowing != "none":
        return None
    if not all(w[0] == "term" or w in (("dtheta",), ("dphi0",)) for w in wanted):
        return None
    if not wanted:
        return term(dirs, wavelength), []

    def value(vals):
        return eqx.tree_at(lambda t: tuple(_get(t, w) for w in wanted), term, tuple(vals))(dirs, wavelength)

    return _one_by_one(value, [_get(term, w) for w in wanted], jnp.result_type(term.term.n))


def _diffraction(term: Diffraction, dirs: Directions, wl: Any, wanted: list[tuple[str, ...]]):
    if type(term) is not Diffraction or not all(w in (("a",), ("b",), ("c",), PHI) for w in wanted):
        return None
    hx, hy, _ = dirs.half_vector_xyz()
    k = (2.0 * dirs.cos_theta_i if term.grating_factor else 1.0) / wl
    A, B, C = np.pi * term.a * k, term.b * k, term.distance / term.c
    cos_ = fast_cos(hy * A)
    s, ds = jax.jvp(fast_sinc, (hy * B,), (jnp.ones_like(hy),))  # sinc and sinc' at B h_y
    c2, s2 = jnp.square(cos_), jnp.square(s)
    e = jnp.exp(-jnp.square(hx * C))
    f1 = c2 * s2 * e
    sin2 = jnp.sin(2.0 * hy * A)  # d cos^2(x) = -sin(2x) dx
    dc2_dhy = -sin2 * A
    ds2_dhy = 2.0 * s * ds * B

    def col(w):
        if w == ("a",):
            return -sin2 * (hy * np.pi * k) * s2 * e
        if w == ("b",):
            return c2 * (2.0 * s * ds * hy * k) * e
        if w == ("c",):
            return f1 * 2.0 * jnp.square(hx * C) / term.c
        df_dhx = f1 * (-2.0 * hx * C * C)
        df_dhy = (dc2_dhy * s2 + c2 * ds2_dhy) * e
        return df_dhx * hy - df_dhy * hx  # phi_ref turns h: dh_x = h_y, dh_y = -h_x

    ok = _both_above(dirs)
    rho = term.rho  # 1 where rho is free (the caller's scale), else its fixed value
    return jnp.where(ok, rho * f1, 0.0), [jnp.where(ok, rho * col(w), 0.0) for w in wanted]


def term_columns(term: Any, dirs: Directions, wavelength: Any, wanted: list[tuple[str, ...]]):
    """``(f1, [column per wanted path])`` for the term at ``dirs``, or None where not written by hand.

    ``wanted``: attribute paths inside the term (``("distribution", "m")``, ``("n",)``,
    ``("term", "n")``, ``("dtheta",)``) or :data:`PHI` for the frame's ``phi_ref``.
    """
    if type(term) is Specular:
        return _specular(term, dirs, wavelength, wanted)
    if type(term) is OffsetNormal:
        return _offset(term, dirs, wavelength, wanted)
    if type(term) is Diffraction:
        return _diffraction(term, dirs, wavelength, wanted)
    return None
