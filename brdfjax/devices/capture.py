"""``brdfjax capture CONFIG --out DIR [--resume]``: run a capture plan on a bench, durably.

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

import argparse
import hashlib
import json
import math
import os
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..config import ConfigError, ModelConfig, StrictModel, build_model, read_toml, validate
from ..core.detector import Detector
from ..core.render import Frame
from ..instrument.nd import stack_od
from ..instrument.synthetic import EFFECTS, load_instrument_config
from ..io import check_output_dir, geometry_attrs, toml
from ..io.fingerprint import check_resume, value_digest
from ..io.raw import Exposure, RawAttrs, read_raw_exr, write_raw_exr
from ..runtime.errors import InputError
from ..runtime.progress import make_console
from .alignment import AlignmentResult, run_alignment
from .interfaces import Bench, DeviceError, bench_detector, check_bench
from .lab import open_lab_bench
from .liveview import LiveView
from .plans import (
    DEFAULT_EXPOSURES_S,
    Interlock,
    Measurement,
    peak_above_black,
    probe_stack,
)
from .simulated import SimulatedBench

__all__ = [
    "CaptureConfig",
    "CaptureError",
    "load_capture_config",
    "build_plan",
    "build_bench",
    "run_capture",
    "capture_arguments",
    "run_capture_command",
]

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2
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


# --- bench and plan ------------------------------------------------------------------------------


def build_bench(cfg: CaptureConfig, *, config_dir: Path | None = None):
    """The bench of a config: ``(Bench, simulator or None)``."""
    ins = cfg.instrument
    if ins.kind == "lab":
        return open_lab_bench(ins.lab, wavelength=cfg.wavelength_nm * 1e-9), None
    shape = tuple(ins.shape) if ins.shape else (2472 // ins.bin, 3296 // ins.bin)
    pitch = 5.5e-6 * ins.bin
    det = Detector.seed(
        shape=shape, pixel_pitch=pitch, pixel_pitch_v=pitch,
        roll=math.radians(ins.roll_deg), yaw=math.radians(ins.yaw_deg), pitch=math.radians(ins.pitch_deg),
        m_h=ins.m_h_px, m_v=ins.m_v_px,
    )
    path = None
    if ins.instrument:
        path = Path(ins.instrument)
        if not path.is_absolute() and config_dir is not None:
            path = config_dir / path
    icfg = load_instrument_config(path, ins.camera_seed)
    unknown = sorted(set(ins.without) - set(EFFECTS))
    if unknown:
        raise ConfigError(cfg.source, [("instrument.without", f"unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")])
    # coarse(bin): the seed instrument on binned pixels with the seed's per-pixel counts (footprint 25/bin px),
    # so the ND stacks, noise floors and uncertainties are the seed's (tests/data/make_example_set.py does the same).
    icfg = icfg.without(*ins.without).coarse(ins.bin)
    ex = cfg.exposure
    icfg = icfg.model_copy(update={"exposures_s": tuple(t * 1e-3 for t in ex.exposures_ms), "n_frames": ex.n_frames})
    sim = SimulatedBench(
        _build_model(cfg), det, icfg, seed=cfg.seed, wavelength=cfg.wavelength_nm * 1e-9,
        frame_delay_s=ins.frame_delay_s,
    )
    return sim.bench(), sim


def build_plan(cfg: CaptureConfig) -> list[Measurement]:
    """Alignment (if enabled), the beam signature, then every sample measurement (theta_c = theta_i)."""
    ex = cfg.exposure
    exposures = tuple(t * 1e-3 for t in ex.exposures_ms)
    plan = []
    if cfg.alignment.enabled:
        a = cfg.alignment
        plan.append(
            Measurement(
                "alignment", "alignment", nd="auto", background=False,
                exposures_s=((a.exposure_ms or ex.exposures_ms[0]) * 1e-3,), n_frames=a.n_frames or ex.n_frames,
                options={"slew": math.radians(a.slew_deg), "translation": a.translation_mm * 1e-3},
            )
        )
    plan.append(Measurement("beam", "beam", nd=cfg.beam.nd, exposures_s=exposures, n_frames=ex.n_frames,
                            background=ex.background))
    for m in cfg.measurements:
        ti, ph = math.radians(m.theta_i_deg), math.radians(m.phi_ref_deg)
        plan.append(Measurement(m.stem(), "sample", theta_i=ti, phi_ref=ph, theta_c=ti, nd=m.nd,
                                exposures_s=exposures, n_frames=ex.n_frames, background=ex.background))
    # The beam signature fixes the interlock's safe OD: alignment (a direct-beam step) goes after it.
    if cfg.alignment.enabled:
        plan[0], plan[1] = plan[1], plan[0]
    return plan


# --- manifest with capture state ------------------------------------------------------------------


@dataclass
class CaptureState:
    digest: str
    seed: int
    done: list[str]
    files: dict[str, tuple[str, str]]
    safe_stack: str | None = None
    safe_evidence: str = ""
    alignment: dict | None = None
    overridden: list[str] | None = None
    status: str = "in progress"
    fingerprint: dict[str, Any] | None = None


def write_capture_manifest(path: Path, state: CaptureState, plan: list[Measurement], cfg: CaptureConfig) -> Path:
    """The measurement set's manifest (raw format) plus the ``[capture]`` state table, atomically."""
    doc: dict[str, Any] = {}
    if "beam" in state.done:
        f, bg = state.files["beam"]
        doc["beam"] = {"file": f, "background": bg}
    samples = [m.name for m in plan if m.kind == "sample" and m.name in state.done]
    if samples:
        doc["sample"] = [{"name": n, "file": state.files[n][0], "background": state.files[n][1]} for n in samples]
    tol = cfg.calibration.nd_tolerances
    if tol:
        doc["calibration"] = {"nd_tolerances": {str(float(k)): float(v) for k, v in tol.items()}}
    cap: dict[str, Any] = {
        "status": state.status,
        "config": cfg.source,
        "config_digest": state.digest,
        "seed": state.seed,
        "plan": [m.name for m in plan],
        "done": list(state.done),
        "interlock_safe_nd": state.safe_stack if state.safe_stack is not None else "",
        "interlock_evidence": state.safe_evidence,
        "interlock_overridden": list(state.overridden or []),
        "updated": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if state.fingerprint:
        cap["fingerprint"] = dict(state.fingerprint)
    if state.alignment:
        cap["alignment"] = {k: v for k, v in state.alignment.items() if isinstance(v, int | float | str | bool)}
    doc["capture"] = cap
    toml.write(path, doc, header=(
        "[capture]: brdfjax capture progress (read by --resume; brdfjax reduce ignores it)\n"
        "[capture.fingerprint]: what defines this capture's problem; --resume refuses any difference"))
    return path


def read_capture_state(path: Path) -> CaptureState:
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    cap = data.get("capture")
    if not isinstance(cap, dict) or "config_digest" not in cap:
        raise CaptureError(f"{path}: no [capture] table; this measurement set was not written by brdfjax capture")
    files = {}
    if "beam" in data:
        files["beam"] = (data["beam"]["file"], data["beam"]["background"])
    for s in data.get("sample", []):
        files[s["name"]] = (s["file"], s["background"])
    return CaptureState(
        digest=cap["config_digest"], seed=int(cap["seed"]), done=list(cap.get("done", [])), files=files,
        safe_stack=cap.get("interlock_safe_nd") or None, safe_evidence=cap.get("interlock_evidence", ""),
        alignment=cap.get("alignment"), overridden=list(cap.get("interlock_overridden", [])),
        status=cap.get("status", "in progress"), fingerprint=cap.get("fingerprint"),
    )


# --- the runner ---------------------------------------------------------------------------------


class _Runner:
    def __init__(self, cfg: CaptureConfig, bench: Bench, out: Path, *, log, live, progress, sim=None):
        self.cfg, self.bench, self.out, self.log, self.live, self.progress, self.sim = (
            cfg, bench, out, log, live, progress, sim,
        )
        self.retries = cfg.capture.retries
        self.interlock = Interlock(override=cfg.capture.override_interlock, log=log)
        self.parts = out / ".parts"
        self.current = "setup"
        self.beam_flux: float | None = None  # counts/s, unattenuated (live view)
        self.frames_done = 0

    # device calls ------------------------------------------------------------------------------
    def call(self, what: str, fn: Callable, *args):
        for attempt in range(self.retries + 1):
            try:
                return fn(*args)
            except DeviceError as e:
                if e.retryable and attempt < self.retries:
                    self.log(f"{what}: {e}; retrying ({attempt + 1}/{self.retries})")
                    time.sleep(0.05 * (attempt + 1))
                    continue
                self.stop(what, e)

    def stop(self, what: str, e: Exception):
        try:
            self.bench.shutter.close()
            blocked = "the beam is blocked"
        except Exception:  # noqa: BLE001 -- report, do not mask the original error
            blocked = "the beam block did not respond: BLOCK THE BEAM BY HAND"
        where = []
        for slot, label, unit in (("sample_theta", "theta_i", "deg"), ("arm", "theta_c", "deg"), ("sample_phi", "phi_ref", "deg")):
            try:
                where.append(f"{label} {math.degrees(getattr(self.bench, slot).get_position()):.4f} {unit}")
            except Exception:  # noqa: BLE001
                where.append(f"{label} unknown")
        device = what.split(":")[0]
        raise CaptureError(
            f"capture stopped during '{self.current}' ({what}): {e}. The stages were left where they are "
            f"({', '.join(where)}); {blocked}. Check the {device} (power, cable, limit switches, error lights), then "
            f"resume with: brdfjax capture {self.cfg.source} --out {self.out} --resume "
            "(finished measurements are kept)."
        ) from e

    def seed(self, *key: int) -> None:
        fn = getattr(self.bench.camera, "seed_noise", None)
        if fn is not None:
            fn(*key)

    def frame(self, what: str):
        return self.call(f"camera: {what}", self.bench.camera.read_frame)

    # steps ---------------------------------------------------------------------------------------
    def position(self, m: Measurement) -> None:
        b = self.bench
        self.call("beam block: close", b.shutter.close)
        self.call("sample mount", b.sample_mount.set_in_beam, m.kind == "sample")
        self.call("sample theta_i stage: move", b.sample_theta.move_to, m.theta_i)
        self.call("sample phi_ref stage: move", b.sample_phi.move_to, m.phi_ref)
        self.call("detector arm: move", b.arm.move_to, m.theta_c)

    def choose_nd(self, idx: int, m: Measurement) -> str:
        b = self.bench
        stacks = self.call("filter changer", b.filters.available_stacks)
        t0 = m.exposures_s[0]
        if m.nd != "auto":
            if m.exposes_direct_beam:
                if self.interlock.min_od is None:
                    self.establish(idx, m, stacks, t0)
                self.interlock.check(m.nd, f"the {m.name} measurement")
            return m.nd
        if m.exposes_direct_beam and self.interlock.min_od is not None:
            return self.interlock.min_stack  # type: ignore[return-value]
        res = self.probe(idx, m, stacks, t0)
        if m.exposes_direct_beam:
            self.interlock.establish(res.stack, res.evidence(t0))
        return res.stack

    def establish(self, idx: int, m: Measurement, stacks, t0: float) -> None:
        res = self.probe(idx, m, stacks, t0)
        self.interlock.establish(res.stack, res.evidence(t0))

    def probe(self, idx: int, m: Measurement, stacks, t0: float):
        cam, b = self.bench.camera, self.bench
        self.call("camera: exposure", cam.set_exposure, t0)
        self.call("camera: averaging", cam.set_frame_averaging, 1)
        black = float(self.call("camera: black level", cam.get_black_level))
        k = iter(range(1000))

        def take_peak(stack: str) -> float:
            self.call("filter changer", b.filters.set_filters, stack)
            self.call("beam block: open", b.shutter.open)
            self.seed(idx, 0, next(k))
            f = self.frame(f"ND probe through '{stack}'")
            self.call("beam block: close", b.shutter.close)
            return peak_above_black(f.counts, black)

        res = probe_stack(take_peak, stacks=stacks, t_min=t0, black_level=black, full_scale=float(cam.full_scale))
        self.log(f"{m.name}: ND '{res.stack or 'none'}' by the seed's rule ({res.evidence(t0)})")
        return res

    def attrs(self, m: Measurement, kind: str, nd: str, black: float, full_scale: float,
              shape: tuple[int, int]) -> RawAttrs:
        b = self.bench
        det = bench_detector(b, self.alignment, shape)
        frame = Frame(m.theta_i, m.phi_ref, b.wavelength)
        return RawAttrs(
            kind=kind, optical_density=round(stack_od(nd), 10), nd_filters=nd,
            **geometry_attrs(det, frame, theta_c=m.theta_c), black_level=black, full_scale=full_scale,
            sample=m.name if kind != "background" else f"background for: {m.name}",
            software=f"brdfjax.devices.capture ({b.name})",
            extra={"capture_seed": int(self.cfg.seed)},
        )

    def exposures(self, idx: int, m: Measurement, stem: str, code: int, nd: str, beam_open: bool) -> list[Exposure]:
        cam, b = self.bench.camera, self.bench
        self.call("camera: averaging", cam.set_frame_averaging, m.n_frames)
        out = []
        for j, t in enumerate(m.exposures_s):
            part = self.parts / f"{stem}.e{j}.exr"
            if part.exists():
                try:
                    st = read_raw_exr(part)
                    if st.attrs.nd_filters == nd and abs(st.exposures[0].exposure_s - t) < 1e-12:
                        out.append(st.exposures[0])
                        self.frames_done += 1
                        self.tick(m)
                        continue
                except Exception:  # noqa: BLE001 -- a damaged part is measured again
                    pass
            self.call("filter changer", b.filters.set_filters, nd)
            self.call("camera: exposure", cam.set_exposure, t)
            self.call("beam block: open" if beam_open else "beam block: close",
                      b.shutter.open if beam_open else b.shutter.close)
            self.seed(idx, code, j)
            f = self.frame(f"{stem} at {t * 1e3:g} ms")
            self.frames_done += 1
            self.call("beam block: close", b.shutter.close)
            e = Exposure(float(f.exposure_s), int(f.n_frames), np.asarray(f.counts, np.float32),
                         None if f.counts_std is None else np.asarray(f.counts_std, np.float32))
            a = self.attrs(m, "background" if not beam_open else ("beam" if m.kind == "beam" else "sample"),
                           nd, float(f.black_level), float(f.full_scale), e.counts.shape)
            write_raw_exr(part, a, [e])
            out.append(e)
            if beam_open and self.live is not None:
                self.live.update_exposure(m, nd, e, float(f.black_level), float(f.full_scale), self.beam_flux,
                                          self.alignment or {}, self.bench)
            self.tick(m)
        return out

    def tick(self, m: Measurement) -> None:
        if self.progress is not None:
            self.progress(self.frames_done, m.name)

    def measure(self, idx: int, m: Measurement) -> tuple[str, str]:
        self.current = m.name
        self.position(m)
        nd = self.choose_nd(idx, m)
        if m.exposes_direct_beam:
            self.interlock.check(nd, f"the {m.name} measurement")
        file, bg_file = m.files()
        stem, bg_stem = Path(file).stem, Path(bg_file).stem
        cam = self.bench.camera
        black = float(self.call("camera: black level", cam.get_black_level))
        fs = float(cam.full_scale)
        kind = "beam" if m.kind == "beam" else "sample"
        sig = self.exposures(idx, m, stem, 1, nd, True)
        write_raw_exr(self.out / file, self.attrs(m, kind, nd, black, fs, sig[0].counts.shape), sig)
        if m.kind == "beam":
            self.beam_flux = _beam_flux_estimate(sig, black, fs, nd)
        bg = self.exposures(idx, m, bg_stem, 2, nd, False) if m.background else [
            Exposure(e.exposure_s, e.n_frames, np.full_like(e.counts, black)) for e in sig
        ]
        write_raw_exr(self.out / bg_file, self.attrs(m, "background", nd, black, fs, bg[0].counts.shape), bg)
        for p in list(self.parts.glob(f"{stem}.e*.exr")) + list(self.parts.glob(f"{bg_stem}.e*.exr")):
            p.unlink()
        return file, bg_file

    def align(self, idx: int, m: Measurement) -> dict:
        self.current = m.name
        b = self.bench
        self.position(m)
        nd = self.choose_nd(idx, m)
        self.interlock.check(nd, "the alignment")
        w_px = getattr(self, "footprint_px", None) or 25.0 * 5.5e-6 / b.pixel_pitch[0]
        k = iter(range(1000))
        res: AlignmentResult = run_alignment(
            _RetryingBench(self), nd_filters=nd, slew=m.options["slew"], translation=m.options["translation"],
            w_px=w_px, exposure_s=m.exposures_s[0], n_frames=m.n_frames,
            check_safe=lambda s: self.interlock.check(s, "the alignment"),
            seed_noise=lambda j: self.seed(idx, 3, next(k)), log=self.log,
        )
        self.frames_done += 5
        self.tick(m)
        d = res.degrees()
        d.update(nd_filters=nd, slew_deg=math.degrees(res.slew), translation_mm=res.translation * 1e3,
                 method="seed §3.4 (arm slew, axial translation), refined by the exact geometry")
        self.log(
            "alignment: roll {roll_deg:.4f} deg, yaw {yaw_deg:.4f} deg, pitch {pitch_deg:.4f} deg, "
            "m_h {m_h_px:.2f} px, m_v {m_v_px:.2f} px (seed formulas: {seed_roll_deg:.4f}, {seed_yaw_deg:.4f}, "
            "{seed_pitch_deg:.4f} deg; spot rms residual {rms_residual_px:.3g} px)".format(**d)
        )
        return d

    alignment: dict | None = None


class _RetryingBench:
    """The bench with every device call of the alignment routed through the runner's retry/stop logic."""

    def __init__(self, runner: _Runner):
        b = runner.bench
        self.pixel_pitch, self.distance = b.pixel_pitch, b.distance
        self.camera = _Retrying(runner, "camera", b.camera)
        self.shutter = _Retrying(runner, "beam block", b.shutter)
        self.sample_mount = _Retrying(runner, "sample mount", b.sample_mount)
        self.arm = _Retrying(runner, "detector arm", b.arm)
        self.camera_axial = _Retrying(runner, "camera axial stage", b.camera_axial)
        self.filters = _Retrying(runner, "filter changer", b.filters)


class _Retrying:
    def __init__(self, runner: _Runner, label: str, dev):
        self._r, self._label, self._dev = runner, label, dev

    def __getattr__(self, name):
        v = getattr(self._dev, name)
        if not callable(v):
            return v
        return lambda *a: self._r.call(f"{self._label}: {name}", v, *a)


def _beam_flux_estimate(exposures: list[Exposure], black: float, fs: float, nd: str) -> float | None:
    """Unattenuated incident flux, counts/s, from the longest unsaturated exposure (live view only)."""
    best = None
    for e in exposures:
        if float(np.max(e.counts)) < 0.9 * fs:
            best = float(np.sum(np.asarray(e.counts, np.float64) - black)) / e.exposure_s * 10 ** stack_od(nd)
    return best


def run_capture(
    cfg: CaptureConfig,
    out: str | os.PathLike,
    *,
    resume: bool = False,
    bench: Bench | None = None,
    sim=None,
    log: Callable[[str], None] | None = None,
    live=None,
    progress: bool = False,
) -> Path:
    """Run the plan of ``cfg`` into the folder ``out``; returns the manifest path (see the module docstring).

    ``bench``: the devices (default: built from the config, the simulated
    instrument unless ``[instrument] kind = "lab"``); ``live``: a
    :class:`~brdfjax.devices.liveview.LiveView` or ``None``; ``progress``: a
    rich progress bar on stderr.  Raises :class:`CaptureError`,
    :class:`~brdfjax.devices.plans.InterlockError` or ``FileExistsError``.
    """
    out = Path(out)
    say = log or (lambda s: None)
    config_dir = Path(cfg.source).parent if cfg.source != "<config>" else None
    if bench is None:
        bench, sim = build_bench(cfg, config_dir=config_dir)
    problems = check_bench(bench)
    if problems:
        raise CaptureError("the bench does not provide every device: " + "; ".join(problems))
    plan = build_plan(cfg)
    manifest = out / "manifest.toml"
    digest = cfg.digest()
    fingerprint = cfg.fingerprint()
    if manifest.exists():
        if not resume:
            raise FileExistsError(
                f"{manifest} exists: pass --resume to continue that capture, or choose another --out"
            )
        state = read_capture_state(manifest)
        if state.fingerprint is not None or state.digest != digest:
            check_resume(
                manifest, state.fingerprint, fingerprint,
                f"Resume only with the config that started the capture (config digest {state.digest}, "
                f"this config {digest}), or capture into another --out.",
            )
        if state.status == "complete":
            say(f"{manifest}: the capture is already complete ({len(state.done)} step(s)); nothing to resume")
            return manifest
        state.fingerprint = fingerprint
    else:
        if resume:
            raise CaptureError(
                f"--resume: there is no capture to resume in {out} (no manifest.toml); run without --resume to start one"
            )
        state = CaptureState(digest=digest, seed=cfg.seed, done=[], files={}, fingerprint=fingerprint)
    out.mkdir(parents=True, exist_ok=True)
    runner = _Runner(cfg, bench, out, log=say, live=live, progress=None, sim=sim)
    if sim is not None:
        runner.footprint_px = sim.instrument.config.footprint.w_px
    if state.safe_stack is not None:
        runner.interlock.establish(state.safe_stack, state.safe_evidence)
    if state.alignment is not None:
        runner.alignment = dict(state.alignment)
    elif not cfg.alignment.enabled:
        a = cfg.alignment
        runner.alignment = {"roll_deg": a.roll_deg, "yaw_deg": a.yaw_deg, "pitch_deg": a.pitch_deg,
                            "m_h_px": a.m_h_px, "m_v_px": a.m_v_px, "method": "given in the config"}
    if "beam" in state.done:
        try:
            st = read_raw_exr(out / state.files["beam"][0])
            runner.beam_flux = _beam_flux_estimate(list(st.exposures), st.attrs.black_level, st.attrs.full_scale,
                                                   st.attrs.nd_filters)
        except Exception:  # noqa: BLE001 -- live view only
            pass
    total = sum(5 if m.kind == "alignment" else len(m.exposures_s) * (2 if m.background else 1) for m in plan)
    done_frames = sum(5 if m.kind == "alignment" else len(m.exposures_s) * (2 if m.background else 1)
                      for m in plan if m.name in state.done)
    todo = [m for m in plan if m.name not in state.done]
    say(f"brdfjax capture: {len(plan)} step(s) on the {bench.name} bench, {len(plan) - len(todo)} already done")
    bar = _Progress(total, done_frames, enabled=progress)
    runner.progress = bar.update
    runner.frames_done = done_frames
    try:
        for idx, m in enumerate(plan):
            if m.name in state.done:
                continue
            t0 = time.perf_counter()
            if m.kind == "alignment":
                state.alignment = runner.align(idx, m)
                runner.alignment = dict(state.alignment)
            else:
                state.files[m.name] = runner.measure(idx, m)
            if m.kind == "beam" or m.exposes_direct_beam:
                state.safe_stack = runner.interlock.min_stack
                state.safe_evidence = runner.interlock.evidence
            state.overridden = list(dict.fromkeys((state.overridden or []) + runner.interlock.overridden))
            state.done.append(m.name)
            write_capture_manifest(manifest, state, plan, cfg)
            say(f"done {m.name} ({time.perf_counter() - t0:.1f} s); {len(state.done)}/{len(plan)} step(s)")
    finally:
        bar.close()
    state.status = "complete"
    write_capture_manifest(manifest, state, plan, cfg)
    try:
        runner.parts.rmdir()
    except OSError:
        pass
    return manifest


class _Progress:
    """Plan progress on stderr (frames done / left, time estimate) with rich; silent when disabled."""

    def __init__(self, total: int, done: int, *, enabled: bool):
        self._p = None
        if enabled:
            self._p = Progress(
                TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                TextColumn("left"), TimeRemainingColumn(), console=Console(stderr=True), transient=False,
            )
            self._p.start()
            self._task = self._p.add_task("capture", total=total, completed=done)

    def update(self, done: int, name: str) -> None:
        if self._p is not None:
            self._p.update(self._task, completed=done, description=f"capture: {name}")

    def close(self) -> None:
        if self._p is not None:
            self._p.stop()


# --- CLI ----------------------------------------------------------------------------------------


def capture_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="capture config (TOML), e.g. configs/capture_simulated.toml")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: the raw measurement set + manifest.toml")
    p.add_argument("--resume", action="store_true", help="continue an interrupted capture in DIR from its manifest")
    p.add_argument("--seed", type=int, default=None, help="noise seed of the simulated instrument (overrides seed)")
    p.add_argument("--live", choices=("auto", "window", "png", "off"), default=None,
                   help="live view: a matplotlib window, a PNG + HTML page in DIR/live/, or none (overrides capture.live)")
    p.add_argument("--override-interlock", action="store_true",
                   help="allow direct-beam steps below the safe OD (logged in the manifest); only if the array can take it")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_capture_command(args: argparse.Namespace) -> int:
    # Errors and their exit codes: brdfjax.runtime.errors.run_command (cli.main), 2 for every refusal.
    cfg = load_capture_config(args.config)
    check_output_dir(args.out)
    updates: dict[str, Any] = {}
    if args.seed is not None:
        updates["seed"] = args.seed
    cap = {}
    if args.live is not None:
        cap["live"] = args.live
    if args.override_interlock:
        cap["override_interlock"] = True
    if cap:
        updates["capture"] = cfg.capture.model_copy(update=cap)
    if updates:
        src = cfg.source
        cfg = cfg.model_copy(update=updates)
        cfg._source = src
    console = make_console(args.quiet)
    log = lambda s: console.print(s, markup=False)  # noqa: E731
    live = None
    if cfg.capture.live != "off":
        live = LiveView(Path(args.out) / "live", mode=cfg.capture.live, min_interval_s=cfg.capture.live_interval_s)
    t0 = time.perf_counter()
    try:
        manifest = run_capture(cfg, args.out, resume=args.resume, log=log, live=live,
                               progress=not (args.no_progress or args.quiet))
    except FileExistsError as e:  # a rerun into a started or finished capture: a refusal (exit 2)
        raise CaptureError(str(e)) from None
    finally:
        if live is not None:
            live.close()
    log(f"wrote {manifest} ({time.perf_counter() - t0:.1f} s); reduce it with: brdfjax reduce {manifest} --out DIR")
    return EXIT_OK
