"""The ``[sample]`` table of a fit config: the posterior run that ``brdfjax sample CONFIG --out DIR`` makes.

The config is a fit config (:mod:`brdfjax.fit.config`: data, model, [params],
[fit]) plus an optional ``[sample]`` table (:class:`SampleSection`)::

    [sample]
    sampler = "emcee"               # or "nuts" (blackjax's No-U-Turn sampler; n_chains, n_warmup)
    n_walkers = 32                  # default max(32, 4 x free parameters); >= 2 x free parameters, even
    n_steps = 2000                  # total chain length (a resumed run continues to this length)
    burn = "auto"                   # discarded steps: an integer or "auto" (2 x the largest tau, <= half)
    thin = 1
    seed = 0
    ball = 0.1                      # walkers start within ball x the fit's sigma around the optimum
    stop_when_converged = false     # stop once the chain is > 50 tau and tau is stable to 1 %
    check_every = 100               # steps between convergence checks
    # fit_result = "runs/fit/result.json"   # the least-squares optimum (default: fit first)
    # step = 2                      # sample on every step-th point of the fit's grid ...
    # roi = [-60, 60, -60, 60]      # ... inside this region [h0, h1, v0, v1] (seed pixel indices)
    predictive_draws = 100          # posterior draws for the predictive bands
    # log_weights = true            # sample rho* as log rho (default: on with nuisance parameters)
    # start_covariance = true       # start along the fit's full covariance (default: on with nuisance parameters)

    [sample.priors]                 # keys and units as in [params] (angles <name>_deg, lengths <name>_m)
    rho_s3 = { kind = "uniform", lower = 100.0, upper = 600.0 }
    m1 = { kind = "log_uniform", lower = 5e-5, upper = 1e-3 }
    dtheta_deg = { kind = "normal", mu = 0.5, sigma = 0.1 }
    n1 = { kind = "truncated_normal", mu = 3.6, sigma = 0.5, lower = 1.0, upper = 6.0 }
    "phi_ref_deg[ti20]" = { kind = "normal", mu = 0.0, sigma = 0.05 }   # one frame's entry

Writes ``DIR/chain.h5`` (emcee's HDF5 backend, written as drawn),
``posterior.json``, ``corner.png``, ``trace.png``, ``predictive_<frame>.png``
and, when it fitted first, ``fit_result.json``.  ``--resume`` continues the
chain in ``DIR/chain.h5`` to ``n_steps`` (``--steps`` to extend it).  Ctrl-C
stops after the step in flight; what was drawn is kept and summarised.

The chain records the problem's fingerprint (the model, priors, data
values, grid, masks, sigma settings, sampler settings: see
:func:`brdfjax.sample.problem_fingerprint`) plus, from the config, the
checksum of every data file and every ``[data]`` setting; ``--resume``
refuses a chain drawn under any other problem and names what differs.

Exit codes (:mod:`brdfjax.runtime.errors`): 0 done, 130 interrupted (resumable), 2
bad config, priors, walkers, chain file, a resume of another problem or an
output folder that cannot be written (the message names the file and key),
1 an internal error.
"""

from __future__ import annotations

import re
from typing import Any, Literal

from pydantic import Field, field_validator

from ..config import (
    ConfigError,
    StrictModel,
    check_choice,
    parameter_keys,
    quoted_choices,
    unknown_key_message,
)
from ..fit.internal import FRAME_PARAMETERS
from ..io.fingerprint import file_digest, value_digest
from ._api import SAMPLERS
from ._priors import PRIOR_KINDS, Prior, SampleError
from ._samplers import NUTS, Emcee

__all__ = ["SampleSection", "PriorConfig", "priors_from_config", "config_fingerprint"]


#: The prior kinds a config may name (``flat`` is what a parameter without a prior gets).
_PRIOR_CHOICES = tuple(k for k in PRIOR_KINDS if k != "flat")


class PriorConfig(StrictModel):
    """One entry of ``[sample.priors]``, numbers in the key's unit (degrees for ``<name>_deg``)."""

    kind: str = Field(description=quoted_choices(_PRIOR_CHOICES))
    lower: float | None = Field(None, allow_inf_nan=True, description="lower end (uniform, log_uniform, truncated_normal)")
    upper: float | None = Field(None, allow_inf_nan=True, description="upper end (uniform, log_uniform, truncated_normal)")
    mu: float | None = Field(None, allow_inf_nan=True, description="mean (normal, truncated_normal)")
    sigma: float | None = Field(None, allow_inf_nan=True, description="standard deviation > 0 (normal, truncated_normal)")

    @field_validator("kind")
    @classmethod
    def _kind(cls, v: str) -> str:
        return check_choice("prior kind", v, _PRIOR_CHOICES)


class SampleSection(StrictModel):
    """The ``[sample]`` table of a fit config (see the module docstring)."""

    sampler: str = Field("emcee", description=f"the sampler: {quoted_choices(SAMPLERS)}")
    n_chains: int = Field(4, ge=1, description="NUTS: independent chains (R-hat needs >= 2)")
    n_warmup: int = Field(500, ge=1, description="NUTS: window-adaptation steps per chain (not kept)")
    n_walkers: int | None = Field(None, ge=2, description="number of walkers, even, >= 2 x the free parameters")
    n_steps: int = Field(2000, ge=1, description="total chain length in steps, >= 1")
    burn: int | Literal["auto"] = Field("auto", description="steps discarded as burn-in: an integer >= 0 or 'auto'")
    thin: int = Field(1, ge=1, description="keep every thin-th step of the chain for the summary")
    seed: int = Field(0, description="seed of the walkers' start and of the sampler")
    ball: float = Field(0.1, gt=0, description="start ball radius in units of the fit's sigma, > 0")
    stop_when_converged: bool = Field(False, description="stop early once converged (> 50 tau, tau stable to 1 %)")
    check_every: int = Field(100, ge=10, description="steps between convergence checks, >= 10")
    progress: bool = Field(True, description="show a progress bar")
    fit_result: str | None = Field(None, description="a fit result JSON (brdfjax fit's result.json), relative to the config")
    step: int | None = Field(None, ge=1, description="sample on every step-th point of the fit's grid")
    roi: list[int] | None = Field(None, min_length=4, max_length=4, description="[h0, h1, v0, v1] seed pixel indices")
    predictive_draws: int = Field(100, ge=0, description="posterior draws for the predictive bands (0: none)")
    log_weights: bool | None = Field(
        None, description="sample the weights (rho*) as logarithms (default: on with nuisance parameters)"
    )
    start_covariance: bool | None = Field(
        None, description="start from the fit's full covariance, not its sigmas (default: on with nuisance parameters)"
    )
    priors: dict[str, PriorConfig] = Field(default_factory=dict, description="parameter key -> prior table")

    def sampler_object(self, n_walkers: int | None = None, n_steps: int | None = None) -> Emcee | NUTS:
        """The sampler this table asks for, with its options (``n_walkers``, ``n_steps``: the command line's
        overrides)."""
        steps = self.n_steps if n_steps is None else n_steps
        common = dict(n_steps=steps, ball=self.ball, burn=self.burn, thin=self.thin)
        if self.sampler == "nuts":
            return NUTS(n_chains=self.n_chains, n_warmup=self.n_warmup, **common)
        return Emcee(n_walkers=self.n_walkers if n_walkers is None else n_walkers, stop_when_converged=self.stop_when_converged,
                     check_every=self.check_every, **common)

    @field_validator("sampler")
    @classmethod
    def _sampler(cls, v: str) -> str:
        return check_choice("sampler", v, SAMPLERS)

    @field_validator("burn")
    @classmethod
    def _burn(cls, v: Any) -> Any:
        if isinstance(v, int) and v < 0:
            raise ValueError(f"burn must be >= 0 or 'auto', got {v}")
        return v

    @field_validator("roi")
    @classmethod
    def _roi(cls, v: Any) -> Any:
        if v is not None and not (v[0] <= v[1] and v[2] <= v[3]):
            raise ValueError(f"{list(v)} is not ordered; expected [h0, h1, v0, v1] with h0 <= h1 and v0 <= v1")
        return v


_ENTRY = re.compile(r"^(?P<key>[^\[\]]+)\[(?P<block>[^\[\]]+)\]$")


def priors_from_config(source: str, sec: SampleSection, model: Any) -> dict[str, Any]:
    """``[sample.priors]`` -> {parameter name: Prior (stored units)}; unknown keys raise ConfigError."""
    keys = parameter_keys({**model.parameter_units(), **FRAME_PARAMETERS})
    out: dict[str, Any] = {}
    problems = []
    for key, p in sec.priors.items():
        m = _ENTRY.match(key)
        base_key, block = (m.group("key"), m.group("block")) if m else (key, None)
        if base_key not in keys:
            problems.append((f"sample.priors.{key}", "prior on unknown parameter: " + unknown_key_message(base_key, keys, "this model")))
            continue
        name, scale, _ = keys[base_key]
        full = name if block is None else f"{name}[{block}]"
        prior = Prior(p.kind, **{f: (None if getattr(p, f) is None else getattr(p, f) * scale) for f in ("lower", "upper", "mu", "sigma")})
        try:
            prior.check(full)
        except SampleError as e:
            problems.append((f"sample.priors.{key}", str(e)))
            continue
        out[full] = prior
    if problems:
        raise ConfigError(source, problems)
    return out


def config_fingerprint(cfg: Any) -> dict[str, Any]:
    """The config's part of a chain's fingerprint: every data file's checksum and every ``[data]`` setting."""
    fp: dict[str, Any] = {}
    d = cfg.data
    for f in d.frames:
        fp[f"file[{f}]"] = file_digest(cfg.resolve(f))
    for t in d.tables:
        fp[f"file[{t.path}]"] = file_digest(cfg.resolve(t.path))
    if d.manifest is not None:
        m = cfg.resolve(d.manifest)
        m = m / "manifest.toml" if m.is_dir() else m
        fp[f"file[{d.manifest}]"] = file_digest(m)
        for raw in sorted(m.parent.glob("*.exr")):
            fp[f"file[{raw.name}]"] = file_digest(raw)
    for k, v in d.model_dump(mode="json", exclude={"frames", "tables", "manifest"}).items():
        fp[f"config.data.{k}"] = value_digest(v)
    return fp
