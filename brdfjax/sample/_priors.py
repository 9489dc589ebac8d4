"""Priors of a posterior study: uniform, log-uniform, normal and truncated normal, per free parameter.

A :class:`Prior` is given in **stored units** (radians, metres, 1, sr^-1, as
:class:`brdfjax.fit.Param`); configs give them in natural units (angles in
degrees) and :func:`prior_from_natural` converts.  A parameter without a prior
gets a flat one.  Every prior is combined with the parameter's **physical
bounds** (the fit's bounds: ``>= 0`` for widths, lengths and reflectances,
``[0, pi/2)`` for ``theta_i``, and any ``lower``/``upper`` of the parameter
spec): outside the intersection the log-prior is ``-inf``.

Inside its support each prior is normalised over that support (a normal prior
on a positive parameter is a normal truncated at 0), so log-posteriors of
different prior choices are comparable; a flat prior on an unbounded support
contributes 0 (improper).

The priors of all parameters are packed into :class:`PriorArrays` (kind index,
two shape parameters, the support and the log normalisation per parameter),
evaluated by :func:`log_prior` in one vectorised JAX expression.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..runtime.errors import InputError

__all__ = ["Prior", "PRIOR_KINDS", "PriorArrays", "build_prior_arrays", "log_prior", "prior_from_natural", "SampleError"]

#: Prior kinds; ``flat`` is the default for a parameter without a prior.
PRIOR_KINDS = ("flat", "uniform", "log_uniform", "normal", "truncated_normal")


class SampleError(InputError):
    """Bad input to a posterior study (priors, walkers, chain file, config); the message says what to change."""


def ndtr(x: float) -> float:
    """The standard normal CDF (math.erf; infinities allowed)."""
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def _finite(x: Any) -> bool:
    return x is not None and math.isfinite(float(x))


@dataclass(frozen=True)
class Prior:
    """One parameter's prior in stored units (see the module docstring).

    ``uniform``: ``lower``, ``upper`` (finite); ``log_uniform``: ``0 < lower <
    upper``; ``normal``: ``mu``, ``sigma > 0``; ``truncated_normal``: ``mu``,
    ``sigma > 0`` and ``lower`` and/or ``upper``.
    """

    kind: str
    lower: float | None = None
    upper: float | None = None
    mu: float | None = None
    sigma: float | None = None

    @classmethod
    def uniform(cls, lower: float, upper: float) -> "Prior":
        return cls("uniform", lower=lower, upper=upper)

    @classmethod
    def log_uniform(cls, lower: float, upper: float) -> "Prior":
        return cls("log_uniform", lower=lower, upper=upper)

    @classmethod
    def normal(cls, mu: float, sigma: float) -> "Prior":
        return cls("normal", mu=mu, sigma=sigma)

    @classmethod
    def truncated_normal(cls, mu: float, sigma: float, lower: float | None = None, upper: float | None = None) -> "Prior":
        return cls("truncated_normal", lower=lower, upper=upper, mu=mu, sigma=sigma)

    def check(self, name: str) -> None:
        """Raise :class:`SampleError` naming ``name`` when the prior's settings are inconsistent."""
        kinds = [k for k in PRIOR_KINDS if k != "flat"]
        if self.kind not in kinds:
            raise SampleError(f"prior on '{name}': unknown kind {self.kind!r}; known: {', '.join(kinds)}")
        used = {
            "uniform": ("lower", "upper"),
            "log_uniform": ("lower", "upper"),
            "normal": ("mu", "sigma"),
            "truncated_normal": ("mu", "sigma", "lower", "upper"),
        }[self.kind]
        extra = [f for f in ("lower", "upper", "mu", "sigma") if f not in used and getattr(self, f) is not None]
        if extra:
            raise SampleError(f"prior on '{name}': a {self.kind} prior takes {', '.join(used)}, not {', '.join(extra)}")
        for f in used:
            v = getattr(self, f)
            if v is not None and math.isnan(float(v)):
                raise SampleError(f"prior on '{name}': {f} is NaN")
        if self.kind in ("uniform", "log_uniform"):
            if not (_finite(self.lower) and _finite(self.upper)):
                raise SampleError(
                    f"prior on '{name}': a {self.kind} prior needs finite lower and upper, got "
                    f"lower={self.lower!r}, upper={self.upper!r}"
                )
            if not self.lower < self.upper:
                raise SampleError(f"prior on '{name}': lower {self.lower!r} must be < upper {self.upper!r}")
            if self.kind == "log_uniform" and not self.lower > 0:
                raise SampleError(f"prior on '{name}': a log_uniform prior needs lower > 0, got {self.lower!r}")
        else:
            if not _finite(self.mu):
                raise SampleError(f"prior on '{name}': a {self.kind} prior needs a finite mu, got {self.mu!r}")
            if not (_finite(self.sigma) and float(self.sigma) > 0):
                raise SampleError(f"prior on '{name}': sigma must be a positive number, got {self.sigma!r}")
            if self.kind == "truncated_normal":
                if self.lower is None and self.upper is None:
                    raise SampleError(f"prior on '{name}': a truncated_normal prior needs lower and/or upper")
                lo = -math.inf if self.lower is None else float(self.lower)
                hi = math.inf if self.upper is None else float(self.upper)
                if not lo < hi:
                    raise SampleError(f"prior on '{name}': lower {lo!r} must be < upper {hi!r}")

    def describe(self, factor: float = 1.0, unit: str = "") -> str:
        u = f" {unit}" if unit else ""
        f = lambda v: "-inf" if v is None or v == -math.inf else "inf" if v == math.inf else f"{float(v) * factor:.6g}"  # noqa: E731
        if self.kind in ("uniform", "log_uniform"):
            return f"{self.kind}[{f(self.lower)}, {f(self.upper)}]{u}"
        if self.kind == "normal":
            return f"normal(mu={f(self.mu)}, sigma={f(self.sigma)}){u}"
        return f"truncated_normal(mu={f(self.mu)}, sigma={f(self.sigma)}, [{f(self.lower)}, {f(self.upper)}]){u}"


def prior_from_natural(kind: str, factor: float, **values: float | None) -> Prior:
    """A :class:`Prior` from natural-unit values (``factor``: natural -> stored, e.g. pi/180 for degrees)."""
    conv = {k: (None if v is None else float(v) * factor) for k, v in values.items()}
    return Prior(kind, **conv)


class PriorArrays(eqx.Module):
    """All priors of a study as arrays (one entry per free parameter, in the layout's order)."""

    kind: Array  # int32 index into PRIOR_KINDS
    mu: Array
    sigma: Array
    lower: Array  # support: prior bounds intersected with the physical bounds
    upper: Array
    log_norm: Array  # log of the normalisation over the support


def resolve_priors(
    priors: Mapping[str, Prior] | None, names: Sequence[str], bases: Sequence[str]
) -> list[tuple[Prior | None, str | None]]:
    """The prior of each free parameter: by its full name (``phi_ref[ti20]``), else by its base (``phi_ref``).

    Returns ``(prior, key)`` per parameter; raises for a prior on a name that
    is not a free parameter.
    """
    priors = dict(priors or {})
    known = set(names) | set(bases)
    for key, p in priors.items():
        if key not in known:
            raise SampleError(
                f"prior on unknown parameter '{key}': the free parameters are {', '.join(names)}"
                + (" (a prior needs the parameter to be free in [params])" if names else "")
            )
        if not isinstance(p, Prior):
            raise SampleError(f"prior on '{key}': expected a brdfjax.sample.Prior, got {type(p).__name__}")
        p.check(key)
    out = []
    for name, base in zip(names, bases):
        if name in priors:
            out.append((priors[name], name))
        elif base in priors:
            out.append((priors[base], base))
        else:
            out.append((None, None))
    return out


def build_prior_arrays(
    resolved: Sequence[tuple[Prior | None, str | None]], lower: np.ndarray, upper: np.ndarray, names: Sequence[str]
) -> PriorArrays:
    """Pack the priors with the physical bounds ``lower``/``upper`` (stored units) into :class:`PriorArrays`."""
    n = len(resolved)
    kind = np.zeros(n, np.int32)
    mu = np.zeros(n)
    sigma = np.ones(n)
    lo = np.asarray(lower, np.float64).copy()
    hi = np.asarray(upper, np.float64).copy()
    log_norm = np.zeros(n)
    for i, (p, _) in enumerate(resolved):
        if p is None:
            continue
        kind[i] = PRIOR_KINDS.index(p.kind)
        plo = -math.inf if p.lower is None else float(p.lower)
        phi = math.inf if p.upper is None else float(p.upper)
        lo[i], hi[i] = max(lo[i], plo), min(hi[i], phi)
        if not lo[i] < hi[i]:
            raise SampleError(
                f"prior on '{names[i]}': its range [{plo:.6g}, {phi:.6g}] does not overlap the parameter's "
                f"physical bounds [{lower[i]:.6g}, {upper[i]:.6g}] (stored units)"
            )
        if p.kind == "uniform":
            log_norm[i] = math.log(hi[i] - lo[i])
        elif p.kind == "log_uniform":
            log_norm[i] = math.log(math.log(hi[i] / lo[i]))
        else:
            mu[i], sigma[i] = float(p.mu), float(p.sigma)
            z = float(ndtr((hi[i] - mu[i]) / sigma[i]) - ndtr((lo[i] - mu[i]) / sigma[i]))
            if not z > 0:
                raise SampleError(
                    f"prior on '{names[i]}': the {p.kind} prior has no mass inside [{lo[i]:.6g}, {hi[i]:.6g}] "
                    "(stored units); move mu or widen the bounds"
                )
            log_norm[i] = math.log(sigma[i] * math.sqrt(2 * math.pi)) + math.log(z)
    return PriorArrays(kind, mu, sigma, lo, hi, log_norm)


def log_prior(x: Array, pa: PriorArrays) -> Array:
    """Sum of the log-priors at ``x`` (stored units, one walker); ``-inf`` outside any support."""
    inside = jnp.all((x >= pa.lower) & (x <= pa.upper))
    # log-uniform: -log x (x > 0 inside its support; the guard keeps other kinds finite)
    x_pos = jnp.where(pa.kind == 2, x, 1.0)
    z = (x - pa.mu) / pa.sigma
    terms = jnp.select(
        [pa.kind == 0, pa.kind == 1, pa.kind == 2],
        [jnp.zeros_like(x), jnp.zeros_like(x), -jnp.log(x_pos)],
        -0.5 * z * z,
    ) - pa.log_norm
    return jnp.where(inside, jnp.sum(terms), -jnp.inf)


def log_prior_numpy(x: np.ndarray, pa: PriorArrays) -> np.ndarray:
    """:func:`log_prior` for a batch ``(n, p)`` in NumPy float64 (start checks, reports)."""
    x = np.atleast_2d(np.asarray(x, np.float64))
    kind, mu, sigma = np.asarray(pa.kind), np.asarray(pa.mu), np.asarray(pa.sigma)
    lo, hi, ln = np.asarray(pa.lower), np.asarray(pa.upper), np.asarray(pa.log_norm)
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (x - mu) / sigma
        terms = np.select([kind == 0, kind == 1, kind == 2], [0.0 * x, 0.0 * x, -np.log(np.where(kind == 2, x, 1.0))], -0.5 * z * z) - ln
    return np.where(inside, terms.sum(axis=1), -np.inf)
