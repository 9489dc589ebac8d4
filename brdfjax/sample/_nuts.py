"""The No-U-Turn sampler (blackjax) on a :class:`LogPosterior`, with the chain in an HDF5 file, resumable.

Every brdfjax likelihood has exact gradients, so a gradient-based sampler
can move along the posterior's long, correlated directions (a flux scale
against the weights it multiplies) where emcee's stretch move crawls.  This
module runs ``n_chains`` independent NUTS chains (blackjax's kernel; Stan's
window adaptation of the step size and a diagonal mass matrix) on the same
log-posterior as emcee (:mod:`brdfjax.sample._posterior`), in whitened
coordinates ``x = x_fit + L z`` with ``L`` the Cholesky factor of the fit's
covariance (the Laplace approximation; its diagonal where it is not
usable), so the adaptation starts from unit scales and no correlation: a
weight and the flux-scale nuisance parameters that multiply it form a narrow
ridge that a diagonal mass matrix would cross in hundreds of leapfrog steps.

Determinism and resume: chain ``c``'s key for its warm-up is
``fold_in(fold_in(PRNGKey(seed), c), 0)`` and for step ``i`` (counting from 0
after warm-up) ``fold_in(fold_in(fold_in(PRNGKey(seed), c), 1), i)``: a draw
depends only on the seed, the chain and the step index, never on how the run
was cut into pieces.  The HDF5 file (group ``nuts``) holds the adapted step
sizes and inverse mass matrices, and per step the whitened position, its
log-density and gradient (the full NUTS state), the natural-unit chain, the
log-posterior and the transition's divergence flag, integration steps and
acceptance rate; the step counter ``iteration`` is written after the rows, so
a run killed at any moment resumes from the last complete step and draws
exactly what the uninterrupted run would have.

Diagnostics (:func:`nuts_diagnostics`): per parameter the effective sample
size and the split potential scale reduction R-hat across chains
(blackjax.diagnostics), the autocorrelation time ``tau = n_chains * m /
ESS``, the divergent transitions; converged when every R-hat is below 1.01
and the kept chain is longer than 50 tau for every parameter.
"""

from __future__ import annotations

import functools
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np

from ._chain import N_TAU, Diagnostics, RunOutcome
from ._posterior import LogPosterior, _log_posterior_sampler
from ._priors import SampleError
from ._store import ChainStore

__all__ = ["NUTS_GROUP", "NutsChain", "have_blackjax", "open_nuts", "run_nuts", "nuts_diagnostics", "RHAT_MAX"]

NUTS_GROUP = "nuts"
#: Convergence: every parameter's R-hat below this ...
RHAT_MAX = 1.01
#: Steps per compiled piece of a run (the file is written after each).
CHUNK = 25


def have_blackjax() -> bool:
    try:
        import blackjax  # noqa: F401  (function-local: blackjax is optional, in the test extra)
    except ImportError:
        return False
    return True


def _blackjax() -> Any:
    try:
        import blackjax  # function-local: blackjax is an optional dependency (pip install blackjax)
    except ImportError:
        raise SampleError(
            "sampler = 'nuts' needs blackjax (pip install blackjax, or brdfjax[test]); use sampler = 'emcee' without it"
        ) from None
    return blackjax


@dataclass
class NutsChain:
    """An open NUTS chain file (or an in-memory one when ``path`` is None)."""

    path: Path | None
    names: tuple[str, ...]
    n_chains: int
    center: np.ndarray  # x = center + scale @ z
    scale: np.ndarray  # (ndim, ndim) lower triangular
    seed: int
    n_warmup: int
    step_size: np.ndarray | None = None  # (n_chains,) after warm-up
    inv_mass: np.ndarray | None = None  # (n_chains, ndim)
    iteration: int = 0
    # in-memory copies of the per-step rows (for path None, and after reading)
    rows: dict[str, np.ndarray] = field(default_factory=dict)
    # what defines the problem (brdfjax.io.fingerprint); a resume must match it
    fingerprint: dict[str, Any] | None = None

    @property
    def store(self) -> ChainStore:
        assert self.path is not None
        return _store(self.path)

    @property
    def ndim(self) -> int:
        return len(self.names)

    def to_x(self, z: np.ndarray) -> np.ndarray:
        return self.center + np.asarray(z, np.float64) @ self.scale.T

    # -- file ---------------------------------------------------------------------------
    def _write_header(self) -> None:
        if self.path is None:
            return
        self.store.write_meta(self.names, {"sampler": "nuts", "seed": self.seed}, self.fingerprint)
        with h5py.File(self.path, "a") as f:
            g = f.require_group(NUTS_GROUP)
            g.attrs["n_chains"] = self.n_chains
            g.attrs["seed"] = self.seed
            g.attrs["n_warmup"] = self.n_warmup
            g.attrs["iteration"] = self.iteration
            for k, v in (("center", self.center), ("scale", self.scale)):
                if k in g:
                    del g[k]
                g.create_dataset(k, data=np.asarray(v, np.float64))

    def save_warmup(self, step_size: np.ndarray, inv_mass: np.ndarray, z: np.ndarray, ld: np.ndarray, grad: np.ndarray) -> None:
        self.step_size, self.inv_mass = np.asarray(step_size, np.float64), np.asarray(inv_mass, np.float64)
        self.rows["warm"] = (np.asarray(z, np.float64), np.asarray(ld, np.float64), np.asarray(grad, np.float64))
        if self.path is None:
            return
        with h5py.File(self.path, "a") as f:
            g = f[NUTS_GROUP]
            w = g.require_group("warmup")
            for k, v in (("step_size", self.step_size), ("inv_mass", self.inv_mass), ("z", z), ("logdensity", ld), ("grad", grad)):
                if k in w:
                    del w[k]
                w.create_dataset(k, data=np.asarray(v, np.float64))
            g.attrs["warmup_done"] = 1

    def append(self, rows: dict[str, np.ndarray]) -> None:
        """Append steps (arrays with a leading step axis), then advance ``iteration``."""
        n_new = next(iter(rows.values())).shape[0]
        for k, v in rows.items():
            self.rows[k] = v if k not in self.rows else np.concatenate([self.rows[k], v])
        if self.path is not None:
            self.store.append(rows, self.iteration)
        self.iteration += n_new

    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The NUTS state (whitened position, log-density, gradient) after the last step (or the warm-up)."""
        if self.iteration == 0:
            return self.rows["warm"]
        i = self.iteration - 1
        return self.rows["z"][i], self.rows["logdensity"][i], self.rows["grad"][i]


def _store(path: str | os.PathLike) -> ChainStore:
    return ChainStore(Path(path), NUTS_GROUP, "NUTS", "; an emcee chain? keep sampler = 'emcee' to resume it")


def _read(path: Path) -> NutsChain:
    store = _store(path)
    meta = store.read_meta()  # refuses a file that is not HDF5 or holds no NUTS chain
    try:
        with h5py.File(path, "r") as f:
            g = f[NUTS_GROUP]
            # files written before the shared chain store kept the names and fingerprint on the nuts group
            names = meta["names"] if "names" in meta else json.loads(g.attrs["names"])
            fp = meta.get("fingerprint", json.loads(g.attrs["fingerprint"]) if "fingerprint" in g.attrs else None)
            chain = NutsChain(
                path, tuple(names), int(g.attrs["n_chains"]), np.asarray(g["center"]),
                np.asarray(g["scale"]), int(g.attrs["seed"]), int(g.attrs["n_warmup"]), fingerprint=fp,
            )
            it = int(g.attrs["iteration"])
            if "warmup" in g and int(g.attrs.get("warmup_done", 0)):
                w = g["warmup"]
                chain.step_size, chain.inv_mass = np.asarray(w["step_size"]), np.asarray(w["inv_mass"])
                chain.rows["warm"] = (np.asarray(w["z"]), np.asarray(w["logdensity"]), np.asarray(w["grad"]))
            elif it:
                raise store.corrupt(f"{it} steps but no warm-up")
            for k in ("z", "logdensity", "grad", "x", "log_prob", "diverging", "n_leapfrog", "accept"):
                if it:
                    if k not in g or g[k].shape[0] < it:
                        raise store.corrupt(f"iteration {it} but '{k}' holds fewer steps")
                    chain.rows[k] = np.asarray(g[k][:it])
            chain.iteration = it
            if it and not np.all(np.isfinite(chain.rows["z"])):
                raise store.corrupt("non-finite positions")
    except SampleError:
        raise
    except (OSError, KeyError, ValueError, RuntimeError) as e:
        raise store.corrupt(f"{type(e).__name__}: {e}") from None
    return chain


def open_nuts(
    path: str | os.PathLike | None, names: Sequence[str], n_chains: int, *, resume: bool, center: np.ndarray,
    scale: np.ndarray, seed: int, n_warmup: int, fingerprint: dict[str, Any] | None = None,
) -> NutsChain:
    """The NUTS chain at ``path`` (a new one, or the existing one when resuming; checks as for emcee).

    With ``fingerprint`` a new chain records it and a resumed one must match
    it (:func:`brdfjax.io.fingerprint.check_resume`, as for emcee chains).
    """
    existing = ChainStore.check_open(path, resume=resume)
    if path is None:
        return NutsChain(None, tuple(names), n_chains, np.asarray(center, np.float64), np.asarray(scale, np.float64), seed, n_warmup)
    path = Path(path)
    if existing:
        chain = _read(path)
        chain.store.check_same_problem({"names": chain.names, "fingerprint": chain.fingerprint}, names,
                                       [("chains", chain.n_chains, n_chains)], "n_chains", fingerprint)
        return chain
    chain = NutsChain(path, tuple(names), n_chains, np.asarray(center, np.float64), np.asarray(scale, np.float64), seed, n_warmup,
                      fingerprint=fingerprint)
    chain._write_header()
    return chain


def _logdensity(problem: Any, priors: Any, est: Any, center: Any, scale: Any, log_mask: Any) -> Callable[[Any], Any]:
    """The log-posterior in whitened coordinates ``z``: ``y = center + scale @ z`` (a constant Jacobian), and
    ``x = exp(y)`` where ``log_mask`` (the log-Jacobian added), else ``x = y``."""

    def logdensity(z):
        lp = _log_posterior_sampler(center + scale @ z, problem, priors, est, log_mask)
        # -inf outside the support: NUTS rejects the transition (a divergence), never moves there
        return jnp.where(jnp.isfinite(lp), lp, -jnp.inf)

    return logdensity


# The problem, priors and whitening are arguments (not closed over), so that a new run of the same shapes -- a
# resumed chain, another chain, another data set -- reuses the compiled programs.
@eqx.filter_jit
def _warmup(problem, priors, est, center, scale, log_mask, key, z0, n_warmup: int):
    bj = _blackjax()
    warmup = bj.window_adaptation(
        bj.nuts, _logdensity(problem, priors, est, center, scale, log_mask),
        adaptation_info_fn=bj.adaptation.base.get_filter_adapt_info_fn(),
    )
    (state, params), _ = warmup.run(key, z0, num_steps=n_warmup)
    return state.position, state.logdensity, state.logdensity_grad, params["step_size"], params["inverse_mass_matrix"]


@eqx.filter_jit
def _piece(problem, priors, est, center, scale, log_mask, z, ld, grad, step_size, inv_mass, key, start):
    """:data:`CHUNK` NUTS steps of one chain from the state ``(z, ld, grad)``; step i's key is fold_in(key, start + i).

    One chain per call (not vmapped over chains): under ``vmap`` the NUTS trajectory's while loops take a batched
    predicate and XLA compiled the program 3x slower (10.5 s against 3.5 s for a one-parameter table on CPU).
    """
    bj = _blackjax()
    kernel = bj.nuts.build_kernel()
    logdensity = _logdensity(problem, priors, est, center, scale, log_mask)

    def one(state, k):
        new, info = kernel(k, state, logdensity, step_size, inv_mass)
        return new, (new.position, new.logdensity, new.logdensity_grad, info.is_divergent,
                     info.num_integration_steps, info.acceptance_rate)

    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(start + jnp.arange(CHUNK))
    _, ys = jax.lax.scan(one, bj.mcmc.hmc.HMCState(z, ld, grad), keys)
    return ys


def _chain_keys(seed: int, n_chains: int, stream: int) -> jax.Array:
    base = jax.random.PRNGKey(seed)
    return jnp.stack([jax.random.fold_in(jax.random.fold_in(base, c), stream) for c in range(n_chains)])


def run_nuts(
    post: LogPosterior,
    chain: NutsChain,
    z0: np.ndarray | None,
    n_steps: int,
    *,
    stop_when_converged: bool = False,
    check_every: int = 100,
    on_step: Callable[[int], None] | None = None,
    log: Callable[[str], None] | None = None,
) -> RunOutcome:
    """Warm up (once) and run ``chain`` until it holds ``n_steps`` steps per chain (see the module docstring)."""
    _blackjax()
    say = log or (lambda m: None)
    t0 = time.perf_counter()
    problem, priors, est = post.problem, post.priors, post.est
    dtype = post.dtype
    center = jnp.asarray(chain.center, dtype)
    scale = jnp.asarray(chain.scale, dtype)
    logged = post.logged
    log_mask = jnp.asarray(logged)  # an array (never None): one compiled program with and without logs

    done0 = chain.iteration
    out = RunOutcome(done0, 0, False, False, 0.0)
    if chain.step_size is None:
        if z0 is None:
            raise SampleError("a new NUTS chain needs its start positions")
        say(f"NUTS: window adaptation, {chain.n_warmup} steps x {chain.n_chains} chains ...")
        keys = _chain_keys(chain.seed, chain.n_chains, 0)
        zs, lds, grads, steps, imms = [], [], [], [], []
        for c in range(chain.n_chains):
            z, ld, grad, h, imm = _warmup(problem, priors, est, center, scale, log_mask, keys[c], jnp.asarray(z0[c], dtype),
                                   chain.n_warmup)
            zs.append(np.asarray(z, np.float64))
            lds.append(float(ld))
            grads.append(np.asarray(grad, np.float64))
            steps.append(float(h))
            imms.append(np.asarray(imm, np.float64))
        chain.save_warmup(np.array(steps), np.stack(imms), np.stack(zs), np.array(lds), np.stack(grads))
        say("NUTS: step sizes " + ", ".join(f"{s:.3g}" for s in steps))
    remaining = int(n_steps) - chain.iteration
    if remaining <= 0:
        out.wall_s = time.perf_counter() - t0
        return out

    keys = _chain_keys(chain.seed, chain.n_chains, 1)
    h = jnp.asarray(chain.step_size, dtype)
    m = jnp.asarray(chain.inv_mass, dtype)
    try:
        while chain.iteration < n_steps:
            z, ld, grad = (jnp.asarray(a, dtype) for a in chain.state())
            start = jnp.asarray(chain.iteration, jnp.int32)
            per = [
                [np.asarray(a) for a in _piece(problem, priors, est, center, scale, log_mask, z[c], ld[c], grad[c], h[c], m[c], keys[c],
                                                  start)]
                for c in range(chain.n_chains)
            ]
            take = min(CHUNK, int(n_steps) - chain.iteration)
            # (steps, chains, ...) like the file's rows
            zz, lds, grads, div, nlf, acc = (np.stack([p[j] for p in per], axis=1)[:take] for j in range(6))
            zz = zz.astype(np.float64)
            x = post.from_sampler(chain.to_x(zz))  # stored units
            lds = lds.astype(np.float64)
            chain.append({
                "z": zz, "logdensity": lds, "grad": grads.astype(np.float64), "x": x,
                # the posterior density of x (the sampler's includes the log-Jacobian of the logged entries)
                "log_prob": lds - np.sum(np.log(x[..., logged]), axis=-1), "diverging": div.astype(np.int8), "n_leapfrog": nlf.astype(np.int32),
                "accept": acc.astype(np.float64),
            })
            out.iterations, out.new_steps = chain.iteration, chain.iteration - done0
            if on_step is not None:
                on_step(chain.iteration)
            if stop_when_converged and chain.iteration % check_every == 0:
                d = nuts_diagnostics(chain, post.names, burn=0, thin=1)
                out.tau_history.append((chain.iteration, d.tau.tolist()))
                if d.converged:
                    out.stopped_converged = True
                    break
    except KeyboardInterrupt:
        out.interrupted = True
        out.iterations = chain.iteration
    out.wall_s = time.perf_counter() - t0
    return out


@functools.cache
def _jitted(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn(samples, chain_axis=0, sample_axis=1)`` as one compiled program (a blackjax diagnostic)."""
    return jax.jit(functools.partial(fn, chain_axis=0, sample_axis=1))


@dataclass(frozen=True)
class NutsDiagnostics(Diagnostics):
    """:class:`Diagnostics` plus R-hat, divergences and the mean trajectory length."""

    rhat: np.ndarray = field(default_factory=lambda: np.zeros(0))
    divergences: int = 0
    mean_leapfrog: float = math.nan
    step_size: np.ndarray = field(default_factory=lambda: np.zeros(0))


def nuts_diagnostics(chain: NutsChain, names: Sequence[str], *, burn: int | str = 0, thin: int = 1) -> NutsDiagnostics:
    """ESS, R-hat, tau, divergences and convergence of a NUTS chain (module docstring)."""
    bj = _blackjax()
    x = chain.rows["x"]  # (n, n_chains, p)
    n = x.shape[0]
    burn_n = 0 if burn == "auto" else int(burn)
    if not 0 <= burn_n < max(n, 1):
        raise SampleError(f"burn = {burn_n} must be between 0 and the chain length {n} - 1")
    kept = x[burn_n:]
    m = kept.shape[0]
    arr = np.swapaxes(kept, 0, 1)  # (chains, samples, p)
    with np.errstate(all="ignore"):
        if m >= 4:
            # jitted: eagerly, blackjax's ESS compiles some fifty small programs (4 s on the test posterior);
            # (p,) even for one parameter (blackjax returns a scalar then)
            ess = np.asarray(_jitted(bj.diagnostics.effective_sample_size)(arr), np.float64).reshape(-1)
            rhat = np.asarray(_jitted(bj.diagnostics.potential_scale_reduction)(arr), np.float64).reshape(-1) \
                if chain.n_chains > 1 else np.full(x.shape[2], np.nan)
        else:
            ess = np.full(x.shape[2], np.nan)
            rhat = np.full(x.shape[2], np.nan)
        tau = chain.n_chains * m / ess
    acc = np.mean(chain.rows["accept"][burn_n:], axis=0) if m else np.full(chain.n_chains, np.nan)
    div = int(np.sum(chain.rows["diverging"][burn_n:])) if m else 0
    short = tuple(nm for nm, t in zip(names, tau) if not (np.isfinite(t) and m > N_TAU * t))
    warns = []
    if short:
        worst = float(np.nanmax(tau)) if np.any(np.isfinite(tau)) else math.nan
        warns.append(
            f"the chain is shorter than {N_TAU} autocorrelation times for {', '.join(short)} ({m} kept steps, largest "
            f"tau {worst:.1f} steps); run longer (--resume with more steps)"
        )
    bad_rhat = [nm for nm, r in zip(names, rhat) if np.isfinite(r) and r >= RHAT_MAX]
    if bad_rhat:
        warns.append(f"R-hat >= {RHAT_MAX} for {', '.join(bad_rhat)}: the chains disagree; run longer")
    if div:
        warns.append(
            f"{div} divergent transitions after warm-up: the sampler met curvature it could not integrate (or the edge "
            "of a prior); the posterior there may be misrepresented"
        )
    converged = bool(not short and m > 0 and (chain.n_chains == 1 or all(np.isfinite(rhat) & (rhat < RHAT_MAX))))
    return NutsDiagnostics(
        n, chain.n_chains, burn_n, int(thin), acc, tau, ess, converged, short, tuple(warns),
        rhat=rhat, divergences=div, mean_leapfrog=float(np.mean(chain.rows["n_leapfrog"][burn_n:])) if m else math.nan,
        step_size=np.asarray(chain.step_size if chain.step_size is not None else [], np.float64),
    )
