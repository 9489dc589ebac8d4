"""``sample``: parameter posteriors of a fit problem with emcee (the Python API behind ``brdfjax sample``)."""

from __future__ import annotations

import importlib.metadata
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.detector import PixelGrid
from ..fit import FitResult, FrameData, Likelihood, TableData, fit, versions
from ..fit.internal import as_param, block_names, get_solver, prepare_problem, to_natural
from ..io import write_json_atomic
from ..io.fingerprint import array_digest, value_digest
from ._chain import Diagnostics, RunOutcome, diagnose, open_chain, run_chain
from ._nuts import NutsDiagnostics, nuts_diagnostics, open_nuts, run_nuts
from ._outputs import (
    model_at_points,
    plot_corner,
    plot_predictive,
    plot_trace,
    slice_columns,
    summarise,
)
from ._posterior import LogPosterior, build_log_posterior, check_walkers, default_walkers, start_ball
from ._priors import Prior, SampleError
from ._samplers import NUTS, Emcee, sampler_options

__all__ = [
    "sample",
    "PosteriorResult",
    "SAMPLERS",
    "check_sampling",
    "decimate_frame",
    "problem_fingerprint",
    "sampling_record",
    "start_from_fit_json",
    "spec_from_fit_json",
]

#: The samplers of ``sample(sampler=...)`` / ``[sample] sampler``.
SAMPLERS = ("emcee", "nuts")

#: Options of :func:`brdfjax.fit.prepare` among a fit's keyword arguments.
_PREPARE_KEYS = (
    "loss",
    "loss_scale",
    "initializer",
    "init_options",
    "floor",
    "precision",
    "allow_different_detectors",
    "use_footprint",
    "nuisance",
)


def decimate_frame(data: FrameData, step: int = 1, roi: tuple[int, int, int, int] | None = None) -> FrameData:
    """A frame on every ``step``-th point of its grid inside ``roi = (h0, h1, v0, v1)`` (seed pixel indices).

    A footprint is subsampled on the coarser spacing (centred, odd-sided).
    """
    if not (isinstance(step, int | np.integer) and step >= 1):
        raise SampleError(f"step must be a positive integer, got {step!r}")
    n_h = np.asarray(data.grid.n_h)
    n_v = np.asarray(data.grid.n_v)
    if roi is not None:
        h0, h1, v0, v1 = (int(x) for x in roi)
        cols = np.flatnonzero((n_h >= h0) & (n_h <= h1))
        rows = np.flatnonzero((n_v >= v0) & (n_v <= v1))
        if not cols.size or not rows.size:
            raise SampleError(
                f"frame '{data.name}': roi {tuple(roi)} contains no pixel of its grid (columns {n_h.min()}..{n_h.max()}, "
                f"rows {n_v.min()}..{n_v.max()})"
            )
    else:
        cols, rows = np.arange(n_h.size), np.arange(n_v.size)
    cols, rows = cols[::step], rows[::step]
    if step == 1 and roi is None:
        return data
    grid = PixelGrid(n_h[cols], n_v[rows])
    ix = np.ix_(rows, cols)
    brdf = np.asarray(data.brdf)[ix]
    sig = np.asarray(data.sigma_rel)
    sig = sig[ix] if sig.ndim == 2 else sig
    mask = None if data.mask is None else np.asarray(data.mask)[ix]
    fp = data.footprint
    if fp is not None and step > 1:
        k = np.asarray(fp)
        cy, cx = k.shape[0] // 2, k.shape[1] // 2
        ry, rx = cy // step, cx // step
        fp = k[cy - ry * step : cy + ry * step + 1 : step, cx - rx * step : cx + rx * step + 1 : step]
    return FrameData(
        brdf=brdf,
        sigma_rel=sig,
        theta_i=data.theta_i,
        detector=data.detector,
        grid=grid,
        mask=mask,
        phi_ref=data.phi_ref,
        wavelength=data.wavelength,
        footprint=fp,
        name=data.name,
        systematics=data.systematics,
    )


#: Options of the fit that define the likelihood (the start-value initialiser does not).
_LIKELIHOOD_KEYS = ("loss", "loss_scale", "floor", "precision", "allow_different_detectors", "use_footprint")


def _grid_text(b: FrameData) -> str:
    n_h, n_v = np.asarray(b.grid.n_h), np.asarray(b.grid.n_v)
    st = lambda a: int(np.min(np.diff(a))) if a.size > 1 else 1  # noqa: E731
    return (
        f"{n_h.size} x {n_v.size} points, n_h {int(n_h[0])}..{int(n_h[-1])} step {st(n_h)}, "
        f"n_v {int(n_v[0])}..{int(n_v[-1])} step {st(n_v)}; " + array_digest(np.concatenate([n_h, n_v]))
    )


def problem_fingerprint(
    model: Any,
    blocks: Sequence[FrameData | TableData],
    post: LogPosterior,
    layout: Any,
    fit_kwargs: Mapping[str, Any],
    *,
    n_walkers: int,
    seed: int,
    ball: float,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Everything that defines a sampling problem, component by component (:mod:`brdfjax.io.fingerprint`).

    The model (its class, terms and every fixed value), each free
    parameter (unit, physical bounds) and its prior, each data block's
    values, uncertainties, mask and grid (after ``step``/``roi``), the
    likelihood's settings (loss, floor, precision, footprint) and the
    sampler's (walkers, seed, start ball); ``extra`` adds the caller's
    components (the CLI: data files' checksums and the config's data
    settings).  Not in it: ``n_steps`` (a resume extends the chain),
    ``burn``, ``thin`` and the figures, which only change the summary.
    """
    fp: dict[str, Any] = {
        "model.structure": value_digest(f"{type(model).__name__}: {sorted(model.parameter_units())}"),
    }
    for e in layout.fixed:
        fp[f"fixed.{e.name}"] = float(e.value)
    for name, unit, lo, hi in zip(post.names, post.units, post.lower, post.upper):
        fp[f"free.{name}"] = f"{unit or '1'} [{float(lo):.9g}, {float(hi):.9g}]"
    for name, text in post.describe_priors().items():
        fp[f"priors.{name}"] = text
    for b in blocks:
        key = f"data[{b.name}]"
        fp[f"{key}.brdf"] = array_digest(np.asarray(b.brdf))
        fp[f"{key}.sigma_rel"] = array_digest(None if b.sigma_rel is None else np.asarray(b.sigma_rel))
        fp[f"{key}.mask"] = array_digest(b.usable())
        if isinstance(b, FrameData):
            fp[f"{key}.grid"] = _grid_text(b)
            fp[f"{key}.footprint"] = array_digest(None if b.footprint is None else np.asarray(b.footprint))
            fp[f"{key}.detector"] = value_digest(repr(b.detector))
        else:
            fp[f"{key}.directions"] = array_digest(
                np.stack([np.broadcast_to(np.asarray(getattr(b, k), np.float64), np.shape(b.brdf))
                          for k in ("theta_i", "phi_i", "theta_s", "phi_s")])
            )
    for k in _LIKELIHOOD_KEYS:
        v = fit_kwargs.get(k)
        fp[f"likelihood.{k}"] = value_digest(v if v is None or isinstance(v, bool | int | float | str) else repr(v))
    fp["sampler.n_walkers"] = int(n_walkers)
    fp["sampler.seed"] = int(seed)
    fp["sampler.ball"] = float(ball)
    fp.update(dict(extra or {}))
    return fp


def check_sampling(
    model: Any,
    data: FrameData | TableData | Sequence[FrameData | TableData],
    params: Mapping[str, Any] | None = None,
    *,
    priors: Mapping[str, Prior] | None = None,
    n_walkers: int | None = None,
    fit_kwargs: Mapping[str, Any] | None = None,
    step: int | None = None,
    roi: tuple[int, int, int, int] | None = None,
) -> int:
    """Check a sampling problem before any fit: priors on unknown or fixed parameters, the walker count.

    Returns the number of walkers (the default when ``n_walkers`` is
    ``None``); raises :class:`SampleError` (or the fit's input errors).  A
    prior that excludes the start can only be checked once the start (the
    fit's optimum) is known; :func:`sample` does that before writing anything.
    """
    fit_kwargs = dict(fit_kwargs or {})
    blocks = [data] if isinstance(data, FrameData | TableData) else list(data)
    if step is not None or roi is not None:
        blocks = [decimate_frame(b, step or 1, roi) if isinstance(b, FrameData) else b for b in blocks]
    solver = get_solver(fit_kwargs.get("solver", "levenberg_marquardt"), **dict(fit_kwargs.get("solver_options") or {}))
    prep_kw = {k: fit_kwargs[k] for k in _PREPARE_KEYS if k in fit_kwargs and k not in ("initializer", "init_options")}
    # No auto-initialisation here (it can cost a fit's worth of model evaluations): 'auto' starts stand in as 1.
    spec = {k: (replace(as_param(k, v), value=None) if _is_auto(k, v) else v) for k, v in dict(params or {}).items()}
    prep = prepare_problem(model, blocks, spec, solver=solver, **prep_kw)
    post = build_log_posterior(prep, priors, loss=fit_kwargs.get("loss", "linear"))
    nw = default_walkers(post.ndim) if n_walkers is None else n_walkers
    check_walkers(nw, post.ndim)
    return nw


def _is_auto(k: str, v: Any) -> bool:
    p = as_param(k, v)
    return isinstance(p.value, str) and p.value == "auto"


def sampling_record(blocks: Sequence[FrameData | TableData], step: int | None, roi: Any) -> dict[str, Any]:
    """What the sampler saw: per block its grid (step, extent, shape) and usable points."""
    out = []
    for b in blocks:
        if isinstance(b, FrameData):
            n_h, n_v = np.asarray(b.grid.n_h), np.asarray(b.grid.n_v)
            st = int(np.min(np.diff(n_h))) if n_h.size > 1 else 1
            out.append(
                {
                    "name": b.name,
                    "kind": "frame",
                    "grid_step_px": st,
                    "extent": [int(n_h.min()), int(n_h.max()), int(n_v.min()), int(n_v.max())],
                    "grid_shape": list(b.grid.shape),
                    "n_points": int(b.usable().sum()),
                }
            )
        else:
            out.append({"name": b.name, "kind": "table", "n_points": int(b.usable().sum())})
    return {
        "step": step,
        "roi": None if roi is None else [int(x) for x in roi],
        "blocks": out,
        "n_points": int(sum(d["n_points"] for d in out)),
    }


def start_from_fit_json(data: Mapping[str, Any], names: Sequence[str], units: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Start values and sigmas (stored units) of ``names`` from a fit result JSON (natural units)."""
    params = data.get("parameters")
    if not isinstance(params, Mapping):
        raise SampleError("the fit result has no 'parameters' table (expected the JSON of brdfjax fit / FitResult.to_json)")
    x, s = [], []
    for n, u in zip(names, units):
        if n not in params or not isinstance(params[n], Mapping) or params[n].get("value") is None:
            raise SampleError(
                f"the fit result gives no value for the free parameter '{n}' (it has: {', '.join(params)}); "
                "run the fit with the same [params], or leave the result out to fit first"
            )
        f = to_natural(u)
        x.append(float(params[n]["value"]) / f)
        sg = params[n].get("sigma")
        s.append(math.nan if sg is None else float(sg) / f)
    return np.array(x), np.array(s)


def fit_json_values(start_json: Mapping[str, Any]) -> dict[str, float]:
    """The free parameters' values of a fit result JSON (brdfjax fit's ``result.json``), in stored units."""
    values = {}
    for k, p in (start_json.get("parameters") or {}).items():
        if isinstance(p, Mapping) and p.get("free") and p.get("value") is not None:
            unit = p.get("unit", "")
            values[k] = float(p["value"]) * (math.pi / 180 if unit == "deg" else 1.0)
    return values


def _spec_from_result(spec: Mapping[str, Any], values: Mapping[str, float], block_names: Sequence[str],
                      every: bool = False) -> dict[str, Any]:
    """The parameter spec with each free 'auto' start (``every``: each free start) replaced by the fit's value
    (no second auto-init)."""
    out = dict(spec)
    for k, v in spec.items():
        p = as_param(k, v)
        if not (p.free and (every or (isinstance(p.value, str) and p.value == "auto"))):
            continue
        if k in values:
            out[k] = replace(p, value=float(values[k]))
        else:
            per = [f"{k}[{b}]" for b in block_names]
            have = [values.get(n) for n in per]
            if all(h is not None for h in have):
                out[k] = replace(p, value=[float(h) for h in have])
    return out


def spec_from_fit_json(spec: Mapping[str, Any], start_json: Mapping[str, Any], block_names: Sequence[str]) -> dict[str, Any]:
    """The parameter spec with every free start at a fit result JSON's value (a warm start of the same fit)."""
    return _spec_from_result(spec, fit_json_values(start_json), block_names, every=True)


@dataclass(eq=False)
class PosteriorResult:
    """A posterior study's chain, diagnostics and summary (``summary`` is posterior.json's content)."""

    posterior: LogPosterior
    chain: np.ndarray  # (n_steps, n_walkers, p) stored units
    log_prob: np.ndarray  # (n_steps, n_walkers)
    diagnostics: Diagnostics
    summary: dict[str, Any]
    run: RunOutcome
    fit_result: FitResult | None = None
    files: dict[str, str] = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        return self.posterior.names

    def flat(self, natural: bool = False) -> np.ndarray:
        """Samples after burn-in (and thinning), ``(n, p)``; natural units (degrees) when asked."""
        d = self.diagnostics
        c = self.chain[d.burn :: d.thin].reshape(-1, self.chain.shape[2])
        return self.posterior.to_natural(c) if natural else c

    def interval(self, name: str, level: float = 0.68) -> tuple[float, float]:
        """Equal-tailed credible interval of ``name`` (stored units)."""
        i = self.names.index(name)
        lo = 50 - 50 * level
        return tuple(float(v) for v in np.percentile(self.flat()[:, i], [lo, 100 - lo]))

    def correlation(self) -> np.ndarray:
        return np.corrcoef(self.flat().T) if len(self.names) > 1 else np.ones((1, 1))

    def write(self, out_dir: str | Path, figures: bool = True) -> dict[str, str]:
        """Write ``posterior.json`` (the summary) and, with ``figures``, ``corner.png`` into ``out_dir``
        (atomically; a run with ``sample(..., out_dir=...)`` has written these already, with its chain)."""
        out = Path(out_dir)
        files = {}
        if figures:
            files["corner"] = str(plot_corner(out / "corner.png", self.flat(natural=True), self.names,
                                              self.posterior.natural_units, None))
        write_json_atomic(out / "posterior.json", self.summary, allow_nan=False)
        files["summary"] = str(out / "posterior.json")
        self.files.update(files)
        return files


def sample(
    model: Any,
    data: FrameData | TableData | Sequence[FrameData | TableData] | Mapping[str, Prior] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    priors: Mapping[str, Prior] | None = None,
    n_walkers: int | None = None,
    n_steps: int = 1000,
    out_dir: str | Path | None = None,
    resume: bool = False,
    start: FitResult | Mapping[str, Any] | None = None,
    fit_kwargs: Mapping[str, Any] | None = None,
    seed: int = 0,
    ball: float = 0.1,
    burn: int | str = "auto",
    thin: int = 1,
    stop_when_converged: bool = False,
    check_every: int = 100,
    progress: bool = False,
    figures: bool = True,
    predictive_draws: int = 100,
    step: int | None = None,
    roi: tuple[int, int, int, int] | None = None,
    vectorize: bool = True,
    log: Any = None,
    extra_record: Mapping[str, Any] | None = None,
    extra_fingerprint: Mapping[str, Any] | None = None,
    sampler: str | Emcee | NUTS = "emcee",
    n_chains: int = 4,
    n_warmup: int = 500,
    log_weights: bool | None = None,
    start_covariance: bool | None = None,
) -> PosteriorResult:
    """Sample the posterior of ``params`` (as for :func:`brdfjax.fit.fit`) given ``data`` with emcee.

    ``sample(likelihood, priors, sampler=Emcee(...) | NUTS(...), out_dir=...)`` samples a
    :class:`~brdfjax.fit.Likelihood` built by :func:`brdfjax.fit.prepare` (the data, params and the
    likelihood's options are then the likelihood's; the sampler's options are on the sampler object).
    ``sample(model, data, params, priors=..., fit_kwargs=...)`` is the older spelling (``fit_kwargs``
    is deprecated: build the likelihood instead).

    The likelihood is the fit's (same residuals, weights and loss, from
    ``fit_kwargs``: loss, loss_scale, floor, precision, use_footprint, ...);
    ``priors`` (parameter name -> :class:`Prior`, stored units) multiply it,
    and the physical bounds always apply.  Walkers start in a ball of
    ``ball`` fit sigmas around the least-squares optimum: ``start`` (a
    :class:`~brdfjax.fit.FitResult` or its JSON dict), else a fit run here.
    ``step``/``roi`` decimate the frames for sampling (recorded in the
    summary).  With ``out_dir`` the chain goes to ``out_dir/chain.h5`` as it
    is drawn (``resume=True`` continues it to ``n_steps`` in total) and
    ``posterior.json``, ``corner.png``, ``trace.png`` and
    ``predictive_<frame>.png`` are written there.

    The chain file records the problem's fingerprint
    (:func:`problem_fingerprint`, plus ``extra_fingerprint``); a resume of a
    chain drawn under another problem (a prior, a data value, the grid, a
    sigma setting, the walkers ...) is refused naming what differs.  A run
    that fails or is interrupted before its first step leaves no chain file.
    ``sampler``: ``"emcee"`` (the affine-invariant ensemble, ``n_walkers``)
    or ``"nuts"`` (blackjax's No-U-Turn sampler: ``n_chains`` independent
    chains after ``n_warmup`` steps of window adaptation; needs blackjax;
    :mod:`brdfjax.sample._nuts`), same outputs and resume guarantees.

    ``log_weights``: the samplers move the weights (free parameters named
    ``rho*`` with a lower bound >= 0) as their logarithms, with the
    log-Jacobian in the density (the same posterior): a flux-scale nuisance
    parameter multiplies them, so in their logarithms the ridge it forms is
    straight.  ``start_covariance``: emcee's walkers (NUTS's chains) start
    in a ball of ``ball`` times the fit's full covariance (its Cholesky
    factor), not of its sigmas: on the ridge, not across it.  Both default
    (``None``) to on when the likelihood has nuisance parameters.  Outputs
    are in stored units either way.
    """
    if isinstance(model, Likelihood):
        if params is not None or fit_kwargs is not None:
            raise SampleError("sample(likelihood, priors): params and fit_kwargs are the likelihood's; "
                              "set them with brdfjax.fit.prepare(...) or likelihood.replace(...)")
        if data is not None:
            if priors is not None:
                raise SampleError("sample(likelihood, priors) got priors twice (positionally and as priors=)")
            priors = data
        model, data, params, fit_kwargs = model.model, model.blocks, model.params, model.options()
    elif data is None:
        raise SampleError("sample(model, data, params): data is missing (or pass a Likelihood from brdfjax.fit.prepare)")
    elif fit_kwargs is not None:
        warnings.warn("sample(..., fit_kwargs=...) is deprecated: build the likelihood with brdfjax.fit.prepare(model, "
                      "data, params, **options) and call sample(likelihood, priors)", DeprecationWarning, stacklevel=2)
    if not isinstance(sampler, str):
        opts = sampler_options(sampler)
        given = {"n_walkers": (n_walkers, None), "n_steps": (n_steps, 1000), "ball": (ball, 0.1), "burn": (burn, "auto"),
                 "thin": (thin, 1), "stop_when_converged": (stop_when_converged, False), "check_every": (check_every, 100),
                 "vectorize": (vectorize, True), "n_chains": (n_chains, 4), "n_warmup": (n_warmup, 500)}
        clash = [k for k, (v, d) in given.items() if v != d]
        if clash:
            raise SampleError(f"{', '.join(clash)} belong on the sampler object ({type(sampler).__name__}(...)), "
                              "not on sample()")
        sampler = opts.pop("sampler")
        n_steps, ball, burn, thin = opts["n_steps"], opts["ball"], opts["burn"], opts["thin"]
        if sampler == "emcee":
            n_walkers, stop_when_converged = opts["n_walkers"], opts["stop_when_converged"]
            check_every, vectorize = opts["check_every"], opts["vectorize"]
        else:
            n_chains, n_warmup = opts["n_chains"], opts["n_warmup"]
    t_start = time.perf_counter()
    say = log or (lambda msg: None)
    fit_kwargs = dict(fit_kwargs or {})
    spec = dict(params or {})
    blocks = [data] if isinstance(data, FrameData | TableData) else list(data)
    if step is not None or roi is not None:
        blocks = [decimate_frame(b, step or 1, roi) if isinstance(b, FrameData) else b for b in blocks]
    names_b = block_names(blocks)
    if thin < 1:
        raise SampleError(f"thin must be a positive integer, got {thin!r}")
    if n_steps < 1:
        raise SampleError(f"n_steps must be a positive integer, got {n_steps!r}")
    if sampler not in SAMPLERS:
        raise SampleError(f"unknown sampler {sampler!r}; known: {', '.join(map(repr, SAMPLERS))}")
    if sampler == "nuts" and not (isinstance(n_chains, int | np.integer) and n_chains >= 1 and n_warmup >= 1):
        raise SampleError(f"NUTS needs n_chains >= 1 and n_warmup >= 1, got {n_chains!r} and {n_warmup!r}")

    # the least-squares optimum
    fit_res: FitResult | None = None
    start_json: Mapping[str, Any] | None = None
    if isinstance(start, FitResult):
        fit_res = start
    elif isinstance(start, Mapping):
        start_json = start
    elif start is not None:
        raise SampleError(f"start must be a FitResult or its JSON dict, got {type(start).__name__}")
    chain_path = None if out_dir is None else Path(out_dir) / "chain.h5"
    resuming = bool(resume and chain_path is not None and chain_path.exists())
    if chain_path is not None and chain_path.exists() != bool(resume):
        open_chain(chain_path, (), 0, resume=resume)  # raises the message (before any fitting)
    if not resuming:  # priors on fixed or unknown parameters and the walker count, before any fit
        check_sampling(model, blocks, spec, priors=priors, n_walkers=n_walkers, fit_kwargs=fit_kwargs)
    if fit_res is None and start_json is None and not resuming:
        say("no fit result given: fitting first (the walkers start around the least-squares optimum)")
        fit_res = fit(model, blocks, spec, **fit_kwargs)
        say(fit_res.summary())
        if not fit_res.converged:
            say(f"warning: the fit did not converge ({fit_res.message}); sampling from where it stopped")
    if fit_res is not None:
        values = {k: p.value for k, p in fit_res.parameters.items() if p.free}
    elif start_json is not None:
        values = fit_json_values(start_json)
    else:
        values = {}
    spec_start = _spec_from_result(spec, values, names_b)

    solver = get_solver(fit_kwargs.get("solver", "levenberg_marquardt"), **dict(fit_kwargs.get("solver_options") or {}))
    prep = prepare_problem(model, blocks, spec_start, solver=solver, **{k: fit_kwargs[k] for k in _PREPARE_KEYS if k in fit_kwargs})
    post = build_log_posterior(prep, priors, loss=fit_kwargs.get("loss", "linear"))
    has_nuisance = prep.nuisance is not None
    use_log = has_nuisance if log_weights is None else bool(log_weights)
    use_cov = has_nuisance if start_covariance is None else bool(start_covariance)
    if use_log:
        post = post.with_log(weight_mask(post))
    ndim = post.ndim
    nw = (default_walkers(ndim) if n_walkers is None else n_walkers) if sampler == "emcee" else int(n_chains)
    if sampler == "emcee":
        check_walkers(nw, ndim)

    if fit_res is not None:
        x0 = np.array([fit_res.value(n) for n in post.names])
        s0 = np.array([np.nan if fit_res.sigma(n) is None else fit_res.sigma(n) for n in post.names])
    elif start_json is not None:
        if prep.nuisance is not None:  # a fit without the nuisance parameters: they start at 0, their prior's sigma
            pars = dict(start_json.get("parameters") or {})
            for n, sg in zip(prep.nuisance.names, prep.nuisance.prior_sigma):
                pars.setdefault(n, {"value": 0.0, "sigma": float(sg), "unit": "1", "free": True})
            start_json = {**start_json, "parameters": pars}
        x0, s0 = start_from_fit_json(start_json, post.names, post.units)
    else:
        x0 = np.array([e.x0 for e in prep.layout.free])
        s0 = np.full(ndim, np.nan)

    fingerprint = problem_fingerprint(
        model, blocks, post, prep.layout, fit_kwargs, n_walkers=nw, seed=seed, ball=ball,
        extra={**dict(extra_fingerprint or {}), "sampler": sampler, **({"n_warmup": int(n_warmup)} if sampler == "nuts" else {}),
               **({"sampler.log": ", ".join(n for n, m in zip(post.names, post.logged) if m)} if post.logged.any() else {}),
               **({"sampler.start": "covariance"} if use_cov else {})},
    )
    cov = _fit_covariance(fit_res, start_json, post.names, s0)
    chol = _cholesky(cov) if use_cov else None
    if sampler == "emcee":
        chain, lp, diag, outcome, seed = _run_emcee(
            post, chain_path, x0, s0, nw, ball, seed, resume, n_steps, vectorize, progress, stop_when_converged,
            check_every, burn, thin, say, fingerprint, chol,
        )
    else:
        chain, lp, diag, outcome = _run_nuts_sampler(
            post, chain_path, x0, s0, cov, nw, ball, seed, resume,
            n_steps, n_warmup, stop_when_converged, check_every, burn, thin, say, fingerprint, chol,
        )
    flat = chain[diag.burn :: diag.thin].reshape(-1, ndim)
    flat_nat = post.to_natural(flat)
    i_map = np.unravel_index(int(np.argmax(lp)), lp.shape)
    x_map = chain[i_map]
    f = post.factors
    fit_x = x0 * f if (fit_res is not None or start_json is not None) else None
    fit_s = s0 * f if fit_x is not None else None
    priors_text = post.describe_priors()
    spec_n = prep.nuisance
    if spec_n is not None:
        for name, sg in zip(spec_n.names, spec_n.prior_sigma):
            priors_text[name] = f"normal(0, {sg:.4g}) in the likelihood (nuisance)"
    params_summary = summarise(flat_nat, post.names, post.natural_units, diag.tau, diag.ess, x_map * f, fit_x, fit_s, priors_text)
    if spec_n is not None:
        _add_conditional(params_summary, flat_nat, post.names, spec_n.names)
    ll_fit = float(post.log_likelihood(x0[None, :])[0])
    corr = np.corrcoef(flat.T) if ndim > 1 else np.ones((1, 1))
    summary: dict[str, Any] = {
        "parameters": params_summary,
        "sampler": sampler,
        "n_steps": int(diag.n_steps),
        "n_walkers": int(nw),
        "n_dim": int(ndim),
        "burn": int(diag.burn),
        "thin": int(diag.thin),
        "n_samples": int(flat.shape[0]),
        "acceptance_fraction_mean": float(diag.acceptance_fraction_mean),
        "acceptance_fraction": [float(a) for a in diag.acceptance_fraction],
        "converged": bool(diag.converged),
        "stopped_when_converged": bool(outcome.stopped_converged),
        "interrupted": bool(outcome.interrupted),
        "tau_max": None if not np.any(np.isfinite(diag.tau)) else float(np.nanmax(diag.tau)),
        "chain_shorter_than_50_tau": list(diag.short),
        "warnings": list(diag.warnings),
        "map": {
            "log_posterior": float(lp[i_map]),
            "log_likelihood": float(post.log_likelihood(x_map[None, :])[0]),
            "values": {n: float(v) for n, v in zip(post.names, x_map * f)},
        },
        "least_squares": {
            "values": None if fit_x is None else {n: float(v) for n, v in zip(post.names, fit_x)},
            "log_likelihood": ll_fit,
            "chi2": -2.0 * ll_fit,
        },
        "correlation": {"names": list(post.names), "matrix": [[float(v) for v in row] for row in np.atleast_2d(corr)]},
        "likelihood": {
            "loss": post.loss, "n_points": post.n_points,
            "form": "log L = -sum rho(r), r = (log(f + floor) - log d) / sigma_rel"
            + ("; over the points without uncertainties -(N/2) ln sum r^2 (the log-normal noise profiled out)"
               if post.sigma_estimated else ""),
            "sigma_estimated": post.sigma_estimated,
            "noise": None if fit_res is None else dict(fit_res.noise),
        },
        "sampling": {**sampling_record(blocks, step, roi), **dict(extra_record or {})},
        "seed": int(seed),
        "ball_sigma": float(ball),
        "start": "fit covariance (Cholesky)" if chol is not None else "fit sigmas (diagonal)",
        "sampled_as_log": [n for n, m in zip(post.names, post.logged) if m],
        "vectorized": bool(vectorize),
        "wall_s": None,
        "run_wall_s": float(outcome.wall_s),
        "new_steps": int(outcome.new_steps),
        "versions": {**versions(), **_versions()},
    }
    if isinstance(diag, NutsDiagnostics):
        summary["nuts"] = {
            "n_chains": int(nw),
            "n_warmup": int(n_warmup),
            "rhat": {n: _finite(r) for n, r in zip(post.names, diag.rhat)},
            "rhat_max": _finite(np.nanmax(diag.rhat)) if np.any(np.isfinite(diag.rhat)) else None,
            "divergences": int(diag.divergences),
            "mean_leapfrog_steps": _finite(diag.mean_leapfrog),
            "step_size": [float(h) for h in diag.step_size],
            "converged_rule": "R-hat < 1.01 for every parameter and kept chain > 50 tau (tau = n_chains m / ESS)",
        }
    if spec_n is not None:
        summary["nuisance"] = {
            "parameters": spec_n.describe(),
            "note": "each parameter's std/q16/q84 is marginalised over the nuisance parameters (systematics "
            "included); sigma_conditional is its std with the nuisance parameters held fixed (Gaussian "
            "conditioning of the posterior covariance): the data's own uncertainty",
        }
    result = PosteriorResult(post, chain, lp, diag, summary, outcome, fit_res)
    if out_dir is not None:
        out = Path(out_dir)
        files = {"chain": str(chain_path)}
        if figures:
            truths = fit_x
            files["corner"] = str(plot_corner(out / "corner.png", flat_nat, post.names, post.natural_units, truths))
            files["trace"] = str(plot_trace(out / "trace.png", chain * f, post.names, post.natural_units, diag.burn))
            files.update(_predictive(out, post, blocks, flat, predictive_draws, seed))
        summary["files"] = {k: Path(v).name for k, v in files.items()}
        summary["wall_s"] = time.perf_counter() - t_start
        write_json_atomic(out / "posterior.json", summary, allow_nan=False)  # strict JSON: NaN is not JSON
        files["summary"] = str(out / "posterior.json")
        result.files = files
    else:
        summary["wall_s"] = time.perf_counter() - t_start
    return result


def _fit_covariance(fit_res: FitResult | None, start_json: Mapping[str, Any] | None, names: Sequence[str],
                    s0: np.ndarray) -> np.ndarray | None:
    """The fit's covariance of ``names`` (stored units), from a FitResult or its JSON's correlation; None if unknown."""
    if fit_res is not None and tuple(fit_res.free_names) == tuple(names):
        return np.asarray(fit_res.covariance, np.float64)
    corr = (start_json or {}).get("correlation") or {}
    if list(corr.get("names") or []) == list(names):
        c = np.array([[np.nan if v is None else v for v in row] for row in corr["matrix"]], np.float64)
        return c * np.outer(s0, s0)
    return None


def _finite(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _add_conditional(summary: dict[str, Any], flat: np.ndarray, names: Sequence[str], nuisance: Sequence[str]) -> None:
    """Each physical parameter's std with the nuisance parameters fixed (Gaussian conditioning), beside the marginal."""
    j = [i for i, n in enumerate(names) if n in nuisance]
    k = [i for i, n in enumerate(names) if n not in nuisance]
    if not j or not k or flat.shape[0] < len(names) + 2:
        return
    c = np.cov(flat.T)
    cond = c[np.ix_(k, k)] - c[np.ix_(k, j)] @ np.linalg.pinv(c[np.ix_(j, j)]) @ c[np.ix_(j, k)]
    for a, i in enumerate(k):
        summary[names[i]]["sigma_conditional"] = _finite(np.sqrt(max(cond[a, a], 0.0)))
        summary[names[i]]["sigma_marginal"] = _finite(np.sqrt(c[i, i]))


def weight_mask(post: LogPosterior) -> np.ndarray:
    """The weights (free parameters whose base is named ``rho*``, lower bound >= 0): what a flux scale multiplies."""
    return np.array([b.split(".")[-1].startswith("rho") and float(lo) >= 0 for b, lo in zip(post.bases, post.lower)], bool)


def _cholesky(cov: np.ndarray | None) -> np.ndarray | None:
    if cov is None or not np.all(np.isfinite(cov)):
        return None
    try:
        return np.linalg.cholesky(np.asarray(cov, np.float64))
    except np.linalg.LinAlgError:
        return None


def _run_emcee(post, chain_path, x0, s0, nw, ball, seed, resume, n_steps, vectorize, progress, stop_when_converged,
               check_every, burn, thin, say, fingerprint, chol=None):
    meta = {
        "units": list(post.units),
        "seed": int(seed),
        "n_walkers": int(nw),
        "ball": float(ball),
        "priors": post.describe_priors(),
    }
    p0 = None
    if not resume:  # the start is checked before the chain file exists: a refusal leaves nothing behind
        p0 = post.to_sampler(start_ball(post, x0, s0, nw, ball, np.random.default_rng(seed), chol=chol))
    backend, info = open_chain(chain_path, post.names, nw, resume=resume, meta=meta, fingerprint=fingerprint)
    created = chain_path is not None and info is None
    if info is not None and info.iteration == 0:
        p0 = post.to_sampler(start_ball(post, x0, s0, nw, ball, np.random.default_rng(seed), chol=chol))
    elif info is not None:
        say(f"resuming {chain_path}: {info.iteration} steps present, running to {n_steps}")
    # the chain file holds the sampler's coordinates (log of the weights when post.logged)
    log_prob = post.sampler_log_prob if vectorize else post.sampler_log_prob_one
    try:
        outcome = run_chain(
            log_prob,
            backend,
            p0,
            n_steps,
            seed=seed,
            vectorize=vectorize,
            progress=progress,
            stop_when_converged=stop_when_converged,
            check_every=check_every,
        )
    except BaseException:
        if created and int(getattr(backend, "iteration", 0)) == 0:
            Path(chain_path).unlink(missing_ok=True)  # failed before its first step: nothing to resume, nothing left
        raise
    if outcome.iterations == 0:
        if created:
            Path(chain_path).unlink(missing_ok=True)
        raise SampleError("the run was interrupted before the first step was saved; nothing was kept")
    chain = post.from_sampler(backend.get_chain())
    # the log-density of the sampler's coordinates includes the log-Jacobian; report the posterior of x
    lp = backend.get_log_prob() - np.sum(np.log(chain[..., post.logged]), axis=-1)
    diag = diagnose(backend, post.names, burn=burn, thin=thin, check_every=check_every)
    if outcome.stopped_converged:
        diag = Diagnostics(**{**diag.__dict__, "converged": True})
    return chain, lp, diag, outcome, seed


def _whitening(x0: np.ndarray, s0: np.ndarray, cov: np.ndarray | None) -> np.ndarray:
    """``L`` with ``x = x0 + L z``: the Cholesky factor of the fit's covariance, else its sigmas on the diagonal."""
    sig = np.asarray(s0, np.float64).copy()
    bad = ~(np.isfinite(sig) & (sig > 0))
    sig[bad] = np.where(x0[bad] != 0, 1e-3 * np.abs(x0[bad]), 1e-6)
    if cov is not None and not bad.any() and np.all(np.isfinite(cov)):
        try:
            return np.linalg.cholesky(np.asarray(cov, np.float64))
        except np.linalg.LinAlgError:
            pass
    return np.diag(sig)


def _run_nuts_sampler(post, chain_path, x0, s0, cov, n_chains, ball, seed, resume, n_steps, n_warmup,
                      stop_when_converged, check_every, burn, thin, say, fingerprint, chol=None):
    # whitened in the sampler's coordinates y (log of the weights when post.logged): dy/dx = 1/x there
    g = np.where(post.logged, 1.0 / np.where(x0 != 0, x0, 1.0), 1.0)
    y0 = post.to_sampler(x0)
    scale = _whitening(y0, s0 * np.abs(g), None if cov is None else np.asarray(cov) * np.outer(g, g))
    X = None
    if not resume:  # the start is checked before the chain file exists: a refusal leaves nothing behind
        X = start_ball(post, x0, s0, n_chains, ball, np.random.default_rng(seed), chol=chol)
    existed = chain_path is not None and Path(chain_path).exists()
    nchain = open_nuts(chain_path, post.names, n_chains, resume=resume, center=y0, scale=scale, seed=seed, n_warmup=n_warmup,
                       fingerprint=fingerprint)
    created = chain_path is not None and not existed
    z0 = None
    if nchain.step_size is None:
        if X is None:
            X = start_ball(post, x0, s0, n_chains, ball, np.random.default_rng(seed), chol=chol)
        z0 = np.linalg.solve(nchain.scale, (post.to_sampler(X) - nchain.center).T).T
    else:
        say(f"resuming {chain_path}: {nchain.iteration} NUTS steps per chain present, running to {n_steps}")
    try:
        outcome = run_nuts(post, nchain, z0, n_steps, stop_when_converged=stop_when_converged, check_every=check_every, log=say)
    except BaseException:
        if created and nchain.iteration == 0:
            Path(chain_path).unlink(missing_ok=True)  # failed before its first step: nothing to resume, nothing left
        raise
    if nchain.iteration == 0:
        if created:
            Path(chain_path).unlink(missing_ok=True)
        raise SampleError("the run was interrupted before the first step was saved; nothing was kept")
    diag = nuts_diagnostics(nchain, post.names, burn=0 if burn == "auto" else burn, thin=thin)
    if outcome.stopped_converged:
        diag = NutsDiagnostics(**{**diag.__dict__, "converged": True})
    return nchain.rows["x"], nchain.rows["log_prob"], diag, outcome


def _versions() -> dict[str, str]:
    out = {}
    for pkg in ("emcee", "h5py", "corner", "blackjax"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _predictive(out: Path, post: LogPosterior, blocks, flat: np.ndarray, n_draws: int, seed: int) -> dict[str, str]:
    files = {}
    if n_draws <= 0 or not any(isinstance(b, FrameData) for b in blocks):
        return files
    rng = np.random.default_rng(seed + 1)
    X = flat[rng.choice(flat.shape[0], size=min(n_draws, flat.shape[0]), replace=False)]
    f_blocks = model_at_points(post, X)
    for k, b in enumerate(blocks[:4]):
        if not isinstance(b, FrameData):
            continue
        safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in b.name)
        files[f"predictive_{safe}"] = str(
            plot_predictive(out / f"predictive_{safe}.png", b, f_blocks[k], slice_columns(b), b.name, seed)
        )
    return files
