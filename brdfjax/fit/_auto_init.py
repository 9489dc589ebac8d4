"""Automatic start values from the data (NumPy float64 at the edge; the core maps the geometry).

A 2e-4 wide peak is never found by a local solver from a guess a few widths
away, so ``"auto"`` starts are read off the data.  Initialisers are registered
by name (:data:`INITIALIZERS`) and called as ``init(model, blocks,
**options) -> {name: value or [value per block]}``.

``solar_cell`` (the seed's three-term model on detector frames), per frame:

1. **Centre and offset peaks.** The brightest usable pixel and the brightest
   one more than six peak widths from it are the two specular peaks; the one
   nearer the macro normal (half-vector slope 0) is the centre peak.  Each is
   fitted with an isotropic log-quadratic in the half-vector slopes
   ``s = (h_x, h_y) / h_z`` (scatter frame, from the core's pixel mapping),
   ``log f = A - |s - s0|^2 / m^2`` (the Beckmann exponent), over the pixels
   within e^-9 of its maximum: ``m`` is the width (m1, m2), ``s0`` the
   peak's normal.  The offset normal relative to the centre one gives
   ``dtheta`` (its tilt) and ``dphi0 + phi_ref`` (its azimuth from +x);
   the centre normal's in-plane slope gives ``theta_i`` (the specular
   direction moves by twice the tilt).
2. **Bar orientation.** Outside six widths of both peaks, the
   intensity-weighted second moment of the slopes about the centre normal has
   its main axis along the diffraction band, the sample's y axis
   ``(-sin phi_ref, cos phi_ref)``: ``phi_ref`` modulo 180 deg, taken nearest
   the frame's nominal value.
3. **Band width and spacing.** In the sample frame, the intensity-weighted
   variance of ``x = R h_x`` across the band is ``c^2 / 2`` (the Gaussian
   ``exp(-x^2/c^2)``); along it, the fringes ``cos^2(pi a u)`` with ``u = 2
   h_y cos(theta_i) / lambda`` are a cosine of frequency ``a`` in ``u``
   (the seed's "peak spacing"): ``a`` maximises the cosine periodogram of the
   band's core, summed over frames, refined on a fine grid.
4. **Amplitudes.** With every shape parameter set and the index priors
   (``n1``, ``n2``; ``b``, which a frame hardly constrains, from its prior),
   ``rho_s1``, ``rho_s2``, ``rho_s3`` solve a log-space least-squares
   problem in the amplitudes (Gauss-Newton on ``log rho``) over every usable
   pixel of every frame.

``specular_peak`` (one Specular term, possibly turned by
:class:`~brdfjax.core.terms.Oriented`, with an optional Lambertian term; detector
frames): the mirror, polished-aluminium and Kapton presets; see
:func:`init_specular_peak`.

``specular_lambertian`` (one specular term with a Beckmann- or GGX-type width,
plus one Lambertian term; tables or frames): ``rho_d`` from the low
quantile of the data, the width the best (least squared log residual, with
the amplitudes as in 4 at each width) of a log-quadratic in ``tan^2 theta_h``
over the points well above the diffuse level and 11 widths from 0.003 to 1,
the index from its prior (``n``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.distributions import GGX, Beckmann, BeckmannAniso, GGXAniso
from ..core.geometry import Directions
from ..core.render import Conditions, pixel_directions
from ..core.terms import Diffraction, Lambertian, Model, OffsetNormal, Oriented, Specular
from ..instrument.synthetic import convolve_footprint
from ..io.blocks import FrameData, TableData
from ._common import FitInputError

__all__ = [
    "INITIALIZERS", "get_initializer", "init_solar_cell", "init_specular_lambertian", "init_specular_peak",
    "fit_amplitudes",
]


# --- helpers ------------------------------------------------------------------------------


def _frame_geometry(b: FrameData) -> dict[str, np.ndarray]:
    """Half-vector slopes and unit half vectors (scatter frame) of every grid pixel, float64."""
    det = b.arm_detector()
    dirs = det.directions(np.asarray(b.grid.n_h, float)[None, :], np.asarray(b.grid.n_v, float)[:, None], np.float64(b.theta_i))
    w = np.asarray(dirs.w_sum, np.float64)
    h = w / np.linalg.norm(w, axis=-1, keepdims=True)
    return {"sx": w[..., 0] / w[..., 2], "sy": w[..., 1] / w[..., 2], "h": h}


def _peak_fit(sx: np.ndarray, sy: np.ndarray, L: np.ndarray, ok: np.ndarray, seed: int, radius: float, depth: float):
    """Isotropic log-quadratic ``L = A - |s - s0|^2 / m^2`` around pixel ``seed`` (flat index)."""
    sx0, sy0 = sx.flat[seed], sy.flat[seed]
    d2 = (sx - sx0) ** 2 + (sy - sy0) ** 2
    near = ok & (d2 < radius**2) & (L > L.flat[seed] - depth)
    if near.sum() < 6:
        raise FitInputError("automatic initialisation: fewer than 6 usable pixels on a peak; use a finer grid or give starts")
    X = np.stack([np.ones(near.sum()), sx[near], sy[near], sx[near] ** 2 + sy[near] ** 2], -1)
    coef, *_ = np.linalg.lstsq(X, L[near], rcond=None)
    alpha, beta, gamma, delta = coef
    if not delta < 0:
        raise FitInputError("automatic initialisation: a peak is not peaked (log-quadratic fit has no maximum)")
    m2 = -1.0 / delta
    cx, cy = -beta / (2 * delta), -gamma / (2 * delta)
    A = alpha - (cx**2 + cy**2) * delta
    return cx, cy, math.sqrt(m2), A


def _find_peak(sx, sy, L, ok, seed: int) -> tuple[float, float, float, float]:
    """Two passes: a first width from the top e^-3 within a wide radius, then within 3 widths and e^-9."""
    radius = 2e-3
    for _ in range(6):
        cx, cy, m, A = _peak_fit(sx, sy, L, ok, seed, radius, 3.0)
        if m < radius / 3:
            break
        radius *= 4
    return _peak_fit(sx, sy, L, ok, seed, max(3.5 * m, 1e-6), 9.0)


def fit_amplitudes(
    unit_values: Sequence[np.ndarray], data: np.ndarray, weights: np.ndarray | None = None, steps: int = 30
) -> np.ndarray:
    """Non-negative amplitudes ``a`` of ``f = sum_k a_k g_k`` with log residuals ``log f - log d``.

    A relative linear least-squares start, then Gauss-Newton in ``log a``.
    """
    G = np.stack([np.asarray(g, np.float64).ravel() for g in unit_values], -1)
    d = np.asarray(data, np.float64).ravel()
    w = np.ones_like(d) if weights is None else np.asarray(weights, np.float64).ravel()
    active = np.any(G > 0, axis=0)
    a = np.ones(G.shape[1])
    A = (G / d[:, None])[:, active] * w[:, None]
    sol, *_ = np.linalg.lstsq(A, w, rcond=None)
    a[active] = np.where(sol > 0, sol, np.abs(sol) + 1e-12)
    tiny = 1e-300
    for _ in range(steps):
        f = G @ a + tiny
        r = (np.log(f) - np.log(d)) * w
        J = (G * a / f[:, None])[:, active] * w[:, None]
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        step = np.clip(step, -3.0, 3.0)
        a_new = a.copy()
        a_new[active] *= np.exp(step)
        if np.sum((np.log(G @ a_new + tiny) - np.log(d)) ** 2 * w**2) > np.sum(r**2):
            a_new[active] = a[active] * np.exp(0.3 * step)
        a = a_new
        if np.max(np.abs(step)) < 1e-8:
            break
    return a


def _wrap(x: float) -> float:
    return float((x + np.pi) % (2 * np.pi) - np.pi)


# --- solar cell ---------------------------------------------------------------------------


def _solar_terms(model: Model) -> tuple[Specular, OffsetNormal, Diffraction]:
    t = model.terms
    if not (
        set(t) == {"center", "offset", "bars"}
        and isinstance(t["center"], Specular)
        and isinstance(t["offset"], OffsetNormal)
        and isinstance(t["bars"], Diffraction)
    ):
        raise FitInputError(
            "initializer 'solar_cell' needs the solar-cell model (terms center: Specular, offset: OffsetNormal, "
            f"bars: Diffraction), got terms {sorted(t)}"
        )
    return t["center"], t["offset"], t["bars"]


def _band_orientation(sx, sy, d, sel, c1, nominal: float) -> float:
    w = d[sel]
    x = sx[sel] - c1[0]
    y = sy[sel] - c1[1]
    M = np.array([[np.sum(w * x * x), np.sum(w * x * y)], [np.sum(w * x * y), np.sum(w * y * y)]])
    evals, evecs = np.linalg.eigh(M)
    ex, ey = evecs[:, -1]
    phi = math.atan2(-ex, ey)
    # pi-periodic: the branch nearest the nominal orientation
    k = round((nominal - phi) / math.pi)
    return phi + k * math.pi


def _periodogram_a(us: list[np.ndarray], ys: list[np.ndarray], a_lo: float, a_hi: float) -> float:
    span = max(float(np.ptp(u)) for u in us)
    n_grid = int(min(20000, max(200, 8 * (a_hi - a_lo) * span)))
    grid = np.linspace(a_lo, a_hi, n_grid)

    def power(a_values):
        p = np.zeros(a_values.size)
        for u, y in zip(us, ys):
            yc = y / np.mean(y) - 1.0
            for i0 in range(0, a_values.size, 512):
                blk = a_values[i0 : i0 + 512]
                p[i0 : i0 + 512] += np.cos(2 * np.pi * blk[:, None] * u[None, :]) @ yc / u.size
        return p

    p = power(grid)
    best = grid[int(np.argmax(p))]
    step = grid[1] - grid[0]
    for _ in range(3):
        fine = np.linspace(best - 2 * step, best + 2 * step, 81)
        pf = power(fine)
        best, step = fine[int(np.argmax(pf))], fine[1] - fine[0]
    return float(best)


def init_solar_cell(
    model: Model,
    blocks: Sequence[FrameData | TableData],
    *,
    n1: float | None = None,
    n2: float | None = None,
    b: float | None = None,
    a_range: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Start values of the solar-cell model from detector frames (see the module docstring).

    ``n1``, ``n2`` (index priors) and ``b`` (bar width prior, m) default to
    the model's values; ``a_range`` bounds the spacing search (m; default
    from the frames' sampling).
    """
    center, offset, bars = _solar_terms(model)
    frames = [blk for blk in blocks if isinstance(blk, FrameData)]
    if len(frames) != len(blocks):
        raise FitInputError("initializer 'solar_cell' works on detector frames only; give starts for tables")
    n1 = float(np.asarray(center.n)) if n1 is None else float(n1)
    n2 = float(np.asarray(offset.term.n)) if n2 is None else float(n2)
    b_width = float(np.asarray(bars.b)) if b is None else float(b)
    R = float(bars.distance)

    per: list[dict[str, Any]] = []
    for fr in frames:
        geo = _frame_geometry(fr)
        sx, sy, h = geo["sx"], geo["sy"], geo["h"]
        d = np.asarray(fr.brdf, np.float64)
        ok = fr.check_usable()
        L = np.where(ok, np.log(np.where(ok, d, 1.0)), -np.inf)
        first = int(np.argmax(L))
        p1 = _find_peak(sx, sy, L, ok, first)
        far = ok & (((sx - p1[0]) ** 2 + (sy - p1[1]) ** 2) > (6 * p1[2]) ** 2)
        if not far.any():
            raise FitInputError(f"frame '{fr.name}': only one peak found; the solar-cell model needs both specular peaks")
        second = int(np.argmax(np.where(far, L, -np.inf)))
        p2 = _find_peak(sx, sy, L, ok, second)
        if math.hypot(p1[0], p1[1]) <= math.hypot(p2[0], p2[1]):
            pc, po = p1, p2
        else:
            pc, po = p2, p1
        # offset normal relative to the centre normal
        ddx, ddy = po[0] - pc[0], po[1] - pc[1]
        dtheta = math.atan(math.hypot(ddx, ddy))
        azimuth = math.atan2(ddy, ddx)  # dphi0 + phi_ref, from +x toward +y
        theta_i = float(fr.theta_i) + 2.0 * math.atan(pc[0])
        # band: outside both peaks
        away = ok & (((sx - pc[0]) ** 2 + (sy - pc[1]) ** 2) > (6 * pc[2]) ** 2) & (
            ((sx - po[0]) ** 2 + (sy - po[1]) ** 2) > (6 * po[2]) ** 2
        )
        if away.sum() < 20:
            raise FitInputError(f"frame '{fr.name}': too few pixels off the peaks to see the diffraction band")
        dmax = d[away].max()
        band = away & (d > 1e-2 * dmax)
        phi_ref = _band_orientation(sx, sy, d, band, pc, float(fr.phi_ref))
        cph, sph = math.cos(phi_ref), math.sin(phi_ref)
        hx = cph * h[..., 0] + sph * h[..., 1]  # sample frame (Rz(-phi_ref) h)
        hy = -sph * h[..., 0] + cph * h[..., 1]
        xbar = R * hx
        w = d[band]
        c = math.sqrt(2.0 * np.sum(w * xbar[band] ** 2) / np.sum(w))
        # refit the centre peak without the band that crosses it (it biases the width)
        off_band = ok & (np.abs(xbar) > 2.5 * c)
        try:
            pc = _peak_fit(sx, sy, L, off_band, first if pc is p1 else second, 3.5 * pc[2], 9.0)
        except FitInputError:
            pass  # too few pixels off the band: keep the first estimate
        per.append(
            dict(
                frame=fr, m1=pc[2], m2=po[2], dtheta=dtheta, azimuth=azimuth, theta_i=theta_i, phi_ref=phi_ref,
                c=c, hy=hy, xbar=xbar, away=away, d=d, ok=ok,
            )
        )

    c = float(np.median([p["c"] for p in per]))
    # spacing: cosine periodogram of the band core along u, all frames together
    us, ys, du = [], [], []
    for p in per:
        fr = p["frame"]
        core = p["away"] & (np.abs(p["xbar"]) < c) & p["ok"]
        if core.sum() < 20:
            raise FitInputError(f"frame '{fr.name}': too few pixels in the core of the diffraction band")
        scale = (2.0 * math.cos(float(fr.theta_i)) if bars.grating_factor else 1.0) / float(fr.wavelength)
        u = p["hy"][core] * scale
        y = p["d"][core] / np.exp(-((p["xbar"][core] / c) ** 2))
        us.append(u)
        ys.append(y)
        us_sorted = np.sort(np.abs(u))
        gaps = np.diff(us_sorted)
        du.append(np.median(gaps[gaps > 0]) if np.any(gaps > 0) else np.inf)
    span = max(float(np.ptp(u)) for u in us)
    if a_range is None:
        # sampling along the band: rows of the grid; at least two fringes in view
        a_hi = 0.5 / max(_along_band_step(p) for p in per)
        a_lo = 2.0 / span
    else:
        a_lo, a_hi = (float(x) for x in a_range)
    if not a_hi > a_lo:
        raise FitInputError(f"automatic initialisation: empty search range for the bar spacing a: [{a_lo:.3g}, {a_hi:.3g}] m")
    a = _periodogram_a(us, ys, a_lo, a_hi)

    m1 = float(np.median([p["m1"] for p in per]))
    m2 = float(np.median([p["m2"] for p in per]))
    dtheta = float(np.median([p["dtheta"] for p in per]))
    dphi_k = np.array([p["azimuth"] - p["phi_ref"] for p in per])
    dphi0 = _wrap(math.atan2(np.mean(np.sin(dphi_k)), np.mean(np.cos(dphi_k))))

    shape = model.with_params(
        {"center.m": m1, "center.n": n1, "offset.m": m2, "offset.n": n2, "offset.dtheta": dtheta, "offset.dphi0": dphi0,
         "bars.a": a, "bars.b": b_width, "bars.c": c, "center.rho_s": 1.0, "offset.rho_s": 1.0, "bars.rho": 1.0}
    )
    units = {"center": [], "offset": [], "bars": []}
    data = []
    for p in per:
        fr = p["frame"]
        frame = Conditions(np.float64(p["theta_i"]), np.float64(p["phi_ref"]), np.float64(fr.wavelength))
        # the whole grid (one compiled shape for every frame of a joint fit), then the usable pixels
        tv = _grid_term_values(shape, frame, fr)
        for k in units:
            units[k].append(tv[k][p["ok"]])
        data.append(p["d"][p["ok"]])
    amp = fit_amplitudes([np.concatenate(units[k]) for k in ("center", "offset", "bars")], np.concatenate(data))
    return {
        "m1": m1, "rho_s1": float(amp[0]), "n1": n1,
        "m2": m2, "rho_s2": float(amp[1]), "n2": n2,
        "dtheta": dtheta, "dphi0": dphi0,
        "a": a, "b": b_width, "c": c, "rho_s3": float(amp[2]),
        "theta_i": [p["theta_i"] for p in per],
        "phi_ref": [p["phi_ref"] for p in per],
    }


@eqx.filter_jit
def _term_values_jit(model, frame, detector, n_h, n_v):
    return model.term_values(pixel_directions(detector, frame, n_h[None, :], n_v[:, None]), frame.wavelength)


def _grid_term_values(model: Model, frame: Conditions, fr: FrameData) -> dict[str, np.ndarray]:
    tv = _term_values_jit(model, frame, fr.arm_detector(), np.asarray(fr.grid.n_h, float), np.asarray(fr.grid.n_v, float))
    return {k: np.asarray(v, np.float64) for k, v in tv.items()}


def _along_band_step(p: dict[str, Any]) -> float:
    """The largest step of ``u`` between neighbouring grid pixels along the band (for the Nyquist limit)."""
    fr = p["frame"]
    scale = (2.0 * math.cos(float(fr.theta_i))) / float(fr.wavelength)
    hy = p["hy"] * scale
    steps = []
    if hy.shape[0] > 1:
        steps.append(np.nanmedian(np.abs(np.diff(hy, axis=0))))
    if hy.shape[1] > 1:
        steps.append(np.nanmedian(np.abs(np.diff(hy, axis=1))))
    return float(max(steps))


# --- specular + Lambertian ----------------------------------------------------------------

#: Distributions whose width this initializer estimates (their ``width_field`` says which field).
_WIDTH_ESTIMATED = (Beckmann, GGX)


def _specular_lambertian_terms(model: Model) -> tuple[str, Specular, str, str]:
    spec = [(k, t) for k, t in model.terms.items() if isinstance(t, Specular)]
    lamb = [k for k, t in model.terms.items() if isinstance(t, Lambertian)]
    if len(spec) != 1 or len(lamb) != 1 or len(model.terms) != 2:
        raise FitInputError(
            "initializer 'specular_lambertian' needs a model of one Specular and one Lambertian term, got "
            + ", ".join(f"{k}: {type(t).__name__}" for k, t in model.terms.items())
        )
    name, term = spec[0]
    dist = type(term.distribution)
    if dist not in _WIDTH_ESTIMATED:
        raise FitInputError(
            f"initializer 'specular_lambertian': no width estimate for the {type(term.distribution).__name__} "
            f"distribution (known: {', '.join(c.__name__ for c in _WIDTH_ESTIMATED)}); give its start value"
        )
    return name, term, lamb[0], dist.width_field


def _public(model: Model, flat: str) -> str:
    back = {v: k for k, v in model.aliases}
    return back.get(flat, flat)


def _directions_of(blk: FrameData | TableData) -> tuple[Directions, np.ndarray, np.ndarray]:
    ok = blk.check_usable()
    d = np.asarray(blk.brdf, np.float64)[ok]
    if isinstance(blk, TableData):
        ang = [np.asarray(getattr(blk, f), np.float64)[ok] for f in ("theta_i", "phi_i", "theta_s", "phi_s")]
        wl = np.broadcast_to(np.asarray(blk.wavelength, np.float64), ok.shape)[ok]
        return Directions.from_angles(*ang), wl, d
    rows, cols = np.nonzero(ok)
    frame = Conditions(np.float64(blk.theta_i), np.float64(blk.phi_ref), np.float64(blk.wavelength))
    dirs = pixel_directions(blk.arm_detector(), frame, np.asarray(blk.grid.n_h, float)[cols], np.asarray(blk.grid.n_v, float)[rows])
    return dirs, np.full(d.shape, float(blk.wavelength)), d


def init_specular_lambertian(
    model: Model, blocks: Sequence[FrameData | TableData], *, n: float | None = None, k: float | None = None,
    diffuse_quantile: float = 0.05,
) -> dict[str, Any]:
    """Start values of a specular (Beckmann or GGX) + Lambertian model from any data (module docstring)."""
    sname, sterm, lname, width = _specular_lambertian_terms(model)
    n = float(np.asarray(sterm.n)) if n is None else float(n)
    k = float(np.asarray(sterm.k)) if k is None else float(k)
    dirs_l, wl_l, d_l = zip(*(_directions_of(b) for b in blocks))
    d = np.concatenate(d_l)
    t2 = np.concatenate([np.asarray(sum(dd.half_slopes()[:2]), np.float64) for dd in dirs_l])
    diffuse = float(np.quantile(d, diffuse_quantile))
    rho_d = math.pi * diffuse
    excess = d - diffuse
    sel = excess > 3.0 * diffuse
    if sel.sum() >= 3:
        # log(excess) = A - t2 / m^2 over the points well above the diffuse level, upper half of their range
        le = np.log(excess[sel])
        top = le > np.median(le)
        X = np.stack([np.ones(top.sum()), t2[sel][top]], -1)
        coef, *_ = np.linalg.lstsq(X, le[top], rcond=None)
        m = 1.0 / math.sqrt(-coef[1]) if coef[1] < 0 else 0.1
    else:
        m = 0.3
    m_reg = float(np.clip(m, 1e-4, 1.0))

    def amplitudes(m: float) -> tuple[float, np.ndarray]:
        """The amplitudes at width ``m`` and the sum of squared log residuals they leave."""
        shape = model.with_params({f"{sname}.{width}": m, f"{sname}.n": n, f"{sname}.k": k, f"{sname}.rho_s": 1.0,
                                   f"{lname}.rho_d": 1.0})
        g_s, g_d = [], []
        for dd, wl in zip(dirs_l, wl_l):
            tv = shape.term_values(dd, jnp.asarray(wl))
            g_s.append(np.asarray(tv[sname], np.float64))
            g_d.append(np.asarray(tv[lname], np.float64))
        gs, gd = np.concatenate(g_s), np.concatenate(g_d)
        amp = fit_amplitudes([gs, gd], d)
        f = amp[0] * gs + amp[1] * gd
        return (float(np.sum((np.log(f) - np.log(d)) ** 2)) if np.all(f > 0) else math.inf), amp

    # The regression's width is one candidate of a profile over the width: the log-quadratic is Beckmann's form
    # and is fitted to the points far above the floor, so on a lobe with a broad haze it comes out too wide, and
    # the amplitude fit then hands all the signal to the floor.  Measured on the Cornell Cayman table (every 2nd
    # row, GGX + Lambertian): the regression gave alpha 0.57 and rho_s 1.6e-15, a dead lobe that the fit kept
    # (rank 1 of 3, sigma_ln 2.03; from alpha 0.1 by hand: alpha 0.045, rho_s 0.43, sigma_ln 1.83).
    profile = [(*amplitudes(w), w) for w in [m_reg, *map(float, np.geomspace(3e-3, 1.0, 11))]]
    _, amp, m = min(profile, key=lambda x: x[0])
    return {
        _public(model, f"{sname}.{width}"): m,
        _public(model, f"{sname}.rho_s"): float(amp[0]),
        _public(model, f"{sname}.n"): n,
        _public(model, f"{sname}.k"): k,
        _public(model, f"{lname}.rho_d"): float(amp[1]) if amp[1] > 0 else rho_d,
    }



# --- a single specular peak (mirror, polished aluminium, Kapton presets) ------------------


def _peak_terms(model: Model) -> tuple[str, Specular, Any, str | None] | None:
    """``(name, specular, oriented wrapper or None, lambertian name or None)`` of a one-peak model, else None."""
    spec, lamb = [], []
    for name, t in model.terms.items():
        if isinstance(t, Specular):
            spec.append((name, t, None))
        elif isinstance(t, Oriented) and isinstance(t.term, Specular):
            spec.append((name, t.term, t))
        elif isinstance(t, Lambertian):
            lamb.append(name)
        else:
            return None
    if len(spec) != 1 or len(lamb) > 1:
        return None
    name, term, wrapper = spec[0]
    return name, term, wrapper, (lamb[0] if lamb else None)


#: Distributions whose peak widths this initializer estimates: each class's ``width_fields`` and
#: ``peak_width_factor`` (from the Beckmann-equivalent slope width to the field's width; near its
#: maximum GGX is ``(1 + t^2/alpha^2)^-2 ~ exp(-2 t^2 / alpha^2)``: alpha = sqrt(2) m).
_PEAK_WIDTH_ESTIMATED = (Beckmann, GGX, BeckmannAniso, GGXAniso)


def _quadratic_peak(sx, sy, L, ok, seed: int, ggx: bool = False, depth: float = 3.0):
    """A general quadratic peak ``(s - s0)^T M (s - s0)`` over the top ``depth`` of the peak at ``seed``.

    Beckmann-type (``ggx=False``): ``L = A - (s - s0)^T M (s - s0)``.  GGX-type: ``exp(-(L - A) / 2) =
    1 + (s - s0)^T M (s - s0)`` (``D^-1/2`` is quadratic in the slopes), fitted as a quadratic and
    normalised by its value at ``s0``; its ``M^-1`` is ``diag(alpha_x^2, alpha_y^2)`` turned, returned as the
    Beckmann-equivalent ``M^-1 / 2`` (the peaks agree to second order).  Returns ``(s0, C)`` with ``C`` the
    Beckmann-equivalent ``diag(mx^2, my^2)`` in the axes of the peak.  Two passes: a window from an
    isotropic first guess, then the top ``depth`` within 3.5 widths.
    """
    cx, cy, m, _ = _find_peak(sx, sy, L, ok, seed)
    top = L.flat[seed]
    radius = 4.0 * m
    for _ in range(2):
        d2 = (sx - cx) ** 2 + (sy - cy) ** 2
        sel = ok & (L > top - depth) & (d2 < radius**2)
        if sel.sum() < 8:
            raise FitInputError("automatic initialisation: fewer than 8 usable pixels on the peak; use a finer grid or give starts")
        x, y = sx[sel] - cx, sy[sel] - cy
        X = np.stack([np.ones(x.size), x, y, x * x, x * y, y * y], -1)
        v = np.exp(-(L[sel] - top) / 2.0) if ggx else L[sel]
        c, *_ = np.linalg.lstsq(X, v, rcond=None)
        Q = np.array([[c[3], c[4] / 2], [c[4] / 2, c[5]]])
        M = Q if ggx else -Q
        if not np.all(np.linalg.eigvalsh(M) > 0):
            raise FitInputError("automatic initialisation: the peak is not peaked (its quadratic has no extremum)")
        shift = np.linalg.solve(2 * M, -c[1:3] if ggx else c[1:3])
        cx, cy = cx + shift[0], cy + shift[1]
        if ggx:
            v0 = c[0] - 0.25 * c[1:3] @ np.linalg.solve(Q, c[1:3])  # the quadratic's value at its minimum
            C = np.linalg.inv(M / max(v0, 1e-12)) / 2.0
        else:
            C = np.linalg.inv(M)
        radius = 3.5 * math.sqrt(float(np.max(np.linalg.eigvalsh(C))) * (2.0 if ggx else 1.0))
    return np.array([cx, cy]), C


def _footprint_cov(fr: FrameData, sx: np.ndarray, sy: np.ndarray, idx: int) -> np.ndarray:
    """The footprint's contribution to ``C`` in slope space: ``2 J cov_k J^T`` (``C = M^-1`` adds as 2 cov)."""
    k = np.asarray(fr.footprint, np.float64)
    k = k / k.sum()
    r = np.arange(k.shape[0]) - k.shape[0] // 2
    c = np.arange(k.shape[1]) - k.shape[1] // 2
    R, Cc = np.meshgrid(r, c, indexing="ij")
    cov_pix = np.array([[np.sum(k * Cc * Cc), np.sum(k * Cc * R)], [np.sum(k * Cc * R), np.sum(k * R * R)]])
    i, j = np.unravel_index(idx, sx.shape)
    i0, i1 = max(i - 1, 0), min(i + 1, sx.shape[0] - 1)
    j0, j1 = max(j - 1, 0), min(j + 1, sx.shape[1] - 1)
    J = np.array(
        [
            [(sx[i, j1] - sx[i, j0]) / max(j1 - j0, 1), (sx[i1, j] - sx[i0, j]) / max(i1 - i0, 1)],
            [(sy[i, j1] - sy[i, j0]) / max(j1 - j0, 1), (sy[i1, j] - sy[i0, j]) / max(i1 - i0, 1)],
        ]
    )  # d(sx, sy) / d(column, row)
    return 2.0 * J @ cov_pix @ J.T


def init_specular_peak(
    model: Model, blocks: Sequence[FrameData | TableData], *, n: float | None = None, k: float | None = None,
    diffuse_quantile: float = 0.05,
) -> dict[str, Any]:
    """Start values of a one-peak model (a Specular term, possibly :class:`~brdfjax.core.terms.Oriented`, and an
    optional Lambertian) from detector frames: the mirror, polished-aluminium and Kapton presets.

    Per frame, a general log-quadratic in the sample-frame half-vector slopes over the top e^-3 of the
    brightest peak gives its centre and its matrix ``C`` (``diag(mx^2, my^2)`` turned by the orientation);
    with a footprint on the frame, the footprint's own ``C`` (its second moments mapped to slopes) is
    subtracted first.  The widths are the square roots of ``C``'s eigenvalues (times sqrt(2) for GGX), the
    orientation ``psi`` the azimuth of the x axis (the branch of ``psi`` modulo 90 deg nearest the model's
    ``psi``; an un-oriented anisotropic D takes ``C``'s diagonal); medians over frames.  ``rho_s`` (and
    ``rho_d``) from the amplitude fit of :func:`fit_amplitudes` over every usable pixel (footprint
    applied); the index ``n`` (``k``) from its prior, default the model's.  ``theta_i`` per frame from the
    peak's in-plane slope.
    """
    found = _peak_terms(model)
    if found is None:
        raise FitInputError(
            "initializer 'specular_peak' needs a model of one Specular term (or Oriented(Specular)) and at most one "
            "Lambertian term, got " + ", ".join(f"{k_}: {type(t).__name__}" for k_, t in model.terms.items())
        )
    sname, sterm, wrapper, lname = found
    dist = type(sterm.distribution)
    if dist not in _PEAK_WIDTH_ESTIMATED:
        raise FitInputError(
            f"initializer 'specular_peak': no width estimate for the {dist.__name__} distribution "
            f"(known: {', '.join(c.__name__ for c in _PEAK_WIDTH_ESTIMATED)}); give its start values"
        )
    fields, factor = dist.width_fields, dist.peak_width_factor
    frames = [b for b in blocks if isinstance(b, FrameData)]
    if len(frames) != len(blocks):
        raise FitInputError("initializer 'specular_peak' works on detector frames only; give starts for tables")
    n = float(np.asarray(sterm.n)) if n is None else float(n)
    k = float(np.asarray(sterm.k)) if k is None else float(k)
    psi_prior = float(np.asarray(wrapper.psi)) if wrapper is not None else 0.0
    widths, psis, theta_is = [], [], []
    for fr in frames:
        geo = _frame_geometry(fr)
        cph, sph = math.cos(float(fr.phi_ref)), math.sin(float(fr.phi_ref))
        sx = cph * geo["sx"] + sph * geo["sy"]  # sample frame
        sy = -sph * geo["sx"] + cph * geo["sy"]
        d = np.asarray(fr.brdf, np.float64)
        ok = fr.check_usable()
        L = np.where(ok, np.log(np.where(ok, d, 1.0)), -np.inf)
        seed = int(np.argmax(L))
        s0, C = _quadratic_peak(sx, sy, L, ok, seed, ggx=dist in (GGX, GGXAniso))
        if fr.footprint is not None:
            Cb = _footprint_cov(fr, sx, sy, seed)
            ev_obs = np.linalg.eigvalsh(C)
            C = C - Cb
            ev, vec = np.linalg.eigh(C)
            ev = np.maximum(ev, 0.01 * float(ev_obs.min()))  # a peak narrower than the beam: keep it positive
            C = vec @ np.diag(ev) @ vec.T
        theta_is.append(float(fr.theta_i) + 2.0 * math.atan(s0[0] * cph - s0[1] * sph))
        if len(fields) == 1:
            widths.append([math.sqrt(math.sqrt(float(np.linalg.det(C))))])
            continue
        if wrapper is None:
            widths.append([math.sqrt(C[0, 0]), math.sqrt(C[1, 1])])
            continue
        ev, vec = np.linalg.eigh(C)
        psi = math.atan2(vec[1, 0], vec[0, 0])  # axis of ev[0]
        cands = [(psi, ev[0], ev[1]), (psi + math.pi / 2, ev[1], ev[0])]
        best = min(cands, key=lambda c_: abs(_wrap(2 * (c_[0] - psi_prior))))
        p = best[0] + math.pi * round((psi_prior - best[0]) / math.pi)  # nearest the prior modulo 180 deg
        psis.append(p)
        widths.append([math.sqrt(best[1]), math.sqrt(best[2])])
    w = np.median(np.array(widths), axis=0) * factor
    values: dict[str, Any] = {f"{sname}.{f}": float(x) for f, x in zip(fields, w)}
    if wrapper is not None:
        values[f"{sname}.psi"] = float(np.median(psis)) if psis else psi_prior
    shape_values = {**values, f"{sname}.n": n, f"{sname}.k": k, f"{sname}.rho_s": 1.0}
    if lname is not None:
        shape_values[f"{lname}.rho_d"] = 1.0
    shape = model.with_params(shape_values)
    units: dict[str, list[np.ndarray]] = {sname: [], **({lname: []} if lname else {})}
    data = []
    for fr in frames:
        frame = Conditions(np.float64(fr.theta_i), np.float64(fr.phi_ref), np.float64(fr.wavelength))
        tv = _grid_term_values(shape, frame, fr)
        ok = fr.check_usable()
        for name in units:
            img = tv[name]
            if fr.footprint is not None:
                kern = np.asarray(fr.footprint, np.float64)
                img = np.asarray(convolve_footprint(img.astype(np.float32), (kern / kern.sum()).astype(np.float32)), np.float64)
            units[name].append(img[ok])
        data.append(np.asarray(fr.brdf, np.float64)[ok])
    amp = fit_amplitudes([np.concatenate(units[nm]) for nm in units], np.concatenate(data))
    values[f"{sname}.rho_s"] = float(amp[0])
    values[f"{sname}.n"] = n
    values[f"{sname}.k"] = k
    if lname is not None:
        d_all = np.concatenate(data)
        values[f"{lname}.rho_d"] = float(amp[1]) if amp[1] > 0 else math.pi * float(np.quantile(d_all, diffuse_quantile))
    out: dict[str, Any] = {_public(model, key): v for key, v in values.items()}
    out["theta_i"] = theta_is
    return out

INITIALIZERS: dict[str, Callable[..., Mapping[str, Any]]] = {
    "solar_cell": init_solar_cell,
    "specular_lambertian": init_specular_lambertian,
    "specular_peak": init_specular_peak,
}


def get_initializer(initializer: str | Callable | None, model: Model) -> Callable[..., Mapping[str, Any]]:
    """An initialiser by name, a callable, or (``None``) the one that fits the model's terms."""
    if callable(initializer):
        return initializer
    if initializer is None:
        terms = model.terms
        if set(terms) == {"center", "offset", "bars"}:
            return init_solar_cell
        kinds = sorted(type(t).__name__ for t in terms.values())
        if kinds == ["Lambertian", "Specular"]:
            return init_specular_lambertian
        if _peak_terms(model) is not None:
            return init_specular_peak
        raise FitInputError(
            "'auto' start values need an initializer for this model (terms "
            + ", ".join(f"{k}: {type(t).__name__}" for k, t in terms.items())
            + f"); known: {', '.join(sorted(INITIALIZERS))}, or pass a callable (model, blocks, **options) -> values"
        )
    if initializer not in INITIALIZERS:
        raise FitInputError(f"unknown initializer '{initializer}'; known: {', '.join(sorted(INITIALIZERS))}")
    return INITIALIZERS[initializer]
