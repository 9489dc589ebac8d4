"""The library of candidate unmodelled effects, on both sides of the sim-to-real gap.

Diagnosis side (used by :func:`brdfjax.diagnose.diagnose`): every
:class:`Effect` is a named, documented extension of a base model (or of the
data's instrument function) with

- :meth:`Effect.present_in` -- the base model already has it;
- :meth:`Effect.identifiable` -- ``None``, or the reason the data cannot tell
  it apart from the base's free parameters (e.g. ``flux_scale`` when every
  term's weight is free);
- :meth:`Effect.signature` -- a residual statistic computed from the base
  fit's normalised residual ``r = (ln d - ln f) / sigma`` alone (no refit),
  reported as ``score`` in sigma-like units (the two-sided normal quantile of
  its p-value under pure noise, look-elsewhere included; ``> 3``: present);
- :meth:`Effect.extend` -- the base model plus the effect, warm-started at
  the base fit's optimum, with the effect's new parameters initialised from
  the residual (:class:`Extension`).

Generator side (synthetic truth with any effect): :func:`base_scenario`
draws a plausible single-peak base (random theta_i in 20-60 deg, phi_ref in
0-180 deg), :func:`inject` adds an effect with random plausible parameters
to a :class:`Scenario`, and :func:`synthesize` produces the measured frames
(:class:`~brdfjax.fit.FrameData`) or goniometer tables.

Effects (see each class's ``doc``): ``offset_normal_peak``, ``diffraction``,
``instrument_function``, ``lambertian``, ``anisotropic_roughness``,
``distribution_shape``, ``misalignment``, ``flux_scale``,
``pixel_nonlinearity``, ``spectral_bandwidth``, ``stray_light``,
``angular_sampling``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..detector import Detector
from ..distributions import (
    GGX,
    AbstractDistribution,
    Beckmann,
    BeckmannAniso,
    GGXAniso,
    HyperCauchy,
    StudentT,
    StudentTAniso,
)
from ..fit import FitResult, FrameData, Param, TableData
from ..fit.internal import as_param
from ..geometry import Directions
from ..render import Frame, render, sample_directions
from ..terms import AbstractTerm, Diffraction, Lambertian, Model, OffsetNormal, Specular, param_fields
from ._extensions import InstrumentResponse, Oriented, SpectralDiffraction, block_camera, camera_axes, camera_params, response_features

__all__ = [
    "Extension",
    "Effect",
    "Context",
    "Signature",
    "EFFECTS",
    "Scenario",
    "base_scenario",
    "table_scenario",
    "inject",
    "synthesize",
]


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


@dataclass
class Signature:
    """A refit-independent residual statistic: ``value`` (the effect's own measure), ``score`` (sigma-like)."""

    value: float
    score: float
    detail: str = ""


@dataclass
class Context:
    """The base fit as the effects see it (built by :func:`brdfjax.diagnose.engine.build_context`)."""

    model: Model
    params: dict
    result: FitResult
    blocks: list
    residuals: list
    model_values: list
    geometry: list
    fit_kwargs: dict = field(default_factory=dict)  # the options of the diagnosis' fits (loss, floor, ...)

    def block_model(self, k: int) -> Model:
        return self.result.models[k] if self.result.models else self.model

    def block_frame(self, k: int) -> Frame:
        b = self.blocks[k]
        if self.result.frames and self.result.frames[k] is not None:
            return self.result.frames[k]
        return Frame(b.theta_i, b.phi_ref, b.wavelength)

    def frames(self) -> list[int]:
        return [k for k, b in enumerate(self.blocks) if isinstance(b, FrameData)]

    def sigma(self, k: int) -> np.ndarray:
        b = self.blocks[k]
        if isinstance(b, TableData) and b.sigma_rel is None:
            return np.ones(np.shape(b.brdf))
        return np.broadcast_to(np.asarray(b.sigma_rel, float), np.shape(b.brdf))


class Effect:
    """One candidate effect.  Subclasses set ``name``, ``title``, ``doc``, ``needs_2d`` and the four methods."""

    name: str = ""
    title: str = ""
    doc: str = ""
    needs_2d: bool = True

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


def _precision() -> str:
    return "float64" if jax.config.jax_enable_x64 else "float32"


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


def _log_sf_normal(z: float) -> float:
    """ln P(N(0,1) > z)."""
    if z < 5:
        return math.log(max(1.0 - _ND.cdf(z), 1e-300))
    return -0.5 * z * z - math.log(z * math.sqrt(2 * math.pi)) + math.log1p(-1.0 / (z * z))


def _log_sf_chi2_even(x: float, dof: int) -> float:
    """ln P(chi2_dof > x) for even dof (Poisson sum)."""
    k = dof // 2
    h = x / 2.0
    terms = [j * math.log(h) - math.lgamma(j + 1) if h > 0 else (0.0 if j == 0 else -math.inf) for j in range(k)]
    m = max(terms)
    return -h + m + math.log(sum(math.exp(t - m) for t in terms))


def _weight_names(model: Model) -> list[tuple[str, str | None]]:
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


def _is_free(params: Mapping[str, Any], name: str | None) -> bool:
    if name is None or name not in params:
        return False
    return as_param(name, params[name]).free


def _unique_name(model: Model, base: str) -> str:
    name, i = base, 2
    while name in model.terms:
        name, i = f"{base}{i}", i + 1
    return name


def _with_terms(model: Model, terms: dict[str, AbstractTerm]) -> Model:
    """``model`` (any Model subclass, response kept) with other terms; aliases to vanished names dropped."""
    new = dataclasses.replace(model, terms=terms, aliases=())
    paths = new._paths()
    aliases = tuple((a, f) for a, f in model.aliases if f in paths)
    return dataclasses.replace(model, terms=terms, aliases=aliases)


def _drop_missing(params: Mapping[str, Any], model: Model) -> dict[str, Any]:
    known = set(model.params())
    return {k: v for k, v in params.items() if k in known or k in ("theta_i", "phi_ref")}


def _map_models(model: Model, fn: Callable[[Model], Model]) -> Model:
    return fn(model)


def _block_values(block: Any, model: Model, frame: Frame | None) -> np.ndarray:
    """Model BRDF on a block's points (frames: the whole grid, convolved with the block's footprint)."""
    if isinstance(block, FrameData):
        img = np.asarray(render(model, frame, block.arm_detector(), grid=block.grid, precision=_precision()), float)
        if block.footprint is not None:
            from ..instrument.synthetic import convolve_footprint

            k = np.asarray(block.footprint, float)
            img = np.asarray(convolve_footprint(img, k / k.sum()), float)
        return img
    dirs = Directions.from_angles(*(np.asarray(getattr(block, f), float) for f in ("theta_i", "phi_i", "theta_s", "phi_s")))
    wl = np.broadcast_to(np.asarray(block.wavelength, float), np.shape(block.brdf))
    return np.asarray(model(dirs, wl), float)


def _cache(ctx: Context) -> dict:
    return ctx.__dict__.setdefault("_fx_cache", {})


def _f0(ctx: Context, k: int) -> np.ndarray:
    """The fitted base model on block ``k``'s points, as the fit compares it (footprint applied)."""
    c = _cache(ctx)
    key = ("f0", k)
    if key not in c:
        b = ctx.blocks[k]
        c[key] = _block_values(b, ctx.block_model(k), ctx.block_frame(k) if isinstance(b, FrameData) else None)
    return c[key]


def _ok(ctx: Context, k: int) -> np.ndarray:
    return np.isfinite(np.asarray(ctx.residuals[k], float))


def _base_jacobian(ctx: Context) -> np.ndarray | None:
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
                ok = _ok(ctx, k)
                if blk is not None and blk != b.name:
                    col.append(np.zeros(int(ok.sum())))
                    continue
                model, frame = ctx.block_model(k), ctx.block_frame(k) if isinstance(b, FrameData) else None
                if base in ("theta_i", "phi_ref") and frame is not None:
                    frame = eqx_tree_at(lambda f, base=base: getattr(f, base), frame, np.float64(v + h))
                else:
                    model = model.with_params({base: v + h})
                f1 = _block_values(b, model, frame)
                with np.errstate(divide="ignore", invalid="ignore"):
                    d = (np.log(np.maximum(f1, 1e-300)) - np.log(np.maximum(_f0(ctx, k), 1e-300))) / h / ctx.sigma(k)
                col.append(np.where(np.isfinite(d), d, 0.0)[ok])
            cols.append(np.concatenate(col))
        J = np.stack(cols, axis=1) if cols else None
    except Exception:  # noqa: BLE001 - the orthogonalisation is a refinement; without it z is conservative
        J = None
    c["J"] = J
    return J


def eqx_tree_at(where, tree, value):
    import equinox as eqx

    return eqx.tree_at(where, tree, value)


def _template_z(ctx: Context, transform: Callable[[Model], Model], blocks: Sequence[int] | None = None,
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
        ok = _ok(ctx, k)
        r = np.asarray(ctx.residuals[k], float)[ok]
        if k not in use or not ok.any():
            rs.append(r); ts.append(np.zeros_like(r)); sel.append(np.zeros(r.size, bool))
            continue
        b = ctx.blocks[k] if data_blocks is None else data_blocks[k]
        f1 = _block_values(b, transform(ctx.block_model(k)), ctx.block_frame(k) if isinstance(b, FrameData) else None)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.log(np.maximum(f1, 1e-300)) - np.log(np.maximum(_f0(ctx, k), 1e-300))) / ctx.sigma(k))[ok]
        good = np.isfinite(t)
        rs.append(r); ts.append(np.where(good, t, 0.0)); sel.append(good)
    r, t = np.concatenate(rs), np.concatenate(ts)
    J = _base_jacobian(ctx)
    if J is not None and J.shape[0] == t.size and J.shape[1]:
        coef, *_ = np.linalg.lstsq(J, t, rcond=1e-10)
        t = t - J @ coef
    den = float(np.sum(t**2))
    z = float(np.sum(r * t) / math.sqrt(den)) if den > 0 else 0.0
    if full:
        # linearised refit with the extension at full strength: chi^2 change ||r - t_perp||^2 - ||r||^2
        return z, float(np.sum((r - t) ** 2) - np.sum(r**2))
    return z


def _best_by_linear_chi2(ctx: Context, candidates, make) -> tuple[float, Any, float]:
    """Among ``candidates``, the one whose linearised refit lowers chi^2 most: ``(z, best, dchi2)``; z its score."""
    rows = [(*_template_z(ctx, *make(c), full=True), c) for c in candidates]
    z, dchi2, best = min(rows, key=lambda x: x[1])
    return z, best, dchi2


def _scatter_half_vectors(block: FrameData, frame: Frame, phi: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-vector components on a frame's grid in the frame rotated by ``-phi`` about the normal (rad)."""
    f = Frame(frame.theta_i, np.float64(phi), frame.wavelength)
    nh = jnp.asarray(block.grid.n_h, float)[None, :]
    nv = jnp.asarray(block.grid.n_v, float)[:, None]
    dirs = sample_directions(block.arm_detector(), f, nh, nv)
    h = np.asarray(dirs.half_vector(), float)
    return h[..., 0], h[..., 1], h[..., 2]


def _sample_ws(block: FrameData, frame: Frame) -> np.ndarray:
    nh = jnp.asarray(block.grid.n_h, float)[None, :]
    nv = jnp.asarray(block.grid.n_v, float)[:, None]
    return np.asarray(sample_directions(block.arm_detector(), frame, nh, nv).w_s, float)


def _smooth_z(r: np.ndarray, s: float) -> np.ndarray:
    """Gaussian-weighted residual scaled to unit variance under noise: ``sum k r / sqrt(sum k^2)`` (NaN-aware)."""
    ok = np.isfinite(r)
    r0 = np.where(ok, r, 0.0)
    half = max(1, int(math.ceil(3 * s)))
    x = np.arange(-half, half + 1)
    k = np.exp(-0.5 * (x / s) ** 2)

    def conv(a, kern):
        a = np.apply_along_axis(lambda v: np.convolve(v, kern, mode="same"), 0, a)
        return np.apply_along_axis(lambda v: np.convolve(v, kern, mode="same"), 1, a)

    num = conv(r0, k)
    den = np.sqrt(conv(ok.astype(float), k * k))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = num / den
    z[den < 0.5 * np.sqrt(np.sum(k * k) ** 2) / 4] = np.nan
    return z


def _robust_mean_z(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    if v.size < 5:
        return 0.0
    return float(np.median(v) * math.sqrt(v.size) / 1.2533)


def _main_specular(model: Model) -> tuple[str, Specular] | None:
    """The first top-level Specular term (or one wrapped by Oriented)."""
    for name, t in model.terms.items():
        inner = t.term if isinstance(t, Oriented) else t
        if isinstance(inner, Specular):
            return name, inner
    return None


def _width_field(dist: AbstractDistribution) -> str:
    return param_fields(dist)[0].name


def _public(model: Model, flat: str) -> str:
    back = {v: k for k, v in model.aliases}
    return back.get(flat, flat)


def _ws_turn(w_from: np.ndarray, w_to: np.ndarray) -> tuple[float, float]:
    """Small turns ``(ax, ay)`` about x and y with ``turn(w_from) ~ w_to`` (least squares)."""
    d = w_to - w_from
    ex, ey = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    A = np.stack([np.cross(ex, w_from), np.cross(ey, w_from)], axis=1)
    sol, *_ = np.linalg.lstsq(A, d, rcond=None)
    return float(sol[0]), float(sol[1])


def _no_frames(blocks: Sequence[Any]) -> bool:
    return not any(isinstance(b, FrameData) for b in blocks)


# --- effects ------------------------------------------------------------------------------------


def _golden(fn, lo: float, hi: float, n: int) -> tuple[float, float]:
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


def _profiled_chi2(ctx: Context, transform: Callable[[Model], Model], blocks: Sequence[int],
                   data_blocks: Sequence[Any] | None = None, lo: float = 0.15, hi: float = 1.3) -> float:
    """chi^2 of the fitted base with an extension applied, profiled over the main lobe's width (golden-section
    search of its scale in [lo, hi]) and a global log scale (closed form), on ``blocks``."""
    main = _main_specular(ctx.model)
    data = ctx.blocks if data_blocks is None else data_blocks

    def chi2(scale):
        num = den = 0.0
        parts = []
        for k in blocks:
            b = data[k]
            model = ctx.block_model(k)
            if main:
                name, spec = main
                pub = _public(model, f"{name}.{_width_field(spec.distribution)}")
                model = model.with_params({pub: float(np.asarray(model.params()[pub])) * scale})
            f = _block_values(b, transform(model), ctx.block_frame(k) if isinstance(b, FrameData) else None)
            ok = _ok(ctx, k) & (f > 0)
            sig = ctx.sigma(k)[ok]
            dl = (np.log(np.asarray(b.brdf, float)[ok]) - np.log(f[ok])) / sig
            parts.append((dl, 1.0 / sig))
            num += float(np.sum(dl / sig)); den += float(np.sum(1.0 / sig**2))
        c = num / den if den else 0.0
        return sum(float(np.sum((dl - c * inv) ** 2)) for dl, inv in parts)

    if not main:
        return chi2(1.0)
    return _golden(lambda x: chi2(math.exp(x)), math.log(lo), math.log(hi), 22)[1]


def _gaussianise(r: np.ndarray) -> np.ndarray:
    """Ranks turned into standard-normal scores: N(0, 1) under noise, and no single point dominates."""
    order = np.argsort(np.argsort(r))
    return np.array([_ND.inv_cdf((i + 0.5) / r.size) for i in order])


def _detrend(r: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``r`` minus its least-squares quadratic surface in ``(x, y)`` (the envelope of a band's residual)."""
    sx, sy = (np.std(x) or 1.0), (np.std(y) or 1.0)
    u, v = (x - x.mean()) / sx, (y - y.mean()) / sy
    A = np.stack([np.ones_like(u), u, v, u * u, v * v, u * v], axis=1)
    if r.size <= A.shape[1]:
        return r - r.mean()
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    return r - A @ coef


class DiffractionEffect(Effect):
    name = "diffraction"
    title = "periodic bars (Fraunhofer diffraction)"
    doc = (
        "Adds a Diffraction term (Eq 114-115) turned about the sample normal by its own angle psi "
        "(Oriented(Diffraction), parameters <bars>.rho, .a, .c, .psi free; .b held at a/80, it is not "
        "determined by a near-specular frame).  Initialised in two stages: the band through the peak (orientation psi in 3 deg steps "
        "and half-width |h_x| < 1e-4, 2e-4 or 4e-4 with the largest summed Gaussianised residual), then the "
        "spacing a with the orientation refined: a grid search of psi (+-9 deg, 1.5 deg steps) and a "
        "(160 values from 1.5 fringes per frame to Nyquist) by the chi^2 of base + bars over a grid of rho "
        "(c = 0.8 R x half-width), refined to 0.5 deg and 0.2 %.  Signature: the periodogram of the Gaussianised (rank -> normal score), "
        "detrended residual in the band along the transverse axis h_y, |sum g exp(i k h_y)|^2 / n "
        "(exponential under noise, summed over frames), maximised over the bar frequency "
        "k = 2 pi a 2 cos(theta_i) / lambda, with the look-elsewhere factor of that search; the score is "
        "the stronger of it and the band's z (look-elsewhere over the orientations and widths), times 2 "
        "(a frame with few fringes shows the band more than its period)."
    )

    def present_in(self, model):
        return any(isinstance(t.term if isinstance(t, Oriented) else t, Diffraction | SpectralDiffraction) for t in model.terms.values())

    def identifiable(self, model, params, blocks):
        if _no_frames(blocks):
            return "needs detector frames (the bar pattern is 2-D)"
        return None

    psis = np.deg2rad(np.arange(0.0, 180.0, 3.0))
    vmaxes = (1e-4, 2e-4, 4e-4)

    def _frames(self, ctx):
        out = []
        for k in ctx.frames():
            b, fr = ctx.blocks[k], ctx.block_frame(k)
            r = np.asarray(ctx.residuals[k], float)
            ok = np.isfinite(r)
            if ok.sum() < 20:
                continue
            hx0, hy0, _ = _scatter_half_vectors(b, fr, 0.0)
            g = np.full(r.shape, np.nan)
            g[ok] = _gaussianise(r[ok])
            out.append(dict(k=k, r=r, g=g, ok=ok, hx0=hx0, hy0=hy0, phi=float(fr.phi_ref), ci=float(np.cos(fr.theta_i)),
                            wl=float(fr.wavelength), f=np.asarray(ctx.model_values[k], float), s=ctx.sigma(k),
                            d=np.asarray(ctx.blocks[k].brdf, float)))
        return out

    @staticmethod
    def _rot(c, psi):
        phi = c["phi"] + psi
        return (np.cos(phi) * c["hx0"] + np.sin(phi) * c["hy0"], -np.sin(phi) * c["hx0"] + np.cos(phi) * c["hy0"])

    def _band(self, cache):
        """Stage 1: the band through the peak: orientation and half-width with the largest summed residual."""
        best = (-np.inf, 0.0, self.vmaxes[0])
        for psi in self.psis:
            for vm in self.vmaxes:
                tot, n = 0.0, 0
                for c in cache:
                    hx, _ = self._rot(c, psi)
                    sel = c["ok"] & (np.abs(hx) < vm)
                    tot += float(np.sum(c["g"][sel])); n += int(sel.sum())
                z = tot / math.sqrt(n) if n else -np.inf
                if z > best[0]:
                    best = (z, float(psi), vm)
        return best

    def _a_grid(self, cache):
        c = cache[0]
        span = float(np.nanmax(np.hypot(c["hx0"], c["hy0"])) * 2)
        dh = float(np.median(np.abs(np.diff(c["hy0"], axis=0)))) + float(np.median(np.abs(np.diff(c["hx0"], axis=1))))
        a_lo = 1.0 * c["wl"] / (2 * c["ci"] * span)
        a_hi = c["wl"] / (2 * c["ci"] * 2.5 * max(dh, 1e-12))
        return np.geomspace(a_lo, max(a_hi, 1.01 * a_lo), 160)

    def _periodogram(self, cache, psi, vm, a_grid):
        """Stage 2: |sum g exp(i k h_y)|^2 / n of the Gaussianised, detrended residual in the band (each frame ~Exp(1))."""
        stat = np.zeros(len(a_grid))
        for c in cache:
            hx, hy = self._rot(c, psi)
            sel = c["ok"] & (np.abs(hx) < vm)
            n = int(sel.sum())
            if n < 8:
                continue
            gv = _detrend(c["g"][sel], hx[sel], hy[sel])
            freq = 2 * np.pi * a_grid[:, None] * 2 * c["ci"] / c["wl"]
            stat += np.abs(np.exp(1j * freq * hy[sel][None, :]) @ gv) ** 2 / n
        return stat

    def _chi2_a(self, cache, psi, vm, a_values, distance=0.325):
        """chi^2 of the base plus bars of spacing a (rho on a log grid, c from the band width): [(chi2, a, rho)]."""
        c0 = 0.8 * distance * vm
        rhos = np.geomspace(1e-2, 1e4, 25)
        a_values = np.asarray(a_values, float)
        tot = np.zeros((len(rhos), len(a_values)))
        for c in cache:
            hx, hy = self._rot(c, psi)
            sel = c["ok"]
            u = hy[sel] * 2 * c["ci"] / c["wl"]
            B = np.cos(np.pi * a_values[:, None] * u[None, :]) ** 2 * np.exp(-((distance * hx[sel] / c0) ** 2))[None, :]
            m = c["f"][sel][None, None, :] + rhos[:, None, None] * B[None, :, :]
            res = (np.log(np.maximum(m, 1e-300)) - np.log(c["d"][sel])[None, None, :]) / c["s"][sel][None, None, :]
            tot += np.sum(np.minimum(res**2, 1e4), axis=2)
        i = np.argmin(tot, axis=0)
        return [(float(tot[i[j], j]), float(a_values[j]), float(rhos[i[j]])) for j in range(len(a_values))]

    def signature(self, ctx):
        cache = self._frames(ctx)
        if not cache:
            return Signature(0.0, 0.0, "no detector frame with enough pixels for a periodogram")
        zb, psi, vm = self._band(cache)
        a_grid = self._a_grid(cache)
        stat = self._periodogram(cache, psi, vm, a_grid)
        m = int(np.argmax(stat))
        x = float(stat[m])
        logp_per = math.log(len(a_grid) / 3.0) + _log_sf_chi2_even(2 * x, 2 * len(cache))
        logp_band = math.log(len(self.psis) * len(self.vmaxes) / 3.0) + _log_sf_normal(zb)
        logp = math.log(2.0) + min(logp_per, logp_band)
        return Signature(
            x, score_from_logp(logp),
            f"band through the peak at psi = {np.degrees(psi):.0f} deg, |h_x| < {vm:.2g} (z = {zb:.1f}); periodogram "
            f"maximum {x:.1f} (noise mean {len(cache)}) at a = {a_grid[m]:.3g} m",
        )

    def extend(self, ctx):
        cache = self._frames(ctx)
        if not cache:
            raise ValueError("diffraction: no detector frame to initialise the bars from")
        _, psi, vm = self._band(cache)
        a_grid = self._a_grid(cache)
        # joint grid search of orientation (+-9 deg) and spacing (the whole grid) by chi^2, then a local refinement
        rows = []
        for dpsi in np.deg2rad(np.arange(-9.0, 9.1, 1.5)):
            rows += [(*row, psi + dpsi) for row in self._chi2_a(cache, psi + dpsi, vm, a_grid)]
        _, a1, _, psi1 = min(rows)
        rows = []
        for dpsi in np.deg2rad(np.arange(-1.5, 1.6, 0.5)):
            rows += [(*row, psi1 + dpsi) for row in self._chi2_a(cache, psi1 + dpsi, vm, a1 * np.linspace(0.98, 1.02, 21))]
        chi, a0, rho0, psi = min(rows)
        distance = 0.325
        c0 = 0.8 * distance * vm
        name = _unique_name(ctx.model, "bars")
        term = Oriented(Diffraction(rho=rho0, a=a0, b=a0 / 80.0, c=c0, distance=distance), psi=psi)
        model = _with_terms(ctx.model, {**ctx.model.terms, name: term})
        params = dict(ctx.params)
        params.update({
            f"{name}.rho": Param(rho0, lower=0.0),
            f"{name}.a": Param(a0, lower=a0 / 1.1, upper=a0 * 1.1),
            f"{name}.c": Param(c0, lower=0.0),
            f"{name}.psi": Param(psi, lower=psi - 0.35, upper=psi + 0.35),
        })
        return Extension(model, params, 4, note=f"bars '{name}': psi {np.degrees(psi):.1f} deg, a {a0:.4g} m, c {c0:.3g} m, rho {rho0:.3g} sr^-1 (b = a/80 held)")


class OffsetNormalPeakEffect(Effect):
    name = "offset_normal_peak"
    title = "second specular peak about a tilted normal"
    doc = (
        "Adds OffsetNormal(Specular(D)) (Eq 112-113) with D of the base's main specular lobe (its width "
        "copied), n = 1.5 held; <offset>.rho_s, the width, .dtheta and .dphi0 free.  Initialised from several "
        "start pixels per frame (the secondary residual maximum outside the peak core, the largest local "
        "maxima of the excess d - f and of the data itself): the half vector of a pixel gives the tilt "
        "(dtheta, dphi0); for each start and two widths (the base lobe's, 0.6 of it) the weight is "
        "profiled (golden-section search of the chi^2 of ln(f + rho p)), and the start of lowest chi^2 is "
        "refitted without the fit's soft first stage (and so are the later steps of a path that holds "
        "it).  (Measured: the residual maximum alone sits in the far wing of a wide base lobe when the "
        "second peak lies inside the base's core; that start refitted to chi^2 above the base's.)  "
        "Signature: the largest Gaussian-smoothed residual "
        "(sum k r / |k|) outside the base model's peak core, with the number of pixels searched as the "
        "look-elsewhere factor."
    )

    def present_in(self, model):
        return any(isinstance(t, OffsetNormal) for t in model.terms.values())

    def identifiable(self, model, params, blocks):
        if _no_frames(blocks):
            return "needs detector frames (a secondary lobe is located in 2-D)"
        return None

    def _find(self, ctx):
        best = None
        n_search = 0
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            z = _smooth_z(r, 1.2)
            core = f > 0.05 * np.nanmax(f)
            # grow the core by two pixels
            grown = core.copy()
            for _ in range(2):
                g = grown.copy()
                g[1:] |= grown[:-1]; g[:-1] |= grown[1:]; g[:, 1:] |= grown[:, :-1]; g[:, :-1] |= grown[:, 1:]
                grown = g
            zz = np.where(grown | ~np.isfinite(z), -np.inf, z)
            n_search += int(np.isfinite(z).sum())
            idx = np.unravel_index(int(np.argmax(zz)), zz.shape)
            if best is None or zz[idx] > best[0]:
                best = (float(zz[idx]), k, idx)
        return best, n_search

    def signature(self, ctx):
        best, n = self._find(ctx)
        if best is None or not math.isfinite(best[0]):
            return Signature(0.0, 0.0, "no pixels outside the peak core")
        z, k, (row, col) = best
        logp = math.log(max(n, 1) / 4.0) + _log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"secondary residual maximum z = {z:.1f} in block {k} at grid (row {row}, col {col})")

    @staticmethod
    def _local_maxima(a: np.ndarray, n: int) -> list[tuple[int, int]]:
        """The ``n`` largest local maxima (3 x 3) of ``a`` (NaN ignored), at least 3 grid pixels apart."""
        v = np.where(np.isfinite(a), a, -np.inf)
        pad = np.pad(v, 1, constant_values=-np.inf)
        neigh = np.max(np.stack([pad[1 + dr:pad.shape[0] - 1 + dr, 1 + dc:pad.shape[1] - 1 + dc]
                                 for dr in (-1, 0, 1) for dc in (-1, 0, 1)]), axis=0)
        peaks = np.argwhere((v >= neigh) & np.isfinite(v))
        peaks = peaks[np.argsort(-v[tuple(peaks.T)])]
        out: list[tuple[int, int]] = []
        for rc in peaks:
            if all(max(abs(int(rc[0]) - r), abs(int(rc[1]) - c)) >= 3 for r, c in out):
                out.append((int(rc[0]), int(rc[1])))
            if len(out) == n:
                break
        return out

    def _starts(self, ctx, best) -> list[tuple[int, int, int]]:
        """Start pixels ``(block, row, col)``: the signature's maximum, then excess and data maxima of every frame."""
        out = [] if best is None or not math.isfinite(best[0]) else [(best[1], *map(int, best[2]))]
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            d = np.where(np.isfinite(r), np.asarray(ctx.blocks[k].brdf, float), np.nan)
            excess = f * np.expm1(r * ctx.sigma(k))  # d - f against the fitted model as the fit compared it; NaN where unused
            for rc in self._local_maxima(excess, 3) + self._local_maxima(d, 2):
                if (k, *rc) not in out:
                    out.append((k, *rc))
        return out

    def _tilt(self, ctx, k, row, col) -> tuple[float, float]:
        b, fr = ctx.blocks[k], ctx.block_frame(k)
        hx, hy, hz = _scatter_half_vectors(b, fr, float(fr.phi_ref))
        h = np.array([hx[row, col], hy[row, col], hz[row, col]])
        return float(np.arctan2(np.hypot(h[0], h[1]), h[2])), float(np.arctan2(h[1], h[0]))

    @staticmethod
    def _frame_data(ctx) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Per frame on its used points: ``(k, used, ln d, f, sigma)`` (shared by every start's profile)."""
        out = []
        for k in ctx.frames():
            ok = _ok(ctx, k)
            out.append((k, ok, np.log(np.asarray(ctx.blocks[k].brdf, float)[ok]), np.asarray(ctx.model_values[k], float)[ok],
                        ctx.sigma(k)[ok]))
        return out

    def _profile(self, ctx, frames, dist, dtheta, dphi0) -> tuple[float, float]:
        """``(chi2, rho)``: the chi^2 of ln(f + rho p) over ``frames``, minimised over ln rho (golden section)."""
        if not frames:
            return math.inf, 0.1
        probe = Model(terms={"p": OffsetNormal(Specular(dist, rho_s=1.0, n=1.5), dtheta=dtheta, dphi0=dphi0)})
        parts = [(ld, f, _block_values(ctx.blocks[k], probe, ctx.block_frame(k))[ok], sg) for k, ok, ld, f, sg in frames]

        def chi2(lnrho):
            rho = math.exp(lnrho)
            return sum(float(np.sum(((ld - np.log(np.maximum(f + rho * p, 1e-300))) / sg) ** 2)) for ld, f, p, sg in parts)

        x, c = _golden(chi2, math.log(1e-4), math.log(10.0), 30)
        return c, math.exp(x)

    def extend(self, ctx):
        best, _ = self._find(ctx)
        starts = self._starts(ctx, best)
        if not starts:
            raise ValueError("offset_normal_peak: no secondary residual maximum to start from")
        main = _main_specular(ctx.model)
        dist0 = main[1].distribution if main else Beckmann(2e-4)
        wfield = _width_field(dist0)
        frames = self._frame_data(ctx)
        trials = []
        for k, row, col in starts:
            dtheta, dphi0 = self._tilt(ctx, k, row, col)
            for wf in (1.0, 0.6):
                dist = eqx_tree_at(lambda d: getattr(d, wfield), dist0, getattr(dist0, wfield) * wf)
                c, rho = self._profile(ctx, frames, dist, dtheta, dphi0)
                trials.append((c, dtheta, dphi0, dist, rho, (k, row, col)))
        c, dtheta, dphi0, dist, rho, (k, row, col) = min(trials, key=lambda t: t[0])
        name = _unique_name(ctx.model, "offset")
        term = OffsetNormal(Specular(dist, rho_s=rho, n=1.5), dtheta=dtheta, dphi0=dphi0)
        model = _with_terms(ctx.model, {**ctx.model.terms, name: term})
        wname = f"{name}.{wfield}"
        width = float(np.asarray(getattr(dist, wfield)))
        params = dict(ctx.params)
        params.update({
            f"{name}.rho_s": Param(rho, lower=0.0),
            wname: Param(width, lower=0.0),
            f"{name}.dtheta": Param(dtheta, scale=max(dtheta, 1e-3)),
            f"{name}.dphi0": Param(dphi0, scale=0.5),
        })
        # the start is profiled; the fit's default soft first stage (wings below the median softened) walked
        # away from it (measured on an offset + anisotropic truth: reduced chi^2 16804 with it, 1026 without).
        # Like every extension's fit_kwargs it stays with the path: later steps refit without it too.
        return Extension(model, params, 4, fit_kwargs={"first_stage": None}, note=(
            f"offset peak '{name}': dtheta {np.degrees(dtheta):.4f} deg, dphi0 {np.degrees(dphi0):.1f} deg, rho_s {rho:.3g}, "
            f"width {width:.3g} (best of {len(trials)} starts: block {k}, grid row {row}, col {col}; profiled chi^2 {c:.4g})"))


class LambertianEffect(Effect):
    name = "lambertian"
    title = "diffuse floor (Lambertian)"
    needs_2d = False
    doc = (
        "Adds Lambertian(rho_d) (rho_d / pi sr^-1).  Signature: the matched filter of the residual with the "
        "change in ln f a uniform floor makes (largest far from the peak, one-sided: a floor raises the "
        "data), at floors of 0.1, 0.3 and 1 times the faint data's level (the 10 % quantile), "
        "look-elsewhere over the three; the best level initialises rho_d = pi level."
    )

    def present_in(self, model):
        return any(isinstance(t, Lambertian) for t in model.terms.values())

    def _levels(self, ctx):
        faint = []
        for b in ctx.blocks:
            d = np.asarray(b.brdf, float)[b.usable()]
            faint.append(np.quantile(d, 0.1))
        base = float(np.median(faint))
        return [base * f for f in (0.1, 0.3, 1.0)]

    def _scan(self, ctx):
        out = []
        for c in self._levels(ctx):
            out.append((_template_z(ctx, lambda m, c=c: _with_terms(m, {**m.terms, "_floor": Lambertian(math.pi * c)})), c))
        return max(out)

    def signature(self, ctx):
        z, c = self._scan(ctx)
        logp = math.log(1.5) + _log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"matched filter of a uniform floor: z = {z:.1f} at a level {c:.3g} sr^-1")

    def extend(self, ctx):
        z, c = self._scan(ctx)
        rho_d = math.pi * c
        name = _unique_name(ctx.model, "floor")
        model = _with_terms(ctx.model, {**ctx.model.terms, name: Lambertian(rho_d)})
        params = dict(ctx.params)
        params[f"{name}.rho_d"] = Param(rho_d, lower=0.0)
        return Extension(model, params, 1, note=f"diffuse floor '{name}': rho_d start {rho_d:.3g}")


class InstrumentFunctionEffect(Effect):
    name = "instrument_function"
    title = "convolution with the beam signature (instrument function)"
    doc = (
        "Data side: every frame gets a footprint (FrameData.footprint), the pixel-integrated Gaussian "
        "exp(-2 r^2 / w^2) of the focused beam (Eq 73), with which the fit convolves the model.  No new "
        "model parameter; the 1/e^2 radius w (0.5-11 grid pixels, then a golden-section search) is the one with the lowest "
        "chi^2 profiled over the main lobe's width (golden-section search) and a global log scale; n_new = 1 (w).  Signature: the score test "
        "z = r . t_perp / |t_perp| at that width (the symmetric shoulder: core down, wings up)."
    )
    widths = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.5, 6.0, 8.0, 11.0)

    def present_in(self, model):
        return False

    def identifiable(self, model, params, blocks):
        frames = [b for b in blocks if isinstance(b, FrameData)]
        if not frames:
            return "needs detector frames (the instrument function is a 2-D convolution)"
        if all(b.footprint is not None for b in frames):
            return "every frame already carries an instrument function (footprint)"
        return None

    def _blocks(self, ctx, w):
        from ..instrument.synthetic import footprint_kernel

        ker = footprint_kernel(w)
        return [dataclasses.replace(b, footprint=ker) if isinstance(b, FrameData) and b.footprint is None else b for b in ctx.blocks]

    def _profile(self, ctx, w):
        return _profiled_chi2(ctx, lambda m: m, ctx.frames(), self._blocks(ctx, w))

    def _scan(self, ctx):
        rows = [(self._profile(ctx, w), w) for w in self.widths]
        _, w = min(rows)
        lw, _ = _golden(lambda x: self._profile(ctx, math.exp(x)), math.log(w / 1.4), math.log(w * 1.4), 14)
        w = math.exp(lw)
        z = _template_z(ctx, lambda m: m, ctx.frames(), self._blocks(ctx, float(w)))
        return z, float(w)

    def signature(self, ctx):
        z, w = self._scan(ctx)
        logp = math.log(len(self.widths) / 2.0) + _log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"matched filter z = {z:.1f} for a footprint of 1/e^2 radius {w:g} grid pixels")

    def extend(self, ctx):
        z, w = self._scan(ctx)
        return Extension(ctx.model, dict(ctx.params), 1, blocks=self._blocks(ctx, w), fit_kwargs={"use_footprint": True},
                         note=f"footprint 1/e^2 radius {w:.3g} grid pixels (matched-filter z {z:.1f})")


class FluxScaleEffect(Effect):
    name = "flux_scale"
    title = "global flux scale (OD / incident-flux error)"
    needs_2d = False
    doc = (
        "Instrument side: the measured BRDF is flux_scale times the model (InstrumentResponse feature "
        "'flux_scale', parameter instrument.flux_scale in [0.1, 10]).  Initialised as exp of the median "
        "log residual.  Not identifiable when every term's weight is free (they absorb any global "
        "scale); fix the weights by calibration to test it.  Signature: a constant offset of the residual: "
        "the smaller (same sign) of the robust mean-residual z of the bright and the faint half of the points."
    )

    def present_in(self, model):
        return "flux_scale" in response_features(model)

    def identifiable(self, model, params, blocks):
        w = _weight_names(model)
        if w and all(_is_free(params, n) for _, n in w):
            names = ", ".join(n for _, n in w)
            return (f"flux_scale multiplies every term and every term's weight is free ({names}): a global scale "
                    "is absorbed by them; fix the weights (calibration) to test a flux error")
        return None

    def _halves(self, ctx):
        bright, faint, all_ = [], [], []
        for k in range(len(ctx.blocks)):
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            ok = np.isfinite(r)
            if not ok.any():
                continue
            med = np.median(f[ok])
            bright.append(r[ok & (f >= med)]); faint.append(r[ok & (f < med)])
            all_.append((r * ctx.sigma(k))[ok])
        cat = lambda x: np.concatenate(x) if x else np.zeros(0)  # noqa: E731
        return cat(bright), cat(faint), cat(all_)

    def signature(self, ctx):
        b, f, a = self._halves(ctx)
        zb, zf = _robust_mean_z(b), _robust_mean_z(f)
        z = min(abs(zb), abs(zf)) if zb * zf > 0 else 0.0
        return Signature(float(np.median(a)) if a.size else 0.0, score_from_logp(_log_sf_normal(z) + math.log(2)),
                         f"residual offset: bright half z = {zb:.1f}, faint half z = {zf:.1f}")

    def extend(self, ctx):
        _, _, a = self._halves(ctx)
        s = float(np.clip(np.exp(np.median(a)), 0.2, 5.0)) if a.size else 1.0
        model = InstrumentResponse.wrap(ctx.model, "flux_scale", flux_scale=s)
        params = dict(ctx.params)
        params["instrument.flux_scale"] = Param(s, lower=0.1, upper=10.0)
        return Extension(model, params, 1, note=f"flux scale start {s:.4g}")


class PixelNonlinearityEffect(Effect):
    name = "pixel_nonlinearity"
    title = "non-linear signal response (power law)"
    needs_2d = False
    doc = (
        "Instrument side: the measured BRDF is f_ref (s f / f_ref)^gamma (InstrumentResponse features "
        "'nonlinearity' and 'flux_scale': instrument.gamma in [0.5, 1.5], f_ref the geometric mean of the "
        "fitted model over the points, held).  The level at which the response is exact is not known, so "
        "the scale s (instrument.flux_scale in [0.1, 10]) is freed with gamma whenever a global scale is "
        "identifiable (some term's weight fixed by calibration) and not already in the model; with f_ref "
        "at the geometric mean, s and gamma are nearly uncorrelated.  (Measured: with gamma alone, a "
        "response exact at 1 sr^-1 was ranked behind flux_scale in 2 of 3 withheld-effect trials and "
        "needed both on the path.)  A power law of a lone Beckmann lobe is a narrower lobe times a "
        "scale; frames at different incident angles separate them only to second order (the geometric "
        "factor 1 / (cos theta_i cos theta_s) raised to gamma), so a lone Beckmann lobe of free width is "
        "reported as not identifiable.  Initialised by regressing the log residual on ln f (slope: gamma - 1, "
        "intercept at f_ref: ln s).  Signature: the t-statistic of that slope over the points where the "
        "model is above 1e-3 of its maximum (a residual correlated with the log signal)."
    )

    def present_in(self, model):
        return "nonlinearity" in response_features(model)

    def identifiable(self, model, params, blocks):
        terms = list(model.terms.values())
        if len(terms) == 1 and isinstance(terms[0], Specular) and isinstance(terms[0].distribution, Beckmann):
            (tname, _), = _weight_names(model)
            width = _public(model, f"{tname}.m")
            # the scale comes with gamma where a weight is fixed (extend), so a free weight is not needed for this
            if _is_free(params, width):
                return (f"a power law f^gamma of a lone Beckmann lobe is the same lobe with m / sqrt(gamma) and another "
                        f"scale: with {width} free the data cannot tell it from a flux scale or a weight (measured: "
                        f"flux_scale alone reached the true model's chi^2); fix the width or add a term of another "
                        f"shape with a calibrated weight (a diffuse floor)")
        return None

    def _regress(self, ctx):
        X, Y, W = [], [], []
        for k in range(len(ctx.blocks)):
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            s = ctx.sigma(k)
            ok = np.isfinite(r) & (f > 0)
            if not ok.any():
                continue
            ok &= f > 1e-3 * f[ok].max()
            X.append(np.log(f[ok])); Y.append(r[ok] * s[ok]); W.append(1.0 / s[ok] ** 2)
        if not X:
            return 0.0, 0.0, 1.0, 0.0
        x, y, w = np.concatenate(X), np.concatenate(Y), np.concatenate(W)
        xm = np.sum(w * x) / np.sum(w)
        ym = float(np.sum(w * y) / np.sum(w))
        sxx = np.sum(w * (x - xm) ** 2)
        if sxx <= 0:
            return 0.0, 0.0, float(np.exp(xm)), ym
        beta = float(np.sum(w * (x - xm) * (y - ym)) / sxx)
        return beta, beta * math.sqrt(sxx), float(np.exp(xm)), ym

    def signature(self, ctx):
        beta, z, _, _ = self._regress(ctx)
        return Signature(beta, score_from_logp(_log_sf_normal(abs(z)) + math.log(2)), f"slope of the log residual on ln f: {beta:.4f} (t = {z:.1f})")

    def extend(self, ctx):
        beta, _, fref, ym = self._regress(ctx)
        g = float(np.clip(1.0 + beta, 0.6, 1.4))
        params = dict(ctx.params)
        params["instrument.gamma"] = Param(g, lower=0.5, upper=1.5)
        scale = ("flux_scale" not in response_features(ctx.model)
                 and EFFECTS["flux_scale"].identifiable(ctx.model, ctx.params, ctx.blocks) is None)
        if not scale:
            model = InstrumentResponse.wrap(ctx.model, "nonlinearity", gamma=g, f_ref=fref)
            return Extension(model, params, 1, note=f"gamma start {g:.4f} about f_ref {fref:.3g} sr^-1")
        # the response's exact level is unknown: a scale with it (s^gamma at f_ref: the residual's mean there)
        s = float(np.clip(np.exp(ym / g), 0.2, 5.0))
        model = InstrumentResponse.wrap(ctx.model, "flux_scale", "nonlinearity", gamma=g, f_ref=fref, flux_scale=s)
        params["instrument.flux_scale"] = Param(s, lower=0.1, upper=10.0)
        return Extension(model, params, 2, note=f"gamma start {g:.4f} about f_ref {fref:.3g} sr^-1, with scale start {s:.4g}")


_FAMILIES: dict[str, tuple[type, tuple[str, ...]]] = {
    "beckmann": (Beckmann, ("m",)),
    "ggx": (GGX, ("alpha",)),
    "student_t": (StudentT, ("sigma", "gamma")),
    "hyper_cauchy": (HyperCauchy, ("sigma", "gamma")),
}


def _family_of(dist: AbstractDistribution) -> str | None:
    for name, (cls, _) in _FAMILIES.items():
        if type(dist) is cls:
            return name
    return None


def _matched(dist: AbstractDistribution, family: str, gamma: float = 3.0) -> AbstractDistribution:
    """A distribution of ``family`` whose log matches ``dist`` over its bright part (width by a 1-D search)."""
    cls, _ = _FAMILIES[family]
    w0 = float(np.asarray(getattr(dist, _width_field(dist))))
    t = w0 * np.linspace(0.0, 4.0, 80)
    d0 = np.asarray(dist(jnp.asarray(t**2), jnp.zeros_like(jnp.asarray(t))), float)
    keep = d0 > 1e-3 * d0[0]
    best, arg = np.inf, w0
    for w in w0 * np.geomspace(0.3, 3.0, 81):
        cand = cls(w) if len(_FAMILIES[family][1]) == 1 else cls(w, gamma)
        d1 = np.asarray(cand(jnp.asarray(t**2), jnp.zeros_like(jnp.asarray(t))), float)
        with np.errstate(divide="ignore"):
            err = np.sum((np.log(d1[keep]) - np.log(d0[keep])) ** 2)
        if err < best:
            best, arg = err, w
    return cls(arg) if len(_FAMILIES[family][1]) == 1 else cls(arg, gamma)


def _specular_terms(model: Model) -> list[str]:
    out = []
    for name, t in model.terms.items():
        inner = t.term if isinstance(t, OffsetNormal | Oriented) else t
        if isinstance(inner, Specular) and _family_of(inner.distribution):
            out.append(name)
    return out


def _swap_dist(term: AbstractTerm, new: AbstractDistribution) -> AbstractTerm:
    if isinstance(term, OffsetNormal | Oriented):
        return dataclasses.replace(term, term=_swap_dist(term.term, new))
    return dataclasses.replace(term, distribution=new)


def _inner_specular(term: AbstractTerm) -> Specular:
    return term.term if isinstance(term, OffsetNormal | Oriented) else term


class DistributionShapeEffect(Effect):
    name = "distribution_shape"
    title = "microfacet distribution shape (swap D)"
    needs_2d = False
    doc = (
        "Swaps the distribution D of every specular term (plain or offset) among Beckmann, GGX, Student-t "
        "and Hyper-Cauchy.  One effect: extend() width-matches each alternative family to the fitted D "
        "(least squares of ln D over the bright part; Student-t starts at gamma = 3, Hyper-Cauchy at 2), "
        "refits the model with each family and keeps the lowest chi^2 (the families' chi^2 are in the "
        "note); the widths (and gamma) are free, n_new counts the added shape "
        "parameters (0 for GGX <-> Beckmann).  Signature: the wing-vs-core residual pattern, the "
        "difference of the mean residual in the wings (1e-3 to 0.1 of the peak) and in the core (> 0.1), "
        "in units of its standard error."
    )

    def present_in(self, model):
        return False

    def identifiable(self, model, params, blocks):
        if not _specular_terms(model):
            return "no specular term with a Beckmann, GGX, Student-t or Hyper-Cauchy distribution to swap"
        return None

    def signature(self, ctx):
        core, wing = [], []
        for k in range(len(ctx.blocks)):
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            ok = np.isfinite(r)
            if not ok.any():
                continue
            mx = f[ok].max()
            core.append(r[ok & (f > 0.1 * mx)]); wing.append(r[ok & (f > 1e-3 * mx) & (f <= 0.1 * mx)])
        c, w = np.concatenate(core), np.concatenate(wing)
        if c.size < 3 or w.size < 3:
            return Signature(0.0, 0.0, "too few points in the core or the wings")
        d = (w.mean() - c.mean()) / math.sqrt(1.0 / w.size + 1.0 / c.size)
        return Signature(float(d), score_from_logp(_log_sf_normal(abs(d)) + math.log(2)),
                         f"wing mean residual {w.mean():.2f} ({w.size} points) vs core {c.mean():.2f} ({c.size}): z = {d:.1f}")

    #: start of the shape exponent of the families that have one (free in [1.05, 50])
    gamma_start = {"student_t": 3.0, "hyper_cauchy": 2.0}

    def _candidate(self, ctx, family, gamma=3.0):
        names = _specular_terms(ctx.model)
        swaps = {}
        for n in names:
            d = _inner_specular(ctx.model.terms[n]).distribution
            if _family_of(d) == family:
                continue
            swaps[n] = _matched(d, family, gamma)

        def transform(m: Model) -> Model:
            terms = dict(m.terms)
            for n, new in swaps.items():
                old = _inner_specular(terms[n]).distribution
                w = float(np.asarray(getattr(old, _width_field(old))))
                w_new = float(np.asarray(getattr(new, _width_field(new))))
                w0 = float(np.asarray(getattr(_inner_specular(ctx.model.terms[n]).distribution, _width_field(old))))
                scaled = dataclasses.replace(new, **{_width_field(new): w_new * w / w0})
                terms[n] = _swap_dist(terms[n], scaled)
            return _with_terms(m, terms)

        return swaps, transform

    def _params(self, ctx, model, swaps):
        params = _drop_missing(ctx.params, model)
        n_new = 0
        for n in swaps:
            inner = _inner_specular(model.terms[n]).distribution
            old = _inner_specular(ctx.model.terms[n]).distribution
            for f in param_fields(inner):
                v = float(np.asarray(getattr(inner, f.name)))
                pub = _public(model, f"{n}.{f.name}")
                params[pub] = Param(v, lower=1.05, upper=50.0) if f.name == "gamma" else Param(v, lower=0.0)
            n_new += len(param_fields(inner)) - len(param_fields(old))
        return params, max(n_new, 0)

    def extend(self, ctx):
        # Each alternative family is refitted and the best chi^2 kept (its fitted values are the engine's warm
        # start).  A linearised score cannot choose: where the base D underflows in the far wings, the change
        # in ln f of every heavier-tailed family is the same huge number, and in the withheld-effect benchmark
        # all three families scored alike (z = 810) and the first one (GGX) was refitted to 45x the chi^2 of
        # the true Student-t model.
        from ..fit import fit
        from .engine import warm_params

        base_fams = {_family_of(_inner_specular(ctx.model.terms[n]).distribution) for n in _specular_terms(ctx.model)}
        tried, errors = [], []
        for fam in _FAMILIES:
            if base_fams == {fam}:
                continue
            gamma = self.gamma_start.get(fam, 3.0)
            swaps, tr = self._candidate(ctx, fam, gamma)
            if not swaps:
                continue
            model = tr(ctx.model)
            params, n_new = self._params(ctx, model, swaps)
            try:
                r = fit(model, ctx.blocks, params, **ctx.fit_kwargs)
            except Exception as e:  # noqa: BLE001 - one family failing leaves the others
                errors.append(f"{fam}: {type(e).__name__}: {e}")
                continue
            chi2 = float(r.chi2)
            if math.isfinite(chi2):
                tried.append((chi2, fam, swaps, model, warm_params(params, r), n_new))
        if not tried:
            raise ValueError("distribution_shape: nothing to swap" + (f" ({'; '.join(errors)})" if errors else ""))
        tried.sort(key=lambda t: t[0])
        _, fam, swaps, model, params, n_new = tried[0]
        others = ", ".join(f"{f} chi2={c:.6g}" for c, f, *_ in tried)
        return Extension(model, params, n_new, note=f"D -> {fam} for {', '.join(swaps)} (refitted families: {others})")


_ANISO = {Beckmann: (BeckmannAniso, ("mx", "my")), GGX: (GGXAniso, ("alpha_x", "alpha_y")), StudentT: (StudentTAniso, ("sigma_x", "sigma_y"))}


class AnisotropicRoughnessEffect(Effect):
    name = "anisotropic_roughness"
    title = "anisotropic roughness (elliptical lobe)"
    doc = (
        "Replaces each top-level specular term's isotropic D (Beckmann, GGX, Student-t) by its anisotropic "
        "form (BeckmannAniso, GGXAniso, StudentTAniso) turned by its own angle psi (Oriented); widths along "
        "x', y' and psi free (n_new = 2 per term).  Initialised from the quadrupole of the residual about "
        "the half vector: psi = atan2(S, C) / 2 with C, S the sums of r cos 2 phi_h, r sin 2 phi_h in the "
        "peak's wings; widths m (1 +- 0.15).  Signature: chi^2 = C^2 / var + S^2 / var (2 dof per frame): "
        "an elliptical residual pattern."
    )

    def present_in(self, model):
        for t in model.terms.values():
            inner = t.term if isinstance(t, Oriented) else t
            if isinstance(inner, Specular) and type(inner.distribution) in (BeckmannAniso, GGXAniso, StudentTAniso):
                return True
        return False

    def _terms(self, model):
        out = []
        for n, t in model.terms.items():
            if isinstance(t, Specular) and type(t.distribution) in _ANISO:
                out.append(n)
        return out

    def identifiable(self, model, params, blocks):
        if _no_frames(blocks):
            return "needs detector frames (an elliptical lobe is seen in 2-D)"
        if not self._terms(model):
            return "no top-level isotropic specular term (Beckmann, GGX, Student-t) to make anisotropic"
        return None

    def _quad(self, ctx):
        C = S = vc = vs = 0.0
        chi2, nfr = 0.0, 0
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            ok = np.isfinite(r)
            if not ok.any():
                continue
            fr = ctx.block_frame(k)
            hx, hy, _ = _scatter_half_vectors(ctx.blocks[k], fr, float(fr.phi_ref))
            mx = f[ok].max()
            sel = ok & (f > 1e-3 * mx) & (f < 0.7 * mx)
            ph = np.arctan2(hy, hx)
            c, s = np.cos(2 * ph)[sel], np.sin(2 * ph)[sel]
            ck, sk = float(np.sum(r[sel] * c)), float(np.sum(r[sel] * s))
            vck, vsk = float(np.sum(c * c)), float(np.sum(s * s))
            if vck > 0 and vsk > 0:
                chi2 += ck**2 / vck + sk**2 / vsk
                nfr += 1
            C, S, vc, vs = C + ck, S + sk, vc + vck, vs + vsk
        return C, S, chi2, nfr

    def signature(self, ctx):
        C, S, chi2, n = self._quad(ctx)
        if n == 0:
            return Signature(0.0, 0.0, "no wing pixels")
        return Signature(chi2, score_from_logp(_log_sf_chi2_even(chi2, 2 * n)),
                         f"quadrupole chi^2 = {chi2:.1f} ({2 * n} dof), axis {np.degrees(0.5 * math.atan2(S, C)):.0f} deg")

    def extend(self, ctx):
        C, S, _, _ = self._quad(ctx)
        psi = 0.5 * math.atan2(S, C)
        names = self._terms(ctx.model)
        terms = dict(ctx.model.terms)
        params = dict(ctx.params)
        for n in names:
            old = ctx.model.terms[n].distribution
            w = float(np.asarray(getattr(old, _width_field(old))))
            cls, (fx, fy) = _ANISO[type(old)]
            kw = {fx: w * 1.15, fy: w * 0.85}
            if isinstance(old, StudentT):
                kw["gamma"] = old.gamma
            terms[n] = Oriented(dataclasses.replace(ctx.model.terms[n], distribution=cls(**kw)), psi=psi)
        model = _with_terms(ctx.model, terms)
        params = _drop_missing(params, model)
        for n in names:
            old = ctx.model.terms[n].distribution
            cls, (fx, fy) = _ANISO[type(old)]
            w = float(np.asarray(getattr(old, _width_field(old))))
            params[_public(model, f"{n}.{fx}")] = Param(w * 1.15, lower=0.0)
            params[_public(model, f"{n}.{fy}")] = Param(w * 0.85, lower=0.0)
            params[_public(model, f"{n}.psi")] = Param(psi, scale=0.5)
        return Extension(model, params, 2 * len(names), note=f"anisotropic {', '.join(names)}: psi start {np.degrees(psi):.1f} deg")


class MisalignmentEffect(Effect):
    name = "misalignment"
    title = "detector misalignment (roll/yaw/pitch, m_h, m_v)"
    doc = (
        "Instrument side, as a model-side wrapper (brdfjax.fit has no detector parameters): the model is "
        "evaluated at scatter directions turned by Rz(rz) Ry(ry) Rx(rx) about the camera's axes "
        "(InstrumentResponse feature 'misalignment'; instrument.rx, .ry, .rz shared by all frames, start 0; "
        "instrument.arm, .arm_phi fixed per frame at the frame's arm angle and phi_ref).  An offset of the array by m_h, m_v "
        "pixels is a turn of m * pitch / R, a roll a turn about the optical axis; yaw and pitch of the "
        "array about its centre change the pixel directions only to second order.  One camera, one turn: "
        "the same turn predicts frames not fitted (held-out frames).  Signature: the dipole of the residual at the peak: the residual regressed on the "
        "model's log gradient (-d ln f / d row, -d ln f / d col) over the peak (chi^2, 2 dof per frame); "
        "the fitted shift in grid pixels is reported."
    )

    def present_in(self, model):
        return "misalignment" in response_features(model)

    def identifiable(self, model, params, blocks):
        if _no_frames(blocks):
            return "needs detector frames (a goniometer table has no detector mapping)"
        return None

    def _dipole(self, ctx):
        chi2, n, shifts = 0.0, 0, []
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            s = ctx.sigma(k)
            ok = np.isfinite(r) & (f > 0)
            if ok.sum() < 10:
                continue
            L = np.log(np.maximum(f, 1e-300))
            gr, gc = np.gradient(L)
            sel = ok & (f > 1e-3 * f[ok].max()) & np.isfinite(gr) & np.isfinite(gc)
            A = np.stack([-gr[sel] / s[sel], -gc[sel] / s[sel]], axis=1)
            AtA = A.T @ A
            if np.linalg.cond(AtA) > 1e12:
                continue
            beta = np.linalg.solve(AtA, A.T @ r[sel])
            chi2 += float(beta @ AtA @ beta)
            n += 1
            shifts.append(beta)
        return chi2, n, shifts

    def signature(self, ctx):
        chi2, n, shifts = self._dipole(ctx)
        if n == 0:
            return Signature(0.0, 0.0, "no peak to test")
        sh = "; ".join(f"({b[0]:+.2f}, {b[1]:+.2f})" for b in shifts)
        return Signature(chi2, score_from_logp(_log_sf_chi2_even(chi2, 2 * n)), f"dipole chi^2 = {chi2:.1f} ({2 * n} dof); shift (rows, cols) per frame: {sh}")

    def extend(self, ctx):
        model = InstrumentResponse.wrap(ctx.model, "misalignment")
        params = dict(ctx.params)
        for p in ("rx", "ry", "rz"):
            params[f"instrument.{p}"] = Param(0.0, per_frame=False, scale=2e-3)
        params.update(camera_params(ctx.blocks))
        return Extension(model, params, 3, note="camera turns rx, ry, rz (shared by all frames) from 0")


class SpectralBandwidthEffect(Effect):
    name = "spectral_bandwidth"
    title = "finite source bandwidth (smeared diffraction orders)"
    doc = (
        "Replaces the base's Diffraction term by SpectralDiffraction: the bars averaged over a Gaussian "
        "line of relative rms width <bars>.width = sigma_lambda / lambda (15 Gauss-Hermite nodes), free in "
        "[0, 0.3]; higher orders smear into stripes.  Needs a diffraction term in the base.  Initialised "
        "at the width (0.2 %-8 %) whose linearised refit lowers chi^2 most; signature: the score test "
        "z = r . t_perp / |t_perp| of that smearing (t_perp: its change in ln f less what the base absorbs)."
    )
    widths = (0.002, 0.005, 0.01, 0.02, 0.04, 0.08)

    def present_in(self, model):
        return any(isinstance(t.term if isinstance(t, Oriented) else t, SpectralDiffraction) for t in model.terms.values())

    def _bars(self, model):
        return [n for n, t in model.terms.items() if isinstance(t.term if isinstance(t, Oriented) else t, Diffraction)]

    def identifiable(self, model, params, blocks):
        if not self._bars(model):
            return "the base model has no diffraction term: a source bandwidth shows through diffraction only"
        return None

    def _transform(self, width):
        def tr(m: Model) -> Model:
            terms = dict(m.terms)
            for n in self._bars(m):
                t = terms[n]
                if isinstance(t, Oriented):
                    terms[n] = dataclasses.replace(t, term=SpectralDiffraction.from_diffraction(t.term, width))
                else:
                    terms[n] = SpectralDiffraction.from_diffraction(t, width)
            return _with_terms(m, terms)

        return tr

    def _scan(self, ctx):
        z, w, _ = _best_by_linear_chi2(ctx, self.widths, lambda w: (self._transform(w),))
        return z, w

    def signature(self, ctx):
        z, w = self._scan(ctx)
        logp = math.log(len(self.widths) / 2.0) + _log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"matched filter z = {z:.1f} for a relative line width {w:g}")

    def extend(self, ctx):
        z, w = self._scan(ctx)
        names = self._bars(ctx.model)
        model = self._transform(w)(ctx.model)
        params = dict(ctx.params)
        for n in names:
            params[f"{n}.width"] = Param(w, lower=0.0, upper=0.3)
        return Extension(model, params, len(names), note=f"line width start {w:g} (sigma_lambda / lambda) for {', '.join(names)}")


class StrayLightEffect(Effect):
    name = "stray_light"
    title = "stray light (displaced sub-peak and background)"
    doc = (
        "Instrument side: the measured BRDF is f + ghost f(turned) + background (InstrumentResponse "
        "feature 'stray_light': instrument.ghost, .background, and the copy's turn .ghost_x, .ghost_y about "
        "the camera's axes, shared by all frames: a ghost sits at a fixed offset on the array).  Initialised from the cross-correlation of the residual with the base model's peak "
        "footprint (the model above 10 % of its maximum): its maximum away from zero shift gives the copy's "
        "offset (turned into ghost_x, ghost_y) and the excess there its relative amplitude.  Signature: "
        "that matched filter's maximum z over the shifts searched."
    )

    def present_in(self, model):
        return "stray_light" in response_features(model)

    def identifiable(self, model, params, blocks):
        if _no_frames(blocks):
            return "needs detector frames (sub-peaks are displaced images on the array)"
        return None

    def _xcorr(self, ctx):
        best, n_shift = None, 0
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            ok = np.isfinite(r)
            if not ok.any():
                continue
            T = (f > 0.1 * np.nanmax(f)).astype(float)
            rows, cols = r.shape
            shape = (2 * rows, 2 * cols)
            R0 = np.where(ok, r, 0.0)
            F = np.fft.rfft2(R0, shape) * np.conj(np.fft.rfft2(T, shape))
            num = np.fft.irfft2(F, shape)
            N = np.fft.irfft2(np.fft.rfft2(ok.astype(float), shape) * np.conj(np.fft.rfft2(T * T, shape)), shape)
            with np.errstate(invalid="ignore", divide="ignore"):
                z = num / np.sqrt(np.maximum(N, 1e-12))
            z[N < 0.5 * T.sum()] = -np.inf
            # exclude small shifts (the peak itself): within the footprint's extent
            rr, cc = np.nonzero(T)
            ext_r = (rr.max() - rr.min()) if rr.size else 1
            ext_c = (cc.max() - cc.min()) if cc.size else 1
            dr = np.fft.fftfreq(shape[0], 1.0 / shape[0])[:, None]
            dc = np.fft.fftfreq(shape[1], 1.0 / shape[1])[None, :]
            z[(np.abs(dr) <= max(ext_r // 2 + 1, 2)) & (np.abs(dc) <= max(ext_c // 2 + 1, 2))] = -np.inf
            n_shift += int(np.isfinite(z).sum())
            i = np.unravel_index(int(np.argmax(z)), z.shape)
            if best is None or z[i] > best[0]:
                best = (float(z[i]), k, int(dr[i[0], 0]), int(dc[0, i[1]]))
        return best, n_shift

    def signature(self, ctx):
        best, n = self._xcorr(ctx)
        if best is None or not math.isfinite(best[0]):
            return Signature(0.0, 0.0, "no room for a displaced copy in the frames")
        z, k, dr, dc = best
        logp = math.log(max(n, 1) / 4.0) + _log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"displaced-copy matched filter z = {z:.1f} at a shift of ({dr}, {dc}) grid pixels (block {k})")

    def extend(self, ctx):
        best, _ = self._xcorr(ctx)
        if best is None or not math.isfinite(best[0]):
            raise ValueError("stray_light: no displaced copy to start from")
        _, k0, dr, dc = best
        gx, gy, ratio = [], [], []
        for k in ctx.frames():
            b, fr = ctx.blocks[k], ctx.block_frame(k)
            f = np.asarray(ctx.model_values[k], float)
            ws = _sample_ws(b, fr)
            pr, pc = np.unravel_index(int(np.nanargmax(f)), f.shape)
            qr, qc = int(np.clip(pr + dr, 0, f.shape[0] - 1)), int(np.clip(pc + dc, 0, f.shape[1] - 1))
            # the turn about the camera's axes (one offset on the array is one turn in every frame)
            to_cam = np.asarray(camera_axes(*block_camera(b)), float).T
            ax, ay = _ws_turn(to_cam @ ws[qr, qc], to_cam @ ws[pr, pc])
            gx.append(ax); gy.append(ay)
            r = np.asarray(ctx.residuals[k], float)
            if np.isfinite(r[qr, qc]):
                ratio.append(f[qr, qc] * (math.exp(r[qr, qc] * float(ctx.sigma(k)[qr, qc])) - 1.0) / f[pr, pc])
        g0 = float(np.clip(np.median(ratio), 1e-7, 0.5)) if ratio else 1e-4
        data_min = min(float(np.nanmin(np.asarray(b.brdf, float)[b.usable()])) for b in ctx.blocks)
        bg = 1e-3 * data_min
        gx0, gy0 = float(np.median(gx)), float(np.median(gy))
        model = InstrumentResponse.wrap(ctx.model, "stray_light", ghost=g0, ghost_x=gx0, ghost_y=gy0, background=bg)
        params = dict(ctx.params)
        params["instrument.ghost"] = Param(g0, lower=0.0, upper=1.0)
        params["instrument.ghost_x"] = Param(gx0, per_frame=False, scale=2e-3)
        params["instrument.ghost_y"] = Param(gy0, per_frame=False, scale=2e-3)
        params["instrument.background"] = Param(bg, lower=0.0)
        params.update(camera_params(ctx.blocks))
        return Extension(model, params, 4, note=f"copy shifted by ({dr}, {dc}) grid pixels at {g0:.3g} of the peak")


class AngularSamplingEffect(Effect):
    name = "angular_sampling"
    title = "angular footprint of each goniometer sample"
    needs_2d = False
    doc = (
        "Model averaged over each sample's square angular footprint of full width instrument.aperture "
        "(InstrumentResponse feature 'aperture': 21 x 5 midpoints, in-plane x out-of-plane turns of the "
        "scatter direction), for goniometer tables whose step can straddle a narrow peak.  Initialised at "
        "the aperture (0.05-3 deg, refined to 10 %) with the lowest chi^2 profiled over the main lobe's "
        "width (x 0.05-1.5, golden section) and a global log scale; signature: that profiled chi^2 decrease "
        "against no aperture, as sqrt (1 dof) with the look-elsewhere factor of the apertures (a lobe "
        "narrower than the footprint gives a flat-topped, box-like measured peak that no lobe width fits).  Frames only: pixels are far smaller than "
        "any feature, so it is not identifiable there."
    )
    apertures_deg = (0.05, 0.1, 0.2, 0.4, 0.8, 1.5, 3.0)

    def present_in(self, model):
        return "aperture" in response_features(model)

    def identifiable(self, model, params, blocks):
        if not any(isinstance(b, TableData) for b in blocks):
            return "concerns goniometer tables; a detector pixel's footprint is far below any feature of the model"
        return None

    def _tr(self, a):
        return lambda m: InstrumentResponse.wrap(m, "aperture", aperture=a)

    def _scan(self, ctx):
        tables = [k for k, b in enumerate(ctx.blocks) if isinstance(b, TableData)]
        none = _profiled_chi2(ctx, lambda m: m, tables, lo=0.05, hi=1.5)
        rows = [(_profiled_chi2(ctx, self._tr(np.deg2rad(a)), tables, lo=0.05, hi=1.5), a) for a in self.apertures_deg]
        chi, a = min(rows)
        rows = [(_profiled_chi2(ctx, self._tr(np.deg2rad(a * f)), tables, lo=0.05, hi=1.5), a * f) for f in (0.8, 0.9, 1.0, 1.12, 1.25)]
        chi, a = min(rows)
        return max(none - chi, 0.0), float(a)

    def signature(self, ctx):
        d, a = self._scan(ctx)
        z = math.sqrt(d)
        logp = math.log(len(self.apertures_deg) / 2.0) + _log_sf_normal(z)
        return Signature(d, score_from_logp(logp), f"profiled chi^2 decrease {d:.1f} for an aperture of {a:.3g} deg")

    def extend(self, ctx):
        z, a = self._scan(ctx)
        a = float(np.deg2rad(a))
        model = InstrumentResponse.wrap(ctx.model, "aperture", aperture=a)
        params = dict(ctx.params)
        params["instrument.aperture"] = Param(a, lower=0.0, upper=float(np.deg2rad(10.0)))
        return Extension(model, params, 1, note=f"aperture start {np.degrees(a):.3g} deg")


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        OffsetNormalPeakEffect(),
        DiffractionEffect(),
        InstrumentFunctionEffect(),
        LambertianEffect(),
        AnisotropicRoughnessEffect(),
        DistributionShapeEffect(),
        MisalignmentEffect(),
        FluxScaleEffect(),
        PixelNonlinearityEffect(),
        SpectralBandwidthEffect(),
        StrayLightEffect(),
        AngularSamplingEffect(),
    )
}


# --- generator side (synthetic truth with any effect) ---------------------------------------------

from ._fx_generate import (  # noqa: E402
    EXCLUSIVE as EXCLUSIVE,
    GENERATORS as GENERATORS,
    Scenario as Scenario,
    base_scenario as base_scenario,
    inject as inject,
    synthesize as synthesize,
    table_scenario as table_scenario,
)
