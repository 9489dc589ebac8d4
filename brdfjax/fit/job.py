"""A fit config's job: the steps that turn a loaded :class:`~brdfjax.fit.config.FitConfig` into data and a fit.

Loading a config (:func:`brdfjax.fit.config.load_fit_config`) validates it and checks that its files
exist; it reads no frame and runs no instrument.  :func:`build_fit_job` then runs the data steps,
each visible as a step of its own:

1. :func:`reduce_step`: a raw measurement set (``data.manifest``) reduced to BRDF frames
   (:func:`brdfjax.instrument.reduce.reduce_measurement_set`);
2. :func:`synthesize_step`: a synthetic measurement set (``[data.synthetic]``) measured by the
   synthetic instrument and reduced, cached under a key of everything that shapes it;
3. reading the frames (with their masks and region of interest) and the tables (with their screening);

and returns a :class:`FitJob`, whose :meth:`FitJob.likelihood` is the likelihood that ``fit``,
``sample`` and ``diagnose`` share.  :func:`run_fit` runs the job and writes ``result.json`` and the
figures (``brdfjax fit CONFIG --out DIR``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ConfigError
from ..core.detector import Detector
from ..core.render import Conditions
from ..core.terms import Model
from ..instrument.reduce import (
    FLAG_BELOW_ARTIFACT_FLOOR,
    FLAG_BELOW_NOISE,
    FLAG_LOW_SNR,
    ReductionError,
    read_reduced_frame,
    reduce_measurement_set,
)
from ..instrument.synthetic import SyntheticInstrument, load_instrument_config
from ..io import ExrError, atomic_output, write_json_atomic
from ..io.blocks import FrameData, TableData
from ..io.raw import RawFormatError, read_manifest
from ..io.tables import Screen, read_astm_e1392, read_cornell_brdf, read_merl_inplane, read_table
from ..runtime.progress import ProgressLine
from ._common import FitInputError, natural_unit, to_natural
from ._figures import frame_model_image, write_figures
from ._fit import fit
from ._frames_io import read_frame_data
from ._likelihood import LIKELIHOOD_OPTIONS, Likelihood, prepare
from ._nuisance import NuisanceOptions, build_nuisance, check_sigma_choice
from ._params import Param
from ._prepare import _check_detectors, _resolve_precision, block_names
from ._result import FitResult
from ._reweight import model_noise_weights, warm_params
from .config import FitConfig, FitDataConfig, ReduceConfig, TableConfig, load_fit_config

__all__ = ["FitJob", "build_fit_job", "reduce_step", "synthesize_step", "run_fit"]

#: The reduction's mask bits that test each pixel's own reading against a level (the refit tests the model).
DETECTION_FLAGS = FLAG_BELOW_NOISE | FLAG_BELOW_ARTIFACT_FLOOR | FLAG_LOW_SNR


# --- the job ----------------------------------------------------------------------------------


@dataclass
class FitJob:
    """A fit ready to run: the model, the data blocks, the parameter spec (stored units) and fit()'s options."""

    model: Model
    blocks: list[FrameData | TableData]
    params: dict[str, Param | str | float]
    fit_kwargs: dict[str, Any]
    config: FitConfig | None = None
    notes: list[str] = field(default_factory=list)
    truth: dict[str, float] | None = None  # synthetic data: the model's parameters (stored units)
    # per block: what a refit with the noise weights at the fitted model needs (config noise_weights =
    # "model"; brdfjax.fit._reweight), None for a block that keeps its weights; None: no refit
    reweight: list[dict | None] | None = None
    first_result: FitResult | None = None  # after run() with a reweighting: the fit with the readings' weights

    def likelihood(self) -> Likelihood:
        """The config's :class:`~brdfjax.fit.Likelihood` (what ``fit``, ``sample`` and ``diagnose`` take)."""
        return prepare(self.model, self.blocks, self.params,
                       **{k: v for k, v in self.fit_kwargs.items() if k in LIKELIHOOD_OPTIONS})

    def solver_options(self) -> dict[str, Any]:
        """How the config's fit finds the optimum (``solver``, ``solver_options``, ``first_stage``)."""
        return {k: v for k, v in self.fit_kwargs.items() if k not in LIKELIHOOD_OPTIONS}

    def run(self, progress: Any = None):
        """``brdfjax.fit.fit(self.likelihood(), ...)`` with the config's solver (``progress``: see
        :func:`~brdfjax.fit.fit`).

        With frames whose noise weights are to be evaluated at the model (``reweight``; the config's
        ``[data] noise_weights = "model"``): the first fit's weights are re-evaluated at its model
        (:func:`~brdfjax.fit._reweight.model_noise_weights`), the blocks replaced by the reweighted ones (so
        that a later ``likelihood()`` uses them) and the fit repeated from the first one's values; the
        result says so in a note of its ``noise``.
        """
        result = fit(self.likelihood(), progress=progress, **self.solver_options())
        if not self.reweight or not any(self.reweight):
            return result
        first = self.first_result = result
        self.blocks = self.reweighted_blocks(first)
        self.reweight = None
        names = block_names(self.blocks)
        lik = self.likelihood().with_params(warm_params(self.params, first, names))
        result = fit(lik, progress=progress, **self.solver_options())
        result.noise["reweighted"] = (
            f"noise weights evaluated at the model of a first fit (chi2_red {first.chi2_reduced:.4g}, "
            f"{first.n_iterations} steps) and refitted"
        )
        return result

    def reweighted_blocks(self, result: Any) -> list[FrameData | TableData]:
        """The blocks with the noise part of each frame's weights evaluated at ``result``'s model."""
        use_fp = bool(self.fit_kwargs.get("use_footprint", True))
        out: list[FrameData | TableData] = []
        for k, b in enumerate(self.blocks):
            info = self.reweight[k] if self.reweight and k < len(self.reweight) else None
            if info is None or not isinstance(b, FrameData):
                out.append(b)
                continue
            img = frame_model_image(result.models[k], result.frames[k], b, use_fp)
            out.append(model_noise_weights(b, info["data"], info["u_noise"], info["sigma_other"], info["mask"], img,
                                           info["max_sigma_rel"], info.get("detection")))
        return out


def _fingerprint(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def synthesize_step(cfg: FitConfig, model: Model, folder: Path, notes: list[str]) -> tuple[list[Path], float | None]:
    """Step 2: generate (or reuse) the synthetic measurement set of ``[data.synthetic]`` and reduce it;
    returns the reduced frames' paths and the footprint width (px)."""
    s = cfg.data.synthetic
    assert s is not None
    inst_cfg = load_instrument_config(None if s.instrument is None else cfg.resolve(s.instrument), s.camera_seed)
    inst_cfg = inst_cfg.without(*s.without)
    det = Detector.seed(
        shape=(2472 // s.bin, 3296 // s.bin), pixel_pitch=5.5e-6 * s.bin, pixel_pitch_v=5.5e-6 * s.bin
    )
    inst_cfg = inst_cfg.for_pixel_pitch(float(det.pixel_pitch))
    w_px = inst_cfg.footprint.w_px if inst_cfg.footprint.enabled else 0.0
    truth = {k: float(np.asarray(v)) for k, v in model.params().items()}
    key = _fingerprint({
        "synthetic": s.model_dump(exclude={"cache_dir"}), "instrument": inst_cfg.model_dump(), "truth": truth,
        "reduce": cfg.data.reduce.model_dump(), "version": 1,
    })
    stamp = folder / "synthetic.json"
    reduced_dir = folder / "reduced"
    phis = s.phi_ref_deg if isinstance(s.phi_ref_deg, list) else [s.phi_ref_deg] * len(s.theta_i_deg)
    names = [f"ti{t:g}" + (f"_pr{p:g}" if p else "") for t, p in zip(s.theta_i_deg, phis)]
    paths = [reduced_dir / f"{n}.exr" for n in names]
    if stamp.is_file():
        try:
            old = json.loads(stamp.read_text())
        except (OSError, ValueError):
            old = {}
        if old.get("key") == key and all(p.is_file() for p in paths):
            notes.append(f"synthetic frames reused from {folder}")
            return paths, w_px
    folder.mkdir(parents=True, exist_ok=True)
    instrument = SyntheticInstrument(det, inst_cfg, seed=s.seed)
    frames = {n: Conditions.from_degrees(t, p, s.wavelength_nm) for n, t, p in zip(names, s.theta_i_deg, phis)}
    manifest = instrument.measure_set(folder / "raw", model, frames)
    r = cfg.data.reduce
    reduce_measurement_set(manifest, reduced_dir, merge=r.merge, step=r.step, **_reduce_options(r))
    write_json_atomic(stamp, {"key": key, "frames": [p.name for p in paths], "footprint_w_px": w_px,
                              "truth": truth, "camera": list(det.shape)})
    notes.append(f"synthetic frames generated in {folder} (seed {s.seed})")
    return paths, w_px


def reduce_step(cfg: FitConfig, out: Path, notes: list[str]) -> list[Path]:
    """Step 1: reduce the raw measurement set of ``data.manifest`` into ``out``; returns the frames' paths."""
    d = cfg.data
    r = d.reduce
    try:
        written = reduce_measurement_set(cfg.resolve(d.manifest), out, merge=r.merge, step=r.step, **_reduce_options(r))
    except (ReductionError, RawFormatError, ValueError, OSError) as e:
        raise ConfigError(str(cfg.source), [("data.manifest", f"cannot reduce the measurement set: {e}")]) from None
    notes.append(f"reduced {len(written)} frame(s) of {cfg.resolve(d.manifest)} into {out}")
    return list(written)


def _reduce_options(r: ReduceConfig) -> dict[str, Any]:
    return dict(correct_nonlinearity=r.correct_nonlinearity, min_snr=r.min_snr,
                artifact_decades=r.artifact_decades, saturation_fraction=r.saturation_fraction)


def _roi_pixels(cfg: FitConfig, frame: FrameData) -> tuple[int, int, int, int] | None:
    d = cfg.data
    if d.roi is not None:
        return tuple(d.roi)  # type: ignore[return-value]
    if d.roi_deg is None:
        return None
    det = frame.detector
    R = float(np.asarray(det.distance))
    ph, pv = float(np.asarray(det.pixel_pitch)), float(np.asarray(det.pixel_pitch_v))
    h0, h1, v0, v1 = (math.tan(math.radians(x)) * R for x in d.roi_deg)
    return (math.floor(h0 / ph), math.ceil(h1 / ph), math.floor(v0 / pv), math.ceil(v1 / pv))


def _apply_masks(cfg: FitConfig, f: FrameData, key: str) -> FrameData:
    d = cfg.data
    m = np.ones(f.shape, bool) if f.mask is None else np.asarray(f.mask, bool)
    b = np.asarray(f.brdf, float)
    with np.errstate(invalid="ignore"):
        if d.min_brdf is not None:
            m &= b >= d.min_brdf
        if d.max_sigma_rel is not None:
            m &= np.broadcast_to(np.asarray(f.sigma_rel, float), f.shape) <= d.max_sigma_rel
    for h0, h1, v0, v1 in d.exclude:
        cols = (f.grid.n_h >= h0) & (f.grid.n_h <= h1)
        rows = (f.grid.n_v >= v0) & (f.grid.n_v <= v1)
        m &= ~np.outer(rows, cols)
    f = replace(f, mask=m)
    if not f.usable().any():
        raise ConfigError(str(cfg.source), [(key, _empty_message(f, d))])
    return f


def _empty_message(f: FrameData, d: FitDataConfig) -> str:
    try:
        f.check_usable()
    except FitInputError as e:
        msg = str(e)
    else:  # pragma: no cover
        msg = f"frame '{f.name}': no usable pixels"
    opts = [f"{k} = {getattr(d, k)!r}" for k in ("roi", "roi_deg", "min_brdf", "max_sigma_rel", "exclude") if getattr(d, k)]
    return "empty mask: " + msg + (f" (after {', '.join(opts)})" if opts else "")


def _load_frames(cfg: FitConfig, work_dir: Path | None, notes: list[str], model: Model) -> tuple[list[FrameData], dict]:
    d = cfg.data
    entries: list[tuple[str, Path]] = [(f"data.frames[{i}]", cfg.resolve(p)) for i, p in enumerate(d.frames)]
    footprint = d.footprint_w_px
    info: dict[str, Any] = {}
    if d.manifest is not None:
        out = (work_dir / "reduced") if work_dir is not None else Path(tempfile.mkdtemp(prefix="brdfjax-fit-"))
        written = reduce_step(cfg, out, notes)
        info.setdefault("manifests", []).append(str(cfg.resolve(d.manifest)))
        entries += [("data.manifest", p) for p in written]
    if d.synthetic is not None:
        s = d.synthetic
        folder = cfg.resolve(s.cache_dir) if s.cache_dir else (
            (work_dir / "synthetic") if work_dir is not None else Path(tempfile.mkdtemp(prefix="brdfjax-synthetic-"))
        )
        paths, w_px = synthesize_step(cfg, model, folder, notes)
        info["synthetic_dir"] = str(folder)
        info.setdefault("manifests", []).append(str(folder / "raw" / "manifest.toml"))
        if footprint is None:
            footprint = w_px
        entries += [("data.synthetic", p) for p in paths]
    frames = []
    for key, path in entries:
        try:
            opts = dict(footprint_w_px=footprint, sigma=d.sigma, sigma_floor=d.sigma_floor)
            f0 = read_frame_data(path, step=d.step, **opts)
            roi = _roi_pixels(cfg, f0)
            f = f0 if roi is None else read_frame_data(path, step=d.step, roi=roi, **opts)
        except FitInputError as e:
            raise ConfigError(str(cfg.source), [(key, str(e))]) from None
        frames.append(_apply_masks(cfg, f, key))
        info.setdefault("reweight", []).append(_reweight_info(cfg, f, path, roi, footprint, key))
    return frames, info


def _reweight_info(cfg: FitConfig, f: FrameData, path: Path, roi: Any, footprint: Any, key: str) -> dict | None:
    """What :meth:`FitJob.reweighted_blocks` needs of a frame (``noise_weights = "model"``; None: nothing to do).

    The reading's relative noise ``u_scatter_noise`` on the frame's grid, the rest of its sigma, its data
    and its mask before the ``max_sigma_rel`` cut (and, for a brdfjax reduction, before its detection cuts,
    with what they need).  Frames without a noise channel keep their weights.
    """
    d = cfg.data
    if d.noise_weights != "model":
        return None
    try:
        fn = read_frame_data(path, step=d.step, roi=roi, footprint_w_px=footprint, sigma="noise", sigma_floor=0.0)
    except FitInputError:
        return None
    u = np.broadcast_to(np.asarray(fn.sigma_rel, float), f.shape)
    sig = np.broadcast_to(np.asarray(f.sigma_rel, float), f.shape)
    with np.errstate(invalid="ignore"):
        other = np.sqrt(np.clip(np.square(sig) - np.square(u), 0.0, None))
    uncut = cfg.model_copy(update={"data": d.model_copy(update={"max_sigma_rel": None})})
    info = {"data": np.asarray(f.brdf, float), "u_noise": u, "sigma_other": other,
            "mask": _apply_masks(uncut, f, key).mask, "max_sigma_rel": d.max_sigma_rel, "detection": None}
    # The reduction's detection cuts (below the noise-equivalent BRDF, the artifact floor, min_snr) were
    # made on each pixel's own reading: with them known, the refit makes them on the model instead.
    try:
        red = read_reduced_frame(path)
        extra, attrs = dict(red.extra or {}), dict(red.attrs or {})
        flags = _on_grid(red, f, extra["flags"]).astype(np.int64)
        neb = _on_grid(red, f, extra["noise_equivalent_brdf"])
        floor, min_snr = float(attrs["artifact_floor"]), float(attrs["min_snr"])
    except (KeyError, ValueError, OSError, ExrError):
        return info
    structural = (flags & ~DETECTION_FLAGS) == 0
    if roi is not None:
        h0, h1, v0, v1 = (int(x) for x in roi)
        nh, nv = np.asarray(f.grid.n_h), np.asarray(f.grid.n_v)
        structural &= np.outer((nv >= v0) & (nv <= v1), (nh >= h0) & (nh <= h1))
    info["mask"] = _apply_masks(uncut, replace(f, mask=structural), key).mask
    info["detection"] = {"noise_equivalent_brdf": neb, "artifact_floor": floor, "min_snr": min_snr}
    return info


def _on_grid(reduced: Any, f: FrameData, channel: Any) -> np.ndarray:
    """A channel of a reduced frame (its stored grid) at the points of ``f``'s grid."""
    attrs = dict(reduced.attrs)
    h0, _, v0, _ = (int(x) for x in attrs["roi"])
    step = int(attrs["step"])
    rows = (np.asarray(f.grid.n_v) - v0) // step
    cols = (np.asarray(f.grid.n_h) - h0) // step
    return np.asarray(channel, np.float64)[np.ix_(rows, cols)]


def _load_table(cfg: FitConfig, i: int, t: TableConfig) -> TableData:
    key = f"data.tables[{i}]"
    path = cfg.resolve(t.path)
    name = t.name or path.stem
    wl = None if t.wavelength_nm in (None, "mean") else float(t.wavelength_nm)
    screen = Screen(
        on_bad_rows=t.on_bad_rows, placeholder_run=t.placeholder_run, floor_repeats=t.floor_repeats,
        check_mirror=t.check_mirror, mirror_tolerance_deg=t.mirror_tolerance_deg,
    )
    conv = []
    for k, default in (("azimuth_offset", -180.0 if t.format in ("merl", "lumos-sat") else 0.0),
                       ("signed_inplane", t.format in ("merl", "lumos-sat"))):
        v = getattr(t, k)
        conv.append(f"{key}.{k} (now {default if v is None else v!r})")
    screen = replace(screen, convention=" or ".join(conv))
    try:
        if t.format in ("merl", "lumos-sat"):
            table = read_merl_inplane(
                path, name=name, columns=t.columns,
                signed_inplane=True if t.signed_inplane is None else t.signed_inplane,
                azimuth_offset=-180.0 if t.azimuth_offset is None else t.azimuth_offset,
                wavelength=wl, screen=screen,
            )
        elif t.format == "cornell":
            table = read_cornell_brdf(path, "mean" if t.wavelength_nm is None else t.wavelength_nm, name=name, screen=screen)
        elif t.format == "astm":
            table = read_astm_e1392(path, name=name, wavelength=wl, screen=screen)
        else:
            table = read_table(
                path, t.columns or {}, angle_unit=t.angle_unit, signed_inplane=bool(t.signed_inplane),
                azimuth_offset=t.azimuth_offset or 0.0, wavelength=wl, delimiter=t.delimiter, name=name,
                screen=screen,
            )
    except FitInputError as e:
        raise ConfigError(str(cfg.source), [(key, str(e))]) from None
    n = len(table)
    keep = np.ones(n, bool) if table.mask is None else np.asarray(table.mask, bool)
    if t.theta_i_deg is not None:
        ti = np.degrees(np.asarray(table.theta_i, float))
        sel = np.zeros(n, bool)
        for a in t.theta_i_deg:
            sel |= np.abs(ti - a) < 1e-6 + 1e-9 * abs(a)
        if not sel.any():
            have = ", ".join(f"{x:g}" for x in np.unique(np.round(ti, 6)))
            raise ConfigError(str(cfg.source), [(f"{key}.theta_i_deg", f"none of {t.theta_i_deg} is in {path} (it has: {have})")])
        keep &= sel
    if t.max_theta_s_deg is not None:
        keep &= np.degrees(np.asarray(table.theta_s, float)) <= t.max_theta_s_deg
    if t.min_brdf is not None:
        with np.errstate(invalid="ignore"):
            low = keep & ~(np.asarray(table.brdf, float) >= t.min_brdf)  # among the rows still selected
        keep &= ~low
        table = replace(table, screening=_with_min_brdf(table, low, t.min_brdf))
    sigma = table.sigma_rel
    if t.sigma_rel is not None:
        if sigma is not None:
            raise ConfigError(str(cfg.source), [(f"{key}.sigma_rel", f"{path} has its own uncertainties; drop sigma_rel")])
        sigma = np.full(n, float(t.sigma_rel))
    table = replace(table, mask=keep, sigma_rel=sigma)
    if not table.usable().any():
        try:
            table.check_usable()
        except FitInputError as e:
            raise ConfigError(str(cfg.source), [(key, f"empty mask: {e}")]) from None
    return table


def _with_min_brdf(table: TableData, low: np.ndarray, min_brdf: float) -> dict[str, Any]:
    """The table's screening record with the rows below ``min_brdf`` counted as dropped (with their lines)."""
    rec = dict(table.screening or {"n_rows": len(table), "n_kept": len(table), "dropped": {}})
    dropped = dict(rec.get("dropped") or {})
    n = int(low.sum())
    if n:
        entry: dict[str, Any] = {"count": n, "min_brdf": float(min_brdf)}
        if table.lines is not None:
            entry["lines"] = np.asarray(table.lines)[low][:50].tolist()
        dropped["min_brdf"] = entry
    rec["dropped"] = dropped
    rec["n_kept"] = int(rec.get("n_kept", len(table))) - n
    return rec


def build_fit_job(cfg: FitConfig, *, work_dir: str | os.PathLike | None = None) -> FitJob:
    """Load (reduce, generate) the data of a config and return the :class:`FitJob`.

    ``work_dir``: where a raw set is reduced and synthetic frames are cached
    (``<work_dir>/reduced``, ``<work_dir>/synthetic``; default: a temporary
    folder).  Bad data raise :class:`ConfigError` naming the config key.
    """
    work = None if work_dir is None else Path(work_dir)
    model = cfg.build_model()
    notes: list[str] = []
    frames, info = _load_frames(cfg, work, notes, model)
    tables = [_load_table(cfg, i, t) for i, t in enumerate(cfg.data.tables)]
    for i, t in enumerate(tables):
        rec = t.screening or {}
        if rec.get("dropped"):
            what = ", ".join(f"{v['count']} {k}" for k, v in rec["dropped"].items())
            notes.append(f"data.tables[{i}] ({t.source}): dropped {rec['n_rows'] - rec['n_kept']} of {rec['n_rows']} rows: {what}")
    blocks: list[FrameData | TableData] = [*frames, *tables]
    names = [b.name for b in blocks]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        notes.append(f"blocks share names {dup}; the result numbers them")
    if len(frames) > 1 and not cfg.data.allow_different_detectors:
        try:
            _check_detectors(frames, block_names(frames), False)
        except FitInputError as e:
            raise ConfigError(str(cfg.source), [("data", f"{e} (set data.allow_different_detectors = true)")]) from None
    f = cfg.fit
    fit_kwargs: dict[str, Any] = dict(
        solver=f.solver,
        solver_options=dict(f.solver_options),
        loss=f.loss,
        loss_scale=f.loss_scale,
        first_stage=None if f.first_stage == "none" else f.first_stage,
        initializer=f.initializer,
        init_options=dict(f.init_options),
        floor=f.floor,
        precision=cfg.precision,
        absolute_sigma=f.absolute_sigma,
        allow_different_detectors=cfg.data.allow_different_detectors,
        use_footprint=f.use_footprint,
    )
    fit_kwargs["nuisance"] = _nuisance_for(cfg, blocks, info.pop("manifests", []), notes)
    truth = None
    if cfg.data.synthetic is not None:
        truth = {k: float(np.asarray(v)) for k, v in model.params().items()}
    reweight = info.pop("reweight", [])
    reweight = reweight + [None] * len(tables) if any(reweight) else None
    job = FitJob(model, blocks, dict(cfg.build_params()), fit_kwargs, cfg, notes, truth, reweight)
    job.notes.extend(f"{k}: {v}" for k, v in info.items())
    return job


def _nuisance_for(cfg: FitConfig, blocks: list[FrameData | TableData], manifests: list[str], notes: list[str]) -> Any:
    """The nuisance parameters of a config's data (``None``: none): on by default for frames with ND stacks."""
    opts = cfg.nuisance
    if opts.enabled is False or not any(getattr(b, "systematics", None) is not None for b in blocks):
        if opts.enabled:
            notes.append("nuisance: enabled, but no frame carries ND stacks (frames through the instrument); none added")
        return None
    src = str(cfg.source)
    try:
        check_sigma_choice(cfg.data.sigma, src)
    except FitInputError as e:
        raise ConfigError(src, [("data.sigma", str(e).split(": ", 1)[1])]) from None
    table = None
    for m in manifests:
        try:
            cal = read_manifest(m, check_files=False).calibration
        except (RawFormatError, OSError) as e:
            raise ConfigError(src, [("data", f"cannot read the calibration of {m}: {e}")]) from None
        table = {**(table or NuisanceOptions().tolerance_table()), **{round(float(k), 6): float(v) for k, v in cal.nd_tolerances.items()}}
    try:
        spec = build_nuisance(blocks, block_names(blocks), opts, table, source=src)
    except FitInputError as e:
        msg = str(e).split(": ", 1)[1]
        key, msg = msg.split(": ", 1) if msg.startswith("nuisance.") else ("nuisance", msg)
        raise ConfigError(src, [(key, msg)]) from None
    if spec is None:
        return None
    notes.append(
        "nuisance parameters (systematic errors): "
        + ", ".join(f"{n} (prior sigma {s:.3g})" for n, s in zip(spec.names, spec.prior_sigma))
    )
    # the options (not the spec): a fit of other blocks (the diagnosis' held-out frames) builds its own
    return opts.model_copy(update={"enabled": True}).with_calibration(table)


# --- running ----------------------------------------------------------------------------------


def run_fit(
    config_path: str | os.PathLike, out_dir: str | os.PathLike, *, console: Any = None, figures: bool | None = None
) -> FitResult:
    """Load a config, run the fit and write ``out_dir/result.json`` (atomically) and the figures.

    Returns the :class:`~brdfjax.fit.FitResult`.  ``result.json`` is
    :meth:`FitResult.to_dict` plus ``config`` (the file), ``data`` (the
    blocks fitted) and, for synthetic data, ``truth`` (natural units).
    Raises :class:`ConfigError` / :class:`FitInputError` for a config or
    data that cannot be fitted (nothing is written then).
    """
    out = Path(out_dir)
    t0 = time.perf_counter()
    cfg = load_fit_config(config_path)
    _resolve_precision(cfg.precision)  # float64 without 64-bit JAX fails now, before anything is written
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        job = build_fit_job(cfg, work_dir=out)
    except Exception:
        if created and not any(out.iterdir()):
            out.rmdir()  # bad data: leave nothing behind
        raise
    t_data = time.perf_counter() - t0
    say = (lambda s: console.print(s, markup=False)) if console is not None else (lambda s: None)
    for n in job.notes:
        say(n)
    say(f"data: {len(job.blocks)} block(s) loaded in {t_data:.1f} s; fitting ...")
    with ProgressLine(console, "fit", None, unit="solver evaluation(s)") as bar:
        # nobody to tell (--quiet): no progress callback, so the solve runs as one program, which a later
        # process reads back traced (brdfjax.runtime.export_cache); the stepped solve's state cannot be exported
        heard = (lambda k, chi2: bar.update(k, f"chi2 = {chi2:.6g}")) if bar.enabled else None
        result = job.run(progress=heard)
    doc = result.to_dict()
    doc["config"] = str(cfg.source)
    doc["data"] = [_describe_block(b) for b in job.blocks]
    doc["data_s"] = t_data
    if job.truth is not None:
        units = job.model.parameter_units()
        doc["truth"] = {
            k: {"value": v * to_natural(units[k]), "unit": natural_unit(units[k])} for k, v in job.truth.items()
        }
        # a synthetic demo knows its truth: one outside 3 sigma is said, not left for the reader to find
        doc["truth_warnings"] = result.truth_warnings(job.truth)
    _write_json(out / "result.json", doc)
    say(result.summary())
    for w in doc.get("truth_warnings", ()):
        say(f"warning: {w}")
    if (cfg.output.figures if figures is None else figures):
        paths = write_figures(job, result, out, dpi=cfg.output.dpi)
        say(f"figures: {', '.join(p.name for p in paths)}")
    return result


def _describe_block(b: FrameData | TableData) -> dict[str, Any]:
    if isinstance(b, FrameData):
        return {
            "name": b.name, "kind": "frame", "theta_i_deg": math.degrees(b.theta_i), "phi_ref_deg": math.degrees(b.phi_ref),
            "wavelength_nm": b.wavelength * 1e9, "grid": list(b.grid.shape), "n_usable": int(b.usable().sum()),
            "footprint": None if b.footprint is None else list(np.shape(b.footprint)),
        }
    return {
        "name": b.name, "kind": "table", "source": b.source, "n_rows": len(b), "n_usable": int(b.usable().sum()),
        "screening": b.screening,
    }


def _write_json(path: Path, doc: Mapping[str, Any]) -> None:
    def clean(x: Any) -> Any:
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        return x

    text = json.dumps(clean(dict(doc)), indent=2, allow_nan=False)
    with atomic_output(path) as tmp:
        tmp.write_text(text + "\n")
