"""The TOML config of ``brdfjax lightcurve``: satellite facets, models, orbit, observer, time span.

::

    wavelength_nm = 550.0
    precision = "float64"

    [orbit]
    tle = ["1 ...", "2 ..."]            # two TLE lines (checksums verified)

    [observer]
    lat_deg = -30.2446
    lon_deg = -70.7494
    height_m = 2663.0
    min_elevation_deg = 10.0           # the satellite must be this high
    max_sun_elevation_deg = -12.0      # and the sky this dark

    [time]
    start = 2026-12-02T00:00:00Z       # UTC
    stop = 2026-12-02T10:00:00Z
    step_s = 1.0

    [sun]
    disk = "adaptive"                  # or "full" (the rule at every step) or "point" (the centre only)
    disk_rings = 16                    # the full rule's rings (0: point Sun)
    limb_darkening = 0.0
    magnitude = -26.76

    [satellite]
    attitude = "nadir"                 # or "inertial"
    roll_deg = 0.0                     # offsets (nadir) or the inertial orientation
    pitch_deg = 0.0
    yaw_deg = 0.0

    [satellite.facets.array_front]
    area_m2 = 30.0
    normal = [0.0, 0.0, -1.0]          # body frame (z = nadir, x = velocity)
    x_axis = [0.0, 1.0, 0.0]           # in-plane axis; for a tracking facet the rotation axis
    phi_ref_deg = 0.0                  # turns the model's frame about the normal
    tracking = true
    model = "cell"                     # a [models.<name>] table

    [models.cell]                      # a [model]-style table (preset/params or terms) ...
    preset = "solar_cell"
    # fit_result = "result.json"       # ... optionally with a fit's parameters
    # posterior = "chain.h5"           # ... or a posterior's samples (bands)
    [models.white]
    lambertian_albedo = 0.3            # or a Lambertian baseline
    [models.paint]
    phong = {kd = 0.2, ks = 0.3, exponent = 20.0}    # or lumos-sat's Phong

    [compare.no_diffraction]           # the same pass with models replaced
    cell = "cell_nodiff"

    [glints]
    threshold_mag = 4.0                # a glint: total magnitude brighter than this

Every problem raises :class:`~brdfjax.config.ConfigError` naming the file and
the dotted key.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from ..config import ConfigError, ModelConfig, StrictModel, build_model, read_toml, validate
from ..core.terms import Lambertian, Model
from .ephemeris import TLEError, parse_tle
from .models import directional_albedo, lumos_phong, params_from_fit_result, posterior_samples

__all__ = ["LightcurveConfig", "load_lightcurve_config", "FacetConfig", "LCModelConfig"]


class PhongConfig(StrictModel):
    kd: float = Field(ge=0, description="diffuse coefficient")
    ks: float = Field(ge=0, description="specular coefficient")
    exponent: float = Field(ge=0, description="Phong exponent")


class LCModelConfig(StrictModel):
    """``[models.<name>]``: a [model]-style table, a Lambertian or Phong baseline; optionally a fit or posterior."""

    preset: str | None = Field(None, description="a model preset (as in [model])")
    params: dict[str, float] = Field(default_factory=dict, description="overrides of the preset's parameters: angles as <name>_deg, lengths as <name>_m")
    terms: dict[str, Any] | None = Field(None, description="named terms, as [model.terms.<name>]")
    without_terms: tuple[str, ...] = Field((), description="term names to drop (e.g. ['bars']: no diffraction)")
    lambertian_albedo: float | None = Field(None, ge=0, le=1, description="a Lambertian baseline's albedo")
    albedo_of: str | None = Field(None, description="a Lambertian baseline with the directional albedo of this model")
    albedo_theta_deg: float = Field(0.0, ge=0, lt=90, description="incidence angle of that albedo (deg)")
    phong: PhongConfig | None = Field(None, description="lumos-sat's Phong baseline: {kd, ks, exponent}")
    fit_result: str | None = Field(None, description="a brdfjax fit result.json whose parameters replace the model's")
    posterior: str | None = Field(None, description="a brdfjax sample chain.h5: the model's parameters are drawn from it")
    posterior_samples: int = Field(200, ge=2, description="number of posterior draws")
    posterior_burn: int | None = Field(None, ge=0, description="chain steps to discard (default: half)")

    @model_validator(mode="after")
    def _one_of(self) -> "LCModelConfig":
        kinds = [k for k, v in (("preset", self.preset), ("terms", self.terms), ("lambertian_albedo", self.lambertian_albedo),
                                ("albedo_of", self.albedo_of), ("phong", self.phong)) if v is not None]
        if len(kinds) != 1:
            raise ValueError(
                "give exactly one of 'preset', 'terms', 'lambertian_albedo', 'albedo_of' or 'phong'"
                + (f" (got {', '.join(kinds)})" if kinds else "")
            )
        if (self.fit_result or self.posterior) and kinds[0] not in ("preset", "terms"):
            raise ValueError("'fit_result' and 'posterior' go with a 'preset' or 'terms' model")
        if self.fit_result and self.posterior:
            raise ValueError("give 'fit_result' or 'posterior', not both")
        return self


class FacetConfig(StrictModel):
    area_m2: float = Field(gt=0, description="facet area (m^2)")
    normal: tuple[float, float, float] = Field(description="body-frame normal [x, y, z] (nonzero)")
    x_axis: tuple[float, float, float] | None = Field(None, description="body-frame in-plane axis (tracking: rotation axis)")
    phi_ref_deg: float = Field(0.0, description="turns the model's frame about the facet normal, degrees")
    tracking: bool = Field(False, description="the facet turns about x_axis to face the Sun (a solar array)")
    model: str = Field(description="a [models.<name>] table")

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v):
        if float(np.linalg.norm(v)) < 1e-12:
            raise ValueError(f"normal {list(v)} has zero length; expected a nonzero body-frame vector")
        return v


class SatelliteConfig(StrictModel):
    attitude: Literal["nadir", "inertial"] = Field("nadir", description="'nadir' (z toward the Earth, x along the velocity) or 'inertial'")
    roll_deg: float = Field(0.0, description="roll offset (nadir) or inertial orientation, degrees")
    pitch_deg: float = Field(0.0, description="pitch offset (nadir) or inertial orientation, degrees")
    yaw_deg: float = Field(0.0, description="yaw offset (nadir) or inertial orientation, degrees")
    facets: dict[str, FacetConfig] = Field(description="the [satellite.facets.<name>] tables")

    @field_validator("facets")
    @classmethod
    def _some(cls, v):
        if not v:
            raise ValueError("needs at least one facet ([satellite.facets.<name>])")
        return v


class OrbitConfig(StrictModel):
    tle: tuple[str, str] = Field(description="the two lines of a TLE")


class ObserverConfig(StrictModel):
    lat_deg: float = Field(ge=-90, le=90, description="observer's geodetic latitude in degrees")
    lon_deg: float = Field(ge=-180, le=360, description="observer's longitude in degrees (east positive)")
    height_m: float = Field(0.0, description="observer's height above the ellipsoid in metres")
    min_elevation_deg: float = Field(10.0, ge=0, lt=90, description="the satellite must be at least this high, degrees")
    max_sun_elevation_deg: float = Field(-12.0, le=90, description="the Sun must be at most this high (the sky dark), degrees")


class TimeConfig(StrictModel):
    start: dt.datetime = Field(description="start of the time span (UTC, a TOML datetime)")
    stop: dt.datetime = Field(description="end of the time span (UTC, after start)")
    step_s: float = Field(gt=0, description="time step in seconds")

    @model_validator(mode="after")
    def _order(self):
        if self.stop <= self.start:
            raise ValueError("'stop' must be after 'start'")
        return self


class SunConfig(StrictModel):
    disk: Literal["adaptive", "full", "point"] = Field(
        "adaptive", description="'adaptive': the full rule only near sharp features; 'full': everywhere; 'point': the centre")
    disk_rings: int = Field(16, ge=0, le=64, description="rings of the solar-disk quadrature (0: point Sun)")
    limb_darkening: float = Field(0.0, ge=0, le=1, description="linear limb-darkening coefficient of the solar disk (0-1)")
    magnitude: float = Field(-26.76, description="the Sun's apparent magnitude")


class GlintConfig(StrictModel):
    threshold_mag: float = Field(4.0, description="a glint: total magnitude brighter (smaller) than this")
    compare_tolerance_mag: float = Field(0.1, gt=0, description="differences larger than this are reported")


class LightcurveConfig(StrictModel):
    source: str = Field("<string>", description="set by the loader to the config file's path (not written in a config)")
    wavelength_nm: float = Field(550.0, gt=0, description="wavelength the models are evaluated at, nanometres")
    precision: Literal["float32", "float64"] = Field("float64", description="'float32' or 'float64'")
    chunk: int = Field(256, ge=1, description="time steps evaluated per compiled chunk")
    orbit: OrbitConfig = Field(description="the [orbit] table")
    observer: ObserverConfig = Field(description="the [observer] table")
    time: TimeConfig = Field(description="the [time] table")
    sun: SunConfig = Field(SunConfig(), description="the [sun] table")
    satellite: SatelliteConfig = Field(description="the [satellite] table")
    models: dict[str, LCModelConfig] = Field(description="the [models.<name>] tables")
    compare: dict[str, dict[str, str]] = Field(default_factory=dict, description="[compare.<name>]: the same pass with models replaced (model name -> replacement)")
    glints: GlintConfig = Field(GlintConfig(), description="the [glints] table")

    @model_validator(mode="after")
    def _references(self) -> "LightcurveConfig":
        for name, f in self.satellite.facets.items():
            if f.model not in self.models:
                raise ValueError(f"satellite.facets.{name}.model: unknown model '{f.model}'; known: {', '.join(self.models)}")
        for label, repl in self.compare.items():
            for old, new in repl.items():
                for nm in (old, new):
                    if nm not in self.models:
                        raise ValueError(f"compare.{label}.{old}: unknown model '{nm}'; known: {', '.join(self.models)}")
        for name, m in self.models.items():
            if m.albedo_of is not None and m.albedo_of not in self.models:
                raise ValueError(f"models.{name}.albedo_of: unknown model '{m.albedo_of}'; known: {', '.join(self.models)}")
        return self


def load_lightcurve_config(path: str | Path) -> LightcurveConfig:
    """Read and validate a light-curve TOML config (errors name the file and key)."""
    data = read_toml(path, "light-curve config")
    source = str(path)
    data = {**data, "source": source}
    cfg = validate(LightcurveConfig, data, source)
    try:
        parse_tle(*cfg.orbit.tle, where=f"{source}: orbit.tle")
    except TLEError as e:
        raise ConfigError(source, [("orbit.tle", str(e).split(": orbit.tle: ", 1)[-1])]) from None
    return cfg


def _resolve(source: str, path: str) -> Path:
    p = Path(path)
    return p if p.is_absolute() else Path(source).parent / p


class BuiltModel:
    """A facet model built from config: the model, and posterior draws (names, (S, p) array) if any."""

    def __init__(self, model: Model, draws: tuple[tuple[str, ...], np.ndarray] | None = None):
        self.model = model
        self.draws = draws


def build_models(cfg: LightcurveConfig, wavelength: float) -> dict[str, BuiltModel]:
    """Every ``[models.<name>]`` as a :class:`BuiltModel` (errors name the file and key)."""
    out: dict[str, BuiltModel] = {}
    pending = []
    for name, m in cfg.models.items():
        loc = f"models.{name}"
        if m.albedo_of is not None:
            pending.append((name, m))
            continue
        if m.lambertian_albedo is not None:
            out[name] = BuiltModel(Model({"diffuse": Lambertian(m.lambertian_albedo)}))
            continue
        if m.phong is not None:
            out[name] = BuiltModel(lumos_phong(m.phong.kd, m.phong.ks, m.phong.exponent))
            continue
        table = {k: v for k, v in (("preset", m.preset), ("params", m.params), ("terms", m.terms)) if v}
        try:
            model = build_model(cfg.source, validate(ModelConfig, table, cfg.source))
        except ConfigError as e:
            raise ConfigError(cfg.source, [(f"{loc}.{k.removeprefix('model.')}", msg) for k, msg in e.problems]) from None
        if m.without_terms:
            unknown = [t for t in m.without_terms if t not in model.terms]
            if unknown or len(m.without_terms) >= len(model.terms):
                raise ConfigError(cfg.source, [(f"{loc}.without_terms",
                                                f"cannot drop {list(m.without_terms)}; the model's terms: {', '.join(model.terms)}")])
            keep = {k: v for k, v in model.terms.items() if k not in m.without_terms}
            aliases = tuple((a, f) for a, f in model.aliases if f.split(".")[0] in keep)
            model = Model(keep, aliases)
        draws = None
        try:
            if m.fit_result:
                model = model.with_params(params_from_fit_result(_resolve(cfg.source, m.fit_result), model,
                                                                 f"{cfg.source}: {loc}.fit_result"))
            if m.posterior:
                draws = posterior_samples(_resolve(cfg.source, m.posterior), model, f"{cfg.source}: {loc}.posterior",
                                          m.posterior_samples, m.posterior_burn)
        except ValueError as e:
            raise ConfigError(cfg.source, [(f"{loc}", str(e).removeprefix(f"{cfg.source}: {loc}: "))]) from None
        out[name] = BuiltModel(model, draws)
    for name, m in pending:
        ref = out.get(m.albedo_of)
        if ref is None:
            raise ConfigError(cfg.source, [(f"models.{name}.albedo_of", f"'{m.albedo_of}' is itself a derived baseline")])
        albedo = directional_albedo(ref.model, np.deg2rad(m.albedo_theta_deg), wavelength)
        out[name] = BuiltModel(Model({"diffuse": Lambertian(albedo)}))
    return out
