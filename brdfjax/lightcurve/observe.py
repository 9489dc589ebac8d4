"""Predict real satellite observations from facet BRDF models, with predictive bands, lab-coverage flags and metrics.

The library behind ``brdfjax observe CONFIG --out DIR`` (config:
:mod:`brdfjax.lightcurve.observe_config`).  For each observation set:

1. rows are read (:mod:`brdfjax.io.observations`) and their geometry built
   without a TLE (:mod:`.skygeometry`); rows below the horizon or in the
   Earth's shadow are dropped and counted;
2. every facet's flux at the observer is computed by the light-curve engine
   (:func:`~brdfjax.lightcurve.engine.facet_flux`: the Sun a point or a disk
   quadrature) with each facet's chosen model, and turned into magnitudes in
   each row's band (:mod:`.photometry`);
3. a posterior predictive band: ``draws`` predictions, each with every
   facet's model family drawn among the facet's ``model`` and
   ``alternatives`` (model-form uncertainty: families fitted to the same lab
   table) and its parameters drawn from that fit's covariance (result.json:
   sigma and correlation; positive parameters log-normal, the binomial's
   signed coefficients normal) or from a posterior chain; the observation's
   own uncertainty is added when the file has one.  The draws use the point
   Sun times each (row, facet)'s disk/point ratio of the nominal model (the
   solar disk matters only near a glint, where that ratio carries it).  The
   band is the 2.5, 16, 84 and 97.5 percentiles;
4. per row and facet, whether the geometry lies outside what the lab
   measured: incidence beyond the table's largest incident angle, and (for
   tables scanned in the plane of incidence) the observer more than
   ``out_of_plane_deg`` out of that plane.  A row is flagged when a facet
   carrying at least ``min_flux_fraction`` of its flux is;
5. per row, whether the satellite flies below ``min_height_km``, the lowest
   height at which the attitude law holds (``off_shell``): a satellite
   raising or lowering its orbit flies in another attitude (Starlink's
   orbit-raising configuration), which no facet model of the operational
   attitude describes;
6. metrics of observed minus predicted magnitude (RMS, bias, Pearson R of
   observed and predicted, residual scatter, band coverage at 68 and 95 %),
   overall and split by the flags.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.geometry import Directions
from ..core.terms import Model
from ..fit import read_cornell_brdf, read_merl_inplane, read_table
from ..io.observations import Observations
from ..runtime.errors import InputError
from .attitude import lumos_normal_to_body, offset_facets
from .earthshine import earthshine_flux
from .engine import Attitude, Facets, Satellite, SunDisk, facet_flux
from .photometry import BANDS, BandError, band
from .skyeffects import effects_flux
from .skygeometry import SkyGeometry, ecef_to_geodetic, sky_geometry

__all__ = ["FacetSpec", "SetPrediction", "metrics", "covariance_draws", "predict_set", "lab_coverage"]

_SIGNED = re.compile(r"(^|\.)[bc]\d+_\d+$")


@dataclass
class FacetSpec:
    """A facet: geometry (body frame), its model families (the first is the prediction's) and the lab's coverage."""

    name: str
    area: float
    normal: tuple[float, float, float]
    families: list[str]
    x_axis: tuple[float, float, float] | None = None
    tracking: bool = False
    cant_deg: float = 0.0
    yaw_deg: float = 0.0
    max_theta_i_deg: float | None = None
    in_plane: bool = False
    #: model averaging: one weight per family (None: the first family predicts, the band draws them evenly); the
    #: prediction is then the weighted mean of the families' fluxes and the band draws family k with probability w_k
    weights: tuple[float, ...] | None = None


@dataclass
class SetPrediction:
    """Everything predicted for one observation set (kept rows only)."""

    name: str
    obs: Observations
    geometry: SkyGeometry
    facet_names: list[str]
    mag: np.ndarray  # (N,)
    facet_mag: np.ndarray  # (N, J)
    facet_flux: np.ndarray  # (N, J)
    theta_i: np.ndarray  # (N, J) deg
    theta_s: np.ndarray  # (N, J) deg
    out_of_plane: np.ndarray  # (N, J) deg
    flag_incidence: np.ndarray  # (N, J) bool
    flag_plane: np.ndarray  # (N, J) bool
    flagged: np.ndarray  # (N,) bool
    phase_deg: np.ndarray
    sun_mag: np.ndarray
    band: np.ndarray | None = None  # (N, 5): 2.5, 16, 50, 84, 97.5 percentiles
    effect_flux: np.ndarray | None = None  # (N,) the [effects] terms' flux (skyeffects), None without any
    families_drawn: dict[str, dict[str, int]] = field(default_factory=dict)
    height_km: np.ndarray | None = None  # (N,) the satellite's height above the ellipsoid (the Earth's sphere for relative rows)
    off_shell: np.ndarray | None = None  # (N,) bool: below ``min_height_km`` (None: no such height given)

    @property
    def observed(self) -> np.ndarray:
        return self.obs.mag

    def _split(self, rows: np.ndarray) -> dict:
        return metrics(self.observed[rows], self.mag[rows], None if self.band is None else self.band[rows])

    def metrics(self) -> dict:
        """``all``; ``outside_lab`` / ``inside_lab`` (the lab-coverage flag); with ``min_height_km`` also
        ``operational`` / ``off_shell`` and, among the operational rows, ``operational_outside_lab`` /
        ``operational_inside_lab`` (each split only where it has rows)."""
        out = {"all": metrics(self.observed, self.mag, self.band)}
        splits = {"outside_lab": self.flagged, "inside_lab": ~self.flagged}
        if self.off_shell is not None:
            on = ~self.off_shell
            splits.update(operational=on, off_shell=self.off_shell, operational_outside_lab=on & self.flagged,
                          operational_inside_lab=on & ~self.flagged)
        for name, rows in splits.items():
            if rows.any():
                out[name] = self._split(rows)
        return out


def metrics(observed: np.ndarray, predicted: np.ndarray, bands: np.ndarray | None = None) -> dict:
    """RMS, bias (mean of observed - predicted), Pearson R of observed and predicted, residual scatter (std), n; and the
    fractions of observations inside the 68 % (16-84) and 95 % (2.5-97.5) bands when ``bands`` (N, 5) is given."""
    o, p = np.asarray(observed, float), np.asarray(predicted, float)
    ok = np.isfinite(o) & np.isfinite(p)
    r = o[ok] - p[ok]
    out = {"n": int(ok.sum())}
    if ok.sum() == 0:
        return out
    out.update(rms=float(np.sqrt(np.mean(r**2))), bias=float(np.mean(r)), scatter=float(np.std(r)),
               pearson_r=float(np.corrcoef(o[ok], p[ok])[0, 1]) if ok.sum() > 2 and np.std(p[ok]) > 0 else None)
    if bands is not None:
        b = np.asarray(bands)[ok]
        out["coverage_68"] = float(np.mean((o[ok] >= b[:, 1]) & (o[ok] <= b[:, 3])))
        out["coverage_95"] = float(np.mean((o[ok] >= b[:, 0]) & (o[ok] <= b[:, 4])))
    return out


def lab_coverage(path: str | Path, fmt: str = "lumos-sat", columns: dict | None = None) -> tuple[float, bool]:
    """The largest incident angle (deg) of a lab table and whether every row lies in the plane of incidence."""
    path = Path(path)
    if fmt in ("lumos-sat", "merl"):
        t = read_merl_inplane(path, columns=columns)
    elif fmt == "cornell":
        t = read_cornell_brdf(path)
    elif fmt == "table":
        t = read_table(path, columns or {})
    else:
        raise InputError(f"{path}: lab table format '{fmt}' is not one of 'lumos-sat', 'merl', 'cornell', 'table'")
    keep = np.ones(len(t), bool) if t.mask is None else np.asarray(t.mask, bool)
    ti = np.degrees(np.asarray(t.theta_i, float))[keep]
    dphi = (np.asarray(t.phi_s, float) - np.asarray(t.phi_i, float))[keep]
    ts = np.asarray(t.theta_s, float)[keep]
    in_plane = bool(np.all((np.abs(np.sin(dphi)) < 0.02) | (np.abs(np.sin(ts)) < 1e-6)))
    return float(ti.max()), in_plane


# --- parameter draws -------------------------------------------------------------------------------------------


def covariance_draws(result_path: str | Path, model: Model, n: int, rng: np.random.Generator, where: str
                     ) -> tuple[tuple[str, ...], np.ndarray]:
    """``n`` parameter draws (stored units) from a fit's result.json: its values, sigmas and correlation.

    Parameters with a finite sigma are drawn jointly: the binomial's signed
    coefficients (``b<k>_<i>``, ``c<k>_<i>``) normal, every other positive
    parameter log-normal (sigma/value in log); those without a finite sigma
    stay at their value.
    """
    path = Path(result_path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        params = data["parameters"]
        corr_names = list(data["correlation"]["names"])
        corr = np.asarray(data["correlation"]["matrix"], float)
    except FileNotFoundError:
        raise InputError(f"{where}: fit result {path} not found") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{where}: {path} is not a brdfjax fit result.json ({type(e).__name__}: {e})") from None
    known = model.parameter_units()
    names, mean, sig, logs, conv = [], [], [], [], []
    for name in corr_names:
        e = params.get(name, {})
        v, s = e.get("value"), e.get("sigma")
        if name not in known or v is None or s is None or not np.isfinite(s) or s <= 0:
            continue
        log = not _SIGNED.search(name) and v > 0
        names.append(name)
        mean.append(np.log(v) if log else v)
        sig.append(s / v if log else s)
        logs.append(log)
        conv.append(np.pi / 180 if e.get("unit") == "deg" else 1.0)
    if not names:
        return (), np.zeros((n, 0))
    idx = [corr_names.index(k) for k in names]
    c = np.nan_to_num(corr[np.ix_(idx, idx)], nan=0.0)
    np.fill_diagonal(c, 1.0)
    cov = c * np.outer(sig, sig)
    w, V = np.linalg.eigh(cov)
    L = V * np.sqrt(np.clip(w, 0, None))
    z = rng.standard_normal((n, len(names))) @ L.T + np.asarray(mean)
    z = np.where(np.asarray(logs), np.exp(np.clip(z, -700, 700)), z)
    return tuple(names), z * np.asarray(conv)


# --- prediction ------------------------------------------------------------------------------------------------


def _facets(specs: list[FacetSpec], normals: str) -> Facets:
    conv = lumos_normal_to_body if normals == "lumos" else (lambda v: np.asarray(v, float))
    fac = Facets.build([f.name for f in specs], [f.area for f in specs], [conv(f.normal) for f in specs],
                       x_axis=[None if f.x_axis is None else conv(f.x_axis) for f in specs],
                       tracking=[f.tracking for f in specs])
    cant = np.deg2rad([f.cant_deg for f in specs])
    yaw = np.deg2rad([f.yaw_deg for f in specs])
    if np.any(cant) or np.any(yaw):
        fac = offset_facets(fac, cant, yaw)
    return fac


def _facet_directions(sat: Satellite, geo):
    """Facet-frame Sun-centre and observer directions (T, J, 3) and the per-row scale (T,)."""
    M = sat.attitude.matrix(geo.r_hat, geo.v_hat)
    s_b = jnp.einsum("tij,ti->tj", M, geo.s)
    o_b = jnp.einsum("tij,ti->tj", M, geo.o)
    x, y, n = sat.facets.frames(s_b)

    def to_facet(v):
        vv = v[:, None]
        return jnp.stack([jnp.sum(vv * x, -1), jnp.sum(vv * y, -1), jnp.sum(vv * n, -1)], -1)

    scale = jnp.square(1.495978707e11 / geo.d_sun) / jnp.square(geo.d_obs)
    return to_facet(s_b), to_facet(o_b), scale, s_b, o_b


@jax.jit
def _angles(w_c, w_s):
    ti = jnp.degrees(jnp.arctan2(jnp.hypot(w_c[..., 0], w_c[..., 1]), w_c[..., 2]))
    ts = jnp.degrees(jnp.arctan2(jnp.hypot(w_s[..., 0], w_s[..., 1]), w_s[..., 2]))
    # the plane of incidence holds the normal (0, 0, 1) and w_i: its normal is (w_iy, -w_ix, 0) / |.|
    pn = jnp.stack([w_c[..., 1], -w_c[..., 0]], -1)
    pl = jnp.hypot(pn[..., 0], pn[..., 1])
    sin_out = jnp.abs(pn[..., 0] * w_s[..., 0] + pn[..., 1] * w_s[..., 1]) / jnp.where(pl > 0, pl, 1.0)
    out = jnp.where(pl > 1e-9, jnp.degrees(jnp.arcsin(jnp.clip(sin_out, 0, 1))), 0.0)
    return ti, ts, out


@eqx.filter_jit
def _draw_values(model: Model, names: tuple[str, ...], draws, w_c, w_s, wavelength: float):
    """BRDF x cos_i x cos_s of ``model`` at each parameter draw (rows of ``draws``): (S, T, Jm).  One compilation per
    model structure and shape (``names`` and ``wavelength`` static)."""
    cos = jnp.maximum(w_c[..., 2], 0.0) * jnp.maximum(w_s[..., 2], 0.0)
    dirs = Directions.from_vectors(w_c, w_s)

    def one(pp):
        m = model.with_params({n: pp[i] for i, n in enumerate(names)}) if names else model
        return m(dirs, wavelength) * cos

    return jax.lax.map(one, draws, batch_size=16)


def _family_flux_draws(model: Model, names: tuple[str, ...], draws: np.ndarray, w_c, w_s, wavelength: float,
                       block: int = 128) -> np.ndarray:
    """:func:`_draw_values` with the draws padded to a multiple of ``block`` (fewer distinct shapes to compile)."""
    S = draws.shape[0]
    if S == 0:
        return np.zeros((0,) + tuple(w_c.shape[:-1]))
    pad = (-S) % block
    d = np.concatenate([draws, np.repeat(draws[-1:], pad, 0)]) if pad else draws
    if d.shape[1] == 0:
        d = np.zeros((d.shape[0], 1))
    return np.asarray(_draw_values(model, tuple(names), jnp.asarray(d), w_c, w_s, float(wavelength)))[:S]


def predict_set(name: str, obs: Observations, facets: list[FacetSpec], models: dict[str, "object"],
                *, normals: str = "body", yaw_law: str = "sun_yaw", roll_deg: float = 0.0, pitch_deg: float = 0.0,
                yaw_deg: float = 0.0, convention: str = "physical", band_map: dict[str, str] | None = None,
                disk: SunDisk | None = None, earth_radius: float | None = None, wavelength: float = 550e-9,
                draws: int = 0, seed: int = 0, parameter_uncertainty: bool = True, model_form: bool = True,
                result_paths: dict[str, Path] | None = None, out_of_plane_deg: float = 5.0,
                incidence_margin_deg: float = 1.0, min_flux_fraction: float = 0.1,
                min_altitude_deg: float = 0.0, min_height_km: float | None = None,
                earthshine_albedo: float | None = None,
                earthshine_grid: tuple[int, int] = (32, 64),
                model_error: dict[str, tuple[float, float]] | None = None,
                effects: dict[str, float] | None = None, effects_theta_max_deg: dict[str, float] | None = None
                ) -> SetPrediction:
    """Predict one observation set (see the module docstring).

    ``models``: model name -> object with ``.model`` (a Model) and ``.draws``
    (None or posterior (names, (S, p))); ``result_paths``: model name -> the
    result.json its covariance draws come from.  ``earthshine_albedo``: add
    the light of a Lambertian Earth of that albedo (:mod:`.earthshine`, on an
    ``earthshine_grid`` of polar x azimuthal elements); the band's draws scale
    each facet's direct flux by the nominal (direct + earthshine) / direct
    ratio.  ``model_error``: model name -> (inside, outside) RMS of ln BRDF:
    each draw multiplies a facet's flux by ``exp(sigma z)`` (z normal, per
    draw, row and facet), sigma the model's error inside the lab's geometry
    (its fit's log-RMS) or outside it (e.g. its log-RMS on a withheld
    incidence), by the facet's flag on that row.  ``effects``: values of
    :mod:`.skyeffects` keys (e.g. ``wide.<facet>.k``; radians) whose flux
    is added to the total (and to each draw of the band);
    ``effects_theta_max_deg``: facet -> the incidence beyond which its wide
    lobe switches on (default: the facet's ``max_theta_i_deg``, else 75).
    ``min_height_km``: rows whose satellite flies lower are flagged
    ``off_shell`` (the attitude law does not hold there); they are still
    predicted, and the metrics are split by the flag.
    """
    geo = sky_geometry(obs, yaw_law=yaw_law, earth_radius=earth_radius, min_altitude_deg=min_altitude_deg)
    kept = obs.take(geo.keep)
    kept = Observations(**{**kept.__dict__, "dropped": {**obs.dropped, **geo.dropped}})
    band_map = band_map or {}
    sun_mag = np.empty(len(kept))
    cache: dict[str, float] = {}
    for i, b in enumerate(kept.band):
        key = str(b)
        if key not in cache:
            try:
                cache[key] = band(band_map.get(key, key), where="").sun_magnitude
            except BandError:
                raise BandError(f"{obs.source}: line {kept.line[i]}: unknown band '{key}'; known: {', '.join(BANDS)} "
                                f"(map it in the config: photometry.bands = {{ {key} = \"V\" }})") from None
        sun_mag[i] = cache[key]
    fac = _facets(facets, normals)
    fam_names = sorted({m for f in facets for m in f.families})
    primary = [fam_names.index(f.families[0]) for f in facets]
    all_models = tuple(models[m].model for m in fam_names)
    att = Attitude.nadir(np.deg2rad(roll_deg), np.deg2rad(pitch_deg), np.deg2rad(yaw_deg))
    sat = Satellite(fac, all_models, att, tuple(primary))
    g = geo.engine_geometry(sun_distance_factor=(convention == "physical"))
    disk = disk or SunDisk.point()
    er = geo.earth_radius
    # the nominal prediction: each facet's first family, or the weighted mean of its families' fluxes (averaging)
    weights = _family_weights(facets)
    flux = point = es = 0.0
    for k in range(weights.shape[0]):
        if not weights[k].any():
            continue
        sat_k = sat if k == 0 else Satellite(fac, all_models, att, tuple(
            fam_names.index(f.families[min(k, len(f.families) - 1)]) for f in facets))
        flux = flux + weights[k] * np.asarray(facet_flux(sat_k, g, disk, wavelength, earth_radius=er)["flux"])
        if disk.n_nodes > 1:
            point = point + weights[k] * np.asarray(
                facet_flux(sat_k, g, SunDisk.point(), wavelength, earth_radius=er)["flux"])
        if earthshine_albedo is not None:
            es = es + weights[k] * np.asarray(earthshine_flux(
                sat_k, g, earthshine_albedo, n_psi=earthshine_grid[0], n_chi=earthshine_grid[1], earth_radius=er,
                wavelength=wavelength))
    if disk.n_nodes > 1:
        ratio = np.where(point > 0, flux / np.where(point > 0, point, 1.0), 1.0)
    else:
        ratio = np.ones_like(flux)
    if earthshine_albedo is not None:
        ratio = ratio * np.where(flux > 0, (flux + es) / np.where(flux > 0, flux, 1.0), 1.0)
        flux = flux + es
    w_c, w_s, scale, s_b, o_b = _facet_directions(sat, g)
    extra = None
    if effects:
        tmax = effects_theta_max_deg or {}
        theta_max = np.deg2rad([tmax.get(f.name, 75.0 if f.max_theta_i_deg is None else f.max_theta_i_deg)
                                for f in facets])
        extra = np.asarray(effects_flux({k: jnp.asarray(v) for k, v in effects.items()}, [f.name for f in facets],
                                        w_c, w_s, s_b, o_b, scale, sat.facets.area, theta_max))
    total = flux.sum(-1) + (0.0 if extra is None else extra)
    with np.errstate(divide="ignore"):
        mag = sun_mag - 2.5 * np.log10(total)
        facet_mag = sun_mag[:, None] - 2.5 * np.log10(flux)
    ti, ts, oop = (np.asarray(a) for a in _angles(w_c, w_s))
    lit = (ti < 90) & (ts < 90)
    max_ti = np.array([np.inf if f.max_theta_i_deg is None else f.max_theta_i_deg + incidence_margin_deg for f in facets])
    flag_i = lit & (ti > max_ti)
    flag_p = lit & np.array([f.in_plane for f in facets])[None, :] & (oop > out_of_plane_deg)
    frac = flux / np.where(total > 0, total, 1.0)[:, None]
    flagged = np.any((flag_i | flag_p) & (frac >= min_flux_fraction), -1)
    height_km = (ecef_to_geodetic(geo.r_sat)[2] if kept.kind == "absolute" else np.asarray(kept.sat_height_m, float)) / 1e3
    off_shell = None if min_height_km is None else height_km < min_height_km
    pred = SetPrediction(name, kept, geo, [f.name for f in facets], mag, facet_mag, flux, ti, ts, oop, flag_i, flag_p,
                         flagged, geo.phase_angle_deg(), sun_mag, effect_flux=extra, height_km=height_km,
                         off_shell=off_shell)
    if draws > 0:
        pred.band, pred.families_drawn = _bands(sat, facets, fam_names, models, result_paths or {}, np.asarray(w_c),
                                                np.asarray(w_s), np.asarray(scale), ratio, sun_mag, kept.mag_err, draws,
                                                seed, parameter_uncertainty, model_form, wavelength, model_error or {},
                                                flag_i | flag_p, extra)
    return pred


def _family_weights(facets: list[FacetSpec]) -> np.ndarray:
    """(K, J) weight of each facet's k-th family in the nominal prediction (rows sum to 1 per facet)."""
    K = max(len(f.families) if f.weights is not None else 1 for f in facets)
    W = np.zeros((K, len(facets)))
    for j, f in enumerate(facets):
        if f.weights is None:
            W[0, j] = 1.0
        else:
            w = np.asarray(f.weights, float)
            W[:len(w), j] = w / w.sum()
    return W


def _bands(sat, facets, fam_names, models, result_paths, w_c, w_s, scale, ratio, sun_mag, mag_err, S, seed,
           parameter_uncertainty, model_form, wavelength, model_error, outside, extra=None):
    rng = np.random.default_rng(seed)
    J = len(facets)
    T = w_c.shape[0]
    area = np.asarray(sat.facets.area)
    # which family each facet uses in each draw
    choice = np.empty((S, J), int)
    for j, f in enumerate(facets):
        if f.weights is not None:
            # a model-averaged facet: its families drawn with their weights (the averaged prediction's mixture)
            w = np.asarray(f.weights, float)
            choice[:, j] = rng.choice([fam_names.index(m) for m in f.families], size=S, p=w / w.sum())
            continue
        opts = [fam_names.index(m) for m in (f.families if model_form else f.families[:1])]
        choice[:, j] = rng.choice(opts, size=S)
    total = np.zeros((S, T))
    counts: dict[str, dict[str, int]] = {}
    for fi, fam in enumerate(fam_names):
        cols = [j for j in range(J) if np.any(choice[:, j] == fi)]
        if not cols:
            continue
        bm = models[fam]
        model = bm.model
        if parameter_uncertainty and getattr(bm, "draws", None) is not None:
            names, d = bm.draws
            d = d[rng.choice(d.shape[0], size=S, replace=d.shape[0] < S)]
        elif parameter_uncertainty and fam in result_paths:
            names, d = covariance_draws(result_paths[fam], model, S, rng, f"models.{fam}")
        else:
            names, d = (), np.zeros((S, 0))
        # only the draws in which one of its facets uses this family are evaluated
        used = np.flatnonzero(np.any(choice[:, cols] == fi, 1))
        vals = _family_flux_draws(model, tuple(names), d[used], jnp.asarray(w_c[:, cols]), jnp.asarray(w_s[:, cols]),
                                  wavelength)  # (S_used, T, len(cols))
        vals = np.nan_to_num(vals, nan=0.0, posinf=0.0)
        for q, j in enumerate(cols):
            use = choice[used, j] == fi
            contrib = vals[use, :, q] * (area[j] * scale * ratio[:, j])[None, :]
            if fam in model_error:
                sig = np.where(outside[:, j], model_error[fam][1], model_error[fam][0])  # (T,)
                contrib = contrib * np.exp(sig[None, :] * rng.standard_normal(contrib.shape))
            total[used[use]] += contrib
            counts.setdefault(facets[j].name, {})[fam] = int(use.sum())
    if extra is not None:
        total = total + extra[None, :]
    with np.errstate(divide="ignore"):
        m = sun_mag[None, :] - 2.5 * np.log10(total)
    err = np.where(np.isfinite(mag_err), mag_err, 0.0)
    m = m + rng.standard_normal(m.shape) * err[None, :]
    band_ = np.percentile(m, [2.5, 16, 50, 84, 97.5], axis=0).T
    return band_, counts

