"""The ``brdfjax simulate`` config: parsed at the edge into frozen, validated objects.

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

import re
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, PrivateAttr, field_validator

from ..core.detector import Detector, PixelGrid
from ..core.render import Conditions, Precision
from ..core.terms import Model
from .base import ConfigError, StrictModel, read_toml, validate
from .model import ModelConfig, build_model, describe_model

__all__ = [
    "DetectorConfig",
    "GridConfig",
    "FrameConfig",
    "SimulateConfig",
    "DETECTOR_PRESETS",
    "load_simulate_config",
    "parse_simulate_config",
    "default_config_path",
]

#: Detector presets: config keys filled in when ``[detector]`` leaves them out.
DETECTOR_PRESETS: dict[str, dict[str, float | int]] = {
    "seed": {"n_h": 3296, "n_v": 2472, "pixel_pitch_um": 5.5, "distance_m": 0.325},
}

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


# --- schema --------------------------------------------------------------------------------


class DetectorConfig(StrictModel):
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


class GridConfig(StrictModel):
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


class FrameConfig(StrictModel):
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


class SimulateConfig(StrictModel):
    """A whole ``brdfjax simulate`` config; see the module docstring for the TOML layout."""

    precision: Precision = Field("float32", description="'float32' or 'float64'")
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
        """The :class:`~brdfjax.core.detector.Detector` (SI units, radians)."""
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
        """The :class:`~brdfjax.core.detector.PixelGrid` of ``[grid]`` on the detector."""
        detector = self.build_detector() if detector is None else detector
        roi = None if self.grid.roi is None else tuple(self.grid.roi)
        try:
            return detector.grid(self.grid.step, roi)
        except ValueError as e:
            raise ConfigError(self.source, [("grid.roi", str(e))]) from None

    @property
    def roi(self) -> tuple[int, int, int, int] | None:
        return None if self.grid.roi is None else tuple(self.grid.roi)  # type: ignore[return-value]

    def build_frames(self) -> list[tuple[str, Conditions]]:
        """``(stem, Conditions)`` for every ``[[frames]]`` entry, in order."""
        out = []
        for i, f in enumerate(self.frames):
            try:
                frame = Conditions.from_degrees(f.theta_i_deg, f.phi_ref_deg, f.wavelength_nm)
            except ValueError as e:
                raise ConfigError(self.source, [(f"frames[{i}]", str(e))]) from None
            out.append((f.stem, frame))
        return out

    def build_model(self) -> Model:
        """The BRDF :class:`~brdfjax.core.terms.Model` of ``[model]`` (parameters in SI units and radians)."""
        return build_model(self.source, self.model)

    def describe_model(self) -> str:
        """A one-line description of the model for file headers, e.g. ``preset solar_cell (m1=...)``."""
        return describe_model(self.model)


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
    return parse_simulate_config(read_toml(path), source=str(path))


def parse_simulate_config(data: Mapping[str, Any], source: str = "<config>") -> SimulateConfig:
    """Validate an already-parsed TOML mapping (see :func:`load_simulate_config`)."""
    cfg = validate(SimulateConfig, data, source)
    cfg._source = source
    detector = cfg.build_detector()
    cfg.build_grid(detector)
    cfg.build_frames()
    cfg.build_model()
    return cfg
