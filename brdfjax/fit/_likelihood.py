"""One likelihood object for fit, sample and diagnose.

A :class:`Likelihood` is the data, the model whose parameters they constrain, which of those
parameters are free (with their starts and bounds), and every option that changes the value of
``-2 ln L``: the residual loss, the log model's floor, the precision, the footprint, the nuisance
parameters, whether uncertainties are taken at face value.  It is built once with :func:`prepare`
and handed to :func:`brdfjax.fit.fit` (with a solver), :func:`brdfjax.sample.sample` (with priors
and a sampler) and :func:`brdfjax.diagnose.diagnose` (with candidate effects), so that a fit, the
posterior around it and a diagnosis of its residuals are of one likelihood, by construction.

How the optimum is *found* (the solver and its options, the first stage, progress) is not part of the
likelihood: those belong to the call, as in optimistix, where the solver is an object of its own.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..config.base import check_choice
from ..core.terms import Model
from ..io.blocks import FrameData, TableData
from ._common import FitInputError
from ._prepare import _as_blocks
from ._residuals import LOSSES

__all__ = ["Likelihood", "prepare", "LIKELIHOOD_OPTIONS"]

Data = FrameData | TableData

#: The keyword options of :func:`brdfjax.fit.fit` that belong to the likelihood, with their defaults.
LIKELIHOOD_OPTIONS: dict[str, Any] = {
    "loss": "linear",
    "loss_scale": None,
    "floor": "auto",
    "precision": None,
    "absolute_sigma": None,
    "use_footprint": True,
    "nuisance": None,
    "initializer": None,
    "init_options": None,
    "allow_different_detectors": False,
    "resolution_check": True,
}


@dataclass(frozen=True)
class Likelihood:
    """The likelihood of ``model``'s parameters given ``blocks`` (see the module docstring).

    Fields are those of :func:`prepare`; ``params`` is the parameter spec of :func:`brdfjax.fit.fit`
    (name -> :class:`~brdfjax.fit.Param`, a start value, ``"auto"``, ``"free"`` or ``"fixed"``).
    """

    model: Model
    blocks: tuple[Data, ...]
    params: Mapping[str, Any] = field(default_factory=dict)
    loss: str = "linear"
    loss_scale: float | None = None
    floor: float | str = "auto"
    precision: str | None = None
    absolute_sigma: bool | None = None
    use_footprint: bool = True
    nuisance: Any = None
    initializer: str | Callable | None = None
    init_options: Mapping[str, Any] | None = None
    allow_different_detectors: bool = False
    resolution_check: bool = True

    def options(self) -> dict[str, Any]:
        """The likelihood's options as keyword arguments of :func:`brdfjax.fit.fit`."""
        return {k: getattr(self, k) for k in LIKELIHOOD_OPTIONS}

    def replace(self, **changes: Any) -> Likelihood:
        """A copy with some fields changed (checked as :func:`prepare` checks them)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise FitInputError(f"Likelihood has no field {', '.join(map(repr, unknown))}; "
                                f"fields: {', '.join(f.name for f in dataclasses.fields(self))}")
        new = dataclasses.replace(self, **changes)
        _check(new)
        return new

    def with_params(self, params: Mapping[str, Any]) -> Likelihood:
        """The same likelihood with another parameter spec (e.g. a fit's values as starts)."""
        return self.replace(params=dict(params))

    @property
    def n_points(self) -> int:
        """Usable data points over every block."""
        return int(sum(int(b.check_usable().sum()) for b in self.blocks))


def _check(lik: Likelihood) -> None:
    if not isinstance(lik.model, Model):
        raise FitInputError(f"model must be a brdfjax Model (a named sum of terms), got {type(lik.model).__name__}")
    if not isinstance(lik.params, Mapping):
        raise FitInputError(f"params must be a mapping of parameter name -> spec, got {type(lik.params).__name__}")
    if lik.loss not in LOSSES:
        raise FitInputError(f"unknown loss '{lik.loss}'; known: {', '.join(LOSSES)}")
    if lik.loss_scale is not None and not (isinstance(lik.loss_scale, int | float) and lik.loss_scale > 0
                                           and math.isfinite(lik.loss_scale)):
        raise FitInputError(f"loss_scale must be a positive number (in sigma), got {lik.loss_scale!r}")
    if lik.precision not in (None, "float32", "float64"):
        raise FitInputError(f"precision must be 'float32' or 'float64' (or None), got {lik.precision!r}")


def prepare(
    model: Model,
    data: Data | Sequence[Data],
    params: Mapping[str, Any] | None = None,
    **options: Any,
) -> Likelihood:
    """The :class:`Likelihood` of ``model``'s parameters ``params`` given ``data``.

    ``options``: the likelihood's options (:data:`LIKELIHOOD_OPTIONS`: ``loss``, ``loss_scale``,
    ``floor``, ``precision``, ``absolute_sigma``, ``use_footprint``, ``nuisance``, ``initializer``,
    ``init_options``, ``allow_different_detectors``, ``resolution_check``; see
    :func:`brdfjax.fit.fit`).  Checked here, so a wrong name fails before any compilation::

        lik = bj.fit.prepare(model, table, {"spec.alpha": "auto", "spec.rho_s": "auto"}, loss="huber")
        result = bj.fit.fit(lik)
        post = bj.sample.sample(lik, priors, sampler=bj.sample.Emcee(n_walkers=32, n_steps=2000))
        gap = bj.diagnose.diagnose(lik, effects=["diffraction", "lambertian"])
    """
    for name in options:
        try:
            check_choice("likelihood option", name, LIKELIHOOD_OPTIONS)
        except ValueError as e:
            raise FitInputError(f"{e} (the solver and its options are given to fit(), not to the likelihood)") from None
    lik = Likelihood(model, tuple(_as_blocks(data)), dict(params or {}), **options)
    _check(lik)
    return lik
