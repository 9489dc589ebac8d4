"""TOML configs for ``brdfjax simulate``: parsed at the edge into frozen, validated objects.

A config names the detector, the pixel grid, the BRDF model and the frames to
render.  Keys carry their units (``theta_i_deg``, ``wavelength_nm``,
``distance_m``); the builders convert to the SI units and radians of the core::

    precision = "float32"                 # or "float64"

    [detector]                            # every key optional; defaults: the seed camera
    preset = "seed"                       # known: seed
    n_h = 3296                            # columns
    n_v = 2472                            # rows
    pixel_pitch_um = 5.5                  # horizontal pitch d_h
    pixel_pitch_v_um = 5.5                # vertical pitch d_v (default: pixel_pitch_um)
    distance_m = 0.325                    # sample-to-array distance R
    theta_c_deg = 20.0                    # arm angle; omitted: centred on each frame's specular peak
    roll_deg = 0.0                        # CCD misalignment (seed Eq 105)
    yaw_deg = 0.0
    pitch_deg = 0.0
    m_h_px = 0.0
    m_v_px = 0.0

    [grid]
    step = 1                              # every k-th pixel
    roi = [-200, 200, -150, 150]          # optional: [h0, h1, v0, v1], seed pixel indices, inclusive

    [model]                               # either a preset ...
    preset = "solar_cell"
    [model.params]                        # ... with optional overrides of its parameters
    m1 = 2e-4
    dtheta_deg = 0.5                      # angle parameters as <name>_deg
    a_m = 8e-4                            # length parameters as <name>_m

    # ... or named terms (instead of preset):
    # [model.terms.center]
    # kind = "specular"                   # specular, offset_specular, lambertian, diffraction
    # distribution = "beckmann"           # specular kinds only
    # params = { m = 2e-4, rho_s = 0.015, n = 3.6 }

    [[frames]]
    theta_i_deg = 20.0                    # 0 <= theta_i_deg < 90
    phi_ref_deg = 0.0
    wavelength_nm = 632.8
    name = "ti20"                         # optional; output file stem

:func:`load_simulate_config` reads and validates a file (unknown keys are
errors; every message names the file and the dotted key, e.g.
``frames[1].theta_i_deg``) and raises :class:`ConfigError`.  The builders
:meth:`SimulateConfig.build_detector`, :meth:`SimulateConfig.build_frames`
and :meth:`SimulateConfig.build_model` return the core objects.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import tomllib
import types
import typing
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import equinox as eqx
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from .errors import InputError
from . import registry
from .detector import Detector, PixelGrid
from .render import Frame
from .instrument.synthetic import InstrumentConfig
from .terms import AbstractTerm, Diffraction, Model, OffsetNormal, Specular

__all__ = [
    "ConfigError",
    "DetectorConfig",
    "GridConfig",
    "TermConfig",
    "ModelConfig",
    "FrameConfig",
    "SimulateConfig",
    "DETECTOR_PRESETS",
    "load_simulate_config",
    "load_instrument_config",
    "parse_simulate_config",
    "default_config_path",
    "parameter_keys",
]

#: Detector presets: config keys filled in when ``[detector]`` leaves them out.
DETECTOR_PRESETS: dict[str, dict[str, float | int]] = {
    "seed": {"n_h": 3296, "n_v": 2472, "pixel_pitch_um": 5.5, "distance_m": 0.325},
}

#: Config-key suffix and scale to stored units, by the unit a parameter is stored in.
_UNIT_KEYS: dict[str, tuple[str, float]] = {
    "rad": ("_deg", np.pi / 180.0),
    "m": ("_m", 1.0),
    "px": ("_px", 1.0),
}

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class ConfigError(InputError):
    """A config that cannot be used; the message names the file and the key.

    ``source`` is the file (or ``"<string>"``), ``problems`` a list of
    ``(dotted key, message)`` pairs.
    """

    def __init__(self, source: str, problems: list[tuple[str, str]]):
        self.source = source
        self.problems = list(problems)
        lines = [f"{source}: {key}: {msg}" if key else f"{source}: {msg}" for key, msg in self.problems]
        super().__init__("\n".join(lines))


# --- schema --------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)


class DetectorConfig(_Strict):
    """``[detector]``: the CCD on the arm.  Omitted keys come from ``preset``."""

    preset: str = Field("seed", description=f"a detector preset name; known: {', '.join(DETECTOR_PRESETS)}")
    n_h: int | None = Field(None, gt=0, description="number of pixel columns, a positive integer")
    n_v: int | None = Field(None, gt=0, description="number of pixel rows, a positive integer")
    pixel_pitch_um: float | None = Field(None, gt=0, description="horizontal pixel pitch in micrometres, > 0")
    pixel_pitch_v_um: float | None = Field(
        None, gt=0, description="vertical pixel pitch in micrometres, > 0 (default: pixel_pitch_um)"
    )
    distance_m: float | None = Field(None, gt=0, description="sample-to-array distance R in metres, > 0")
    theta_c_deg: float | None = Field(
        None, ge=0, lt=90, description="detector arm angle in degrees, 0 <= theta_c_deg < 90 (omit: theta_i)"
    )
    roll_deg: float = Field(0.0, description="CCD roll about the optical axis in degrees")
    yaw_deg: float = Field(0.0, description="CCD yaw in degrees")
    pitch_deg: float = Field(0.0, description="CCD pitch in degrees")
    m_h_px: float = Field(0.0, description="in-plane peak offset in pixels")
    m_v_px: float = Field(0.0, description="out-of-plane peak offset in pixels")

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, v: str) -> str:
        if v not in DETECTOR_PRESETS:
            raise ValueError(f"unknown detector preset '{v}'; known: {', '.join(sorted(DETECTOR_PRESETS))}")
        return v

    def resolved(self) -> dict[str, Any]:
        """Every geometric key with the preset's value where the config leaves it out."""
        base = DETECTOR_PRESETS[self.preset]
        out = {k: (getattr(self, k) if getattr(self, k) is not None else base[k]) for k in base}
        out["pixel_pitch_v_um"] = self.pixel_pitch_v_um if self.pixel_pitch_v_um is not None else out["pixel_pitch_um"]
        return out


class GridConfig(_Strict):
    """``[grid]``: which pixels to evaluate."""

    step: int = Field(1, ge=1, description="evaluate every step-th pixel, an integer >= 1")
    roi: list[int] | None = Field(
        None,
        min_length=4,
        max_length=4,
        description="[h0, h1, v0, v1]: inclusive seed pixel indices with h0 <= h1 and v0 <= v1 (omit: whole array)",
    )

    @field_validator("roi")
    @classmethod
    def _ordered(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and not (v[0] <= v[1] and v[2] <= v[3]):
            raise ValueError(f"roi {v} is not ordered; expected [h0, h1, v0, v1] with h0 <= h1 and v0 <= v1")
        return v


def _flatten_params(v: Any) -> Any:
    """``{center = {k = 0.1}}`` (a TOML dotted key) -> ``{"center.k": 0.1}``."""
    if not isinstance(v, Mapping):
        return v
    out: dict[str, Any] = {}
    for k, x in v.items():
        if isinstance(x, Mapping):
            for k2, x2 in _flatten_params(x).items():
                out[f"{k}.{k2}"] = x2
        else:
            out[k] = x
    return out


class TermConfig(_Strict):
    """``[model.terms.<name>]``: one term built from the registry."""

    kind: str = Field(description=f"a term kind; known: {', '.join(sorted(registry.TERMS))}")
    distribution: str | None = Field(
        None, description=f"microfacet distribution of a specular kind; known: {', '.join(sorted(registry.DISTRIBUTIONS))}"
    )
    params: dict[str, float] = Field(
        default_factory=dict,
        description="parameter values: angles as <name>_deg, lengths as <name>_m, others as <name>",
    )
    grating_factor: bool | None = Field(
        None, description="diffraction only: keep the seed's 2 cos(theta_i) factor (default true)"
    )
    distance_m: float | None = Field(
        None, gt=0, description="diffraction only: nominal distance in the Gaussian, metres (default 0.325)"
    )

    @field_validator("params", mode="before")
    @classmethod
    def _dotted_keys(cls, v: Any) -> Any:
        return _flatten_params(v)

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        if v not in registry.TERMS:
            _raise_unknown("term kind", v, registry.TERMS)
        return v

    @field_validator("distribution")
    @classmethod
    def _known_distribution(cls, v: str | None) -> str | None:
        if v is not None and v not in registry.DISTRIBUTIONS:
            _raise_unknown("distribution", v, registry.DISTRIBUTIONS)
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "TermConfig":
        specular = self.kind in ("specular", "offset_specular")
        if specular and self.distribution is None:
            raise ValueError(
                f"a '{self.kind}' term needs 'distribution'; known: {', '.join(sorted(registry.DISTRIBUTIONS))}"
            )
        if not specular and self.distribution is not None:
            raise ValueError(f"a '{self.kind}' term takes no 'distribution' (only specular and offset_specular do)")
        if self.kind != "diffraction" and (self.grating_factor is not None or self.distance_m is not None):
            raise ValueError("'grating_factor' and 'distance_m' apply only to a 'diffraction' term")
        return self


class ModelConfig(_Strict):
    """``[model]``: a preset with optional parameter overrides, or named terms."""

    preset: str | None = Field(None, description=f"a model preset; known: {', '.join(sorted(registry.PRESETS))}")
    params: dict[str, float] = Field(
        default_factory=dict,
        description="overrides of the preset's parameters: angles as <name>_deg, lengths as <name>_m",
    )
    terms: dict[str, TermConfig] | None = Field(None, description="named terms (instead of a preset)")

    @field_validator("params", mode="before")
    @classmethod
    def _dotted_keys(cls, v: Any) -> Any:
        return _flatten_params(v)

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, v: str | None) -> str | None:
        if v is not None and v not in registry.PRESETS:
            _raise_unknown("model preset", v, registry.PRESETS)
        return v

    @field_validator("terms")
    @classmethod
    def _term_names(cls, v: dict[str, TermConfig] | None) -> dict[str, TermConfig] | None:
        if v is not None:
            if not v:
                raise ValueError("needs at least one term")
            bad = [k for k in v if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k)]
            if bad:
                raise ValueError(f"term names must be identifiers (letters, digits, '_'), got {bad}")
        return v

    @model_validator(mode="after")
    def _one_of(self) -> "ModelConfig":
        if (self.preset is None) == (self.terms is None):
            raise ValueError(
                "give exactly one of 'preset' (known: "
                f"{', '.join(sorted(registry.PRESETS))}) or 'terms' ([model.terms.<name>] tables)"
            )
        if self.terms is not None and self.params:
            raise ValueError("'params' overrides go with a 'preset'; with 'terms' put params in each term")
        return self


class FrameConfig(_Strict):
    """``[[frames]]``: the measurement conditions of one rendered frame."""

    theta_i_deg: float = Field(ge=0, lt=90, description="incidence angle in degrees, 0 <= theta_i_deg < 90")
    phi_ref_deg: float = Field(0.0, description="sample rotation about its normal in degrees")
    wavelength_nm: float = Field(632.8, gt=0, description="wavelength in nanometres, > 0")
    name: str | None = Field(
        None, description="output file stem: letters, digits and _ . + - (default from the angles, e.g. ti20_pr45)"
    )

    @field_validator("name")
    @classmethod
    def _file_stem(cls, v: str | None) -> str | None:
        if v is not None and (not _NAME_RE.fullmatch(v) or v == "summary"):
            raise ValueError(f"name {v!r} is not a usable file stem (letters, digits and _ . + -; not 'summary')")
        return v

    @property
    def stem(self) -> str:
        """The output file stem: ``name`` or ``ti<theta_i>[_pr<phi_ref>][_wl<nm>]``."""
        if self.name is not None:
            return self.name
        stem = f"ti{self.theta_i_deg:g}"
        if self.phi_ref_deg != 0:
            stem += f"_pr{self.phi_ref_deg:g}"
        if self.wavelength_nm != 632.8:
            stem += f"_wl{self.wavelength_nm:g}"
        return stem


class SimulateConfig(_Strict):
    """A whole ``brdfjax simulate`` config; see the module docstring for the TOML layout."""

    precision: Literal["float32", "float64"] = Field("float32", description="'float32' or 'float64'")
    detector: DetectorConfig = Field(default_factory=DetectorConfig, description="the [detector] table")
    grid: GridConfig = Field(default_factory=GridConfig, description="the [grid] table")
    model: ModelConfig = Field(description="the [model] table: preset = \"solar_cell\" or [model.terms.<name>]")
    frames: list[FrameConfig] = Field(min_length=1, description="one or more [[frames]] tables")

    _source: str = PrivateAttr(default="<config>")

    @field_validator("frames")
    @classmethod
    def _unique_stems(cls, v: list[FrameConfig]) -> list[FrameConfig]:
        seen: dict[str, int] = {}
        for i, f in enumerate(v):
            if f.stem in seen:
                raise ValueError(
                    f"frames[{seen[f.stem]}] and frames[{i}] would both be written as '{f.stem}'; give them distinct 'name's"
                )
            seen[f.stem] = i
        return v

    @property
    def source(self) -> str:
        """The file this config was read from (used in error messages)."""
        return self._source

    # -- overrides ------------------------------------------------------------------------
    def with_overrides(self, *, step: int | None = None, precision: str | None = None) -> "SimulateConfig":
        """A validated copy with ``grid.step`` and/or ``precision`` replaced (CLI flags)."""
        data = self.model_dump(exclude_unset=True)
        if step is not None:
            data.setdefault("grid", {})["step"] = step
        if precision is not None:
            data["precision"] = precision
        return parse_simulate_config(data, source=self.source)

    # -- builders -------------------------------------------------------------------------
    def build_detector(self) -> Detector:
        """The :class:`~brdfjax.detector.Detector` (SI units, radians)."""
        d = self.detector
        r = d.resolved()
        try:
            return Detector(
                shape=(int(r["n_v"]), int(r["n_h"])),
                pixel_pitch=r["pixel_pitch_um"] * 1e-6,
                pixel_pitch_v=r["pixel_pitch_v_um"] * 1e-6,
                distance=r["distance_m"],
                theta_c=None if d.theta_c_deg is None else np.deg2rad(d.theta_c_deg),
                roll=np.deg2rad(d.roll_deg),
                yaw=np.deg2rad(d.yaw_deg),
                pitch=np.deg2rad(d.pitch_deg),
                m_h=d.m_h_px,
                m_v=d.m_v_px,
            )
        except ValueError as e:
            raise ConfigError(self.source, [("detector", str(e))]) from None

    def build_grid(self, detector: Detector | None = None) -> PixelGrid:
        """The :class:`~brdfjax.detector.PixelGrid` of ``[grid]`` on the detector."""
        detector = self.build_detector() if detector is None else detector
        roi = None if self.grid.roi is None else tuple(self.grid.roi)
        try:
            return detector.grid(self.grid.step, roi)
        except ValueError as e:
            raise ConfigError(self.source, [("grid.roi", str(e))]) from None

    @property
    def roi(self) -> tuple[int, int, int, int] | None:
        return None if self.grid.roi is None else tuple(self.grid.roi)  # type: ignore[return-value]

    def build_frames(self) -> list[tuple[str, Frame]]:
        """``(stem, Frame)`` for every ``[[frames]]`` entry, in order."""
        out = []
        for i, f in enumerate(self.frames):
            try:
                frame = Frame.from_degrees(f.theta_i_deg, f.phi_ref_deg, f.wavelength_nm)
            except ValueError as e:
                raise ConfigError(self.source, [(f"frames[{i}]", str(e))]) from None
            out.append((f.stem, frame))
        return out

    def build_model(self) -> Model:
        """The BRDF :class:`~brdfjax.terms.Model` of ``[model]`` (parameters in SI units and radians)."""
        m = self.model
        if m.preset is not None:
            return _build_preset(self.source, m.preset, m.params)
        terms = {name: _build_term(self.source, f"model.terms.{name}", t) for name, t in (m.terms or {}).items()}
        return registry.build_model(terms)

    def describe_model(self) -> str:
        """A one-line description of the model for file headers, e.g. ``preset solar_cell (m1=...)``."""
        m = self.model
        if m.preset is not None:
            extra = ", ".join(f"{k}={v:g}" for k, v in m.params.items())
            return f"preset {m.preset}" + (f" ({extra})" if extra else "")
        parts = []
        for name, t in (m.terms or {}).items():
            ps = ", ".join(f"{k}={v:g}" for k, v in t.params.items())
            dist = f"/{t.distribution}" if t.distribution else ""
            opts = "".join(
                f", {k}={getattr(t, k)}" for k in ("grating_factor", "distance_m") if getattr(t, k) is not None
            )
            parts.append(f"{name}: {t.kind}{dist}({ps}{opts})")
        return "; ".join(parts)


# --- parameter keys with units ---------------------------------------------------------------


def _config_key(name: str, unit: str) -> tuple[str, float]:
    suffix, scale = _UNIT_KEYS.get(unit, ("", 1.0))
    return name + suffix, scale


def parameter_keys(units: Mapping[str, str]) -> dict[str, tuple[str, float, str]]:
    """Config key -> (stored name, scale to stored units, unit) for parameters with ``units``.

    Angles (stored in 'rad') are given in degrees as ``<name>_deg``, lengths as
    ``<name>_m``; dimensionless and sr^-1 parameters keep their name.
    """
    out = {}
    for name, unit in units.items():
        key, scale = _config_key(name, unit)
        out[key] = (name, scale, unit)
    return out


def _unknown_key_message(key: str, known: Mapping[str, Any], what: str) -> str:
    msg = f"unknown parameter '{key}' for {what}"
    stem = key.removesuffix("_deg").removesuffix("_m").removesuffix("_px")
    hint = [k for k in known if k.removesuffix("_deg").removesuffix("_m").removesuffix("_px") == stem]
    if hint:
        msg += f" (did you mean '{hint[0]}'? angles are given in degrees as <name>_deg, lengths in metres as <name>_m)"
    else:
        close = difflib.get_close_matches(key, list(known), n=1)
        if close:
            msg += f" (did you mean '{close[0]}'?)"
    return msg + f"; known: {', '.join(known)}"


def _rebuild(obj: Any) -> Any:
    """Re-run the constructors (and so the parameter checks) of a module tree."""
    if isinstance(obj, dict):
        return {k: _rebuild(v) for k, v in obj.items()}
    if not isinstance(obj, eqx.Module):
        return obj
    kwargs = {f.name: _rebuild(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    return type(obj)(**kwargs)


def _build_preset(source: str, preset: str, params: Mapping[str, float]) -> Model:
    model = registry.lookup("preset", preset)()
    keys = parameter_keys(model.parameter_units())
    problems: list[tuple[str, str]] = []
    values: dict[str, Any] = {}
    for key, value in params.items():
        loc = f"model.params.{key}"
        if key not in keys:
            problems.append((loc, _unknown_key_message(key, keys, f"preset '{preset}'")))
            continue
        name, scale, unit = keys[key]
        try:  # check each override on its own so that the message names the key
            _rebuild(model.with_params({name: value * scale}))
        except ValueError as e:
            problems.append((loc, f"{e}{_given_in(unit)}"))
            continue
        values[name] = value * scale
    if problems:
        raise ConfigError(source, problems)
    return model.with_params(values) if values else model


def _given_in(unit: str) -> str:
    """A note for core messages about angles, which show radians while the config gives degrees."""
    return " (the value shown is in radians; the config gives degrees)" if unit == "rad" else ""


def _term_units(kind: str, distribution: str | None) -> tuple[dict[str, str], set[str]]:
    """Parameter units of a term kind (and its distribution), and the required ones."""
    classes: list[type] = []
    if kind in ("specular", "offset_specular"):
        classes.append(registry.lookup("distribution", distribution or ""))
        classes.append(Specular)
        if kind == "offset_specular":
            classes.append(OffsetNormal)
    else:
        classes.append(registry.lookup("term", kind))
    units: dict[str, str] = {}
    required: set[str] = set()
    for cls in classes:
        for f in dataclasses.fields(cls):
            if "unit" in f.metadata:
                units[f.name] = f.metadata["unit"]
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    required.add(f.name)
    return units, required


def _build_term(source: str, loc: str, t: TermConfig) -> AbstractTerm:
    units, required = _term_units(t.kind, t.distribution)
    keys = parameter_keys(units)
    what = f"a '{t.kind}' term" + (f" with distribution '{t.distribution}'" if t.distribution else "")
    problems = [
        (f"{loc}.params.{k}", _unknown_key_message(k, keys, what)) for k in t.params if k not in keys
    ]
    given = {keys[k][0] for k in t.params if k in keys}
    for key, (name, _, unit) in keys.items():
        if name in required and name not in given:
            needs = ", ".join(k for k, (n, _, _) in keys.items() if n in required)
            problems.append((f"{loc}.params", f"missing parameter '{key}' for {what}; needs: {needs}"))
    if problems:
        raise ConfigError(source, problems)
    stored = {keys[k][0]: v * keys[k][1] for k, v in t.params.items()}
    try:
        term = registry.build_term(t.kind, stored, t.distribution, owner=loc)
        if isinstance(term, Diffraction) and (t.grating_factor is not None or t.distance_m is not None):
            opts: dict[str, Any] = {}
            if t.grating_factor is not None:
                opts["grating_factor"] = t.grating_factor
            if t.distance_m is not None:
                opts["distance"] = float(t.distance_m)
            term = dataclasses.replace(term, **opts)
    except (ValueError, KeyError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        # Name the config key when the core's message names the parameter ("parameter 'c' = ...").
        where = f"{loc}.params"
        hit = re.search(r"parameter '([^']+)'", msg)
        if hit:
            for key in t.params:
                if keys[key][0] == hit.group(1):
                    where, msg = f"{loc}.params.{key}", msg + _given_in(keys[key][2])
        raise ConfigError(source, [(where, msg)]) from None
    return term


# --- loading -----------------------------------------------------------------------------------


def default_config_path() -> Path:
    """The packaged default job (``brdfjax/data/default.toml``, a copy of ``configs/default.toml``)."""
    return Path(str(resources.files("brdfjax") / "data" / "default.toml"))


def load_simulate_config(path: str | Path | None = None) -> SimulateConfig:
    """Read and validate a ``simulate`` TOML config; ``None`` loads the packaged default.

    The core objects are built once here too, so that a config that loads is a
    config that runs (bad parameter values and ROIs fail now, not mid-job).
    Raises :class:`ConfigError` naming the file and the key.
    """
    path = default_config_path() if path is None else Path(path)
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(source, [("", "config file not found")]) from None
    except IsADirectoryError:
        raise ConfigError(source, [("", "is a directory, not a TOML config file")]) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(source, [("", f"cannot read config file: {e}")]) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(source, [("", f"not valid TOML: {e}")]) from None
    return parse_simulate_config(data, source=source)


def parse_simulate_config(data: Mapping[str, Any], source: str = "<config>") -> SimulateConfig:
    """Validate an already-parsed TOML mapping (see :func:`load_simulate_config`)."""
    try:
        cfg = SimulateConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(source, [describe_validation_error(SimulateConfig, err) for err in e.errors()]) from None
    cfg._source = source
    detector = cfg.build_detector()
    cfg.build_grid(detector)
    cfg.build_frames()
    cfg.build_model()
    return cfg


# --- error messages ----------------------------------------------------------------------------


def _raise_unknown(what: str, name: str, table: Mapping[str, Any]) -> typing.NoReturn:
    close = difflib.get_close_matches(name, list(table), n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    raise ValueError(f"unknown {what} '{name}'{hint}; known: {', '.join(sorted(table))}")


def _dotted(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _inner_model(annotation: Any) -> tuple[type[BaseModel] | None, bool]:
    """The config model inside an annotation, and whether it sits in a dict (keys in the path)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation, False
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is dict:
        inner, _ = _inner_model(args[1])
        return inner, True
    if origin in (list, tuple, typing.Union, types.UnionType):
        for a in args:
            inner, in_dict = _inner_model(a)
            if inner is not None:
                return inner, in_dict
    return None, False


def _walk(root: type[BaseModel], loc: tuple[Any, ...]) -> tuple[Any, type[BaseModel] | None]:
    """The field info at ``loc`` under the config model ``root``, and the config model it leads into."""
    cls: type[BaseModel] | None = root
    info = None
    dict_key_next = False
    for part in loc:
        if isinstance(part, int):
            continue
        if dict_key_next:
            dict_key_next = False
            continue
        if cls is None or part not in cls.model_fields:
            # a union member's tag (pydantic puts e.g. 'list[float]' in the path)
            continue
        info = cls.model_fields[part]
        cls, dict_key_next = _inner_model(info.annotation)
    return info, cls


def describe_validation_error(
    root: type[BaseModel], err: Mapping[str, Any], prefix: tuple[Any, ...] = ()
) -> tuple[str, str]:
    """One pydantic error of a config model as ``(dotted key, message)``: unknown keys get the allowed
    keys (and a close match), other errors the value given and the field's description.  Used by every
    config of the package (simulate, fit, sample, diagnose, capture)."""
    loc = tuple(x for x in err["loc"] if not (isinstance(x, str) and ("[" in x or x in ("str", "int", "float", "bool"))))
    kind = err["type"]
    full = prefix + loc
    if kind == "extra_forbidden":
        _, owner = _walk(root, loc[:-1])
        allowed = list(owner.model_fields) if owner is not None else []
        key = str(loc[-1])
        msg = "unknown key"
        close = difflib.get_close_matches(key, allowed, n=1)
        if close:
            msg += f" (did you mean '{close[0]}'?)"
        if allowed:
            where = _dotted(full[:-1]) or "the top level"
            msg += f"; allowed keys in {where}: {', '.join(allowed)}"
        return _dotted(full), msg
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    if kind not in ("missing", "value_error") and "input" in err and not isinstance(err["input"], Mapping | list):
        msg += f" (got {err['input']!r})"
    info, _ = _walk(root, loc)
    if info is not None and info.description and kind != "value_error":
        msg += f"; expected {info.description}"
    return _dotted(full), msg


def load_instrument_config(path: str | Path | None, camera_seed: int | None = None) -> InstrumentConfig:
    """Read an instrument TOML into :class:`~brdfjax.instrument.synthetic.InstrumentConfig`.

    Raises :class:`ConfigError` naming the file and the dotted key on a bad value or an
    unknown key.
    """
    source = str(path) if path is not None else "<default instrument>"
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(source, [("", "no such instrument config")]) from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(source, [("", f"not valid TOML ({e})")]) from None
    if camera_seed is not None:
        data["camera_seed"] = camera_seed
    try:
        return InstrumentConfig(**data)
    except ValidationError as e:
        raise ConfigError(
            source, [(".".join(str(x) for x in err["loc"]), err["msg"]) for err in e.errors()]
        ) from None
