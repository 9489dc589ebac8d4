"""The capture config (``brdfjax capture CONFIG``): the bench, the exposures, the alignment, the plan.


The config (TOML, validated strictly; errors name the file and the key)::

    seed = 1                                  # noise seed of the simulated instrument
    wavelength_nm = 632.8

    [instrument]                              # kind = "simulated" (default) or "lab"
    kind = "simulated"
    bin = 8                                   # the seed camera binned 8 x 8 (412 x 309 px of 44 um)
    # shape = [309, 412]                      # (n_v, n_h); default: the seed array / bin
    roll_deg = 0.11                           # the TRUE (injected) misalignment of the simulated camera
    yaw_deg = 0.062
    pitch_deg = 0.025
    camera_seed = 0
    # instrument = "instrument_seed.toml"     # effects (see configs/instrument_seed.toml), relative to this file
    # without = ["stray_light"]
    # frame_delay_s = 0.0                     # simulated acquisition time per frame (tests)
    # [instrument.lab]                        # kind = "lab": pylablib adapters (brdfjax.devices.lab)

    [model]                                   # the simulated sample: same schema as the simulate config
    preset = "solar_cell"

    [exposure]
    exposures_ms = [1, 10, 100, 1000]         # the bracket, shortest first
    n_frames = 32                             # frames averaged per exposure
    background = true                         # a background (beam blocked) per measurement

    [alignment]                               # seed §3.4 (run before the beam signature when enabled)
    enabled = true
    slew_deg = 1.0
    translation_mm = 25.4
    # when enabled = false: roll_deg, yaw_deg, pitch_deg, m_h_px, m_v_px known from an earlier alignment

    [beam]
    nd = "auto"                               # or a stack; refused by the interlock below the safe OD

    [[measurements]]
    name = "ti20"                             # optional (default ti<theta_i>_phi<phi_ref>)
    theta_i_deg = 20.0
    phi_ref_deg = 0.0
    nd = "auto"

    [capture]
    override_interlock = false
    retries = 2                               # retries of a device call that failed in a retryable way
    live = "auto"                             # "window", "png", "off"; "auto": window with a display, else png
    live_interval_s = 1.0

    [calibration]                             # copied into the manifest
    nd_tolerances = { "3.0" = 0.15 }

Durability (see the README): every exposure, once read, is written
atomically as a one-part raw file under ``DIR/.parts/``; a finished
measurement and its background are assembled into the raw format of
:mod:`brdfjax.io.raw` (written atomically), their parts removed, and
``manifest.toml`` rewritten (atomically) after every measurement with a
``[capture]`` table (status, config digest, the finished measurements, the
interlock's safe OD, the alignment).  ``--resume`` continues from it: finished
measurements are skipped, finished exposure parts reused, and -- the noise of
every frame being seeded by (seed, measurement index, exposure) -- the result
is bit-identical to an uninterrupted run.  A device error is retried when
the device says that is safe; otherwise the capture stops with the bench left
where it was (the beam blocked) and a message naming the device to check.
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from ..config import ConfigError, ModelConfig, StrictModel, build_model, read_toml, validate
from ..instrument.nd import stack_od
from ..io.fingerprint import value_digest
from ..runtime.errors import InputError
from .plans import (
    DEFAULT_EXPOSURES_S,
)

__all__ = ["CaptureConfig", "CaptureError", "load_capture_config"]

_NAME_CHARS = set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_.+-")


class CaptureError(InputError, RuntimeError):
    """The capture stopped or was refused; the message says where, why and what to check (exit 2)."""


class LabStage(StrictModel):
    serial: str = Field(description="the Kinesis controller's serial number")
    scale: str | float = Field("stage", description="pylablib scale: a stage name (e.g. 'PRM1-Z8'), 'stage' or steps per unit")
    channel: int = Field(1, ge=1, description="the controller's channel (>= 1)")


class LabConfig(StrictModel):
    camera_serial: str | None = Field(None, description="the camera's serial number (default: the first camera found)")
    sample_theta: LabStage = Field(description="the stage that sets the sample's incidence angle theta_i")
    arm: LabStage = Field(description="the stage that sets the detector arm angle theta_c")
    sample_phi: LabStage | None = Field(None, description="None: phi_ref set by hand when prompted")
    camera_axial: LabStage | None = Field(None, description="None: the axial micrometer moved by hand when prompted")
    filters: Literal["manual"] = Field("manual", description="ND filters are changed by hand when prompted")
    shutter: Literal["manual"] = Field("manual", description="the beam is blocked by hand when prompted")
    power_meter: str | None = Field(None, description="the PM160's VISA address")
    pixel_pitch_um: float = Field(5.5, gt=0, description="the camera's pixel pitch in micrometres")
    distance_m: float = Field(0.325, gt=0, description="sample-to-array distance R in metres")


class InstrumentSection(StrictModel):
    kind: Literal["simulated", "lab"] = Field("simulated", description="'simulated' (the simulated bench) or 'lab' (hardware through pylablib)")
    bin: int = Field(8, ge=1, description="binning of the seed camera (pixel pitch 5.5 um x bin)")
    shape: tuple[int, int] | None = Field(None, description="(n_v, n_h) pixels; default the seed array / bin")
    roll_deg: float = Field(0.0, description="simulated bench: the true (injected) CCD roll in degrees")
    yaw_deg: float = Field(0.0, description="simulated bench: the true CCD yaw in degrees")
    pitch_deg: float = Field(0.0, description="simulated bench: the true CCD pitch in degrees")
    m_h_px: float = Field(0.0, description="simulated bench: the true in-plane peak offset in pixels")
    m_v_px: float = Field(0.0, description="simulated bench: the true out-of-plane peak offset in pixels")
    camera_seed: int = Field(0, description="simulated bench: seed of the camera's fixed per-pixel maps")
    instrument: str | None = Field(None, description="an instrument TOML (effects), relative to the config")
    without: list[str] = Field(default_factory=list, description="simulated bench: instrument effects switched off (e.g. ['stray_light'])")
    frame_delay_s: float = Field(0.0, ge=0, description="simulated bench: acquisition time per frame in seconds (tests)")
    lab: LabConfig | None = Field(None, description="the [instrument.lab] table (kind = 'lab')")

    @model_validator(mode="after")
    def _lab_needs_table(self) -> "InstrumentSection":
        if self.kind == "lab" and self.lab is None:
            raise ValueError("kind = \"lab\" needs an [instrument.lab] table (camera_serial, sample_theta, arm, ...)")
        return self


class ExposureSection(StrictModel):
    exposures_ms: list[float] = Field(default_factory=lambda: [t * 1e3 for t in DEFAULT_EXPOSURES_S], description="the exposure bracket in milliseconds, shortest first")
    n_frames: int = Field(32, ge=1, description="frames averaged per exposure")
    background: bool = Field(True, description="take a background (beam blocked) per measurement")

    @field_validator("exposures_ms")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        if not v or any(t <= 0 for t in v) or any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"must be positive and strictly increasing (ms), got {v}")
        return v


class AlignmentSection(StrictModel):
    enabled: bool = Field(False, description="run the seed's alignment (§3.4) before the beam signature")
    slew_deg: float = Field(1.0, gt=0, lt=10, description="arm slew of the alignment scan in degrees (< 10)")
    translation_mm: float = Field(25.4, gt=0, le=25.4, description="axial translation of the alignment in millimetres (<= 25.4)")
    exposure_ms: float | None = Field(None, gt=0, description="default: the shortest exposure")
    n_frames: int | None = Field(None, ge=1, description="frames averaged per alignment exposure (default: the [exposure] value)")
    roll_deg: float = Field(0.0, description="enabled = false: the CCD roll known from an earlier alignment, degrees")
    yaw_deg: float = Field(0.0, description="enabled = false: the known CCD yaw, degrees")
    pitch_deg: float = Field(0.0, description="enabled = false: the known CCD pitch, degrees")
    m_h_px: float = Field(0.0, description="enabled = false: the known in-plane peak offset, pixels")
    m_v_px: float = Field(0.0, description="enabled = false: the known out-of-plane peak offset, pixels")


class BeamSection(StrictModel):
    nd: str = Field("auto", description="ND stack of the beam signature, e.g. '4.0+1.0', or 'auto' (refused by the interlock below the safe OD)")


class MeasurementSection(StrictModel):
    name: str | None = Field(None, description="the measurement's file stem (default ti<theta_i>_phi<phi_ref>)")
    theta_i_deg: float = Field(ge=0, lt=89, description="incidence angle in degrees, 0 <= theta_i_deg < 89")
    phi_ref_deg: float = Field(0.0, description="sample rotation about its normal in degrees")
    nd: str = Field("auto", description="ND stack of the sample measurement, or 'auto'")

    @field_validator("name")
    @classmethod
    def _safe(cls, v: str | None) -> str | None:
        if v is not None and (not v or not set(v) <= _NAME_CHARS or v in ("beam", "beam_background")):
            raise ValueError(f"must be a file-name-safe name (letters, digits, _ . + -), not 'beam', got {v!r}")
        return v

    def stem(self) -> str:
        if self.name:
            return self.name
        return f"ti{self.theta_i_deg:g}_phi{self.phi_ref_deg:g}".replace("-", "m")


class CaptureSection(StrictModel):
    override_interlock: bool = Field(False, description="allow a beam stack below the interlock's safe OD")
    retries: int = Field(2, ge=0, le=10, description="retries of a device call that failed in a retryable way (0-10)")
    live: Literal["auto", "window", "png", "off"] = Field("auto", description="live view: 'window', 'png', 'off', or 'auto' (a window with a display, else png)")
    live_interval_s: float = Field(1.0, ge=0, description="seconds between live-view updates")


class CalibrationSection(StrictModel):
    nd_tolerances: dict[str, float] = Field(default_factory=dict, description="nominal OD -> tolerance of the physical filters, copied into the manifest")


class CaptureConfig(StrictModel):
    seed: int = Field(0, description="noise seed of the simulated instrument")
    wavelength_nm: float = Field(632.8, gt=0, description="source wavelength in nanometres")
    instrument: InstrumentSection = Field(InstrumentSection(), description="the [instrument] table")
    model: ModelConfig | None = Field(None, description="the simulated sample's [model] table (same schema as the simulate config)")
    exposure: ExposureSection = Field(ExposureSection(), description="the [exposure] table")
    alignment: AlignmentSection = Field(AlignmentSection(), description="the [alignment] table")
    beam: BeamSection = Field(BeamSection(), description="the [beam] table")
    measurements: list[MeasurementSection] = Field(default_factory=list, description="one [[measurements]] table per sample measurement")
    capture: CaptureSection = Field(CaptureSection(), description="the [capture] table")
    calibration: CalibrationSection = Field(CalibrationSection(), description="the [calibration] table")

    @model_validator(mode="after")
    def _checks(self) -> "CaptureConfig":
        if not self.measurements:
            raise ValueError("needs at least one [[measurements]] entry (theta_i_deg, phi_ref_deg)")
        stems = [m.stem() for m in self.measurements]
        dup = sorted({s for s in stems if stems.count(s) > 1})
        if dup:
            raise ValueError(f"measurement names must be unique, got duplicates {dup}")
        if self.instrument.kind == "simulated" and self.model is None:
            raise ValueError("the simulated instrument needs a [model] table (the sample), e.g. preset = \"solar_cell\"")
        return self

    _source: str = "<config>"

    @property
    def source(self) -> str:
        return self._source

    def digest(self) -> str:
        """SHA-256 of everything that determines the data (the [capture] run options excluded)."""
        d = self.model_dump(mode="json", exclude={"capture"})
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]

    def fingerprint(self) -> dict[str, Any]:
        """The problem fingerprint (:mod:`brdfjax.io.fingerprint`): every key that determines the data, by name.

        The ``[capture]`` run options (live view, retries, the interlock
        override) are excluded: they do not change what is measured.
        """
        out: dict[str, Any] = {}

        def walk(prefix: str, v: Any) -> None:
            if isinstance(v, dict) and v:
                for k, x in v.items():
                    walk(f"{prefix}.{k}" if prefix else str(k), x)
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                for i, x in enumerate(v):
                    walk(f"{prefix}[{i}]", x)
            else:
                d = value_digest(v)
                out[prefix] = "null" if d is None else d

        walk("", self.model_dump(mode="json", exclude={"capture"}))
        return out


def load_capture_config(path: str | os.PathLike) -> CaptureConfig:
    """Read and validate a capture config; raises :class:`~brdfjax.config.ConfigError` naming the file and key."""
    source = str(path)
    cfg = validate(CaptureConfig, read_toml(path), source)
    cfg._source = source
    if cfg.model is not None:
        _build_model(cfg)  # a config that loads is a config that runs
    for key, nd in [("beam.nd", cfg.beam.nd)] + [
        (f"measurements[{i}].nd", m.nd) for i, m in enumerate(cfg.measurements)
    ]:
        if nd != "auto":
            try:
                stack_od(nd)
            except ValueError as e:
                raise ConfigError(source, [(key, f"{e}; expected \"auto\" or a stack like \"4.0+1.0\"")]) from None
    return cfg


def _build_model(cfg: CaptureConfig):
    return build_model(cfg.source, cfg.model)
