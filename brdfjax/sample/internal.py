"""The posterior package's inner API for brdfjax's other packages (the command line, the experiments).

As :mod:`brdfjax.fit.internal` does for the fit: pieces a user sampling a posterior does not need, but
that the ``brdfjax sample`` command builds on; documented and stable within brdfjax, while the modules
they come from (``brdfjax.sample._*``) stay private.

- :class:`ChainStore`: the chain file that emcee and NUTS share (its refusals, the problem's record);
- :func:`check_walkers`: the walker count's rule (even, >= 2 x the free parameters);
- :func:`check_sampling`: priors on fixed or unknown parameters and the walker count, before any fit;
- :data:`SAMPLERS`: the sampler names;
- :func:`spec_from_fit_json`: a parameter spec warm-started at a fit result JSON's values.
"""

from ._api import SAMPLERS as SAMPLERS, check_sampling as check_sampling, spec_from_fit_json as spec_from_fit_json
from ._posterior import check_walkers as check_walkers
from ._priors import SampleError as SampleError
from ._store import ChainStore as ChainStore

__all__ = ["SAMPLERS", "ChainStore", "SampleError", "check_sampling", "check_walkers", "spec_from_fit_json"]
