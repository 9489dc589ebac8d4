"""Solvers of the fit, by name: one registry shared by ``fit``, configs and error messages.

- ``levenberg_marquardt`` (default; alias ``lm``): optimistix's
  Levenberg-Marquardt on the (robust) residual vector, in the scaled
  coordinates of :mod:`brdfjax.fit._problem`.  Bounds come from the
  reparametrisation.
- ``lbfgsb``: jaxopt's bounded L-BFGS-B on ``sum rho(r)``; two-sided bounds are
  native box constraints (the parameters keep an affine map), one-sided
  bounds still use ``log``.

Each solver is a small ``eqx.Module`` whose ``solve(problem, v0)`` returns a
:class:`SolveOutcome`.  The residual function is the module-level
:func:`brdfjax.fit._problem.residuals`, and the data travel in ``args``, so
the compiled solve is reused across fits of the same shapes (a new closure on
every call would recompile, ``dependencies.md``).
"""

from __future__ import annotations

import abc
import dataclasses
import enum
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..runtime.export_cache import exportable
from ._common import FitInputError
from ._problem import Problem, _emit, half_sum_squares, listening, residuals, switches

__all__ = ["SolveOutcome", "AbstractSolver", "LevenbergMarquardt", "LBFGSB", "SOLVERS", "get_solver"]


class SolveStatus(enum.StrEnum):
    """How a solve ended (a ``str``, so ``result.json`` and comparisons with the plain names keep working)."""

    successful = "successful"
    max_steps_reached = "max_steps_reached"
    diverged = "diverged"
    failed = "failed"


@dataclass(frozen=True)
class SolveOutcome:
    """What a solver returns: the solution in solver coordinates and how it ended."""

    v: np.ndarray
    converged: bool
    status: SolveStatus
    message: str
    n_steps: int
    #: d r~ / d v at ``v`` of the problem that was solved, where the solver had it at hand (Levenberg-Marquardt's
    #: last linearisation); None where it did not
    jacobian: np.ndarray | None = None


class AbstractSolver(eqx.Module):
    """A named solver; concrete solvers are final."""

    name: ClassVar[str]
    #: Whether two-sided bounds are passed as a box (else they are reparametrised with a logit).
    box_bounds: ClassVar[bool] = False

    @abc.abstractmethod
    def solve(self, problem: Problem, v0: Any, box: tuple[np.ndarray, np.ndarray] | None = None) -> SolveOutcome:
        raise NotImplementedError


class _FtolLM(optx.AbstractLeastSquaresSolver):
    """optimistix Levenberg-Marquardt that also stops like scipy's ``ftol``.

    After an accepted step that lowers chi^2 by at most ``ftol`` relative to the previous accepted
    chi^2, the solve terminates (optimistix's own Cauchy test on step and residual change still applies).
    The chi^2 is final long before that test fires: the solve runs about 30 steps where 12 give the
    final chi^2 to 1e-6 relative.
    """

    inner: optx.LevenbergMarquardt
    ftol: float = eqx.field(static=True)

    @property
    def rtol(self):
        return self.inner.rtol

    @property
    def atol(self):
        return self.inner.atol

    @property
    def norm(self):
        return self.inner.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        new_y, new_state, aux = self.inner.step(fn, y, args, options, state, tags)
        if self.ftol > 0:
            old = jnp.sum(jnp.square(state.f_info.residual))
            new = jnp.sum(jnp.square(new_state.f_info.residual))
            accepted = new_state.num_accepted_steps > state.num_accepted_steps
            small = accepted & (state.num_accepted_steps > 0) & (old - new <= self.ftol * old)
            new_state = eqx.tree_at(lambda s: s.terminate, new_state, new_state.terminate | small)
        return new_y, new_state, aux

    def terminate(self, fn, y, args, options, state, tags):
        return self.inner.terminate(fn, y, args, options, state, tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state, tags, result)


def _lm(rtol, atol, ftol):
    return _FtolLM(optx.LevenbergMarquardt(rtol=rtol, atol=atol), ftol)


@eqx.filter_jit
def _lm_solve(v0, problem, rtol, atol, max_steps, ftol=0.0):
    """The whole solve as one program: the solution, optimistix's result code (an integer array, so the
    program can be exported: :mod:`brdfjax.runtime.export_cache`), the number of steps and the Jacobian at
    the solution.

    The Jacobian is the last accepted linearisation the solver made (optimistix keeps the residuals' linear
    map at the accepted point in its state; with the structured Jacobian that map holds the matrix itself,
    so materialising it is one small product).  The covariance then needs no Jacobian program of its own: on
    the diagnosis' shipped example a second program per model shape was 23 compilations, 39 s of a 148 s
    run (``experiments/profile_diagnose_compiles.py``)."""
    solver = _lm(rtol, atol, ftol)
    sol = optx.least_squares(residuals, solver, v0, args=problem, max_steps=max_steps, throw=False)
    return sol.value, sol.result._value, sol.stats["num_steps"], sol.state.f_info.jac.as_matrix()


_lm_solve_exported = exportable("lm_solve", _lm_solve, switches)


def _result(code) -> Any:
    """optimistix's result item of a result code."""
    return eqx.tree_at(lambda r: r._value, optx.RESULTS.successful, jnp.asarray(code, optx.RESULTS.successful._value.dtype))


_TAGS: frozenset = frozenset()


def _lm_fn(v, problem):
    return residuals(v, problem), None


@eqx.filter_jit
def _lm_init(solver, v0, problem):
    f_struct = jax.eval_shape(residuals, v0, problem)
    state = solver.init(_lm_fn, v0, problem, {}, f_struct, None, _TAGS)
    terminate, result = solver.terminate(_lm_fn, v0, problem, {}, state, _TAGS)
    return state, terminate, optx.RESULTS.where(jnp.all(jnp.isfinite(v0)), result, optx.RESULTS.nonfinite)


@eqx.filter_jit
def _lm_step(solver, v, state, problem):
    # one iteration of optimistix's own loop (optimistix._iterate: step, then terminate at the old point)
    new_v, new_state, _ = solver.step(_lm_fn, v, problem, {}, state, _TAGS)
    terminate, result = solver.terminate(_lm_fn, v, problem, {}, new_state, _TAGS)
    result = optx.RESULTS.where(jnp.all(jnp.isfinite(v)), result, optx.RESULTS.nonfinite)
    return new_v, new_state, terminate, result, jnp.sum(jnp.square(new_state.f_info.residual))


def _lm_stepwise(v0, problem, rtol, atol, max_steps, report, ftol=0.0):
    """``_lm_solve`` stepped from Python: ``report(chi2)`` after each step, no host callback in any program.

    The same iterations as ``optx.least_squares`` (its loop body, run one step per call), so the compiled
    step and its start come from JAX's persistent compilation cache in a later process (a program with
    a host callback never does), and a fit with progress reaches the same point as one without.
    """
    solver = _lm(rtol, atol, ftol)
    state, terminate, result = _lm_init(solver, v0, problem)
    v, n = v0, 0
    while n < max_steps and not bool(terminate) and result == optx.RESULTS.successful:
        v, state, terminate, result, chi2 = _lm_step(solver, v, state, problem)
        n += 1
        report(float(chi2))
    if result == optx.RESULTS.successful and not bool(terminate):
        result = optx.RESULTS.nonlinear_max_steps_reached
    # the last accepted linearisation, as _lm_solve returns it (a product with the stored matrix, run eagerly)
    return v, result, n, state.f_info.jac.as_matrix()


class LevenbergMarquardt(AbstractSolver):
    """optimistix Levenberg-Marquardt (``optx.least_squares``, ``throw=False``).

    ``rtol``/``atol``: the Cauchy termination of optimistix (step and residual
    change both below ``atol + rtol * |value|``), in solver coordinates where
    a unit step is about one standard deviation of the start's Jacobian.
    ``ftol``: also stop after an accepted step that lowers chi^2 by at most
    ``ftol`` relative (scipy ``least_squares``' rule; 0 turns it off).
    """

    name: ClassVar[str] = "levenberg_marquardt"
    rtol: float = eqx.field(static=True, default=1e-5)
    atol: float = eqx.field(static=True, default=1e-5)
    max_steps: int = eqx.field(static=True, default=256)
    ftol: float = eqx.field(static=True, default=1e-8)

    def __check_init__(self):
        f = self.ftol
        if isinstance(f, bool) or not isinstance(f, (int, float, np.floating, np.integer)) or not np.isfinite(f) or f < 0:
            raise FitInputError(f"solver option 'ftol' must be a finite number >= 0 (0 turns it off), got {f!r}")

    def solve(self, problem, v0, box=None):
        # No host callback in the compiled programs (they can then come from the persistent cache): a solve
        # somebody listens to is stepped from Python and reports the chi^2 after each step.
        problem = dataclasses.replace(problem, report=False)
        if listening():
            value, result, steps, jac = _lm_stepwise(
                jnp.asarray(v0), problem, self.rtol, self.atol, self.max_steps, _emit, float(self.ftol)
            )
            J = np.asarray(jac, np.float64)
        else:
            value, code, steps, jac = _lm_solve_exported(
                jnp.asarray(v0), problem, self.rtol, self.atol, self.max_steps, float(self.ftol)
            )
            result = _result(code)
            J = np.asarray(jac, np.float64)
        v = np.asarray(value)
        n = int(steps)
        # (the solver's linearisation replaces a non-finite derivative by 0, so that a far trial step is rejected,
        # not fatal: the caller differences a zero column itself)
        if n == 0 or not np.all(np.isfinite(v)):
            J = None
        if result == optx.RESULTS.successful:
            if not np.all(np.isfinite(v)):
                return SolveOutcome(v, False, SolveStatus.failed, "the solution is not finite", n)
            return SolveOutcome(
                v, True, SolveStatus.successful,
                f"converged in {n} steps (rtol={self.rtol:g}, atol={self.atol:g}, ftol={self.ftol:g})", n, J,
            )
        message = str(optx.RESULTS[result])
        if result == optx.RESULTS.nonlinear_max_steps_reached:
            return SolveOutcome(
                v, False, SolveStatus.max_steps_reached,
                f"not converged: max_steps={self.max_steps} reached; increase max_steps, or check the start "
                f"(optimistix: {message})", n, J,
            )
        if result == optx.RESULTS.nonlinear_divergence:
            return SolveOutcome(v, False, SolveStatus.diverged, f"not converged: the solve diverged (optimistix: {message})", n, J)
        return SolveOutcome(v, False, SolveStatus.failed, f"not converged (optimistix: {message})", n, J)


def _jaxopt():
    with warnings.catch_warnings():
        # jaxopt is unmaintained and says so on import (dependencies.md); it is still correct for L-BFGS-B.
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        import jaxopt  # imported on first use: it warns on import, and only L-BFGS-B needs it
    return jaxopt


@eqx.filter_jit
def _lbfgsb_solve(v0, lower, upper, problem, tol, max_steps):
    jaxopt = _jaxopt()
    solver = jaxopt.LBFGSB(fun=half_sum_squares, maxiter=max_steps, tol=tol, implicit_diff=False)
    params, state = solver.run(v0, bounds=(lower, upper), problem=problem)
    return params, state.iter_num, state.error, state.value


class LBFGSB(AbstractSolver):
    """jaxopt bounded L-BFGS-B on ``sum rho(r)`` (converged when the projected gradient norm <= ``tol``)."""

    name: ClassVar[str] = "lbfgsb"
    box_bounds: ClassVar[bool] = True
    tol: float = eqx.field(static=True, default=1e-4)
    max_steps: int = eqx.field(static=True, default=1000)

    def solve(self, problem, v0, box=None):
        v0 = jnp.asarray(v0)
        if box is None:
            lower = jnp.full_like(v0, -jnp.inf)
            upper = jnp.full_like(v0, jnp.inf)
        else:
            lower, upper = (jnp.asarray(b, v0.dtype) for b in box)
        params, iters, error, _ = _lbfgsb_solve(v0, lower, upper, problem, self.tol, self.max_steps)
        v = np.asarray(params)
        n, err = int(iters), float(error)
        if not (np.all(np.isfinite(v)) and np.isfinite(err)):
            return SolveOutcome(v, False, SolveStatus.failed, "not converged: the solution or its gradient is not finite", n)
        if err <= self.tol:
            return SolveOutcome(
                v, True, SolveStatus.successful, f"converged in {n} iterations (projected gradient {err:.3g} <= tol={self.tol:g})", n
            )
        if n >= self.max_steps:
            return SolveOutcome(
                v, False, SolveStatus.max_steps_reached,
                f"not converged: max_steps={self.max_steps} reached with projected gradient {err:.3g} > "
                f"tol={self.tol:g}; increase max_steps", n,
            )
        return SolveOutcome(
            v, False, SolveStatus.failed,
            f"not converged: the line search stopped after {n} iterations with projected gradient {err:.3g} > tol={self.tol:g}",
            n,
        )


SOLVERS: dict[str, type[AbstractSolver]] = {
    LevenbergMarquardt.name: LevenbergMarquardt,
    LBFGSB.name: LBFGSB,
}
_ALIASES = {"lm": LevenbergMarquardt.name, "l-bfgs-b": LBFGSB.name}


def get_solver(solver: str | AbstractSolver = "levenberg_marquardt", **options: Any) -> AbstractSolver:
    """A solver by name (``options`` are its settings: rtol, atol, max_steps / tol, max_steps)."""
    if isinstance(solver, AbstractSolver):
        if options:
            raise FitInputError("solver options are given with a solver name, not with a solver object")
        return solver
    key = _ALIASES.get(solver, solver)
    if key not in SOLVERS:
        known = sorted(set(SOLVERS) | set(_ALIASES))
        raise FitInputError(f"unknown solver '{solver}'; known: {', '.join(known)}")
    cls = SOLVERS[key]
    try:
        return cls(**options)
    except TypeError:
        names = [f.name for f in dataclasses.fields(cls)]
        raise FitInputError(
            f"solver '{key}': unknown option(s) {sorted(set(options) - set(names))}; known: {', '.join(names)}"
        ) from None
