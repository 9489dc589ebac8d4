"""ND filters: the stacks, their optical densities and tolerances, and the seed's selection rule (seed §3.3, §4.3).

One module for every caller (``brdfjax synthesize``, the device plans, the
generators of the diagnosis, the experiments):

- :func:`parse_nd_filters` / :func:`stack_od`: ``"4.0+1.0+0.2"`` -> its ODs / their sum;
- :data:`ND_STACKS`: the seed's filter stacks in order of increasing OD;
- :data:`SEED_ND_TOLERANCES` and :data:`ND_3_TOLERANCE`: the OD tolerances (Eq 97);
- :func:`select_stack` / :func:`choose_nd_filters`: the seed's rule, the
  thinnest stack whose brightest pixel stays below 0.9 full scale at the
  shortest exposure (``peak rate x 10^-OD x t_min + 2 x black level``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from types import MappingProxyType
from typing import Any

import numpy as np

from ..io.raw import NDSpec, parse_nd_filters
from ..runtime.errors import InputError

__all__ = [
    "ND_STACKS",
    "ND_3_TOLERANCE",
    "SEED_ND_TOLERANCES",
    "NDSpec",
    "parse_nd_filters",
    "stack_od",
    "select_stack",
    "choose_nd_filters",
]


#: ND filter stacks tried, in order of increasing OD, when a stack is picked by the seed's rule (seed §3.3 filters).
ND_STACKS: tuple[str, ...] = (
    "", "0.3", "1.0", "1.0+0.3", "3.0", "3.0+0.3", "4.0", "4.0+0.3", "4.0+1.0", "4.0+1.0+0.2",
    "4.0+1.0+0.3", "4.0+3.0", "4.0+3.0+0.3", "4.0+3.0+1.0",
)
#: ND-filter OD tolerances (nominal OD -> +- OD), seed §4.3.  1.0 is inferred
#: (see :mod:`brdfjax.instrument.uncertainty`'s docstring).
SEED_ND_TOLERANCES: Mapping[float, float] = MappingProxyType({0.1: 0.01, 0.2: 0.01, 0.3: 0.01, 1.0: 0.06, 4.0: 0.2})
#: ND tolerance of the 3.0 filter (+-OD) inferred from the seed's 59.3 % (its tolerance table lacks it).
ND_3_TOLERANCE = 0.15


def stack_od(stack: str) -> float:
    """Total nominal OD of a stack like ``"4.0+1.0+0.2"``."""
    return float(sum(parse_nd_filters(stack)))


def select_stack(
    peak_rate_unattenuated: float, *, t_min: float, black_level: float, full_scale: float,
    stacks: Sequence[str] = ND_STACKS,
) -> str:
    """The seed's rule: the thinnest stack whose brightest pixel stays below 0.9 full scale at the shortest
    exposure.  ``peak_rate_unattenuated``: counts/s with no filter; ``black_level``, ``full_scale``: counts."""
    for stack in sorted(stacks, key=stack_od):
        if peak_rate_unattenuated * 10 ** -stack_od(stack) * t_min + 2 * black_level < 0.9 * full_scale:
            return stack
    raise InputError(  # a refusal (exit 2): the sample is too bright for every stack on the bench
        f"no ND stack up to OD {max(map(stack_od, stacks)):g} keeps the brightest pixel unsaturated "
        f"(peak {peak_rate_unattenuated:.4g} counts/s unattenuated)"
    )


def choose_nd_filters(rate: Callable[[str], np.ndarray], instrument: Any) -> str:
    """:func:`select_stack` for a synthetic instrument, from its light-rate function.

    ``rate(stack)`` is the light rate on the array (counts/s) through an ND stack; it scales
    with ``10**-OD``, so it is evaluated once, without filters.  ``instrument`` is a
    :class:`~brdfjax.instrument.SyntheticInstrument` (its config's shortest exposure, black level
    and full scale).
    """
    cfg = instrument.config
    return select_stack(
        float(np.max(rate(ND_STACKS[0]))), t_min=float(cfg.exposures_s[0]),
        black_level=cfg.black_level.counts, full_scale=cfg.full_scale,
    )
