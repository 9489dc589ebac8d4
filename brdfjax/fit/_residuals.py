"""Log-space residuals, robust losses and the instrument function (pure JAX).

For a BRDF datum ``d`` with relative 1-sigma uncertainty ``s`` and the model
``f`` at the same point, the residual is

    r = (log(f + floor) - log d) / s

(``log d`` has standard deviation ``s`` to first order).  ``floor`` (sr^-1)
guards ``log(0)`` where every term of the model underflows -- a Beckmann peak
``exp(-tan^2/m^2)`` a few widths out, the diffraction band's Gaussian -- and
keeps the gradient finite there; the default is 1e-6 of the smallest datum
fitted, which biases ``log f`` by less than 1e-6 wherever the model is at the
level of the data.  (The seed's pitfall list asks for a log-sum-exp of the
terms' logs; the core terms evaluate ``f``, not ``log f``, so the floor is the
guard available here.)

Robust losses ``rho(r)`` replace ``r^2 / 2``; a least-squares solver then
minimises ``sum rho(r)`` through the transformed residuals

    r~ = r sqrt(2 rho(r) / r^2),   so that  r~^2 / 2 = rho(r),

i.e. each residual reweighted by ``w(r) = 2 rho(r) / r^2`` (1 inside the
quadratic core).  With ``k`` the ``loss_scale`` (in units of sigma):

- ``linear``: ``rho = r^2 / 2``;
- ``huber``: ``r^2 / 2`` for ``|r| <= k``, ``k |r| - k^2 / 2`` beyond;
- ``cauchy``: ``(k^2 / 2) log(1 + (r / k)^2)``.

The IRLS weights ``rho'(r) / r`` (:func:`irls_weights`) say how much each
point counts at the optimum.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import jax.scipy.signal as jsignal
from jaxtyping import Array, ArrayLike

__all__ = ["LOSSES", "DEFAULT_LOSS_SCALE", "robust_residuals", "robust_residuals_by_id", "loss_id", "irls_weights", "log_model", "convolve_same", "block_log_residuals"]

LOSSES = ("linear", "huber", "cauchy")

#: Residual (in sigma) beyond which Huber and Cauchy grow slower than r^2 / 2.
DEFAULT_LOSS_SCALE = 3.0


def _check(loss: str) -> None:
    if loss not in LOSSES:
        raise ValueError(f"unknown loss '{loss}'; known: {', '.join(LOSSES)}")


def _sqrt_weight(loss: str, r: Array, k: ArrayLike) -> Array:
    """``sqrt(2 rho(r) / r^2)``, finite and differentiable at r = 0."""
    _check(loss)
    if loss == "linear":
        return jnp.ones_like(r)
    a = jnp.abs(r)
    if loss == "huber":
        outside = a > k
        a_safe = jnp.where(outside, a, 2.0 * k + 1.0)
        w = (2.0 * k * a_safe - k * k) / (a_safe * a_safe)
        return jnp.where(outside, jnp.sqrt(w), 1.0)
    # cauchy: 2 rho / r^2 = log1p(z) / z with z = (r / k)^2
    z = jnp.square(r / k)
    big = z > 1e-6
    z_safe = jnp.where(big, z, 1.0)
    w = jnp.where(big, jnp.log1p(z_safe) / z_safe, 1.0 - 0.5 * z)
    return jnp.sqrt(w)


def robust_residuals(loss: str, r: Array, k: ArrayLike) -> Array:
    """Residuals ``r~`` with ``r~^2 / 2 = rho(r)`` for a least-squares solver."""
    if loss == "linear":
        return r
    return r * _sqrt_weight(loss, r, k)


def loss_id(loss: str) -> int:
    """The index of a loss in :data:`LOSSES` (for :func:`robust_residuals_by_id`)."""
    _check(loss)
    return LOSSES.index(loss)


def robust_residuals_by_id(loss_index: Array, r: Array, k: ArrayLike) -> Array:
    """:func:`robust_residuals` with the loss chosen by a traced index into :data:`LOSSES`.

    One compiled program then serves every loss (a fit that starts with a
    robust loss and finishes with the linear one compiles once).
    """
    w = jnp.select(
        [loss_index == i for i in range(len(LOSSES))],
        [_sqrt_weight(name, r, k) for name in LOSSES],
    )
    return r * w


def irls_weights(loss: str, r: Array, k: ArrayLike) -> Array:
    """IRLS weights ``rho'(r) / r`` in [0, 1]: how much each point counts."""
    _check(loss)
    if loss == "linear":
        return jnp.ones_like(r)
    a = jnp.abs(r)
    if loss == "huber":
        return jnp.where(a > k, k / jnp.where(a > k, a, 1.0), 1.0)
    return 1.0 / (1.0 + jnp.square(r / k))


def log_model(f: Array, floor: ArrayLike) -> Array:
    """``log(f + floor)``: the model's log with the underflow guard (see the module docstring)."""
    return jnp.log(f + floor)


def convolve_same(image: Array, kernel: Array) -> Array:
    """``image`` convolved with a centred odd-sided ``kernel`` (FFT, zero padding), same shape as ``image``."""
    return jsignal.fftconvolve(image, kernel, mode="same")


def block_log_residuals(f: Array, block: Any, soften: Array) -> Array:
    """``(log(f + floor + s) - log(d + s)) (d + s) / (d sigma_rel)`` with ``s = soften * soft_level``.

    ``s = 0`` is the plain log residual; ``s > 0`` softens the log below the
    level ``s`` (a first stage that keeps the zeros of the model -- dark
    fringes -- from trapping the solver), with the weight rescaled so that
    the residual stays in units of sigma.
    """
    s = soften * block.soft_level
    d = block.data
    return (log_model(f, block.floor + s) - jnp.log(d + s)) * block.inv_sigma * ((d + s) / d)
