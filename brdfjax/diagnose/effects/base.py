"""The effect interface, the statistics of the signatures and the score-test engine the effects share.

- :class:`Effect` (``present_in``, ``identifiable``, ``signature``,
  ``extend``), :class:`Extension` (what ``extend`` returns),
  :class:`Signature` (what ``signature`` returns) and the
  :class:`~brdfjax.diagnose.context.Context` an effect sees (re-exported);
- statistics: :func:`score_from_logp` (p-value -> sigma-like score),
  normal and chi^2 tails, robust and smoothed residual statistics;
- model helpers: the weight parameters of a model's terms, unique term names,
  swapping terms, the main specular lobe;
- the score-test engine: :func:`template_z` (the residual projected on the
  change in ln f an extension makes, less what the base's free parameters
  absorb: ``base_jacobian``), :func:`best_by_linear_chi2` and
  :func:`profiled_chi2` (chi^2 profiled over the main lobe's width).

These helpers are public within :mod:`brdfjax.diagnose.effects` (the
model-side and instrument-side effects and the generators use them); the
package's ``__init__`` re-exports only the interface.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ...core.geometry import Directions
from ...core.render import Conditions, pixel_directions, render
from ...core.terms import (
    AbstractTerm,
    Diffraction,
    Lambertian,
    Model,
    OffsetNormal,
    Specular,
)
from ...fit import FrameData
from ...fit.internal import as_param
from ...instrument.synthetic import convolve_footprint
from ..context import Context, precision_name
from .terms import Oriented, SpectralDiffraction

__all__ = ["Effect", "Extension", "Signature", "Context", "score_from_logp"]


# --- interface ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Extension:
    """A base model extended by one effect, ready for :func:`brdfjax.fit.fit` (warm start)."""

    model: Model
    params: dict[str, Any]
    n_new: int
    blocks: list | None = None
    fit_kwargs: dict = field(default_factory=dict)
    note: str = ""
    #: other starts the refit also tries, ``(model, params, note)`` each: the refit of lowest chi^2 is kept
    #: (an effect whose start search ends in a near-tie between distinct optima, e.g. a spacing and its alias)
    alternatives: list = field(default_factory=list)


@dataclass
class Signature:
    """A refit-independent residual statistic: ``value`` (the effect's own measure), ``score`` (sigma-like)."""

    value: float
    score: float
    detail: str = ""
    #: the effect is found by this statistic itself, not by a refit's chi^2 decrease (an unresolved peak: its
    #: value is the widened range of the lobe's width and weight, which no chi^2 shows); such a candidate is
    #: ranked by its score, ahead of the BIC ranking, and says so
    detection: bool = False


class Effect:
    """One candidate effect.  Subclasses set ``name``, ``title``, ``doc``, ``needs_2d`` and the four methods."""

    name: str = ""
    title: str = ""
    doc: str = ""
    needs_2d: bool = True
    #: "material" (what the surface does) or "instrument" (what the measurement does); the report separates them
    side: str = "material"
    #: a broad, unspecific change (a uniform floor, a response curve, another distribution family): its score
    #: can hold what a more specific effect's signature explains, so the engine compares the two on a joint refit
    generic: bool = False
    #: the signature score below which the effect counts as weakly evidenced (a flag only where the diagnosis
    #: is asked for it: ``diagnose(presence=True)``)
    presence: float = 3.0
    #: effects this one reduces to at a neutral value of one of its parameters (``pixel_nonlinearity`` at
    #: gamma = 1 is ``flux_scale``); informative (the search refits every candidate at every step)
    nests: tuple[str, ...] = ()
    #: False for a swap of a part of the model for another that does not contain it (a distribution family):
    #: its refit cannot return to the model it changes, so ending above it is the data rejecting the effect
    nested: bool = True

    def applicable(self, ctx: Any) -> str | None:
        """Why the effect cannot be tried on this fit's context (None: it can); e.g. no room in the frames."""
        return None

    def present_in(self, model: Model) -> bool:
        raise NotImplementedError

    def identifiable(self, model: Model, params: Mapping[str, Any], blocks: Sequence[Any]) -> str | None:
        return None

    def signature(self, ctx: Context) -> Signature:
        raise NotImplementedError

    def extend(self, ctx: Context) -> Extension:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<effect {self.name}: {self.title}>"


# --- small helpers ------------------------------------------------------------------------------

_ND = NormalDist()


def score_from_logp(logp: float) -> float:
    """Two-sided normal quantile of a p-value given as ``ln p`` (0 when p >= 1)."""
    if not math.isfinite(logp):
        return 0.0 if logp > 0 else 40.0
    if logp >= 0:
        return 0.0
    if logp < -700:
        x = -2.0 * logp
        return float(math.sqrt(max(x - math.log(x) - math.log(2 * math.pi), 0.0)))
    return float(max(0.0, -_ND.inv_cdf(math.exp(logp) / 2.0)))


def log_sf_normal(z: float) -> float:
    """ln P(N(0,1) > z)."""
    if z < 5:
        return math.log(max(1.0 - _ND.cdf(z), 1e-300))
    return -0.5 * z * z - math.log(z * math.sqrt(2 * math.pi)) + math.log1p(-1.0 / (z * z))


def log_sf_chi2_even(x: float, dof: int) -> float:
    """ln P(chi2_dof > x) for even dof (Poisson sum)."""
    k = dof // 2
    h = x / 2.0
    terms = [j * math.log(h) - math.lgamma(j + 1) if h > 0 else (0.0 if j == 0 else -math.inf) for j in range(k)]
    m = max(terms)
    return -h + m + math.log(sum(math.exp(t - m) for t in terms))


def weight_names(model: Model) -> list[tuple[str, str | None]]:
    """Per term: (term name, public name of its weight parameter or None)."""
    back = {v: k for k, v in model.aliases}
    out = []
    for tname, term in model.terms.items():
        inner = term
        while isinstance(inner, OffsetNormal | Oriented):
            inner = inner.term
        field_name = {Specular: "rho_s", Lambertian: "rho_d", Diffraction: "rho", SpectralDiffraction: "rho"}.get(type(inner))
        flat = f"{tname}.{field_name}" if field_name else None
        out.append((tname, back.get(flat, flat) if flat else None))
    return out


def is_free(params: Mapping[str, Any], name: str | None) -> bool:
    if name is None or name not in params:
        return False
    return as_param(name, params[name]).free


def unique_name(model: Model, base: str) -> str:
    name, i = base, 2
    while name in model.terms:
        name, i = f"{base}{i}", i + 1
    return name


def with_terms(model: Model, terms: dict[str, AbstractTerm]) -> Model:
    """``model`` (any Model subclass, response kept) with other terms; aliases to vanished names dropped."""
    new = dataclasses.replace(model, terms=terms, aliases=())
    paths = new._paths()
    aliases = tuple((a, f) for a, f in model.aliases if f in paths)
    return dataclasses.replace(model, terms=terms, aliases=aliases)


def drop_missing(params: Mapping[str, Any], model: Model) -> dict[str, Any]:
    known = set(model.params())
    return {k: v for k, v in params.items() if k in known or k in ("theta_i", "phi_ref")}



def block_values(block: Any, model: Model, frame: Conditions | None) -> np.ndarray:
    """Model BRDF on a block's points (frames: the whole grid, convolved with the block's footprint)."""
    if isinstance(block, FrameData):
        img = np.asarray(render(model, frame, block.arm_detector(), grid=block.grid, precision=precision_name()), float)
        if block.footprint is not None:
            k = np.asarray(block.footprint, float)
            img = np.asarray(convolve_footprint(img, k / k.sum()), float)
        return img
    dirs = Directions.from_angles(*(np.asarray(getattr(block, f), float) for f in ("theta_i", "phi_i", "theta_s", "phi_s")))
    wl = np.broadcast_to(np.asarray(block.wavelength, float), np.shape(block.brdf))
    return np.asarray(model(dirs, wl), float)


def _cache(ctx: Context) -> dict:
    return ctx.__dict__.setdefault("_fx_cache", {})


def fitted_values(ctx: Context, k: int) -> np.ndarray:
    """The fitted base model on block ``k``'s points, as the fit compares it (footprint applied)."""
    c = _cache(ctx)
    key = ("f0", k)
    if key not in c:
        b = ctx.blocks[k]
        c[key] = block_values(b, ctx.block_model(k), ctx.block_frame(k) if isinstance(b, FrameData) else None)
    return c[key]


def used_points(ctx: Context, k: int) -> np.ndarray:
    return np.isfinite(np.asarray(ctx.residuals[k], float))


def base_jacobian(ctx: Context) -> np.ndarray | None:
    """d r / d (free parameters) of the base fit at its optimum, by forward differences, on every used point."""
    c = _cache(ctx)
    if "J" in c:
        return c["J"]
    cols = []
    try:
        for name in ctx.result.free_names:
            est = ctx.result.parameters[name]
            base, blk = (name[:-1].split("[", 1) if name.endswith("]") and "[" in name else (name, None))
            v = float(est.value)
            h = max(1e-5 * abs(v), 1e-9)
            col = []
            for k, b in enumerate(ctx.blocks):
                ok = used_points(ctx, k)
                if blk is not None and blk != b.name:
                    col.append(np.zeros(int(ok.sum())))
                    continue
                model, frame = ctx.block_model(k), ctx.block_frame(k) if isinstance(b, FrameData) else None
                if base in ("theta_i", "phi_ref") and frame is not None:
                    frame = eqx.tree_at(lambda f, base=base: getattr(f, base), frame, np.float64(v + h))
                else:
                    model = model.with_params({base: v + h})
                f1 = block_values(b, model, frame)
                with np.errstate(divide="ignore", invalid="ignore"):
                    d = (np.log(np.maximum(f1, 1e-300)) - np.log(np.maximum(fitted_values(ctx, k), 1e-300))) / h / ctx.sigma(k)
                col.append(np.where(np.isfinite(d), d, 0.0)[ok])
            cols.append(np.concatenate(col))
        J = np.stack(cols, axis=1) if cols else None
    except Exception:  # noqa: BLE001 - the orthogonalisation is a refinement; without it z is conservative
        J = None
    c["J"] = J
    return J



def template_z(ctx: Context, transform: Callable[[Model], Model], blocks: Sequence[int] | None = None,
                data_blocks: Sequence[Any] | None = None, full: bool = False) -> Any:
    """Score test of an extension: the residual's projection on the change in ln f it makes, ``t``.

    ``z = sum r t_perp / |t_perp|`` with ``t_perp`` the part of ``t`` that the
    base's free parameters cannot absorb (``t`` minus its least-squares
    projection on the base fit's Jacobian); ``z ~ N(0, 1)`` under pure noise,
    and ``z^2`` approximates the chi^2 decrease the extension brings.
    """
    use = set(range(len(ctx.blocks)) if blocks is None else blocks)
    rs, ts, sel = [], [], []
    for k in range(len(ctx.blocks)):
        ok = used_points(ctx, k)
        r = np.asarray(ctx.residuals[k], float)[ok]
        if k not in use or not ok.any():
            rs.append(r); ts.append(np.zeros_like(r)); sel.append(np.zeros(r.size, bool))
            continue
        b = ctx.blocks[k] if data_blocks is None else data_blocks[k]
        f1 = block_values(b, transform(ctx.block_model(k)), ctx.block_frame(k) if isinstance(b, FrameData) else None)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.log(np.maximum(f1, 1e-300)) - np.log(np.maximum(fitted_values(ctx, k), 1e-300))) / ctx.sigma(k))[ok]
        good = np.isfinite(t)
        rs.append(r); ts.append(np.where(good, t, 0.0)); sel.append(good)
    r, t = np.concatenate(rs), np.concatenate(ts)
    J = base_jacobian(ctx)
    if J is not None and J.shape[0] == t.size and J.shape[1]:
        coef, *_ = np.linalg.lstsq(J, t, rcond=1e-10)
        t = t - J @ coef
    den = float(np.sum(t**2))
    z = float(np.sum(r * t) / math.sqrt(den)) if den > 0 else 0.0
    if full:
        # linearised refit with the extension at full strength: chi^2 change ||r - t_perp||^2 - ||r||^2
        return z, float(np.sum((r - t) ** 2) - np.sum(r**2))
    return z


def best_by_linear_chi2(ctx: Context, candidates, make) -> tuple[float, Any, float]:
    """Among ``candidates``, the one whose linearised refit lowers chi^2 most: ``(z, best, dchi2)``; z its score."""
    rows = [(*template_z(ctx, *make(c), full=True), c) for c in candidates]
    z, dchi2, best = min(rows, key=lambda x: x[1])
    return z, best, dchi2


def scatter_half_vectors(block: FrameData, frame: Conditions, phi: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-vector components on a frame's grid in the frame rotated by ``-phi`` about the normal (rad)."""
    f = Conditions(frame.theta_i, np.float64(phi), frame.wavelength)
    nh = jnp.asarray(block.grid.n_h, float)[None, :]
    nv = jnp.asarray(block.grid.n_v, float)[:, None]
    dirs = pixel_directions(block.arm_detector(), f, nh, nv)
    h = np.asarray(dirs.half_vector(), float)
    return h[..., 0], h[..., 1], h[..., 2]


def sample_ws(block: FrameData, frame: Conditions) -> np.ndarray:
    nh = jnp.asarray(block.grid.n_h, float)[None, :]
    nv = jnp.asarray(block.grid.n_v, float)[:, None]
    return np.asarray(pixel_directions(block.arm_detector(), frame, nh, nv).w_s, float)


def smooth_z(r: np.ndarray, s: float) -> np.ndarray:
    """Gaussian-weighted residual scaled to unit variance under noise: ``sum k r / sqrt(sum k^2)`` (NaN-aware)."""
    ok = np.isfinite(r)
    r0 = np.where(ok, r, 0.0)
    half = max(1, int(math.ceil(3 * s)))
    x = np.arange(-half, half + 1)
    k = np.exp(-0.5 * (x / s) ** 2)

    def same(v, kern):
        # "full" cut to the input's length: np.convolve's "same" returns the longer of the two, so a kernel
        # longer than a frame's side (8 rows at step 16) changed the map's shape
        return np.convolve(v, kern, mode="full")[half:half + v.size]

    def conv(a, kern):
        a = np.apply_along_axis(same, 0, a, kern)
        return np.apply_along_axis(same, 1, a, kern)

    num = conv(r0, k)
    den = np.sqrt(conv(ok.astype(float), k * k))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = num / den
    z[den < 0.5 * np.sqrt(np.sum(k * k) ** 2) / 4] = np.nan
    return z


def robust_mean_z(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    if v.size < 5:
        return 0.0
    return float(np.median(v) * math.sqrt(v.size) / 1.2533)


def main_specular(model: Model) -> tuple[str, Specular] | None:
    """The first top-level Specular term (or one wrapped by Oriented)."""
    for name, t in model.terms.items():
        inner = t.term if isinstance(t, Oriented) else t
        if isinstance(inner, Specular):
            return name, inner
    return None


def public_name(model: Model, flat: str) -> str:
    back = {v: k for k, v in model.aliases}
    return back.get(flat, flat)


def ws_turn(w_from: np.ndarray, w_to: np.ndarray) -> tuple[float, float]:
    """Small turns ``(ax, ay)`` about x and y with ``turn(w_from) ~ w_to`` (least squares)."""
    d = w_to - w_from
    ex, ey = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    A = np.stack([np.cross(ex, w_from), np.cross(ey, w_from)], axis=1)
    sol, *_ = np.linalg.lstsq(A, d, rcond=None)
    return float(sol[0]), float(sol[1])


def no_frames(blocks: Sequence[Any]) -> bool:
    return not any(isinstance(b, FrameData) for b in blocks)



# --- searches and residual statistics -----------------------------------------------------------


def golden(fn, lo: float, hi: float, n: int) -> tuple[float, float]:
    """Golden-section minimum of a 1-D function on [lo, hi] in ``n`` evaluations: ``(x, f(x))``."""
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = fn(c), fn(d)
    for _ in range(max(n - 2, 0)):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = fn(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = fn(d)
    return (c, fc) if fc < fd else (d, fd)


def profiled_chi2(ctx: Context, transform: Callable[[Model], Model], blocks: Sequence[int],
                   data_blocks: Sequence[Any] | None = None, lo: float = 0.15, hi: float = 1.3, n: int = 22) -> float:
    """chi^2 of the fitted base with an extension applied, profiled over the main lobe's width (golden-section
    search of its scale in [lo, hi], ``n`` evaluations) and a global log scale (closed form), on ``blocks``."""
    main = main_specular(ctx.model)
    data = ctx.blocks if data_blocks is None else data_blocks

    def chi2(scale):
        num = den = 0.0
        parts = []
        for k in blocks:
            b = data[k]
            model = ctx.block_model(k)
            if main:
                name, spec = main
                pub = public_name(model, f"{name}.{spec.distribution.width_field}")
                model = model.with_params({pub: float(np.asarray(model.params()[pub])) * scale})
            f = block_values(b, transform(model), ctx.block_frame(k) if isinstance(b, FrameData) else None)
            ok = used_points(ctx, k) & (f > 0)
            sig = ctx.sigma(k)[ok]
            dl = (np.log(np.asarray(b.brdf, float)[ok]) - np.log(f[ok])) / sig
            parts.append((dl, 1.0 / sig))
            num += float(np.sum(dl / sig)); den += float(np.sum(1.0 / sig**2))
        c = num / den if den else 0.0
        return sum(float(np.sum((dl - c * inv) ** 2)) for dl, inv in parts)

    if not main:
        return chi2(1.0)
    return golden(lambda x: chi2(math.exp(x)), math.log(lo), math.log(hi), n)[1]


def gaussianise(r: np.ndarray) -> np.ndarray:
    """Ranks turned into standard-normal scores: N(0, 1) under noise, and no single point dominates."""
    order = np.argsort(np.argsort(r))
    return np.array([_ND.inv_cdf((i + 0.5) / r.size) for i in order])


def detrend(r: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``r`` minus its least-squares quadratic surface in ``(x, y)`` (the envelope of a band's residual)."""
    sx, sy = (np.std(x) or 1.0), (np.std(y) or 1.0)
    u, v = (x - x.mean()) / sx, (y - y.mean()) / sy
    A = np.stack([np.ones_like(u), u, v, u * u, v * v, u * v], axis=1)
    if r.size <= A.shape[1]:
        return r - r.mean()
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    return r - A @ coef
