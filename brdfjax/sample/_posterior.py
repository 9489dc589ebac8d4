"""The log-posterior of a fit problem: the fit's likelihood plus priors, one jit-compiled vmapped JAX function.

The likelihood is exactly the fit's (:mod:`brdfjax.fit._problem`): the
weighted log residuals ``r = (log(f + floor) - log d) / sigma_rel`` of every
usable point of every block, through the fit's robust loss, and

    log L = -sum rho(r)       (= -chi^2 / 2 for the linear loss),

so ``-2 log L`` at the least-squares optimum is the fit's ``chi2`` (its
``cost`` for a robust loss).

Walkers move in **stored units** (radians, metres, ...) of the free
parameters, in the fit layout's order (``LogPosterior.names``).  The fit's
solver coordinates (``x = g(u0 + scale v)``) are not used: the problem is
re-based to the identity map (``u0 = 0``, ``scale = 1``, every transform
``identity``), so the residual function sees the natural values directly
and the physical bounds are enforced by the prior (``-inf`` outside).
emcee's stretch move is affine invariant, so the very different scales of
the parameters (``a ~ 8e-4`` m, ``rho_s3 ~ 300`` sr^-1) do not matter.

:func:`batch_log_posterior` is one module-level ``filter_jit(filter_vmap)``
over walkers taking the problem and the priors as arguments: a new data set
or prior of the same shapes reuses the compiled program (compiled once for
emcee's ``(n_walkers, p)`` start and once for its ``(n_walkers / 2, p)``
half-steps).  It returns NumPy arrays (a JAX array handed to emcee is
iterated element by element).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..fit import TableData
from ..fit.internal import LOSSES, Problem, natural_unit, to_natural
from ._priors import PriorArrays, SampleError, build_prior_arrays, log_prior, log_prior_numpy, resolve_priors

__all__ = ["LogPosterior", "build_log_posterior", "batch_log_posterior", "identity_problem"]


def identity_problem(problem: Problem) -> Problem:
    """The same problem with ``natural(x) = x`` (no reparametrisation, no scaling)."""
    n = problem.u0.shape[0]
    dtype = problem.u0.dtype
    return eqx.tree_at(
        lambda p: (p.u0, p.scale, p.transform_ids),
        problem,
        (jnp.zeros(n, dtype), jnp.ones(n, dtype), jnp.zeros(n, jnp.int32)),
    )


def _log_likelihood_one(x: Array, problem: Problem, est: Array) -> Array:
    """``-chi2/2`` over the points with uncertainties; ``-(N/2) ln RSS`` over the ``N`` points whose noise is
    estimated (``est`` = 1): the log-normal scatter profiled out (equal, up to a constant, to marginalising
    it with the Jeffreys prior ``1/s``), so that no unit of the unknown noise is assumed."""
    r2 = jnp.square(problem.residuals(x).astype(jnp.result_type(x)))
    n_est = jnp.sum(est)
    rss = jnp.sum(r2 * est)
    ll = -0.5 * jnp.sum(r2 * (1.0 - est)) - 0.5 * jnp.where(n_est > 0, n_est * jnp.log(jnp.maximum(rss, 1e-300)), 0.0)
    return jnp.where(jnp.isfinite(ll), ll, -jnp.inf)


def _log_posterior_one(x: Array, problem: Problem, priors: PriorArrays, est: Array) -> Array:
    lp = log_prior(x, priors)
    # The likelihood is evaluated everywhere (vmap has no branches); outside the support the prior wins.
    x_safe = jnp.where(jnp.isfinite(lp), x, jnp.clip(x, priors.lower, priors.upper))
    ll = _log_likelihood_one(x_safe, problem, est)
    return jnp.where(jnp.isfinite(lp), lp + ll, -jnp.inf)


def _log_posterior_sampler(y: Array, problem: Problem, priors: PriorArrays, est: Array, log_mask: Array) -> Array:
    """The log-posterior density of the sampler's coordinates ``y``: ``x = exp(y)`` where ``log_mask``, else ``y``.

    The log-Jacobian ``sum y`` over the logged entries makes it the density of ``y`` (the same posterior of ``x``).
    """
    x = jnp.where(log_mask, jnp.exp(y), y)
    return _log_posterior_one(x, problem, priors, est) + jnp.sum(jnp.where(log_mask, y, 0.0))


@eqx.filter_jit
def batch_log_posterior_sampler(Y: Array, problem: Problem, priors: PriorArrays, est: Array, log_mask: Array) -> Array:
    """:func:`_log_posterior_sampler` of every walker, ``Y``: ``(n_walkers, p)``."""
    return jax.vmap(_log_posterior_sampler, in_axes=(0, None, None, None, None))(Y, problem, priors, est, log_mask)


@eqx.filter_jit
def batch_log_posterior(X: Array, problem: Problem, priors: PriorArrays, est: Array) -> Array:
    """Log-posterior of every walker, ``X``: ``(n_walkers, p)`` stored units."""
    return jax.vmap(_log_posterior_one, in_axes=(0, None, None, None))(X, problem, priors, est)


@eqx.filter_jit
def batch_log_likelihood(X: Array, problem: Problem, est: Array) -> Array:
    return jax.vmap(_log_likelihood_one, in_axes=(0, None, None))(X, problem, est)


@eqx.filter_jit
def single_log_posterior(x: Array, problem: Problem, priors: PriorArrays, est: Array) -> Array:
    """The same log-posterior for one walker (the non-vectorised baseline of the benchmark)."""
    return _log_posterior_one(x, problem, priors, est)


def estimated_noise_mask(prepared: Any) -> np.ndarray:
    """1 at the points of blocks without uncertainties (tables with no sigma: noise profiled), else 0.

    The nuisance parameters' prior rows, which follow the data's residuals
    (``Problem.nuisance``), have a known unit sigma: 0 there.
    """
    parts = [
        np.full(int(c), 1.0 if isinstance(b, TableData) and b.sigma_rel is None else 0.0)
        for b, c in zip(prepared.blocks, prepared.problem.counts)
    ]
    nuisance = prepared.problem.nuisance
    parts.append(np.zeros(0 if nuisance is None else int(nuisance.size)))
    return np.concatenate(parts)


@dataclass(eq=False)
class LogPosterior:
    """A fit problem's log-posterior over its free parameters (stored units; see the module docstring)."""

    problem: Problem  # identity-mapped
    priors: PriorArrays
    names: tuple[str, ...]
    bases: tuple[str, ...]
    units: tuple[str, ...]  # stored units
    lower: np.ndarray  # physical bounds (stored units)
    upper: np.ndarray
    prior_specs: tuple[Any, ...]  # Prior or None per parameter
    prior_keys: tuple[str | None, ...]
    n_points: int
    loss: str
    dtype: Any = field(default=None)
    est: Any = None  # (n_points,) 1 where the noise is estimated (profiled), else 0
    # (p,) bool: the entries the sampler moves as their logarithm (sample(log_weights=...)); None: none
    log_mask: Any = None

    @property
    def logged(self) -> np.ndarray:
        return np.zeros(self.ndim, bool) if self.log_mask is None else np.asarray(self.log_mask, bool)

    def with_log(self, mask: Any) -> "LogPosterior":
        """The same posterior whose sampler moves the entries of ``mask`` as their logarithm."""
        m = np.asarray(mask, bool)
        return replace(self, log_mask=jnp.asarray(m) if m.any() else None)

    def to_sampler(self, X: Any) -> np.ndarray:
        """Stored units -> the sampler's coordinates (log where :attr:`logged`)."""
        X = np.array(X, np.float64)
        m = self.logged
        if m.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                X[..., m] = np.log(X[..., m])
        return X

    def from_sampler(self, Y: Any) -> np.ndarray:
        """The sampler's coordinates -> stored units."""
        Y = np.array(Y, np.float64)
        m = self.logged
        if m.any():
            Y[..., m] = np.exp(Y[..., m])
        return Y

    def sampler_log_prob(self, Y: Any) -> np.ndarray:
        """Vectorised log-density of the sampler's coordinates (emcee ``vectorize=True``): ``(n, p)`` -> ``(n,)``."""
        if self.log_mask is None:
            return self(Y)
        return np.asarray(
            batch_log_posterior_sampler(self._as_batch(Y), self.problem, self.priors, self.est, self.log_mask), np.float64
        )

    def sampler_log_prob_one(self, y: Any) -> float:
        return float(self.sampler_log_prob(np.asarray(y, np.float64)[None, :])[0])

    @property
    def ndim(self) -> int:
        return len(self.names)

    @property
    def factors(self) -> np.ndarray:
        """Stored -> natural unit factors (180/pi for angles)."""
        return np.array([to_natural(u) for u in self.units])

    @property
    def natural_units(self) -> tuple[str, ...]:
        return tuple(natural_unit(u) for u in self.units)

    def _as_batch(self, X: Any) -> Any:
        return jnp.asarray(np.atleast_2d(np.asarray(X, np.float64)), self.dtype)

    def __call__(self, X: Any) -> np.ndarray:
        """Vectorised log-posterior: ``(n, p)`` -> ``(n,)`` NumPy (emcee ``vectorize=True``)."""
        return np.asarray(batch_log_posterior(self._as_batch(X), self.problem, self.priors, self.est), np.float64)

    def log_prob_one(self, x: Any) -> float:
        """One walker through a jitted single-walker function (emcee ``vectorize=False``)."""
        return float(
            single_log_posterior(jnp.asarray(np.asarray(x, np.float64), self.dtype), self.problem, self.priors, self.est)
        )

    def log_likelihood(self, X: Any) -> np.ndarray:
        """``-sum rho(r)`` (no prior; profiled where the noise is estimated): ``-2 log L`` is the fit's chi^2
        for the linear loss with known uncertainties."""
        return np.asarray(batch_log_likelihood(self._as_batch(X), self.problem, self.est), np.float64)

    @property
    def sigma_estimated(self) -> bool:
        return bool(np.any(np.asarray(self.est) > 0))

    def log_prior(self, X: Any) -> np.ndarray:
        return log_prior_numpy(X, self.priors)

    def to_natural(self, X: Any) -> np.ndarray:
        return np.asarray(X, np.float64) * self.factors

    def support(self) -> tuple[np.ndarray, np.ndarray]:
        """Where the log-prior is finite: priors intersected with the physical bounds (stored units)."""
        return np.asarray(self.priors.lower, np.float64), np.asarray(self.priors.upper, np.float64)

    def describe_priors(self) -> dict[str, str]:
        out = {}
        for name, p, unit, f, lo, hi in zip(
            self.names, self.prior_specs, self.units, self.factors, self.lower, self.upper
        ):
            if p is None:
                lo_s = "-inf" if not np.isfinite(lo) else f"{lo * f:.6g}"
                hi_s = "inf" if not np.isfinite(hi) else f"{hi * f:.6g}"
                out[name] = f"flat[{lo_s}, {hi_s}] {natural_unit(unit)}"
            else:
                out[name] = p.describe(f, natural_unit(unit))
        return out


def build_log_posterior(prepared: Any, priors: Mapping[str, Any] | None = None, loss: str | None = None) -> LogPosterior:
    """The :class:`LogPosterior` of a :func:`brdfjax.fit.prepare` result with ``priors`` (name -> Prior).

    Names are the fit's free-parameter names (``m1``, ``phi_ref[ti20]``) or
    their base (``phi_ref``: every frame's entry).  A prior on a name that is
    not free raises :class:`SampleError`.
    """
    layout = prepared.layout
    names = tuple(e.name for e in layout.free)
    bases = tuple(e.base for e in layout.free)
    if not names:
        raise SampleError("nothing to sample: every parameter is fixed; free some in the parameter specification")
    all_names = set(layout.order) | {e.base for e in layout.fixed}
    for key in priors or {}:
        if key in all_names and key not in names and key not in bases:
            raise SampleError(f"prior on '{key}', which is held fixed; make it free (free = true) to sample it")
    resolved = resolve_priors(priors, names, bases)
    lo, hi = layout.bounds()
    pa = build_prior_arrays(resolved, lo, hi, names)
    problem = identity_problem(prepared.problem)
    dtype = problem.u0.dtype
    pa = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype) if a.dtype.kind == "f" else jnp.asarray(a), pa)

    return LogPosterior(
        problem=problem,
        priors=pa,
        names=names,
        bases=bases,
        units=tuple(e.unit for e in layout.free),
        lower=lo,
        upper=hi,
        prior_specs=tuple(p for p, _ in resolved),
        prior_keys=tuple(k for _, k in resolved),
        n_points=int(sum(prepared.problem.counts)),
        loss=loss or LOSSES[int(np.asarray(prepared.problem.loss_index))],
        dtype=dtype,
        est=jnp.asarray(estimated_noise_mask(prepared), dtype),
    )


def start_ball(
    post: LogPosterior,
    x0: np.ndarray,
    sigma: np.ndarray,
    n_walkers: int,
    ball: float,
    rng: np.random.Generator,
    max_tries: int = 100,
    chol: np.ndarray | None = None,
) -> np.ndarray:
    """``n_walkers`` starts ``x0 + ball * sigma * N(0, 1)`` inside the support with a finite log-posterior.

    With ``chol`` (a Cholesky factor of the fit's covariance) the starts are
    ``x0 + ball * chol @ N(0, 1)`` instead: correlated as the fit says.

    ``x0`` outside the prior's support is an error naming the parameter;
    where ``sigma`` is not a positive finite number, 1e-4 of ``|x0|`` (or
    1e-8) stands in.
    """
    x0 = np.asarray(x0, np.float64)
    lo, hi = post.support()
    f = post.factors
    for i, name in enumerate(post.names):
        if not (lo[i] <= x0[i] <= hi[i]):
            p = post.prior_specs[i]
            what = p.describe(f[i], post.natural_units[i]) if p is not None else "its physical bounds"
            raise SampleError(
                f"the prior excludes the starting point: '{name}' = {x0[i] * f[i]:.6g} {post.natural_units[i]} "
                f"(the least-squares optimum) lies outside {what} "
                f"(support [{lo[i] * f[i]:.6g}, {hi[i] * f[i]:.6g}]); widen the prior or check the fit"
            )
    lp0 = post(x0[None, :])[0]
    if not np.isfinite(lp0):
        raise SampleError(
            "the log-posterior at the starting point is not finite (log-likelihood "
            f"{post.log_likelihood(x0[None, :])[0]!r}); check the fit result and the data"
        )
    s = np.asarray(sigma, np.float64).copy()
    bad = ~(np.isfinite(s) & (s > 0))
    s[bad] = np.where(x0[bad] != 0, 1e-4 * np.abs(x0[bad]), 1e-8)
    # keep the ball well inside a bounded support
    width = hi - lo
    s = np.where(np.isfinite(width), np.minimum(s, 0.05 * width / max(ball, 1e-12)), s)
    if chol is None:
        draw = lambda k, b: b * s * rng.standard_normal((k, x0.size))  # noqa: E731
    else:  # along the fit's correlations: the walkers start on a ridge, not across it
        L = np.asarray(chol, np.float64)
        draw = lambda k, b: b * rng.standard_normal((k, x0.size)) @ L.T  # noqa: E731
    X = x0 + draw(n_walkers, ball)
    for _ in range(max_tries):
        lp = post(X)
        need = ~np.isfinite(lp)
        if not need.any():
            return X
        X[need] = x0 + draw(int(need.sum()), 0.5 * ball)
    raise SampleError(
        f"could not place {n_walkers} walkers with a finite log-posterior around the starting point "
        f"(ball {ball} sigma); the optimum may sit on a bound of the prior: widen the prior or reduce 'ball'"
    )


def check_walkers(n_walkers: int, ndim: int) -> None:
    if not isinstance(n_walkers, int | np.integer) or n_walkers < 2 * ndim:
        raise SampleError(
            f"n_walkers = {n_walkers!r} is fewer than twice the {ndim} free parameters; emcee's stretch move "
            f"needs at least {2 * ndim} walkers (use {max(2 * ndim + 2, 32) + (max(2 * ndim + 2, 32) % 2)} or more)"
        )
    if n_walkers % 2:
        raise SampleError(f"n_walkers = {n_walkers} must be even (emcee updates the walkers in two halves)")


def default_walkers(ndim: int) -> int:
    n = max(32, 4 * ndim)
    return n + (n % 2)

