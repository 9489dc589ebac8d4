"""The TOML config of ``brdfjax observe`` and the run that writes its outputs.

::

    precision = "float64"
    wavelength_nm = 550.0

    [photometry]
    convention = "physical"          # or "lumos": no (AU / d_sun)^2 factor, as lumos-sat
    bands = { CLEAR = "V" }          # a file's band name -> a known band (brdfjax.lightcurve.photometry)

    [sun]
    disk = "point"                   # or "rings": the solar disk quadrature
    disk_rings = 4

    [attitude]
    law = "nadir_sun_yaw"            # or "nadir_north" (brdfjax.lightcurve.attitude)
    normals = "lumos"                # facet normals in lumos-sat's frame, or "body"
    roll_deg = 0.0                   # offsets of the bus
    pitch_deg = 0.0
    yaw_deg = 0.0

    [[observations]]                 # one table per observation set
    name = "slingshot"
    path = "data/slingshot.csv"      # relative to this file
    format = "slingshot"             # "score", "slingshot", "absolute", "relative" (brdfjax.io.observations)
    columns = {}                     # role -> column name, over the format's
    band = "AB"                      # rows without a band column
    earth_radius_m = 6378000.0       # sphere of relative rows and of the shadow test
    every = 1                        # keep every n-th row
    # tle = ["1 ...", "2 ..."]       # rows with a time and site only: positions from this TLE (SGP4)
    # tle_max_age_days = 7.0         # refuse rows further than this from the TLE's epoch

    [facets.chassis]
    area_m2 = 11.7
    normal = [0.0, 0.0, -1.0]
    model = "mirror_binomial"        # the prediction's model ...
    alternatives = ["mirror_abg"]    # ... and other families fitted to the same table (model-form spread)
    # weights = [0.6, 0.4]           # model averaging: the prediction is the weighted mean flux of model and
    #                                # alternatives (in that order) and the band draws each with its weight
    lab = "mirror"                   # the lab table it was fitted to (coverage flags)
    cant_deg = 0.0                   # tilt of the normal about the facet's x axis
    yaw_deg = 0.0                    # turn about body z
    tracking = false                 # a Sun-tracking facet turning about x_axis

    [lab.mirror]
    path = "lab/mirror.csv"          # the table: its largest incident angle and whether it is in-plane
    format = "lumos-sat"
    # or: max_theta_i_deg = 75.0, in_plane = true

    [models.mirror_binomial]         # brdfjax lightcurve's [models.<name>] keys, and terms_file
    terms_file = "v2mini/mirror_binomial.terms.toml"
    fit_result = "v2mini/mirror_binomial.result.json"   # values, and the covariance of the band

    [earthshine]
    albedo = 0.3                     # a Lambertian Earth (omit: no earthshine)
    n_psi = 32
    n_chi = 64

    [effects.wide_lobe.chassis]      # light terms beyond the facet models (written by brdfjax skygap)
    k = 0.4
    width_deg = 20.0

    [model_error.mirror_binomial]    # the model's own error, RMS of ln BRDF (widens the band)
    inside_log_rms = 0.79            # its fit's log-RMS
    outside_log_rms = 1.28           # its log-RMS on a withheld incidence (experiments/sky_lab_cv.py)

    [bands]
    draws = 200                      # 0: no band
    seed = 0
    parameter_uncertainty = true
    model_form = true

    [flags]
    out_of_plane_deg = 5.0
    incidence_margin_deg = 1.0
    min_flux_fraction = 0.1

Errors raise :class:`~brdfjax.config.ConfigError` naming the file and key.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from ..config import ConfigError, StrictModel, read_toml, validate
from ..io import check_output_dir, write_json_atomic
from ..io.observations import FORMATS, read_observations
from ..plotting import save_figure_atomic
from ..runtime.atomic import atomic_output
from .config import LCModelConfig, build_models
from .engine import SunDisk
from .observe import FacetSpec, SetPrediction, lab_coverage, predict_set
from .skygeometry import positions_from_tle

__all__ = ["ObserveConfig", "load_observe_config", "run_observe"]


class PhotometryConfig(StrictModel):
    convention: Literal["physical", "lumos"] = Field("physical", description="with or without (AU/d_sun)^2")
    bands: dict[str, str] = Field(default_factory=dict, description="file band name -> known band")


class SunConfig(StrictModel):
    disk: Literal["point", "rings"] = "point"
    disk_rings: int = Field(4, ge=0, le=32)
    limb_darkening: float = Field(0.0, ge=0, le=1)


class AttitudeConfig(StrictModel):
    law: Literal["nadir_sun_yaw", "nadir_north"] = "nadir_sun_yaw"
    normals: Literal["body", "lumos"] = "body"
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    min_height_km: float | None = Field(
        None, gt=0, description="the lowest satellite height at which the law holds; rows below are flagged off_shell "
        "(a satellite raising or lowering its orbit flies in another attitude) and the metrics split by the flag")


class ObservationSetConfig(StrictModel):
    name: str
    path: str
    format: str = "score"
    columns: dict[str, str] = Field(default_factory=dict)
    band: str | None = None
    earth_radius_m: float | None = Field(None, gt=6.3e6, lt=6.4e6)
    min_altitude_deg: float = Field(0.0, ge=0, lt=90)
    every: int = Field(1, ge=1)
    tle: list[str] | None = Field(None, description="two TLE lines: the satellite's position at each row's time")
    tle_max_age_days: float = Field(7.0, gt=0, description="the largest |row time - TLE epoch| accepted (days)")

    @model_validator(mode="after")
    def _format(self) -> "ObservationSetConfig":
        if self.format not in FORMATS:
            raise ValueError(f"format '{self.format}' unknown; known: {', '.join(FORMATS)}")
        if self.tle is not None:
            if len(self.tle) != 2:
                raise ValueError(f"tle: expected two TLE lines, got {len(self.tle)}")
            if FORMATS[self.format]["kind"] != "absolute":
                raise ValueError(f"tle: a TLE gives positions only to absolute rows (time and site); format "
                                 f"'{self.format}' has relative rows")
        return self


class ObserveFacetConfig(StrictModel):
    area_m2: float = Field(gt=0)
    normal: tuple[float, float, float]
    x_axis: tuple[float, float, float] | None = None
    tracking: bool = False
    cant_deg: float = 0.0
    yaw_deg: float = 0.0
    model: str
    alternatives: list[str] = Field(default_factory=list)
    weights: list[float] | None = Field(None, description="model averaging: a weight per model and alternative")
    lab: str | None = None

    @model_validator(mode="after")
    def _weights(self) -> "ObserveFacetConfig":
        if self.weights is not None:
            n = 1 + len(self.alternatives)
            if len(self.weights) != n:
                raise ValueError(f"weights: {len(self.weights)} given, expected {n} (model and each alternative)")
            if any(not np.isfinite(w) or w < 0 for w in self.weights) or sum(self.weights) <= 0:
                raise ValueError(f"weights: expected finite values >= 0 with a positive sum, got {self.weights}")
        return self


class LabConfig(StrictModel):
    path: str | None = None
    format: Literal["lumos-sat", "merl", "cornell", "table"] = "lumos-sat"
    columns: dict[str, str | int] | None = None
    max_theta_i_deg: float | None = Field(None, gt=0, le=90)
    in_plane: bool | None = None

    @model_validator(mode="after")
    def _one(self) -> "LabConfig":
        if (self.path is None) == (self.max_theta_i_deg is None):
            raise ValueError("give 'path' (a lab table) or 'max_theta_i_deg' (and 'in_plane'), not both")
        return self


class EarthshineConfig(StrictModel):
    albedo: float | None = Field(None, ge=0, le=1, description="a Lambertian Earth's albedo; none: no earthshine")
    n_psi: int = Field(32, ge=4, description="polar rings of the visible cap")
    n_chi: int = Field(64, ge=8, description="azimuths of the visible cap")


class ModelErrorConfig(StrictModel):
    inside_log_rms: float = Field(ge=0, description="RMS of ln BRDF inside the lab's geometry (the fit's log-RMS)")
    outside_log_rms: float = Field(ge=0, description="RMS of ln BRDF outside it (e.g. on a withheld incidence)")


class BandsConfig(StrictModel):
    draws: int = Field(200, ge=0)
    seed: int = 0
    parameter_uncertainty: bool = True
    model_form: bool = True


class FlagsConfig(StrictModel):
    out_of_plane_deg: float = Field(5.0, gt=0)
    incidence_margin_deg: float = Field(1.0, ge=0)
    min_flux_fraction: float = Field(0.1, ge=0, le=1)


class MissingFacetEffect(StrictModel):
    """A Lambertian plate the facet model lacks (the sky gap diagnosis's ``missing_facet``)."""

    arho_m2: float = Field(ge=0, description="its area times its albedo (m^2)")
    tilt_deg: float = Field(ge=0, le=180, description="its body-frame normal's angle from body +z (deg)")
    az_deg: float = Field(ge=-360, le=360, description="its normal's azimuth about body z, from body +x (deg)")


class WideLobeEffect(StrictModel):
    """A lobe beyond a facet's measured incidence: k exp(-(1 - h_z) / w^2), switched on beyond theta_max."""

    k: float = Field(ge=0, description="amplitude (sr^-1)")
    width_deg: float = Field(gt=0, le=90, description="width w of the lobe in the half vector (deg)")
    theta_max_deg: float | None = Field(None, gt=0, le=90, description="incidence beyond which it switches on "
                                        "(a 2-deg sigmoid); unset: the facet's lab table's largest incidence, else 75")


class OutOfPlaneEffect(StrictModel):
    """Two offset peaks out of the plane of incidence (6-deg lobes about the half vector)."""

    k: float = Field(ge=0, description="amplitude of the pair (sr^-1)")
    delta_deg: float = Field(ge=0, le=90, description="the peaks' offset from the facet normal, out of the plane (deg)")


class DiffractionEffect(StrictModel):
    """First diffraction orders of grooves along the facet's x axis (out of a lab scan along x)."""

    k: float = Field(ge=0, description="amplitude of the pair of orders (sr^-1)")
    order_spacing: float = Field(gt=0, le=2, description="lambda / groove period: the orders' offset in direction "
                                 "cosine along the facet's y axis")


class EffectsConfig(StrictModel):
    """Light terms added to the facet model (brdfjax.lightcurve.skyeffects); `brdfjax skygap` writes them."""

    missing_facet: MissingFacetEffect | None = Field(None, description="a Lambertian plate the model lacks")
    wide_lobe: dict[str, WideLobeEffect] = Field(default_factory=dict, description="per facet: a lobe beyond "
                                                 "its measured incidence")
    out_of_plane: dict[str, OutOfPlaneEffect] = Field(default_factory=dict, description="per facet: offset peaks "
                                                      "out of the plane of incidence")
    diffraction: dict[str, DiffractionEffect] = Field(default_factory=dict, description="per facet: grating "
                                                      "orders out of the lab's scan plane")

    def values(self) -> tuple[dict[str, float], dict[str, float]]:
        """The :mod:`.skyeffects` parameter values (radians) and each wide lobe's switch-on incidence (deg)."""
        v: dict[str, float] = {}
        tmax: dict[str, float] = {}
        if self.missing_facet is not None:
            m = self.missing_facet
            v.update({"miss.arho": m.arho_m2, "miss.tilt": float(np.deg2rad(m.tilt_deg)),
                      "miss.az": float(np.deg2rad(m.az_deg))})
        for f, e in self.wide_lobe.items():
            v.update({f"wide.{f}.k": e.k, f"wide.{f}.w": float(np.deg2rad(e.width_deg))})
            if e.theta_max_deg is not None:
                tmax[f] = e.theta_max_deg
        for f, e in self.out_of_plane.items():
            v.update({f"oop.{f}.k": e.k, f"oop.{f}.delta": float(np.deg2rad(e.delta_deg))})
        for f, e in self.diffraction.items():
            v.update({f"diff.{f}.k": e.k, f"diff.{f}.s": e.order_spacing})
        return v, tmax


class OutputConfig(StrictModel):
    figures: bool = True


class ObserveConfig(StrictModel):
    source: str = "<string>"
    precision: Literal["float32", "float64"] = "float64"
    wavelength_nm: float = Field(550.0, gt=0)
    photometry: PhotometryConfig = Field(default_factory=PhotometryConfig)
    sun: SunConfig = Field(default_factory=SunConfig)
    attitude: AttitudeConfig = Field(default_factory=AttitudeConfig)
    observations: list[ObservationSetConfig] = Field(min_length=1)
    facets: dict[str, ObserveFacetConfig] = Field(min_length=1)
    lab: dict[str, LabConfig] = Field(default_factory=dict)
    models: dict[str, LCModelConfig] = Field(min_length=1)
    earthshine: EarthshineConfig = Field(default_factory=EarthshineConfig)
    effects: EffectsConfig = Field(default_factory=EffectsConfig)
    model_error: dict[str, ModelErrorConfig] = Field(default_factory=dict)
    bands: BandsConfig = Field(default_factory=BandsConfig)
    flags: FlagsConfig = Field(default_factory=FlagsConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)

    @model_validator(mode="after")
    def _refs(self) -> "ObserveConfig":
        for name, f in self.facets.items():
            for m in [f.model, *f.alternatives]:
                if m not in self.models:
                    raise ValueError(f"facets.{name}: unknown model '{m}'; known: {', '.join(self.models)}")
            if f.lab is not None and f.lab not in self.lab:
                raise ValueError(f"facets.{name}.lab: unknown lab table '{f.lab}'; known: {', '.join(self.lab) or 'none'}")
        for kind in ("wide_lobe", "out_of_plane", "diffraction"):
            for f in getattr(self.effects, kind):
                if f not in self.facets:
                    raise ValueError(f"effects.{kind}.{f}: unknown facet; known: {', '.join(self.facets)}")
        for m in self.model_error:
            if m not in self.models:
                raise ValueError(f"model_error.{m}: unknown model; known: {', '.join(self.models)}")
        names = [o.name for o in self.observations]
        if len(set(names)) != len(names):
            raise ValueError(f"observations: names must differ (got {names})")
        return self

    def resolve(self, path: str) -> Path:
        p = Path(path)
        return p if p.is_absolute() else Path(self.source).parent / p


def load_observe_config(path: str | Path) -> ObserveConfig:
    """Read and validate an observe config (``terms_file`` of a model is read into its ``terms``)."""
    source = str(path)
    data = read_toml(path, "observe config")
    models = data.get("models", {})
    if isinstance(models, dict):
        for name, m in models.items():
            if isinstance(m, dict) and "terms_file" in m:
                tf = m.pop("terms_file")
                p = Path(tf) if Path(tf).is_absolute() else Path(source).parent / tf
                sub = read_toml(p, f"terms file of models.{name}")
                if "terms" not in sub:
                    raise ConfigError(source, [(f"models.{name}.terms_file", f"{p} has no [terms] tables")])
                m["terms"] = sub["terms"]
    return validate(ObserveConfig, {**data, "source": source}, source)


def _facet_specs(cfg: ObserveConfig) -> list[FacetSpec]:
    labs = {}
    for name, lab in cfg.lab.items():
        if lab.path is not None:
            labs[name] = lab_coverage(cfg.resolve(lab.path), lab.format, lab.columns)
        else:
            labs[name] = (lab.max_theta_i_deg, bool(lab.in_plane))
    out = []
    for name, f in cfg.facets.items():
        max_ti, in_plane = labs.get(f.lab, (None, False))
        out.append(FacetSpec(name, f.area_m2, f.normal, [f.model, *f.alternatives], f.x_axis, f.tracking, f.cant_deg,
                             f.yaw_deg, max_ti, in_plane, None if f.weights is None else tuple(f.weights)))
    return out


def predict_all(cfg: ObserveConfig, log=lambda s: None) -> list[SetPrediction]:
    """Every observation set of ``cfg`` predicted (no files written)."""
    built = build_models(cfg, cfg.wavelength_nm * 1e-9)
    results = {n: cfg.resolve(m.fit_result) for n, m in cfg.models.items() if m.fit_result}
    facets = _facet_specs(cfg)
    disk = SunDisk.point() if cfg.sun.disk == "point" else SunDisk.rings(cfg.sun.disk_rings,
                                                                      limb_darkening=cfg.sun.limb_darkening)
    eff, eff_tmax = cfg.effects.values()
    out = []
    for oc in cfg.observations:
        obs = read_observations(cfg.resolve(oc.path), oc.format, oc.columns or None, oc.band,
                                positions="observed" if oc.tle is None else "tle")
        if oc.tle is not None:
            obs = positions_from_tle(obs, *oc.tle, max_age_days=oc.tle_max_age_days,
                                     where=f"{cfg.source}: observations '{oc.name}' tle")
        if oc.every > 1:
            obs = obs.take(np.arange(0, len(obs), oc.every))
        law = "sun_yaw" if cfg.attitude.law == "nadir_sun_yaw" else "north"
        pred = predict_set(
            oc.name, obs, facets, built, normals=cfg.attitude.normals, yaw_law=law, roll_deg=cfg.attitude.roll_deg,
            pitch_deg=cfg.attitude.pitch_deg, yaw_deg=cfg.attitude.yaw_deg, convention=cfg.photometry.convention,
            band_map=cfg.photometry.bands, disk=disk, earth_radius=oc.earth_radius_m,
            wavelength=cfg.wavelength_nm * 1e-9, draws=cfg.bands.draws, seed=cfg.bands.seed,
            parameter_uncertainty=cfg.bands.parameter_uncertainty, model_form=cfg.bands.model_form,
            result_paths=results, out_of_plane_deg=cfg.flags.out_of_plane_deg,
            incidence_margin_deg=cfg.flags.incidence_margin_deg, min_flux_fraction=cfg.flags.min_flux_fraction,
            min_altitude_deg=oc.min_altitude_deg, min_height_km=cfg.attitude.min_height_km,
            earthshine_albedo=cfg.earthshine.albedo,
            earthshine_grid=(cfg.earthshine.n_psi, cfg.earthshine.n_chi),
            model_error={k: (v.inside_log_rms, v.outside_log_rms) for k, v in cfg.model_error.items()},
            effects=eff, effects_theta_max_deg=eff_tmax)
        log(f"{oc.name}: {len(pred.mag)} rows predicted (dropped: {pred.obs.dropped})")
        out.append(pred)
    return out


def _csv(pred: SetPrediction) -> str:
    cols = ["line", "observed_mag", "mag_err", "band", "predicted_mag", "residual_mag", "phase_deg", "outside_lab",
            "height_km", "off_shell"]
    if pred.band is not None:
        cols += ["band_2p5", "band_16", "band_50", "band_84", "band_97p5"]
    for f in pred.facet_names:
        cols += [f"mag_{f}", f"theta_i_deg_{f}", f"theta_s_deg_{f}", f"out_of_plane_deg_{f}", f"beyond_incidence_{f}",
                 f"out_of_plane_{f}"]
    lines = [",".join(cols)]
    o = pred.obs
    for i in range(len(pred.mag)):
        row = [str(int(o.line[i])), f"{o.mag[i]:.6g}", f"{o.mag_err[i]:.4g}", str(o.band[i]), f"{pred.mag[i]:.9g}",
               f"{o.mag[i] - pred.mag[i]:.6g}", f"{pred.phase_deg[i]:.4f}", str(int(pred.flagged[i])),
               f"{pred.height_km[i]:.3f}", str(int(pred.off_shell is not None and pred.off_shell[i]))]
        if pred.band is not None:
            row += [f"{x:.6g}" for x in pred.band[i]]
        for j in range(len(pred.facet_names)):
            row += [f"{pred.facet_mag[i, j]:.6g}", f"{pred.theta_i[i, j]:.4f}", f"{pred.theta_s[i, j]:.4f}",
                    f"{pred.out_of_plane[i, j]:.4f}", str(int(pred.flag_incidence[i, j])), str(int(pred.flag_plane[i, j]))]
        lines.append(",".join(row))
    return "\n".join(lines) + "\n"


def _figures(pred: SetPrediction, out: Path) -> list[str]:
    from matplotlib.figure import Figure  # noqa: PLC0415 -- 0.4 s of matplotlib only when figures are drawn

    res = pred.observed - pred.mag
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    off = pred.off_shell if pred.off_shell is not None else np.zeros(len(res), bool)
    inside, outside = ~pred.flagged & ~off, pred.flagged & ~off
    ax.scatter(pred.phase_deg[inside], res[inside], s=4, label="inside the lab's geometry")
    ax.scatter(pred.phase_deg[outside], res[outside], s=4, c="C3", label="outside (flagged)")
    if off.any():
        ax.scatter(pred.phase_deg[off], res[off], s=6, marker="x", c="0.4", lw=0.6, label="below the operational height")
    if pred.band is not None:
        order = np.argsort(pred.phase_deg)
        ax.fill_between(pred.phase_deg[order], (pred.band[:, 1] - pred.mag)[order], (pred.band[:, 3] - pred.mag)[order],
                        color="0.6", alpha=0.3, lw=0, label="68 % band - prediction")
    ax.axhline(0, c="k", lw=0.8)
    ax.set_xlabel("solar phase angle (deg)")
    ax.set_ylabel("observed - predicted (mag)")
    ax.set_title(f"{pred.name}: residuals")
    ax.legend(fontsize=7)
    names = []
    p1 = out / f"residuals_vs_phase_{pred.name}.png"
    save_figure_atomic(fig, p1, 120)
    names.append(p1.name)
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    total = pred.facet_flux.sum(-1)
    frac = pred.facet_flux / np.where(total > 0, total, 1.0)[:, None]
    order = np.argsort(pred.phase_deg)
    ax.stackplot(pred.phase_deg[order], frac[order].T, labels=pred.facet_names)
    ax.set_xlabel("solar phase angle (deg)")
    ax.set_ylabel("fraction of the predicted flux")
    ax.set_title(f"{pred.name}: per-facet contribution")
    ax.legend(fontsize=6, loc="upper left")
    p2 = out / f"facet_contribution_{pred.name}.png"
    save_figure_atomic(fig, p2, 120)
    names.append(p2.name)
    return names


def run_observe(cfg: ObserveConfig, out_dir: str | Path, log=lambda s: sys.stderr.write(s + "\n"), figures: bool | None = None
                ) -> dict[str, Any]:
    """Predict every set of ``cfg`` and write ``predictions_<set>.csv``, ``observe.json`` and the figures."""
    out = check_output_dir(out_dir)
    Path(out).mkdir(parents=True, exist_ok=True)
    preds = predict_all(cfg, log)
    summary: dict[str, Any] = {"config": cfg.source, "photometry": cfg.photometry.convention, "sun_disk": cfg.sun.disk,
                               "attitude": cfg.attitude.law, "earthshine_albedo": cfg.earthshine.albedo, "sets": {}}
    for pred in preds:
        text = _csv(pred)
        with atomic_output(Path(out) / f"predictions_{pred.name}.csv") as tmp:
            tmp.write_text(text, encoding="utf-8")
        entry = {
            "n_rows_predicted": int(len(pred.mag)), "dropped": pred.obs.dropped,
            "metrics": pred.metrics(),
            "fraction_outside_lab": float(np.mean(pred.flagged)),
            "min_height_km": cfg.attitude.min_height_km,
            "n_off_shell": None if pred.off_shell is None else int(pred.off_shell.sum()),
            "facets": {f: {"model": cfg.facets[f].model, "alternatives": cfg.facets[f].alternatives,
                           "fraction_beyond_incidence": float(np.mean(pred.flag_incidence[:, j])),
                           "fraction_out_of_plane": float(np.mean(pred.flag_plane[:, j])),
                           "median_flux_fraction": float(np.median(pred.facet_flux[:, j] / np.maximum(pred.facet_flux.sum(-1), 1e-300)))}
                       for j, f in enumerate(pred.facet_names)},
            "families_drawn": pred.families_drawn,
            "predictions_csv": f"predictions_{pred.name}.csv",
        }
        if figures if figures is not None else cfg.output.figures:
            entry["figures"] = _figures(pred, Path(out))
        summary["sets"][pred.name] = entry
        h = cfg.attitude.min_height_km
        labels = {"all": ""} if h is None else {
            "all": "", "operational": f" (satellites at or above {h:g} km)",
            "off_shell": f" (below {h:g} km: the attitude law does not hold)"}
        for key, what in labels.items():
            m = entry["metrics"].get(key)
            if m is None or "rms" not in m:
                continue
            log(f"{pred.name}{what}: {m['n']} rows, RMS {m['rms']:.3f} mag, bias {m['bias']:+.3f}, R "
                + (f"{m['pearson_r']:.3f}" if m.get("pearson_r") is not None else "-")
                + (f", coverage 68 % {m['coverage_68']:.2f}, 95 % {m['coverage_95']:.2f}" if "coverage_68" in m else ""))
    write_json_atomic(Path(out) / "observe.json", summary)
    return summary
