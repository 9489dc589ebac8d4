"""``fit``: fit a brdfjax model to detector frames and/or goniometer tables.

The numerical work is pure JAX (:mod:`brdfjax.fit._problem`); this module sets
it up from NumPy inputs, runs the solver and turns the solution into a
:class:`~brdfjax.fit.FitResult`.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import math
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.terms import Model
from ..io.blocks import FrameData, TableData
from ._common import FitInputError, natural_unit, to_natural
from ._covariance import covariance
from ._likelihood import LIKELIHOOD_OPTIONS, Likelihood
from ._nuisance import NuisanceOptions, conditional_sigma
from ._params import Layout
from ._prepare import Prepared, prepare
from ._problem import (
    Problem,
    evaluate_call as evaluate,
    jacobian_call as jacobian,
    report_evaluations,
    with_loss,
    with_scale,
)
from ._residuals import DEFAULT_LOSS_SCALE, irls_weights, loss_id
from ._resolution import check_resolution
from ._result import BlockSummary, FitResult, ParameterEstimate
from ._solvers import AbstractSolver, SolveOutcome, SolveStatus, get_solver

__all__ = ["fit", "prepare", "versions", "FIRST_STAGES"]

#: First stages of a fit (``fit(first_stage=...)``): ``soft`` softens the log residuals below each
#: block's median datum; a loss name runs that robust loss first.
FIRST_STAGES = ("soft", "huber", "cauchy")

Data = FrameData | TableData


def versions() -> dict[str, str]:
    """Versions of Python and the packages a fit depends on."""
    out = {"python": platform.python_version()}
    for pkg in ("brdfjax", "jax", "jaxlib", "equinox", "optimistix", "lineax", "jaxopt", "numpy"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _difference_columns(problem: Problem, v: np.ndarray, columns: Sequence[int], central: bool = True) -> np.ndarray:
    """Columns of the Jacobian d r~ / d v at ``v``, by differences of the residuals.

    The residual program is compiled for every fit anyway (the residuals at the solution, called with ``v`` as
    this does); a Jacobian program compiled for the step scales alone would cost a compilation per model shape
    (1.7 s each: 39 of a diagnosis' 148 s) for numbers that only set the solver's units.  Central differences
    step by the cube root of the model's machine epsilon relative to the parameter (relative error about
    eps^(2/3): 4e-11 in float64, 2e-5 in float32); forward ones (``central=False``, one evaluation a column
    instead of two) by its square root (about eps^(1/2): 1.5e-8, 3e-4)."""
    v = np.asarray(v, np.float64)
    u = np.asarray(problem.u0, np.float64) + np.asarray(problem.scale, np.float64) * v

    def r(at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = jnp.asarray(at)  # as the fit's end evaluates it: one program for both
        raw, robust = evaluate(x, problem)
        out = np.array(robust, np.float64)
        if problem.nuisance is not None:  # the nuisance parameters' prior rows stay quadratic (Problem.robust)
            q = problem.nuisance.size
            out[out.size - q :] = np.asarray(raw, np.float64)[raw.size - q :]
        return out, np.asarray(x, np.float64)  # the point as represented

    eps = float(jnp.finfo(problem.u0.dtype).eps)  # the model's precision
    base = None if central else r(v)
    cols = []
    for i in columns:
        e = np.zeros(v.size)
        e[i] = eps ** (1 / 3 if central else 1 / 2) * max(1.0, abs(float(u[i]))) / float(problem.scale[i])
        (hi, x_hi), (lo, x_lo) = r(v + e), (r(v - e) if central else base)
        cols.append((hi - lo) / (x_hi[i] - x_lo[i]))
    return np.stack(cols, axis=1) if cols else np.zeros((0, 0))


def _scales(problem: Problem, layout: Layout, warnings: list[str]) -> np.ndarray:
    """Per-parameter step scale: 1 / (Jacobian column norm) at the start, capped by ``scale_max``."""
    n = len(layout.free)
    if n == 0:
        return np.ones(0)
    norms = np.linalg.norm(_difference_columns(problem, np.zeros(n), range(n), central=False), axis=0)
    caps = np.array([e.scale_max for e in layout.free])
    scale = np.empty(n)
    for i, e in enumerate(layout.free):
        if not np.isfinite(norms[i]):
            raise FitInputError(
                f"parameter '{e.name}': the Jacobian at the start is not finite; check the start values and data"
            )
        if norms[i] == 0:
            warnings.append(
                f"parameter '{e.name}' does not change the residuals at the start (zero Jacobian column): "
                "the data do not see it there; give a better start or fix it"
            )
            scale[i] = caps[i]
        else:
            scale[i] = min(1.0 / norms[i], caps[i])
    return scale


def _solve_stage(
    problem: Problem, layout: Layout, solver: AbstractSolver, u_start: np.ndarray, warnings: list[str]
) -> tuple[Problem, SolveOutcome]:
    """One solve from ``u_start``, with the step scales recomputed there."""
    n = len(layout.free)
    problem = with_scale(problem, u_start, np.ones(n))
    scale = _scales(problem, layout, warnings)
    problem = with_scale(problem, u_start, scale)
    box = None
    if solver.box_bounds:
        lo, hi = layout.box()
        with np.errstate(invalid="ignore"):
            box = ((lo - u_start) / scale, (hi - u_start) / scale)
    # The solver's coordinates are float64 whenever 64-bit JAX is on (optimistix keeps its own scalars in
    # the default float type); the model is still evaluated at the requested precision.
    outcome = solver.solve(problem, jnp.zeros(n, jnp.result_type(float)), box)
    return problem, outcome


def _segments(counts: Sequence[int]) -> list[tuple[int, int, int]]:
    """``(offset, count, block)`` of each block's points in the concatenated residuals."""
    offs = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    return [(int(offs[k]), int(c), k) for k, c in enumerate(counts)]


def _est_rss(problem: Problem, v: np.ndarray, est: Sequence[int]) -> tuple[float, int]:
    """Sum of squared ln residuals and their number over the blocks whose noise is estimated."""
    r = np.asarray(evaluate(jnp.asarray(v), problem)[0], np.float64)
    rss, n = 0.0, 0
    for o, c, k in _segments(problem.counts):
        if k in est:
            rk = r[o : o + c] / np.asarray(problem.blocks[k].inv_sigma, np.float64)
            rss += float(np.sum(rk**2))
            n += c
    return rss, n


def _estimate_noise(
    problem: Problem, layout: Layout, solver: AbstractSolver, outcome: SolveOutcome, est: Sequence[int],
    robust: bool, prep: "Prepared",
) -> tuple[Problem, SolveOutcome, dict[str, Any]]:
    """The log-normal scatter of tables without uncertainties, profiled out of the likelihood.

    Model: ``ln d = ln f + e``, ``e ~ N(0, s^2)`` with one unknown ``s`` shared by the blocks ``est``.
    Profiling ``s`` out gives ``-2 ln L = chi2_rest + N ln(RSS/N) + N`` at ``s^2 = RSS/N``; its optimum
    is a fixed point of "weight those blocks by 1/s, solve, re-estimate s", which is iterated here when
    it matters (other blocks with their own sigma, or a robust loss whose scale is in sigma); with the
    linear loss and only such blocks the unweighted solve is already the optimum.  The blocks'
    weights are left at ``1/s``, so residuals, zones and the covariance are in units of the estimate.
    """
    dtype = problem.u0.dtype
    base = {k: np.asarray(prep.inv_sigma[k], np.float64) for k in est}
    iterate = robust or len(est) < problem.n_blocks
    s, extra, n_iter = 1.0, 0, 0
    while n_iter < 8:
        n_iter += 1
        rss, n = _est_rss(problem, outcome.v, est)
        s_new = math.sqrt(rss / max(n, 1)) if rss > 0 else 1.0
        problem = eqx.tree_at(
            lambda p: tuple(p.blocks[k].inv_sigma for k in est), problem,
            tuple(jnp.asarray(base[k] / s_new, dtype) for k in est),
        )
        done = abs(s_new / s - 1.0) < 1e-3
        s = s_new
        if not iterate or done or not len(layout.free) or not np.all(np.isfinite(outcome.v)):
            break
        u_start = np.asarray(problem.u0, np.float64) + np.asarray(problem.scale, np.float64) * np.asarray(outcome.v)
        problem, new = _solve_stage(problem, layout, solver, u_start, [])
        extra += new.n_steps
        outcome = SolveOutcome(new.v, new.converged, new.status, new.message, outcome.n_steps + new.n_steps)
    rss, n = _est_rss(problem, outcome.v, est)
    return problem, outcome, {
        "estimated": True,
        "sigma_ln": s,
        "n_points": n,
        "rss_ln": rss,
        "blocks": [prep.names[k] for k in est],
        "iterations": n_iter,
        "method": "profile likelihood: -2 ln L = chi2_other + N ln(RSS/N) + N, s^2 = RSS/N (log-normal scatter of ln BRDF)",
        "extra_steps": extra,
    }


def _group_stats(b: TableData, usable: np.ndarray, r: np.ndarray, log_res: np.ndarray) -> tuple[dict[str, Any], ...]:
    ti = np.asarray(b.theta_i, float)[usable]
    key = np.round(np.degrees(ti), 4)
    out = []
    for t in np.unique(key):
        sel = key == t
        out.append(
            {
                "theta_i_deg": float(t),
                "n_points": int(sel.sum()),
                "chi2": float(np.sum(r[sel] ** 2)),
                "log_rms": float(np.sqrt(np.mean(log_res[sel] ** 2))),
            }
        )
    return tuple(out)


def _is_default(value: Any, default: Any) -> bool:
    return value is default or (type(value) is type(default) and value == default)


def fit(
    model: Model | Likelihood,
    data: Data | Sequence[Data] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    solver: str | AbstractSolver = "levenberg_marquardt",
    solver_options: Mapping[str, Any] | None = None,
    loss: str = "linear",
    loss_scale: float | None = None,
    first_stage: str | None = "soft",
    initializer: str | Callable | None = None,
    init_options: Mapping[str, Any] | None = None,
    floor: float | str = "auto",
    precision: str | None = None,
    absolute_sigma: bool | None = None,
    allow_different_detectors: bool = False,
    use_footprint: bool = True,
    resolution_check: bool = True,
    progress: Callable[[int, float], None] | None = None,
    nuisance: NuisanceOptions | Mapping[str, Any] | bool | None = None,
) -> FitResult:
    """Fit ``model`` to one or several data blocks (detector frames and/or goniometer tables).

    ``fit(likelihood, solver=...)`` fits a :class:`~brdfjax.fit.Likelihood` built by
    :func:`brdfjax.fit.prepare` (the data, params and likelihood options are then the likelihood's);
    ``fit(model, data, params, **options)`` builds it in place.

    ``params`` maps parameter names (the model's public names, ``theta_i``,
    ``phi_ref``) to a :class:`~brdfjax.fit.Param`, a start value (free),
    ``"auto"``, ``"free"`` or ``"fixed"``; parameters not named are held at
    the model's (or the data's) values.  Values and bounds are in stored units
    (radians, metres); the result reports angles in degrees.

    ``solver``: a name from :data:`~brdfjax.fit.SOLVERS` with
    ``solver_options``, or a solver object.  ``loss``: ``linear``, ``huber`` or
    ``cauchy`` with ``loss_scale`` in sigma (default 3).  ``initializer``: the
    automatic initialisation for ``"auto"`` starts (a name from
    :data:`~brdfjax.fit.INITIALIZERS` or a callable ``(model, blocks, **options)
    -> {name: value}``; default: chosen from the model), with
    ``init_options`` (e.g. index priors ``n1``, ``n2``).  ``floor``: the
    underflow guard of the log model (sr^-1, or ``"auto"``).  ``precision``:
    ``float32``/``float64`` (default: float64 when 64-bit JAX is on).
    ``absolute_sigma``: take the data's uncertainties at face value
    (default: yes when every block has ``sigma_rel``).  Frames from different
    detectors need ``allow_different_detectors=True``.  A footprint on a frame
    is convolved with the model unless ``use_footprint=False``.
    ``progress(k, chi2)`` hears of every residual evaluation of the solver
    (about one per step) with the sum of squared residuals there.

    ``nuisance``: the systematic errors of frames that came through the
    instrument as nuisance parameters of the likelihood
    (:mod:`brdfjax.fit._nuisance`; ``True`` or options; default none); the
    result then reports each parameter's sigma with them (marginal) and
    without (conditional) in ``FitResult.nuisance``.

    A fit that does not converge returns normally with ``converged=False``
    and a message that says why; bad inputs raise
    :class:`~brdfjax.fit.FitInputError`.
    """
    call = {
        "loss": loss, "loss_scale": loss_scale, "floor": floor, "precision": precision, "absolute_sigma": absolute_sigma,
        "use_footprint": use_footprint, "nuisance": nuisance, "initializer": initializer, "init_options": init_options,
        "allow_different_detectors": allow_different_detectors, "resolution_check": resolution_check,
    }
    if isinstance(model, Likelihood):
        clash = [k for k, v in call.items() if not _is_default(v, LIKELIHOOD_OPTIONS[k])]
        clash += [k for k, v in (("data", data), ("params", params)) if v is not None]
        if clash:
            raise FitInputError(
                f"fit(likelihood) takes {', '.join(clash)} from the likelihood; set them with "
                "brdfjax.fit.prepare(...) or likelihood.replace(...)"
            )
        return fit(model.model, model.blocks, model.params, solver=solver, solver_options=solver_options,
                   first_stage=first_stage, progress=progress, **model.options())
    if data is None:
        raise FitInputError("fit(model, data, params): data is missing (a FrameData, a TableData or a list of them)")
    t_start = time.perf_counter()
    opts = dict(solver_options or {})
    solver_obj = get_solver(solver, **opts)
    if first_stage is not None and first_stage not in FIRST_STAGES:
        raise FitInputError(f"unknown first_stage '{first_stage}'; known: {', '.join(FIRST_STAGES)} or None")
    prep = prepare(
        model, data, params, solver=solver_obj, loss=loss, loss_scale=loss_scale, initializer=initializer,
        init_options=init_options, floor=floor, precision=precision,
        allow_different_detectors=allow_different_detectors, use_footprint=use_footprint, nuisance=nuisance,
    )
    problem, layout, blocks, auto, warnings = prep.problem, prep.layout, prep.blocks, prep.auto, prep.warnings
    precision_name = "float64" if problem.u0.dtype == jnp.float64 else "float32"
    t_setup = time.perf_counter()
    n_free = len(layout.free)
    u0 = layout.u0()
    k_final = float(np.asarray(problem.loss_scale))
    stages = [(loss_id(loss), k_final, 0.0)]
    if first_stage == "soft":
        stages.insert(0, (loss_id(loss), k_final, 1.0))
    elif first_stage is not None:
        stages.insert(0, (loss_id(first_stage), DEFAULT_LOSS_SCALE, 0.0))
    notes, total_steps = [], 0
    if not n_free:
        problem = with_scale(problem, u0, np.ones(0))
        outcome = SolveOutcome(np.zeros(0), True, "successful", "nothing to fit: every parameter is fixed", 0)
    else:
        u_start = u0
        n_eval = 0

        def heard(chi2: float) -> None:
            nonlocal n_eval
            n_eval += 1
            progress(n_eval, chi2)

        for i, (index, k_stage, soften) in enumerate(stages):
            with report_evaluations(heard if progress is not None else None):
                problem, outcome = _solve_stage(
                    with_loss(problem, index, k_stage, soften), layout, solver_obj, u_start, warnings if i == 0 else []
                )
            total_steps += outcome.n_steps
            if i < len(stages) - 1:
                notes.append(f"first stage ({first_stage}): {outcome.n_steps} steps, {outcome.status}")
                if np.all(np.isfinite(outcome.v)):
                    u_start = np.asarray(problem.u0, np.float64) + np.asarray(problem.scale, np.float64) * outcome.v
        if notes:
            outcome = SolveOutcome(
                outcome.v, outcome.converged, outcome.status, f"{outcome.message} [{'; '.join(notes)}]", total_steps,
                outcome.jacobian,
            )
    est = [k for k, b in enumerate(blocks) if isinstance(b, TableData) and b.sigma_rel is None]
    noise: dict[str, Any] = {"estimated": False}
    inv_eff = list(prep.inv_sigma)
    if est:
        problem, outcome, noise = _estimate_noise(problem, layout, solver_obj, outcome, est, loss != "linear", prep)
        total_steps += noise.pop("extra_steps")
        for kk in est:
            inv_eff[kk] = prep.inv_sigma[kk] / noise["sigma_ln"]
    u0 = np.asarray(problem.u0, np.float64)
    scale = np.asarray(problem.scale, np.float64)
    t_solve = time.perf_counter()

    v = outcome.v
    converged, status, message = outcome.converged, outcome.status, outcome.message
    r_blocks_all, r_tilde = evaluate(jnp.asarray(v), problem)
    r = np.asarray(r_blocks_all, np.float64)
    rt = np.asarray(r_tilde, np.float64)
    if not np.all(np.isfinite(r)) and converged:
        converged, status = False, SolveStatus.failed
        message = "not converged: residuals at the solution are not finite"
    q = 0 if prep.nuisance is None else prep.nuisance.size
    r_prior = r[r.size - q :]  # the nuisance parameters' prior rows (each balances its parameter in the dof)
    r = r[: r.size - q]
    n_points = int(r.size)
    dof = n_points - (n_free - q)
    chi2 = float(np.sum(r**2))
    chi2_red = chi2 / dof if dof > 0 else math.nan
    if dof <= 0:
        warnings.append(f"{n_points} points for {n_free} free parameters: no degrees of freedom left")
    # With estimated noise the residuals are already in units of the estimate: the covariance takes them at
    # face value (the profile likelihood's curvature), which is the old "scale by the residual variance" with
    # RSS / N in place of RSS / dof.
    absolute = True if absolute_sigma is None else bool(absolute_sigma)
    neg2_ll = chi2
    if noise["estimated"]:
        n_e = noise["n_points"]
        chi2_e = float(sum(np.sum(r[o : o + c] ** 2) for o, c, kk in _segments(problem.counts) if kk in est))
        neg2_ll = chi2 - chi2_e + n_e * math.log(noise["rss_ln"] / n_e) + n_e
        warnings.append(
            f"the noise was estimated from the residuals (sigma of ln BRDF = {noise['sigma_ln']:.4g}, the data give "
            "none): chi2_reduced is ~1 by construction and says nothing about the goodness of fit; set sigma_rel "
            "for a known uncertainty"
        )
    u = u0 + scale * v
    if n_free:
        # the solver's own Jacobian at the solution where it has one for this very problem (the noise estimate
        # reweights the problem after the last solve), else the Jacobian program
        J = outcome.jacobian if outcome.jacobian is not None and not noise["estimated"] else None
        if J is None:
            J = np.asarray(jacobian(jnp.asarray(v), problem), np.float64)
        elif np.any(zero := ~np.any(J != 0, axis=0)):
            # the solver's linearisation masks a non-finite derivative as 0: such columns are differenced
            J = J.copy()
            J[:, zero] = _difference_columns(problem, v, np.flatnonzero(zero))
        cov = covariance(J, scale * layout.jacobian_diag(u), chi2_red, absolute)
        if cov.undetermined:
            warnings.append(
                "the data do not determine "
                + ", ".join(layout.free[i].name for i in cov.undetermined)
                + f" (Jacobian rank {cov.rank} < {n_free}): their sigmas are infinite; fix some of them"
            )
        if cov.saturated:
            warnings.append(
                "the sigmas of " + ", ".join(layout.free[i].name for i in cov.saturated)
                + " are infinite: their transform's derivative is not finite at the solution (the parameter ran to "
                "an extreme of its stored form); fix it, bound it, or give a better start"
            )
    else:
        cov = covariance(np.zeros((n_points, 0)), np.zeros(0), chi2_red, absolute)
    nuisance_report: dict[str, Any] = {}
    if prep.nuisance is not None and n_free:
        n_phys = n_free - prep.nuisance.size
        cond = conditional_sigma(J, scale * layout.jacobian_diag(u), range(n_phys), cov.factor)
        nuisance_report = {
            "parameters": prep.nuisance.describe(),
            "sigma_conditional": {layout.free[i].name: float(cond[i]) for i in range(n_phys)},
            "chi2_prior": float(np.sum(r_prior**2)),
            "note": "sigma (marginal) includes the systematic errors; sigma_conditional holds the nuisance "
            "parameters at the optimum (the data's own uncertainty)",
        }
    t_cov = time.perf_counter()
    x = layout.natural(u)
    for i, e in enumerate(layout.free):
        for bound in (e.lower, e.upper):
            if math.isfinite(bound) and abs(x[i] - bound) <= 1e-6 * abs(e.x0 - bound):
                # in the unit a config gives the key in (degrees for angles: '<name>_deg'), radians beside
                u_name = natural_unit(e.unit)
                shown = f"{bound * to_natural(e.unit):.6g}" + ("" if u_name in ("", "1") else f" {u_name}")
                if e.unit == "rad":
                    shown += f" ({bound:.6g} rad; config key '{e.name}_deg')"
                warnings.append(
                    f"parameter '{e.name}' ended on its bound {shown}; its sigma is not meaningful "
                    "(widen the bound, or fix the parameter)"
                )

    estimates: dict[str, ParameterEstimate] = {}
    free_index = {e.name: i for i, e in enumerate(layout.free)}
    fixed_by_name = {e.name: e for e in layout.fixed}
    for name in layout.order:
        if name in free_index:
            i = free_index[name]
            e = layout.free[i]
            estimates[name] = ParameterEstimate(float(x[i]), float(cov.sigma[i]), e.unit, True, e.x0)
        else:
            f = fixed_by_name[name]
            estimates[name] = ParameterEstimate(f.value, None, f.unit, False, f.value)

    # per-block statistics
    summaries = []
    res_blocks, w_blocks = [], []
    offset = 0
    k = float(np.asarray(problem.loss_scale))
    for name, b, n, inv_sigma, conv in zip(prep.names, blocks, problem.counts, inv_eff, prep.convolved):
        rb = r[offset : offset + n]
        offset += n
        log_res = rb / inv_sigma
        res_blocks.append(rb)
        w_blocks.append(np.asarray(irls_weights(loss, jnp.asarray(rb), k)))
        groups = _group_stats(b, b.usable(), rb, log_res) if isinstance(b, TableData) else ()
        summaries.append(
            BlockSummary(
                name, "frame" if isinstance(b, FrameData) else "table", n, float(np.sum(rb**2)),
                float(np.sqrt(np.mean(log_res**2))), conv, groups,
            )
        )
    n_down = int(np.sum(np.abs(r) > k)) if loss != "linear" else 0
    fitted = problem.block_inputs(jnp.asarray(v))
    t_end = time.perf_counter()
    result = FitResult(
        parameters=estimates,
        free_names=layout.free_names,
        covariance=cov.matrix,
        correlation=cov.correlation,
        chi2=chi2,
        dof=dof,
        n_points=n_points,
        converged=bool(converged),
        status=status,
        message=message,
        n_iterations=int(outcome.n_steps),
        wall_s=t_end - t_start,
        solver=solver_obj.name,
        loss=loss,
        loss_scale=k,
        cost=float(np.sum(rt**2)),
        n_downweighted=n_down,
        covariance_absolute=absolute and not (noise["estimated"] and absolute_sigma is None),
        noise=noise,
        neg2_log_likelihood=neg2_ll,
        precision=precision_name,
        blocks=tuple(summaries),
        warnings=tuple(warnings),
        versions=versions(),
        timings={
            "setup_s": t_setup - t_start,
            "auto_init_s": prep.init_s,
            "solve_s": t_solve - t_setup,
            "covariance_s": t_cov - t_solve,
            "total_s": t_end - t_start,
        },
        models=tuple(m for m, _ in fitted),
        frames=tuple(f for _, f in fitted),
        residuals=tuple(res_blocks),
        weights=tuple(w_blocks),
        auto_init={kk: (np.asarray(vv).tolist()) for kk, vv in auto.items()},
        nuisance=nuisance_report,
    )
    if resolution_check and converged and any(isinstance(b, TableData) for b in blocks):
        kwargs = dict(
            solver=solver, solver_options=solver_options, loss=loss, loss_scale=loss_scale, first_stage=first_stage,
            floor=floor, precision=precision, absolute_sigma=absolute_sigma,
            allow_different_detectors=allow_different_detectors, use_footprint=use_footprint, resolution_check=False,
        )
        result = _mark_unresolved(result, model, blocks, dict(params or {}), kwargs)
    return result


def _mark_unresolved(result: FitResult, model: Model, blocks: list[Data], params: dict[str, Any], kwargs: dict) -> FitResult:
    """The result with an unresolved lobe's width and weight reported as not determined (:mod:`._resolution`)."""
    found = check_resolution(model, blocks, params, result, lambda m, spec: fit(m, blocks, spec, **kwargs))
    notes = found.pop("_notes", [])
    if notes:
        result = dataclasses.replace(result, warnings=tuple(result.warnings) + tuple(notes))
    if not found:
        return result
    estimates = dict(result.parameters)
    undetermined = {}
    for name, rec in found.items():
        p = estimates[name]
        f = to_natural(p.unit)
        lo, hi = rec["range"]
        rec = {**rec, "range": [lo * f, hi * f], "unit": natural_unit(p.unit)}
        rec["range_text"] = (f"< {hi * f:.3g}" if rec.get("open_below") else f"{lo * f:.3g} .. {hi * f:.3g}") + (
            f" {rec['unit']}" if rec["unit"] not in ("1", "") else ""
        )
        undetermined[name] = rec
        estimates[name] = dataclasses.replace(p, sigma=math.nan)
    warns = list(result.warnings) + [
        f"{name} is NOT determined: {rec['reason']}; the data allow {rec['range_text']} "
        "(profile -2 ln L within 1 of the best); its sigma is not given" for name, rec in undetermined.items()
    ]
    return dataclasses.replace(result, parameters=estimates, undetermined=undetermined, warnings=tuple(warns))
