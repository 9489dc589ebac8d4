"""Run a light-curve config: geometry, models, comparison, posterior bands, glints; CSV + JSON + PNG outputs.

:func:`build_job` turns a :class:`~brdfjax.lightcurve.config.LightcurveConfig`
into the visible time steps and a :class:`~brdfjax.lightcurve.engine.Satellite`;
:func:`run_lightcurve` evaluates it (and every ``[compare.<label>]``
alternative, and posterior draws) and writes ``lightcurve.csv``,
``lightcurve.json`` and ``lightcurve.png`` through
:func:`brdfjax.io.atomic_output`.
"""

from __future__ import annotations

import csv
import io
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure

from ..config import ConfigError
from ..io import atomic_output, write_json_atomic
from ..plotting import save_figure_atomic
from .config import BuiltModel, LightcurveConfig, build_models
from .engine import (
    AdaptiveDisk,
    Attitude,
    Facets,
    Geometry,
    Satellite,
    SunDisk,
    facet_flux,
    light_curve,
    magnitude,
    phase_angle,
    shadow_mask,
)
from .ephemeris import PassGeometry, parse_tle, pass_geometry, time_grid

__all__ = ["LightcurveJob", "build_job", "run_lightcurve", "glint_runs", "compare_series", "posterior_total_flux"]


@dataclass(frozen=True)
class LightcurveJob:
    cfg: LightcurveConfig
    passes: PassGeometry  # the visible time steps only
    geometry: Geometry
    facets: Facets
    attitude: Attitude
    model_names: tuple[str, ...]  # distinct model names, in facet order of first use
    model_of: tuple[int, ...]
    models: dict[str, BuiltModel]
    disk: SunDisk | AdaptiveDisk  # an unplanned AdaptiveDisk: planned for each satellite it is used with
    wavelength: float
    dtype: Any
    n_steps_total: int

    def satellite(self, replace: Mapping[str, str] | None = None) -> Satellite:
        """The satellite with its models; ``replace`` maps model names to other model names."""
        replace = dict(replace or {})
        models = tuple(self.models[replace.get(n, n)].model for n in self.model_names)
        return Satellite(self.facets, models, self.attitude, self.model_of)


def build_job(cfg: LightcurveConfig) -> LightcurveJob:
    """Geometry of the visible steps, facets, attitude and models of a config (errors name the file and key)."""
    src = cfg.source
    dtype = jnp.float64 if cfg.precision == "float64" else jnp.float32
    if cfg.precision == "float64" and not jax.config.jax_enable_x64:
        raise ConfigError(src, [("precision", "'float64' needs jax_enable_x64 (the brdfjax CLI sets it; "
                                 "call jax.config.update('jax_enable_x64', True) first)")])
    sat = parse_tle(*cfg.orbit.tle, where=f"{src}: orbit.tle")
    times = time_grid(cfg.time.start, cfg.time.stop, cfg.time.step_s)
    ob = cfg.observer
    pg = pass_geometry(sat, times, ob.lat_deg, ob.lon_deg, ob.height_m, where=f"{src}: orbit.tle")
    elev, sun_el = np.rad2deg(pg.elevation()), np.rad2deg(pg.sun_elevation())
    up = elev >= ob.min_elevation_deg
    dark = sun_el <= ob.max_sun_elevation_deg
    s = (pg.r_sun - pg.r_sat) / np.linalg.norm(pg.r_sun - pg.r_sat, axis=-1, keepdims=True)
    r = np.linalg.norm(pg.r_sat, axis=-1)
    lit = np.asarray(shadow_mask(pg.r_sat, r, s[:, None, :]))[:, 0] > 0
    if not np.any(up & dark & lit):
        why = (f"never {ob.min_elevation_deg:g} deg above the horizon (highest {elev.max():.1f} deg)" if not up.any()
               else f"never above {ob.min_elevation_deg:g} deg while the Sun is below {ob.max_sun_elevation_deg:g} deg"
               if not (up & dark).any() else "always in the Earth's shadow while visible in a dark sky")
        raise ConfigError(src, [("time", f"the satellite is {why} between {cfg.time.start} and {cfg.time.stop}; "
                                 "choose another time span or observer")])
    keep = np.flatnonzero(up & dark)
    passes = pg.take(keep)
    geometry = Geometry.from_positions(passes.r_sat, passes.v_sat, passes.r_sun, passes.r_obs, dtype)
    names = list(cfg.satellite.facets)
    fc = [cfg.satellite.facets[n] for n in names]
    try:
        facets = Facets.build(
            names, [f.area_m2 for f in fc], [f.normal for f in fc], [f.x_axis for f in fc],
            [np.deg2rad(f.phi_ref_deg) for f in fc], [f.tracking for f in fc], [1.0] * len(fc),
        )
    except ValueError as e:
        bad = str(e).split("'")[1] if "'" in str(e) else ""
        raise ConfigError(src, [(f"satellite.facets.{bad}", str(e))]) from None
    sc = cfg.satellite
    ang = [np.deg2rad(x) for x in (sc.roll_deg, sc.pitch_deg, sc.yaw_deg)]
    attitude = Attitude.nadir(*ang) if sc.attitude == "nadir" else Attitude.inertial(*ang)
    wavelength = cfg.wavelength_nm * 1e-9
    models = build_models(cfg, wavelength)
    model_names: list[str] = []
    for f in fc:
        if f.model not in model_names:
            model_names.append(f.model)
    model_of = tuple(model_names.index(f.model) for f in fc)
    posts = [n for n in model_names if models[n].draws is not None]
    if len(posts) > 1:
        raise ConfigError(src, [(f"models.{posts[1]}.posterior", f"only one facet model may have a posterior (also {posts[0]})")])
    rule = SunDisk.rings(cfg.sun.disk_rings, limb_darkening=cfg.sun.limb_darkening)
    disk = {"full": rule, "point": SunDisk.point(), "adaptive": AdaptiveDisk(rule)}[cfg.sun.disk]
    return LightcurveJob(cfg, passes, geometry, facets, attitude, tuple(model_names), model_of, models, disk,
                         wavelength, dtype, len(times))


def posterior_total_flux(sat: Satellite, geometry: Geometry, disk: SunDisk | AdaptiveDisk, wavelength: float,
                         model_index: int, names: tuple[str, ...], draws: Any, *, chunk: int = 256,
                         batch: int | None = None, margin: float = 1.25) -> jax.Array:
    """Total flux (S, T) for each row of ``draws`` (S, p) replacing the parameters ``names`` of ``sat.models[model_index]``.

    The facets of the other models do not change between draws: they are evaluated once.  Draws run
    ``batch`` at a time (vmapped), time steps in chunks of ``chunk``.  An unplanned :class:`AdaptiveDisk`
    is planned on the model's own parameters (capacities with ``margin``); if a draw flags more pairs
    than that, the draws are rerun with capacities from the largest counts (a RuntimeWarning says so).
    """
    J = len(sat.facets.names)
    mine = [j for j in range(J) if sat.model_of[j] == model_index]
    rest = [j for j in range(J) if sat.model_of[j] != model_index]
    if not mine:
        raise ValueError(f"posterior_total_flux: no facet uses model {model_index}")
    adaptive = isinstance(disk, AdaptiveDisk)
    other = disk.unplanned() if adaptive else disk  # a planned disk belongs to the facets it was planned for
    fixed = light_curve(sat.subset(rest), geometry, other, wavelength, chunk=chunk)["flux"].sum(-1) if rest else 0.0
    sub = sat.subset(mine)
    if adaptive and disk.capacity is None:
        disk = disk.plan(sub, geometry, chunk=chunk, margin=margin)
    if batch is None:
        per_sample = min(chunk, len(geometry)) * len(mine) * (1 if adaptive else disk.n_nodes)
        if adaptive:
            per_sample += disk.slot_chunk * disk.n_nodes
        batch = int(max(1, min(len(draws), 128, 4_000_000 // max(per_sample, 1))))  # 128: larger batches thrash the CPU caches
    draws = jnp.asarray(draws, geometry.d_obs.dtype)
    flux, flagged, over = _draws_flux(sub, geometry, disk, wavelength, tuple(names), draws, chunk, batch)
    if adaptive and int(jnp.max(over)) > 0:
        counts = np.asarray(jnp.max(flagged, 0)).tolist()
        warnings.warn(f"adaptive solar disk: up to {int(jnp.max(over))} flagged pairs per draw exceeded the capacity "
                      f"{disk.capacity}; rerunning the draws with capacities for {counts}", RuntimeWarning, stacklevel=2)
        disk = disk.capacity_for(counts, margin)
        flux, flagged, over = _draws_flux(sub, geometry, disk, wavelength, tuple(names), draws, chunk, batch)
    return flux + fixed


@eqx.filter_jit
def _draws_flux(sub: Satellite, geometry: Geometry, disk: SunDisk | AdaptiveDisk, wavelength: float,
                names: tuple[str, ...], draws: jax.Array, chunk: int, batch: int):
    base = sub.models[0]

    def one(p):
        m = base.with_params({n: p[i] for i, n in enumerate(names)})
        out = facet_flux(sub.with_models((m,)), geometry, disk, wavelength, chunk=chunk)
        if "disk_flagged" in out:
            return out["flux"].sum(-1), out["disk_flagged"], jnp.sum(out["disk_overflow"])
        return out["flux"].sum(-1), jnp.zeros(1, jnp.int32), jnp.zeros((), jnp.int32)

    return jax.lax.map(one, draws, batch_size=batch)


def glint_runs(mag: np.ndarray, seconds: np.ndarray, step_s: float, threshold: float) -> list[dict[str, float]]:
    """Maximal runs of consecutive time steps brighter than ``threshold``: start, duration (s), peak magnitude."""
    bright = np.isfinite(mag) & (mag < threshold)
    runs: list[dict[str, float]] = []
    i, n = 0, len(mag)
    while i < n:
        if not bright[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and bright[j + 1] and seconds[j + 1] - seconds[j] <= 1.5 * step_s:
            j += 1
        runs.append({"start_s": float(seconds[i]), "duration_s": float((j - i + 1) * step_s),
                     "peak_mag": float(np.min(mag[i : j + 1])), "peak_s": float(seconds[i + int(np.argmin(mag[i : j + 1]))])})
        i = j + 1
    return runs


def compare_series(ref: np.ndarray, other: np.ndarray, seconds: np.ndarray, step_s: float, tol: float) -> dict[str, Any]:
    """Where and by how much ``other`` differs from ``ref`` (magnitudes; only steps where both are finite)."""
    both = np.isfinite(ref) & np.isfinite(other)
    d = np.where(both, other - ref, 0.0)  # positive: other fainter
    if not both.any():
        return {"n_compared": 0}
    k = int(np.argmax(np.abs(d)))
    big = both & (np.abs(d) > tol)
    runs = glint_runs(np.where(big, -np.abs(d), np.inf), seconds, step_s, 0.0)
    return {
        "n_compared": int(both.sum()),
        "max_abs_diff_mag": float(abs(d[k])),
        "at_s": float(seconds[k]),
        "diff_at_max_mag": float(d[k]),
        "median_diff_mag": float(np.median(d[both])),
        "fraction_beyond_tol": float(big.sum() / both.sum()),
        "intervals_beyond_tol": [{"start_s": r["start_s"], "duration_s": r["duration_s"], "max_abs_diff_mag": -r["peak_mag"]}
                                 for r in runs],
    }


def _mag(flux: np.ndarray, sun_mag: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.asarray(magnitude(np.asarray(flux, np.float64), sun_mag))


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def evaluate(job: LightcurveJob, replace: Mapping[str, str] | None = None) -> dict[str, np.ndarray]:
    out = light_curve(job.satellite(replace), job.geometry, job.disk, job.wavelength, chunk=job.cfg.chunk)
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def run_lightcurve(cfg: LightcurveConfig, out_dir: str | Path, *, plot: bool = True,
                   log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Evaluate a config and write lightcurve.csv/json/png into ``out_dir``; returns the JSON summary."""
    log = log or (lambda s: None)
    t0 = time.perf_counter()
    job = build_job(cfg)
    out = Path(out_dir)
    sec = job.passes.seconds()
    step = cfg.time.step_s
    smag = cfg.sun.magnitude
    thr = cfg.glints.threshold_mag
    log(f"{len(job.passes)} visible steps of {job.n_steps_total}; {len(job.facets.names)} facets; "
        f"solar disk {cfg.sun.disk}, {job.disk.n_nodes} node(s)")
    prim = evaluate(job)
    mags = _mag(prim["flux"], smag)  # (T, J)
    total = _mag(prim["flux"].sum(-1), smag)
    series = {"primary": total}
    for label, repl in cfg.compare.items():
        series[label] = _mag(evaluate(job, repl)["flux"].sum(-1), smag)
    bands = None
    post = [i for i, n in enumerate(job.model_names) if job.models[n].draws is not None]
    if post:
        i = post[0]
        names, draws = job.models[job.model_names[i]].draws
        fl = np.asarray(posterior_total_flux(job.satellite(), job.geometry, job.disk, job.wavelength, i, names, draws,
                                             chunk=cfg.chunk), np.float64)
        q = np.quantile(_mag(fl, smag), [0.025, 0.16, 0.5, 0.84, 0.975], axis=0)
        bands = {"q025": q[0], "q16": q[1], "q50": q[2], "q84": q[3], "q975": q[4], "n_samples": int(fl.shape[0])}
    wall = time.perf_counter() - t0
    phase = np.rad2deg(np.asarray(phase_angle(job.geometry), np.float64))
    elev = np.rad2deg(job.passes.elevation())
    glints = {k: glint_runs(v, sec, step, thr) for k, v in series.items()}
    comparisons = {k: compare_series(total, v, sec, step, cfg.glints.compare_tolerance_mag) for k, v in series.items() if k != "primary"}
    summary: dict[str, Any] = {
        "config": cfg.source,
        "n_steps": job.n_steps_total,
        "n_visible_steps": len(job.passes),
        "step_s": step,
        "start_utc": str(job.passes.times[0]),
        "facets": list(job.facets.names),
        "sun_disk": cfg.sun.disk,
        "sun_disk_nodes": job.disk.n_nodes,
        "sun_disk_full_pairs": int(prim["disk_full"].sum()) if "disk_full" in prim else None,
        "glint_threshold_mag": thr,
        "glints": {k: {"count": len(v), "total_duration_s": float(sum(r["duration_s"] for r in v)), "runs": v}
                   for k, v in glints.items()},
        "brightest_mag": {k: _num(np.min(v)) for k, v in series.items()},
        "comparisons": comparisons,
        "wall_s": wall,
    }
    if bands is not None:
        summary["posterior"] = {"model": job.model_names[post[0]], "n_samples": bands["n_samples"]}
    # CSV: one row per visible step
    buf = io.StringIO()
    w = csv.writer(buf)
    fn = list(job.facets.names)
    header = ["time_utc", "t_s", "elevation_deg", "phase_deg", "sunlit_fraction"]
    header += [f"theta_i_deg_{n}" for n in fn] + [f"theta_s_deg_{n}" for n in fn] + [f"mag_{n}" for n in fn]
    header += ["mag_total"] + [f"mag_total_{k}" for k in series if k != "primary"]
    if bands is not None:
        header += ["mag_q025", "mag_q16", "mag_q50", "mag_q84", "mag_q975"]
    w.writerow(header)
    ti, ts = np.rad2deg(prim["theta_i"]), np.rad2deg(prim["theta_s"])

    def cell(x: float) -> str:
        return f"{x:.6g}" if np.isfinite(x) else ""

    for t in range(len(sec)):
        row = [str(job.passes.times[t]) + "Z", f"{sec[t]:.3f}", cell(elev[t]), cell(phase[t]), cell(prim["sunlit"][t])]
        row += [cell(x) for x in ti[t]] + [cell(x) for x in ts[t]] + [cell(x) for x in mags[t]]
        row += [cell(v[t]) for v in series.values()]
        if bands is not None:
            row += [cell(bands[k][t]) for k in ("q025", "q16", "q50", "q84", "q975")]
        w.writerow(row)
    with atomic_output(out / "lightcurve.csv") as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    arrays = {
        "t_s": sec.tolist(),
        "phase_deg": [_num(x) for x in phase],
        "mag_total": {k: [_num(x) for x in v] for k, v in series.items()},
        "mag_facet": {n: [_num(x) for x in mags[:, j]] for j, n in enumerate(fn)},
        "theta_i_deg": {n: [_num(x) for x in ti[:, j]] for j, n in enumerate(fn)},
        "theta_s_deg": {n: [_num(x) for x in ts[:, j]] for j, n in enumerate(fn)},
    }
    if bands is not None:
        arrays["mag_band"] = {k: [_num(x) for x in bands[k]] for k in ("q025", "q16", "q50", "q84", "q975")}
    write_json_atomic(out / "lightcurve.json", {**summary, "series": arrays}, allow_nan=False)
    if plot:
        summary["png"] = str(plot_lightcurve(out / "lightcurve.png", sec, series, glints, thr, bands,
                                             title=f"{Path(cfg.source).name}: {job.passes.times[0]} UTC + t"))
    log(f"done in {wall:.1f} s")
    return summary


def plot_lightcurve(path: Path, sec: np.ndarray, series: Mapping[str, np.ndarray], glints: Mapping[str, list],
                    threshold: float, bands: Mapping[str, Any] | None = None, title: str = "") -> Path:
    """Magnitude vs time per pass (one panel per pass), glints of the primary model shaded."""
    gaps = np.flatnonzero(np.diff(sec) > 60.0)
    starts = np.concatenate([[0], gaps + 1])
    stops = np.concatenate([gaps + 1, [len(sec)]])
    n = len(starts)
    fig = Figure(figsize=(4.2 * n, 3.6), constrained_layout=True)
    axes = fig.subplots(1, n, squeeze=False)[0]
    colors = ["k", "tab:orange", "tab:blue", "tab:green", "tab:purple"]
    for ax, a, b in zip(axes, starts, stops):
        tm = sec[a:b] / 60.0
        if bands is not None:
            ax.fill_between(tm, bands["q025"][a:b], bands["q975"][a:b], color="0.85", label="2.5-97.5 %")
            ax.fill_between(tm, bands["q16"][a:b], bands["q84"][a:b], color="0.65", label="16-84 %")
        for (label, v), c in zip(series.items(), colors):
            ax.plot(tm, v[a:b], color=c, lw=1.0, label=label)
        for r in glints.get("primary", []):
            if sec[a] <= r["start_s"] <= sec[b - 1]:
                ax.axvspan(r["start_s"] / 60, (r["start_s"] + r["duration_s"]) / 60, color="gold", alpha=0.4, lw=0)
        ax.axhline(threshold, color="0.5", ls=":", lw=0.8)
        ax.invert_yaxis()
        ax.set_xlabel("t (min)")
        ax.set_title(f"pass {list(starts).index(a) + 1}", fontsize=9)
    axes[0].set_ylabel("apparent magnitude")
    axes[0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title + f"   (glints < {threshold:g} mag shaded)", fontsize=9)
    return save_figure_atomic(fig, path, dpi=110)

