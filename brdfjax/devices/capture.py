"""The capture runner: a plan of measurements on a bench, durably (``brdfjax capture``).

The config is :mod:`brdfjax.devices.config`; the command is :mod:`brdfjax.cli.capture`.  A capture
writes each exposure as it is taken and the manifest after each measurement, so an interrupted
capture resumes from its manifest.
"""

from __future__ import annotations

import math
import os
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..config import ConfigError
from ..core.detector import Detector
from ..core.render import Conditions
from ..instrument.nd import stack_od
from ..instrument.synthetic import EFFECTS, load_instrument_config
from ..io import geometry_attrs, toml
from ..io.fingerprint import check_resume
from ..io.raw import Exposure, RawAttrs, read_raw_exr, write_raw_exr
from .alignment import AlignmentResult, run_alignment
from .config import CaptureConfig, CaptureError, _build_model, load_capture_config
from .interfaces import Bench, DeviceError, bench_detector, check_bench
from .lab import open_lab_bench
from .plans import (
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
]

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
        frame = Conditions(m.theta_i, m.phi_ref, b.wavelength)
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


