"""Running emcee on a :class:`LogPosterior` with the chain in an HDF5 file, resumable; convergence diagnostics.

The chain lives in emcee's :class:`~emcee.backends.HDFBackend` (group
``mcmc``): every step is written as it is drawn, with the sampler's random
state, so an interrupted run (Ctrl-C, a killed process) loses at most the
step in flight and a resumed run continues the same chain -- and, since the
random state is restored, draws exactly what the uninterrupted run would
have.  A group ``brdfjax`` beside it records the parameter names, units and
seed and the problem's fingerprint (:mod:`brdfjax.io.fingerprint`: model,
fixed values, bounds, priors, every data block's values, uncertainties,
mask and grid, the likelihood's and the sampler's settings); resuming
checks them against the current problem and refuses any difference, naming
it.  The file handling both samplers share (the open policy, the problem's
record, unreadable files) is the chain store, :mod:`brdfjax.sample._store`.

A chain file that cannot be read (corrupted, truncated, not HDF5) or that
belongs to another problem is an error naming the file; it is never
overwritten.  A fresh run refuses to replace an existing chain file.

Diagnostics (:func:`diagnose`): acceptance fraction per walker, emcee's
integrated autocorrelation time per parameter (``get_autocorr_time(tol=0)``
on the chain after burn-in), the effective sample size ``n_walkers *
n_kept / tau``, a warning for every parameter whose kept chain is shorter
than 50 tau, and convergence: kept chain longer than 50 tau for every
parameter and every tau changed by less than 1 % since ``check_every``
steps earlier (emcee's documented criterion).
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import emcee
import h5py
import numpy as np

from ._priors import SampleError
from ._store import ChainStore

__all__ = ["ChainInfo", "Diagnostics", "open_chain", "run_chain", "diagnose", "read_chain"]

GROUP = "mcmc"
#: Convergence: chain longer than this many autocorrelation times ...
N_TAU = 50
#: ... and tau stable to this fraction between checks.
TAU_RTOL = 0.01


@dataclass(frozen=True)
class ChainInfo:
    """What an existing chain file holds."""

    path: Path
    iteration: int
    n_walkers: int
    ndim: int
    names: tuple[str, ...]
    meta: dict[str, Any]


def _store(path: str | os.PathLike) -> ChainStore:
    return ChainStore(Path(path), GROUP, "emcee")


def read_chain_info(path: str | os.PathLike) -> ChainInfo:
    """Open an existing chain file read-only and check it (raises :class:`SampleError` naming the file)."""
    store = _store(path)
    path = store.path
    meta = store.read_meta()  # refuses a file that is not HDF5 or holds no emcee chain
    try:
        with h5py.File(path, "r") as f:
            g = f[GROUP]
            it = int(g.attrs["iteration"])
            nw, nd = int(g.attrs["nwalkers"]), int(g.attrs["ndim"])
            chain = g["chain"]
            lp = g["log_prob"]
            if chain.shape[0] < it or lp.shape[0] < it or chain.shape[1:] != (nw, nd):
                raise store.corrupt(f"iteration {it} but the chain holds {chain.shape[0]} steps of {chain.shape[1:]}")
            if it:
                # read the data back: a damaged file fails here rather than mid-run
                c = chain[:it]
                lpv = lp[:it]
                if not np.all(np.isfinite(c)) or np.any(np.isnan(lpv)):
                    raise store.corrupt("non-finite walker positions or NaN log-probabilities")
    except SampleError:
        raise
    except (OSError, KeyError, ValueError, RuntimeError) as e:
        raise store.corrupt(f"{type(e).__name__}: {e}") from None
    return ChainInfo(path, it, nw, nd, tuple(meta.get("names", ())), meta)


def open_chain(
    path: str | os.PathLike | None,
    names: Sequence[str],
    n_walkers: int,
    *,
    resume: bool,
    meta: dict[str, Any] | None = None,
    fingerprint: dict[str, Any] | None = None,
) -> tuple[Any, ChainInfo | None]:
    """The emcee backend for ``path`` (``None``: in memory) and what it already holds.

    ``resume=False`` with an existing file, ``resume=True`` without one, a
    corrupted file and a chain of another problem (names, walkers) are
    errors; the file is never modified before these checks pass
    (:class:`~brdfjax.sample._store.ChainStore`).  With ``fingerprint`` a new
    chain records it and a resumed one must match it
    (:func:`brdfjax.io.fingerprint.check_resume`: the message names every
    difference).
    """
    existing = ChainStore.check_open(path, resume=resume)
    if path is None:
        return emcee.backends.Backend(), None
    store = _store(path)
    if existing:
        info = read_chain_info(store.path)
        store.check_same_problem(info.meta, names, [("walkers", info.n_walkers, n_walkers),
                                                    ("parameters", info.ndim, len(names))], "n_walkers", fingerprint)
        return emcee.backends.HDFBackend(str(store.path), name=GROUP), info
    store.path.parent.mkdir(parents=True, exist_ok=True)
    backend = emcee.backends.HDFBackend(str(store.path), name=GROUP)
    backend.reset(n_walkers, len(names))
    store.write_meta(names, meta, fingerprint)
    return backend, None


@dataclass
class RunOutcome:
    iterations: int  # steps in the chain now
    new_steps: int
    stopped_converged: bool
    interrupted: bool
    wall_s: float
    tau_history: list[tuple[int, list[float]]] = field(default_factory=list)


def run_chain(
    log_prob: Callable[[np.ndarray], np.ndarray],
    backend: Any,
    p0: np.ndarray | None,
    n_steps: int,
    *,
    seed: int = 0,
    vectorize: bool = True,
    progress: bool = True,
    stop_when_converged: bool = False,
    check_every: int = 100,
    on_step: Callable[[int], None] | None = None,
) -> RunOutcome:
    """Run (or continue) the chain in ``backend`` until it holds ``n_steps`` steps.

    ``p0``: the walkers' start (``(n_walkers, p)``) for a new chain; ignored
    when the backend already holds steps (the last step and the saved random
    state continue the chain).  With ``stop_when_converged`` the run stops
    early at the first check (every ``check_every`` steps) where the chain
    is converged (module docstring).  ``KeyboardInterrupt`` ends the run
    with what was saved (``interrupted=True``).
    """

    t0 = time.perf_counter()
    done = int(backend.iteration) if getattr(backend, "initialized", False) else 0
    if done:
        state = backend.get_last_sample()
        n_walkers, ndim = state.coords.shape
    else:
        if p0 is None:
            raise SampleError("a new chain needs the walkers' start positions")
        n_walkers, ndim = p0.shape
        state = emcee.State(np.asarray(p0, np.float64), random_state=np.random.RandomState(seed).get_state())
    sampler = emcee.EnsembleSampler(n_walkers, ndim, log_prob, vectorize=vectorize, backend=backend)
    remaining = int(n_steps) - done
    out = RunOutcome(done, 0, False, False, 0.0)
    if remaining <= 0:
        out.wall_s = time.perf_counter() - t0
        return out
    last_tau = None
    try:
        for i, _ in enumerate(sampler.sample(state, iterations=remaining, progress=progress), start=1):
            it = done + i
            out.iterations, out.new_steps = it, i
            if on_step is not None:
                on_step(it)
            if stop_when_converged and it % check_every == 0:
                tau = backend.get_autocorr_time(tol=0)
                out.tau_history.append((it, tau.tolist()))
                if last_tau is not None and _converged(tau, last_tau, it):
                    out.stopped_converged = True
                    break
                last_tau = tau
    except KeyboardInterrupt:
        out.interrupted = True
        out.iterations = int(backend.iteration)
    out.wall_s = time.perf_counter() - t0
    return out


def _converged(tau: np.ndarray, tau_prev: np.ndarray, n: int) -> bool:
    tau = np.asarray(tau)
    return bool(np.all(np.isfinite(tau)) and np.all(N_TAU * tau < n) and np.all(np.abs(tau_prev - tau) / tau < TAU_RTOL))


@dataclass(frozen=True)
class Diagnostics:
    """Convergence diagnostics of a chain (see the module docstring)."""

    n_steps: int
    n_walkers: int
    burn: int
    thin: int
    acceptance_fraction: np.ndarray  # per walker
    tau: np.ndarray  # per parameter, steps
    ess: np.ndarray  # per parameter
    converged: bool
    short: tuple[str, ...]  # parameters whose kept chain is shorter than 50 tau
    warnings: tuple[str, ...]

    @property
    def acceptance_fraction_mean(self) -> float:
        return float(np.mean(self.acceptance_fraction))


def _tau(chain: np.ndarray) -> np.ndarray:
    """emcee's integrated autocorrelation time with tol=0 (never raises); NaN for a chain too short."""
    if chain.shape[0] < 2:
        return np.full(chain.shape[2], np.nan)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.asarray(emcee.autocorr.integrated_time(chain, tol=0, quiet=True), np.float64)


def diagnose(
    backend: Any, names: Sequence[str], *, burn: int | str = "auto", thin: int = 1, check_every: int = 100
) -> Diagnostics:
    """Acceptance, autocorrelation times, ESS, convergence of the chain in ``backend``."""
    chain = backend.get_chain()
    n, nw, nd = chain.shape
    acc = np.asarray(backend.accepted, np.float64) / max(n, 1)
    if burn == "auto":
        tau_all = _tau(chain)
        t = np.nanmax(tau_all) if np.any(np.isfinite(tau_all)) else 0.0
        burn_n = int(min(n // 2, math.ceil(2.0 * t)))
    else:
        burn_n = int(burn)
        if not 0 <= burn_n < n:
            raise SampleError(f"burn = {burn_n} must be between 0 and the chain length {n} - 1")
    kept = chain[burn_n:]
    tau = _tau(kept)
    m = kept.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        ess = nw * m / tau
    short = tuple(name for name, t in zip(names, tau) if not (np.isfinite(t) and m > N_TAU * t))
    warnings = []
    if short:
        worst = float(np.nanmax(tau)) if np.any(np.isfinite(tau)) else math.nan
        warnings.append(
            f"the chain is shorter than {N_TAU} autocorrelation times for {', '.join(short)} "
            f"({m} kept steps, largest tau {worst:.1f} steps): the estimates of tau and of the posterior are unreliable; "
            f"run longer (--resume with more steps; about {int(N_TAU * worst) + burn_n if np.isfinite(worst) else '?'} steps)"
        )
    converged = False
    if not short and m > check_every + 2:
        tau_prev = _tau(chain[burn_n : n - check_every])
        converged = _converged(tau, tau_prev, m)
    low = np.flatnonzero((acc < 0.1) | (acc > 0.9))
    if low.size:
        warnings.append(
            f"{low.size} of {nw} walkers have an acceptance fraction outside [0.1, 0.9] "
            f"(min {acc.min():.3f}, max {acc.max():.3f}): stuck or poorly scaled walkers"
        )
    return Diagnostics(n, nw, burn_n, int(thin), acc, tau, ess, converged, short, tuple(warnings))


def read_chain(path: str | os.PathLike) -> Any:
    """A read-only emcee backend of a chain file (checked first)."""
    read_chain_info(path)
    return emcee.backends.HDFBackend(str(path), name=GROUP, read_only=True)
