"""The TOML config of ``brdfjax skygap`` and the run that writes its outputs.

The facet model, the observation sets, the attitude and the photometry come
from an observe config (:mod:`.observe_config`), read the same way as
``brdfjax observe`` reads it; this file says which set to diagnose and how::

    observe = "observe_v2mini_slingshot.toml"   # relative to this file
    set = "slingshot"                  # the observation set (default: the first)
    every = 2                          # keep every n-th row (over the set's own 'every')
    precision = "float64"

    [base]
    free_models = { mirror_abg = ["spec.g"] }   # model parameters the sky may refine (default: none)
    joint_lab = true                   # those models' lab tables enter the likelihood too
    lab_every = 2                      # every n-th lab row
    free_scatter = "auto"              # an extra scatter over the rows' own uncertainties (auto: if rows have them)

    [candidates]
    kinds = ["earthshine", "offset", "missing_facet", "wide_lobe", "out_of_plane", "diffraction", "solar_disk"]
    top_facets = 4                     # facet candidates on the facets carrying most of the light
    facets = []                        # or name them (over top_facets)
    earthshine_n_psi = 8
    earthshine_n_chi = 16
    disk_rings = 4
    limb_darkening = 0.6

    [search]
    bic_threshold = 10.0
    max_steps = 3
    pair_top = 3

    [holdout]
    by = "auto"                        # "night", "satellite", "block"; auto: nights if rows have times, else blocks
    folds = 5
    blocks = 10
    seed = 0

    [bands]
    draws = 200                        # parameter-uncertainty band of the final model (0: none)
    seed = 0

Outputs (:func:`run_skygap`): ``skygap.json``, ``report.md``,
``residuals_by_step.png``, ``skygap_model.toml`` (the final model as an
observe config: ``brdfjax observe`` on it reruns to the same magnitudes; the
run checks this and records the largest difference) and
``predictions.csv``.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import jax
import numpy as np
from pydantic import Field

from ..config import ConfigError, StrictModel, read_toml, validate
from ..io import check_output_dir, write_json_atomic
from ..io.observations import read_observations
from ..plotting import save_figure_atomic
from ..runtime.atomic import atomic_output
from .config import build_models
from .observe_config import _facet_specs, load_observe_config, predict_all
from .skyfit import (
    SkyProblem,
    block_groups,
    cross_validate,
    group_folds,
    lab_table,
    night_groups,
    predictive_band,
    sky_data,
    write_observe_config,
)
from .skygap import KINDS, add_effects, diagnose_sky

__all__ = ["SkygapConfig", "load_skygap_config", "run_skygap"]


class SkygapBaseConfig(StrictModel):
    """The base model the diagnosis starts from: the observe config's facets, their areas free."""

    free_models: dict[str, list[str]] = Field(default_factory=dict, description="model name -> parameter names "
                                              "(e.g. 'spec.g') the sky may refine; default none")
    joint_lab: bool = Field(True, description="the lab tables of the refined models enter the likelihood too "
                            "(lab + sky jointly)")
    lab_every: int = Field(2, ge=1, description="every n-th row of those lab tables")
    free_scatter: bool | Literal["auto"] = Field("auto", description="fit an extra magnitude scatter over the rows' "
                                                 "own uncertainties (auto: when the rows have uncertainties)")


class SkygapCandidatesConfig(StrictModel):
    """The candidate effects (brdfjax.lightcurve.skygap)."""

    kinds: list[str] = Field(default_factory=lambda: list(KINDS), description="effect kinds tried: "
                             + ", ".join(KINDS))
    top_facets: int = Field(4, ge=1, description="facet candidates on this many facets carrying most of the "
                            "predicted light")
    facets: list[str] = Field(default_factory=list, description="facets that get facet candidates (over "
                              "top_facets); empty: top_facets")
    earthshine_n_psi: int = Field(8, ge=4, description="polar rings of the Earth cap in the earthshine candidate")
    earthshine_n_chi: int = Field(16, ge=8, description="azimuths of the Earth cap in the earthshine candidate")
    disk_rings: int = Field(4, ge=1, le=16, description="rings of the solar-disk rule in the solar_disk candidate")
    limb_darkening: float = Field(0.6, ge=0, le=1, description="linear limb-darkening coefficient of the solar disk "
                                  "(about 0.6 in V)")


class SkygapSearchConfig(StrictModel):
    """The search over candidates (brdfjax.diagnose.search, run by brdfjax.lightcurve.skygap)."""

    bic_threshold: float = Field(10.0, gt=0, description="a step must lower BIC by more than this")
    max_steps: int = Field(3, ge=1, le=8, description="at most this many effects on the path")
    pair_top: int = Field(3, ge=0, description="pairs of the best this many candidates are refitted at each step")


class SkygapHoldoutConfig(StrictModel):
    """Cross-validation: whole groups of rows held out, never single rows."""

    by: Literal["auto", "night", "satellite", "block"] = Field("auto", description="hold out whole local nights, "
                                                               "satellites or contiguous blocks of rows; auto: "
                                                               "nights if the rows have times, else blocks")
    folds: int = Field(5, ge=2, description="number of folds")
    blocks: int = Field(10, ge=2, description="blocks of rows (by = 'block')")
    seed: int = Field(0, description="seed of the assignment of groups to folds")


class SkygapBandsConfig(StrictModel):
    """The final model's predictive band: its parameter uncertainty (Laplace) and each row's noise."""

    draws: int = Field(200, ge=0, description="parameter draws of the band (0: no band)")
    seed: int = Field(0, description="seed of the draws")


class SkygapOutputConfig(StrictModel):
    """What is written besides skygap.json, report.md and the model."""

    figures: bool = Field(True, description="write residuals_by_step.png")


class SkygapConfig(StrictModel):
    """A `brdfjax skygap` config."""

    source: str = Field("<string>", description="the config file (set by the reader)")
    observe: str = Field(description="the observe config with the facet model and the observation sets (relative "
                         "to this file)")
    set: str | None = Field(None, description="the observation set to diagnose (default: the observe config's first)")
    every: int = Field(1, ge=1, description="keep every n-th row (over the set's own 'every')")
    precision: Literal["float64"] = Field("float64", description="floating-point precision (the fits need float64)")
    base: SkygapBaseConfig = Field(default_factory=SkygapBaseConfig, description="the base model")
    candidates: SkygapCandidatesConfig = Field(default_factory=SkygapCandidatesConfig, description="candidates")
    search: SkygapSearchConfig = Field(default_factory=SkygapSearchConfig, description="the search")
    holdout: SkygapHoldoutConfig = Field(default_factory=SkygapHoldoutConfig, description="cross-validation")
    bands: SkygapBandsConfig = Field(default_factory=SkygapBandsConfig, description="the final model's band")
    output: SkygapOutputConfig = Field(default_factory=SkygapOutputConfig, description="outputs")

    def resolve(self, path: str) -> Path:
        p = Path(path)
        return p if p.is_absolute() else Path(self.source).parent / p


def load_skygap_config(path: str | Path) -> SkygapConfig:
    """Read and validate a skygap config (the observe config it names is read by :func:`run_skygap`)."""
    data = read_toml(path, "skygap config")
    cfg = validate(SkygapConfig, {**data, "source": str(path)}, str(path))
    bad = [k for k in cfg.candidates.kinds if k not in KINDS]
    if bad:
        raise ConfigError(str(path), [("candidates.kinds", f"unknown effect kinds {bad}; known: {', '.join(KINDS)}")])
    return cfg


# --- the run -----------------------------------------------------------------------------------------------------


def _setup(cfg: SkygapConfig, log):
    opath = cfg.resolve(cfg.observe)
    ocfg = load_observe_config(opath)
    names = [o.name for o in ocfg.observations]
    name = cfg.set or names[0]
    if name not in names:
        raise ConfigError(cfg.source, [("set", f"no observation set '{name}' in {opath}; sets: {', '.join(names)}")])
    oc = ocfg.observations[names.index(name)]
    obs = read_observations(ocfg.resolve(oc.path), oc.format, oc.columns or None, oc.band)
    step = oc.every * cfg.every
    if step > 1:
        obs = obs.take(np.arange(0, len(obs), step))
    d = sky_data(name, obs, yaw_law="sun_yaw" if ocfg.attitude.law == "nadir_sun_yaw" else "north",
                 convention=ocfg.photometry.convention, band_map=ocfg.photometry.bands, earth_radius=oc.earth_radius_m,
                 roll_deg=ocfg.attitude.roll_deg, pitch_deg=ocfg.attitude.pitch_deg, yaw_deg=ocfg.attitude.yaw_deg,
                 min_altitude_deg=oc.min_altitude_deg)
    if ocfg.sun.disk != "point":
        raise ConfigError(cfg.source, [("observe", f"{opath}: [sun] disk = '{ocfg.sun.disk}'; the diagnosis starts "
                                        "from a point Sun (the solar disk is a candidate)")])
    built = build_models(ocfg, ocfg.wavelength_nm * 1e-9)
    facets = [replace(f, families=[f.families[0]]) for f in _facet_specs(ocfg)]
    models = {f.families[0]: built[f.families[0]].model for f in facets}
    for fam in cfg.base.free_models:
        if fam not in models:
            raise ConfigError(cfg.source, [(f"base.free_models.{fam}", f"no facet of {opath} uses model '{fam}'; used: "
                                            f"{', '.join(models)}")])
    labs = []
    if cfg.base.joint_lab:
        for fam in cfg.base.free_models:
            f = next(f for f in facets if f.families[0] == fam)
            lab = ocfg.facets[f.name].lab
            if lab is not None and ocfg.lab[lab].path is not None:
                lc = ocfg.lab[lab]
                labs.append(lab_table(fam, ocfg.resolve(lc.path), lc.format, lc.columns, every=cfg.base.lab_every))
    has_err = bool(np.any(np.isfinite(d.mag_err) & (d.mag_err > 0)))
    scatter = has_err if cfg.base.free_scatter == "auto" else bool(cfg.base.free_scatter)
    P = SkyProblem.build(d, facets, models, normals=ocfg.attitude.normals, model_params=dict(cfg.base.free_models),
                         scatter=scatter, labs=labs, wavelength=ocfg.wavelength_nm * 1e-9)
    log(f"{name}: {len(d)} rows kept (dropped: {d.obs.dropped}); {len(facets)} facets; "
        f"{len(labs)} lab tables in the likelihood")
    return ocfg, opath, oc, step, P


def _groups(cfg: SkygapConfig, d) -> tuple[np.ndarray, str]:
    by = cfg.holdout.by
    if by == "auto":
        by = "night" if d.obs.time is not None and d.obs.lon_deg is not None else "block"
    if by == "night":
        return night_groups(d.obs), "night"
    if by == "satellite":
        if "satellite" not in d.obs.extra:
            raise ConfigError(cfg.source, [("holdout.by", f"{d.obs.source}: the rows name no satellite")])
        return np.asarray(d.obs.extra["satellite"], str), "satellite"
    return block_groups(len(d), cfg.holdout.blocks), "block"


def diagnosed_sections(fit, gp, effects, ocfg) -> dict[str, Any]:
    """The observe-config tables of the diagnosed effects: ``[effects]``, ``[earthshine]``, ``[sun]``."""
    P = gp.problem
    v = fit.values()
    eff: dict[str, Any] = {}
    out: dict[str, Any] = {"sun": {"disk": "point"}}
    for e in effects:
        c = gp.cands[e]
        if c.kind == "earthshine":
            n_psi, n_chi = P._es_grid
            out["earthshine"] = {"albedo": v["es.albedo"], "n_psi": n_psi, "n_chi": n_chi}
        elif c.kind == "solar_disk":
            n, ld = P._disk_rule
            out["sun"] = {"disk": "rings", "disk_rings": n, "limb_darkening": ld}
        elif c.kind == "missing_facet":
            eff["missing_facet"] = {"arho_m2": v["miss.arho"], "tilt_deg": float(np.rad2deg(v["miss.tilt"])),
                                    "az_deg": float(np.rad2deg(v["miss.az"]))}
        elif c.kind == "wide_lobe":
            j = [f.name for f in P.facets].index(c.facet)
            eff.setdefault("wide_lobe", {})[c.facet] = {
                "k": v[f"wide.{c.facet}.k"], "width_deg": float(np.rad2deg(v[f"wide.{c.facet}.w"])),
                "theta_max_deg": float(np.rad2deg(P._theta_max[j]))}
        elif c.kind == "out_of_plane":
            eff.setdefault("out_of_plane", {})[c.facet] = {
                "k": v[f"oop.{c.facet}.k"], "delta_deg": float(np.rad2deg(v[f"oop.{c.facet}.delta"]))}
        elif c.kind == "diffraction":
            eff.setdefault("diffraction", {})[c.facet] = {"k": v[f"diff.{c.facet}.k"],
                                                          "order_spacing": v[f"diff.{c.facet}.s"]}
    if eff:
        out["effects"] = eff
    return out


def _figure(res: dict, P, out: Path) -> str:
    from matplotlib.figure import Figure  # noqa: PLC0415 -- matplotlib only when figures are drawn

    trials = res["_path"]
    n = len(trials)
    fig = Figure(figsize=(7, 2.6 * n))
    d = P.data
    for i, t in enumerate(trials):
        ax = fig.add_subplot(n, 1, i + 1)
        r = d.mag - t.state.predict()
        if i > 0:
            rb = d.mag - trials[i - 1].state.predict()
            ax.scatter(d.phase_deg, rb, s=3, c="0.7", label="before this step")
        ax.scatter(d.phase_deg, r, s=3, c="C0" if i == 0 else "C3", label="after" if i else "base")
        ax.axhline(0, c="k", lw=0.8)
        title = "base" if i == 0 else f"step {i}: {res['path'][i - 1]['effect'].replace('+', ' + ')}"
        ho = f", held-out RMS {t.heldout:.3f}" if t.heldout is not None else ""
        ax.set_title(f"{title} (RMS {np.sqrt(np.mean(r**2)):.3f} mag{ho})", fontsize=9)
        ax.set_ylabel("obs - pred (mag)")
        ax.legend(fontsize=7, loc="upper right")
    ax.set_xlabel("solar phase angle (deg)")
    fig.tight_layout()
    p = out / "residuals_by_step.png"
    save_figure_atomic(fig, p, 110)
    return p.name


def _report(res: dict, summary: dict) -> str:
    h = res.get("heldout", {})
    path = res["path"]
    lines = [f"# Sky gap diagnosis: {summary['set']}", ""]
    if path:
        named = ", ".join(p["effect"] for p in path)
        lines.append(f"**Path: {named} (final set: {', '.join(res['effects'])}).** Held-out RMS "
                     f"{h.get('base_rms', float('nan')):.3f} mag (base) -> {h.get('path_rms', float('nan')):.3f} mag "
                     f"(path), {h.get('folds')} folds by {summary['holdout']}; in-sample RMS "
                     f"{res['base']['rms']:.3f} -> {path[-1]['rms_after']:.3f} mag over {res['n']} rows.")
    else:
        lines.append(f"**Nothing significant:** no candidate lowers BIC by more than {res['threshold']} "
                     f"(held-out RMS of the base {h.get('base_rms', float('nan')):.3f} mag over {res['n']} rows).")
    lines += ["", f"Search: {res['refits']} refits, {res['failed_refits']} failed; stopped: {res['stopped']}.", "",
              "| step | effect | dBIC | chi2_red | in-sample RMS (mag) | held-out RMS (mag) |",
              "|---|---|---|---|---|---|",
              f"| base | - | - | {res['base']['chi2_reduced']:.2f} | {res['base']['rms']:.3f} | "
              f"{h.get('base_rms', float('nan')):.3f} |"]
    for i, p in enumerate(path):
        lines.append(f"| {i + 1} | {p['effect']} | {p['delta_bic']:.1f} | {p['chi2_reduced']:.2f} | "
                     f"{p['rms_after']:.3f} | {p['heldout_rms'] if p['heldout_rms'] is None else round(p['heldout_rms'], 3)} |")
    for i, p in enumerate(path):
        lines += ["", f"## Step {i + 1}: {p['effect']}", "",
                  "Fitted: " + ", ".join(f"`{k}` = {v:.4g}" for k, v in p["values"].items()) if p["values"] else
                  "No free parameter.", "", "Where it changed the residuals (largest share of the RSS reduction first):",
                  "", "| zone | rows | RMS before | RMS after | share |", "|---|---|---|---|---|"]
        for z in p["zones"][:5]:
            lines.append(f"| {z['axis']} in [{z['range'][0]}, {z['range'][1]}) | {z['n']} | {z['rms_before']:.3f} | "
                         f"{z['rms_after']:.3f} | {z['share']:.2f} |")
    lines += ["", "## Candidates at the first step", "", "| candidate | dBIC | flags |", "|---|---|---|"]
    for r in res["ranking"]:
        fl = ", ".join((["on bound: " + " ".join(r["on_bound"])] if r["on_bound"] else []) + (["dead"] if r["dead"] else [])
                       + ([f"failed: {r['failure']}"] if not r["ok"] else []))
        lines.append(f"| {r['name']} | {r['delta_bic']:.1f} | {fl or '-'} |")
    b = summary.get("band")
    if b:
        lines += ["", f"Predictive band of the final model (parameter uncertainty + noise, {b['draws']} draws): "
                  f"held-out coverage 68 % {b['heldout_coverage_68']:.2f}, 95 % {b['heldout_coverage_95']:.2f}; "
                  f"median parameter sd {b['median_param_sd_mag']:.3f} mag."]
    rc = summary["rerun_check"]
    lines += ["", f"Final model: `{summary['model_config']}`; `brdfjax observe` on it reruns to the fit's magnitudes "
              f"within {rc['max_abs_diff_mag']:.2e} mag (largest difference over {rc['rows']} rows).",
              "", "![residuals by step](residuals_by_step.png)" if summary.get("figure") else ""]
    return "\n".join(lines) + "\n"


def run_skygap(cfg: SkygapConfig, out_dir: str | Path, log=lambda s: sys.stderr.write(s + "\n"),
               figures: bool | None = None, progress=None) -> dict[str, Any]:
    """Diagnose one observation set (see the module docstring) and write the outputs into ``out_dir``."""
    jax.config.update("jax_enable_x64", True)
    out = Path(check_output_dir(out_dir))
    out.mkdir(parents=True, exist_ok=True)
    ocfg, opath, oc, step, P = _setup(cfg, log)
    d = P.data
    c = cfg.candidates
    if c.facets:
        bad = [f for f in c.facets if f not in [q.name for q in P.facets]]
        if bad:
            raise ConfigError(cfg.source, [("candidates.facets", f"unknown facets {bad}")])
        top = list(c.facets)
    else:
        frac = np.asarray(P.flux(P.x_of_u(P.u0()))[0]).mean(0)
        top = [P.facets[j].name for j in np.argsort(-frac)[: c.top_facets]]
    cands = add_effects(P, kinds=tuple(c.kinds), facets=top, earthshine_grid=(c.earthshine_n_psi, c.earthshine_n_chi),
                        disk_rings=c.disk_rings, limb_darkening=c.limb_darkening)
    groups, by = _groups(cfg, d)
    folds = group_folds(groups, cfg.holdout.folds, seed=cfg.holdout.seed)
    model_keys = [f"{fam}.{p}" for fam, ps in cfg.base.free_models.items() for p in ps]
    base_free = P.default_free(*model_keys)
    log(f"{len(cands)} candidates on facets {top}; {len(folds)} folds by {by}")
    res = diagnose_sky(P, cands, folds, base_free=base_free, threshold=cfg.search.bic_threshold,
                       max_steps=cfg.search.max_steps, pair_top=cfg.search.pair_top, log=progress or (lambda s: None))
    final = res["_final_fit"]
    gp = res["_gap_problem"]
    # the final model as an observe config (only the diagnosed set, decimated as here), and its rerun
    src = read_toml(opath, "observe config")
    obs_tab = next(o for o in src["observations"] if o.get("name") == oc.name)
    obs_tab = {**obs_tab, "path": str(ocfg.resolve(oc.path).resolve()), "every": step}
    sections = diagnosed_sections(final, gp, res["effects"], ocfg)
    sections["observations"] = [obs_tab]
    model_path = write_observe_config(final, opath, out / "skygap_model.toml", sections=sections, effects_written=True,
                                      header=f"{Path(opath).name} with the diagnosed effects of {Path(cfg.source).name} "
                                      f"({', '.join(res['effects']) or 'none'}; brdfjax skygap)")
    cfg2 = load_observe_config(model_path)
    cfg2 = cfg2.model_copy(update={"bands": cfg2.bands.model_copy(update={"draws": 0})})
    rerun = predict_all(cfg2)[0]
    fitted = final.predict()
    same_rows = len(rerun.mag) == len(fitted)
    rc = {"rows": int(len(fitted)), "same_rows": same_rows,
          "max_abs_diff_mag": float(np.max(np.abs(rerun.mag - fitted))) if same_rows else float("nan")}
    log(f"rerun of {model_path.name} by observe: max |difference| {rc['max_abs_diff_mag']:.2e} mag")
    summary: dict[str, Any] = {
        "config": cfg.source, "observe_config": str(opath), "set": oc.name, "rows": len(d), "every": step,
        "holdout": by, "candidate_facets": top, "effects_named": res["effects"],
        "named_first": res["named"], "seconds": res["seconds"], "rerun_check": rc,
        "model_config": model_path.name,
        **{k: v for k, v in res.items() if not k.startswith("_") and k not in ("seconds",)},
    }
    summary["path_held_out"] = [{"step": 0, "effects": [], "heldout_rms": res["base"]["heldout_rms"],
                                 "bic": res["base"]["bic"]}] + [
        {"step": i + 1, "effects": list(t.effects), "heldout_rms": t.heldout, "bic": t.bic}
        for i, t in enumerate(res["_path"][1:])]
    cols = ["line", "observed_mag", "mag_err", "phase_deg", "base_mag", "final_mag", "heldout_base_mag",
            "heldout_final_mag"]
    band = None
    if cfg.bands.draws > 0:
        pb = predictive_band(final, cfg.bands.draws, cfg.bands.seed)
        band = pb["band"]
        cvb = cross_validate(P, final.free, folds, u0=final.u, band_draws=cfg.bands.draws, seed=cfg.bands.seed)
        summary["band"] = {"draws": cfg.bands.draws, "median_param_sd_mag": float(np.nanmedian(pb["param_sd"])),
                           "heldout_coverage_68": cvb["band_coverage_68"],
                           "heldout_coverage_95": cvb["band_coverage_95"],
                           "heldout_coverage_68_noise_only": cvb["coverage_68"],
                           "heldout_coverage_95_noise_only": cvb["coverage_95"]}
        cols += ["band_2p5", "band_16", "band_50", "band_84", "band_97p5"]
        log(f"band: held-out coverage 68 % {cvb['band_coverage_68']:.2f}, 95 % {cvb['band_coverage_95']:.2f}")
    base_pred = res["_path"][0].state.predict()
    hp = res.get("_heldout_pred", {"base": np.full(len(d), np.nan), "path": np.full(len(d), np.nan)})
    lines = [",".join(cols)]
    for i in range(len(d)):
        row = [str(int(d.obs.line[i])), f"{d.mag[i]:.6g}", f"{d.mag_err[i]:.4g}", f"{d.phase_deg[i]:.4f}",
               f"{base_pred[i]:.9g}", f"{fitted[i]:.9g}", f"{hp['base'][i]:.6g}", f"{hp['path'][i]:.6g}"]
        if band is not None:
            row += [f"{x:.6g}" for x in band[i]]
        lines.append(",".join(row))
    with atomic_output(out / "predictions.csv") as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    if figures if figures is not None else cfg.output.figures:
        summary["figure"] = _figure(res, P, out)
    text = _report(res, summary)
    with atomic_output(out / "report.md") as tmp:
        tmp.write_text(text, encoding="utf-8")
    write_json_atomic(out / "skygap.json", json_ready(summary))
    return summary


def json_ready(obj):
    """``obj`` with NumPy scalars and arrays as JSON values."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj

