"""The samplers of :func:`brdfjax.sample.sample`, as objects holding their own options.

As optimistix keeps a solver's options on the solver, a sampler's options live on its object:
``sample(lik, priors, sampler=Emcee(n_walkers=32, n_steps=2000))`` or ``sampler=NUTS(n_chains=4)``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from ._priors import SampleError

__all__ = ["Emcee", "NUTS", "sampler_options"]


@dataclass(frozen=True)
class Emcee:
    """emcee's affine-invariant ensemble (Foreman-Mackey et al. 2013).

    ``n_walkers`` (default: from the dimension), ``n_steps`` per walker, walkers started in a ball of
    ``ball`` fit sigmas, ``burn`` (steps, or ``"auto"``: from the autocorrelation time), ``thin``,
    ``stop_when_converged`` (checked every ``check_every`` steps), ``vectorize`` (every walker's
    log-posterior in one JAX call).
    """

    n_walkers: int | None = None
    n_steps: int = 1000
    ball: float = 0.1
    burn: int | str = "auto"
    thin: int = 1
    stop_when_converged: bool = False
    check_every: int = 100
    vectorize: bool = True

    name = "emcee"


@dataclass(frozen=True)
class NUTS:
    """blackjax's No-U-Turn sampler (Hoffman & Gelman 2014): ``n_chains`` independent chains of
    ``n_steps`` after ``n_warmup`` steps of window adaptation, started in a ball of ``ball`` fit sigmas."""

    n_chains: int = 4
    n_warmup: int = 500
    n_steps: int = 1000
    ball: float = 0.1
    burn: int | str = "auto"
    thin: int = 1

    name = "nuts"


def sampler_options(sampler: Emcee | NUTS) -> dict[str, Any]:
    """The keyword options of the sampling run that ``sampler`` stands for."""
    if not isinstance(sampler, Emcee | NUTS):
        raise SampleError(f"sampler must be brdfjax.sample.Emcee(...) or NUTS(...) (or 'emcee' / 'nuts'), got {sampler!r}")
    return {"sampler": sampler.name, **asdict(sampler)}
