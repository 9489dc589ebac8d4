"""Parameter posteriors with emcee: the fit's likelihood, priors, resumable HDF5 chains, diagnostics.

``sample(likelihood, priors, sampler=Emcee(...) | NUTS(...), out_dir=...)``, the
likelihood from :func:`brdfjax.fit.prepare` (and ``brdfjax sample
CONFIG --out DIR``) runs an emcee ``EnsembleSampler`` over the same weighted
log-space likelihood as :func:`brdfjax.fit.fit`, with per-parameter priors
(:class:`Prior`: uniform, log-uniform, normal, truncated normal; physical
bounds always enforced), the log-posterior evaluated for all walkers at once
by one jit-compiled vmapped JAX function (:class:`LogPosterior`), walkers
started around the least-squares optimum, the chain written to emcee's HDF5
backend as it is drawn (resumable), and convergence diagnostics
(acceptance, autocorrelation times, effective sample sizes).  See the
module docstrings of ``_posterior``, ``_priors`` and ``_chain``.
"""

from ._api import PosteriorResult as PosteriorResult, decimate_frame as decimate_frame, sample as sample
from ._chain import Diagnostics as Diagnostics, diagnose as diagnose, read_chain as read_chain
from ._posterior import LogPosterior as LogPosterior, build_log_posterior as build_log_posterior
from ._priors import PRIOR_KINDS as PRIOR_KINDS, Prior as Prior, SampleError as SampleError
from ._samplers import NUTS as NUTS, Emcee as Emcee
