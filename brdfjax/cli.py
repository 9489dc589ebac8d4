"""The ``brdfjax`` command line: ``brdfjax <subcommand> ...``.

Subcommands are entries of :data:`COMMANDS` (a name, a help line, a function
adding its arguments and a function running it), so that new ones (fit,
sample, diagnose, capture) slot in without touching :func:`main`.

``brdfjax simulate [CONFIG] --out DIR [--step K] [--precision P] [--no-plot]``
renders every frame of a TOML config (see :mod:`brdfjax.config`; without
CONFIG the packaged default job) and writes, per frame, ``<name>.exr``
(BRDF, theta_s, phi_s, solid angle; see :mod:`brdfjax.io.exr`) and
``<name>.png`` (see :mod:`brdfjax.plotting`), plus ``summary.json``.

Exit codes: 0 success, 1 failure while running (e.g. an output that cannot be
written), 2 bad usage or a bad config (the message names the file and key).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "COMMANDS",
    "Command",
    "FrameResult",
    "build_parser",
    "main",
    "run_simulate",
    "simulate_frame",
]

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2


# --- the simulate pipeline (also used by experiments/reproduce_seed.py) --------------------------


@dataclass(frozen=True)
class FrameResult:
    """One rendered frame in memory: ``(rows, cols)`` NumPy arrays of the grid and timings."""

    stem: str
    frame: Any  # brdfjax.Frame
    grid: Any  # brdfjax.PixelGrid
    brdf: np.ndarray  # sr^-1
    terms: dict[str, np.ndarray]  # sr^-1, each term of the model
    geometry: dict[str, np.ndarray]  # theta_s, phi_s (rad), omega (sr)
    render_s: float
    files: dict[str, str] = field(default_factory=dict)
    write_s: float = 0.0

    def argmax(self, image: np.ndarray | None = None) -> tuple[int, int]:
        """``(n_h, n_v)`` pixel indices of the maximum of ``image`` (default: the BRDF)."""
        a = self.brdf if image is None else image
        r, c = np.unravel_index(int(np.nanargmax(a)), a.shape)
        return int(self.grid.n_h[c]), int(self.grid.n_v[r])

    def at(self, image: np.ndarray, n_h: int, n_v: int) -> float:
        """Value of ``image`` at pixel ``(n_h, n_v)`` (which must be on the grid)."""
        c = int(np.flatnonzero(self.grid.n_h == n_h)[0])
        r = int(np.flatnonzero(self.grid.n_v == n_v)[0])
        return float(image[r, c])


def simulate_frame(model, frame, detector, grid, precision: str = "float32", stem: str = "frame") -> FrameResult:
    """Render ``model`` and the pixel geometry on ``grid``; returns NumPy arrays (blocks until done).

    The BRDF is the sum of the per-term images (the same sum, in the same
    order, as evaluating the model), so one pass gives both.
    """
    from .render import render, render_geometry

    t0 = time.perf_counter()
    per_term = render(model, frame, detector, grid=grid, precision=precision, per_term=True)
    terms = {k: np.asarray(v) for k, v in per_term.items()}
    values = list(terms.values())
    brdf = sum(values[1:], values[0]).copy()
    geometry = {k: np.asarray(v) for k, v in render_geometry(frame, detector, grid=grid, precision=precision).items()}
    return FrameResult(stem, frame, grid, brdf, terms, geometry, time.perf_counter() - t0)


def _frame_attrs(cfg, detector, frame, stem: str) -> dict[str, Any]:
    from . import __version__

    h0, h1, v0, v1 = cfg.roi if cfg.roi is not None else detector.index_range
    theta_c = frame.theta_i if detector.theta_c is None else detector.theta_c
    return {
        "theta_i": float(frame.theta_i),
        "theta_c": float(theta_c),
        "phi_ref": float(frame.phi_ref),
        "wavelength": float(frame.wavelength),
        "R": float(detector.distance),
        "pixel_pitch": float(detector.pixel_pitch),
        "pixel_pitch_v": float(detector.pixel_pitch_v),
        "roll": float(detector.roll),
        "yaw": float(detector.yaw),
        "pitch": float(detector.pitch),
        "m_h": float(detector.m_h),
        "m_v": float(detector.m_v),
        "step": int(cfg.grid.step),
        "roi": (int(h0), int(h1), int(v0), int(v1)),
        "model": cfg.describe_model(),
        "precision": cfg.precision,
        "frame": stem,
        "brdfjax_version": __version__,
    }


def _frame_summary(cfg, res: FrameResult, fcfg) -> dict[str, Any]:
    def peak(image: np.ndarray) -> dict[str, Any]:
        n_h, n_v = res.argmax(image)
        return {"value": float(np.nanmax(image)), "pixel": [n_h, n_v]}

    n_h, n_v = res.argmax()
    th = res.at(res.geometry["theta_s"], n_h, n_v)
    ph = res.at(res.geometry["phi_s"], n_h, n_v)
    return {
        "name": res.stem,
        "theta_i_deg": fcfg.theta_i_deg,
        "phi_ref_deg": fcfg.phi_ref_deg,
        "wavelength_nm": fcfg.wavelength_nm,
        "max_brdf": float(np.nanmax(res.brdf)),
        "max_pixel": [n_h, n_v],
        "max_theta_s_deg": float(np.rad2deg(th)),
        "max_phi_s_deg": float(np.rad2deg(ph)),
        "term_max": {k: peak(v) for k, v in res.terms.items()},
        "grid_shape": list(res.brdf.shape),
        "step": cfg.grid.step,
        "roi": cfg.roi,
        "precision": cfg.precision,
        "config": cfg.source,
        "render_s": round(res.render_s, 4),
        "write_s": round(res.write_s, 4),
        "wall_s": round(res.render_s + res.write_s, 4),
        "files": res.files,
    }


def _write_json_atomic(path: Path, data: Any) -> None:
    from .io import atomic_output

    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def run_simulate(
    cfg,
    out: str | os.PathLike,
    *,
    plot: bool = True,
    console: Any = None,
    on_frame: Callable[[FrameResult], None] | None = None,
) -> dict[str, Any]:
    """Render every frame of a :class:`~brdfjax.config.SimulateConfig` into ``out``.

    Writes ``<stem>.exr``, ``<stem>.png`` (unless ``plot=False``) and
    ``summary.json``; returns the summary.  ``on_frame`` receives each
    :class:`FrameResult` (full arrays) before it is dropped.  ``console`` is a
    ``rich`` console for one status line per frame (``None``: silent).
    A config with ``precision = "float64"`` needs ``jax_enable_x64`` on; the
    CLI turns it on, library callers decide for themselves.
    """
    from . import __version__
    from .io.exr import write_frame_exr

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    detector = cfg.build_detector()
    grid = cfg.build_grid(detector)
    model = cfg.build_model()
    frames = cfg.build_frames()
    if plot:
        from .plotting import plot_frame

    t_start = time.perf_counter()
    entries = []
    for (stem, frame), fcfg in zip(frames, cfg.frames, strict=True):
        status = console.status(f"rendering {stem} ({grid.shape[0]} x {grid.shape[1]} pixels)") if console else None
        if status:
            status.start()
        try:
            res = simulate_frame(model, frame, detector, grid, cfg.precision, stem)
            t0 = time.perf_counter()
            exr = write_frame_exr(
                out / f"{stem}.exr",
                res.brdf,
                res.geometry["theta_s"],
                res.geometry["phi_s"],
                res.geometry["omega"],
                _frame_attrs(cfg, detector, frame, stem),
            )
            files = {"exr": exr.name}
            if plot:
                files["png"] = plot_frame(res.brdf, grid, detector, frame, out / f"{stem}.png").name
            res = dataclasses.replace(res, files=files, write_s=time.perf_counter() - t0)
        finally:
            if status:
                status.stop()
        entry = _frame_summary(cfg, res, fcfg)
        entries.append(entry)
        if console is not None:
            n_h, n_v = entry["max_pixel"]
            console.print(
                f"[green]done[/] {stem}: {res.brdf.shape[0]} x {res.brdf.shape[1]} px, "
                f"max {entry['max_brdf']:.4g} sr^-1 at (n_h, n_v) = ({n_h}, {n_v}), "
                f"render {res.render_s:.2f} s, write {res.write_s:.2f} s -> {', '.join(files.values())}",
                highlight=False,
            )
        if on_frame is not None:
            on_frame(res)
        del res

    summary = {
        "brdfjax_version": __version__,
        "config": cfg.source,
        "precision": cfg.precision,
        "step": cfg.grid.step,
        "roi": cfg.roi,
        "grid_shape": list(grid.shape),
        "detector": {**cfg.detector.resolved(), "theta_c_deg": cfg.detector.theta_c_deg},
        "model": cfg.describe_model(),
        "wall_s": round(time.perf_counter() - t_start, 4),
        "frames": entries,
    }
    _write_json_atomic(out / "summary.json", summary)
    return summary


# --- subcommands -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """A subcommand: ``add_arguments(parser)`` declares its options, ``run(args) -> exit code`` runs it."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config",
        nargs="?",
        default=None,
        metavar="CONFIG",
        help="TOML config (default: the packaged default job, brdfjax/data/default.toml)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument("--step", type=int, default=None, metavar="K", help="evaluate every K-th pixel (overrides grid.step)")
    p.add_argument(
        "--precision", choices=("float32", "float64"), default=None, help="floating-point precision (overrides precision)"
    )
    p.add_argument("--no-plot", action="store_true", help="write the EXR files and summary only, no PNG figures")


def _error(prog: str, message: str) -> None:
    sys.stderr.write(f"{prog}: error: {message}\n")


def _run_simulate(args: argparse.Namespace) -> int:
    from rich.console import Console

    from .config import ConfigError, load_simulate_config
    from .io import ExrError

    prog = "brdfjax simulate"
    try:
        cfg = load_simulate_config(args.config)
        if args.step is not None or args.precision is not None:
            cfg = cfg.with_overrides(step=args.step, precision=args.precision)
    except ConfigError as e:
        _error(prog, str(e))
        return EXIT_USAGE
    if cfg.precision == "float64":
        import jax

        # An edge may flip the process-wide switch; the library never does.
        jax.config.update("jax_enable_x64", True)

    console = Console(stderr=True, highlight=False, soft_wrap=True)
    grid_note = f"every {cfg.grid.step}th pixel" if cfg.grid.step > 1 else "every pixel"
    console.print(
        f"brdfjax simulate: {cfg.source} -> {args.out}: {len(cfg.frames)} frame(s), {grid_note}"
        + (f" of roi {cfg.roi}" if cfg.roi else "")
        + f", {cfg.precision}",
        markup=False,
    )
    try:
        summary = run_simulate(cfg, args.out, plot=not args.no_plot, console=console)
    except (OSError, ExrError) as e:
        _error(prog, str(e))
        return EXIT_FAILURE
    except ConfigError as e:  # e.g. a ROI that only fails once the detector is built
        _error(prog, str(e))
        return EXIT_USAGE
    console.print(f"wrote {Path(args.out) / 'summary.json'} ({summary['wall_s']:.1f} s)", markup=False)
    return EXIT_OK


def _reduce_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("manifest", metavar="MANIFEST", help="a measurement set's manifest.toml (or its folder)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument(
        "--merge",
        choices=("weighted", "replacement"),
        default="weighted",
        help="HDR merge: inverse-variance weighted (default) or the seed's replacement scheme (§3.6)",
    )
    p.add_argument("--step", type=int, default=1, metavar="K", help="keep every K-th pixel of the output frames")
    p.add_argument(
        "--correct-nonlinearity",
        action="store_true",
        help="correct the readings by the camera's response curve (manifest [calibration] nonlinearity_curve, "
        "else the seed's typical 1.72%% curve) before the weighted merge: removes the exposure-switch seams",
    )
    p.add_argument("--no-plot", action="store_true", help="write the EXR files and summary only, no PNG figures")


def _reduced_summary(path: Path, frame: Any) -> dict[str, Any]:
    mask = np.asarray(frame.extra["mask"]) > 0
    sig = np.asarray(frame.extra["sigma_rel"])
    b = np.asarray(frame.brdf)
    keys = (
        "theta_i", "phi_ref", "nd_sample", "od_sample", "incident_flux_sdc", "noise_equivalent_brdf",
        "max_measurable_brdf", "dynamic_range_decades", "usable_fraction", "merge",
    )
    out = {k: frame.attrs[k] for k in keys if k in frame.attrs}
    out.update(
        file=path.name,
        shape=list(b.shape),
        usable_pixels=int(mask.sum()),
        max_brdf=float(np.max(np.where(mask, b, -np.inf))) if mask.any() else None,
        median_sigma_rel=float(np.median(sig[mask])) if mask.any() else None,
    )
    return out


def _run_reduce(args: argparse.Namespace) -> int:
    from rich.console import Console

    from .instrument.raw import ManifestError, RawFormatError
    from .instrument.reduce import ReductionError, read_reduced_frame, reduce_measurement_set
    from .io import ExrError

    prog = "brdfjax reduce"
    if args.step < 1:
        _error(prog, f"--step must be a positive integer, got {args.step}")
        return EXIT_USAGE
    console = Console(stderr=True, highlight=False, soft_wrap=True)
    console.print(f"brdfjax reduce: {args.manifest} -> {args.out} ({args.merge} merge)", markup=False)
    t0 = time.perf_counter()
    try:
        if args.correct_nonlinearity and args.merge != "weighted":
            _error(prog, "--correct-nonlinearity needs --merge weighted (the replacement scheme is the seed's, §3.6)")
            return EXIT_USAGE
        paths = reduce_measurement_set(
            args.manifest, args.out, merge=args.merge, step=args.step, correct_nonlinearity=args.correct_nonlinearity
        )
    except (ManifestError, RawFormatError, FileNotFoundError) as e:
        _error(prog, str(e))
        return EXIT_USAGE
    except (ReductionError, ExrError, OSError) as e:
        _error(prog, str(e))
        return EXIT_FAILURE
    frames = []
    for path in paths:
        frame = read_reduced_frame(path)
        entry = _reduced_summary(path, frame)
        if not args.no_plot:
            from .detector import Detector
            from .plotting import plot_frame
            from .render import Frame

            from .detector import PixelGrid

            a = frame.attrs
            h0, h1, v0, v1 = a["roi"]
            det = Detector(
                shape=(v1 - v0 + 1, h1 - h0 + 1), pixel_pitch=a["pixel_pitch"],
                pixel_pitch_v=a.get("pixel_pitch_v", a["pixel_pitch"]), distance=a["R"],
                theta_c=a["theta_c"], **{k: a.get(k, 0.0) for k in ("roll", "yaw", "pitch", "m_h", "m_v")},
            )
            grid = PixelGrid(np.arange(h0, h1 + 1, a["step"]), np.arange(v0, v1 + 1, a["step"]))
            shown = np.where(np.asarray(frame.extra["mask"]) > 0, frame.brdf, np.nan)
            png = plot_frame(
                shown, grid, det, Frame(a["theta_i"], a["phi_ref"], a["wavelength"]), path.with_suffix(".png"),
                title=f"{path.stem} (reduced, masked pixels blank)",
            )
            entry["png"] = png.name
        frames.append(entry)
        console.print(
            f"done {path.stem}: {entry['usable_pixels']} usable px, median sigma_rel "
            f"{entry['median_sigma_rel']:.3g}, noise-equivalent BRDF "
            f"{entry.get('noise_equivalent_brdf', float('nan')):.3g} sr^-1 -> {path.name}",
            markup=False,
        )
    summary = {"manifest": str(args.manifest), "merge": args.merge, "step": args.step,
               "frames": frames, "wall_s": time.perf_counter() - t0}
    _write_json_atomic(Path(args.out) / "summary.json", summary)
    console.print(f"wrote {Path(args.out) / 'summary.json'} ({summary['wall_s']:.1f} s)", markup=False)
    return EXIT_OK


#: ND filter stacks tried, in order of increasing OD, when ``synthesize`` picks one (seed §3.3 filters).
ND_STACKS = (
    "", "0.3", "1.0", "1.0+0.3", "3.0", "3.0+0.3", "4.0", "4.0+0.3", "4.0+1.0", "4.0+1.0+0.2",
    "4.0+1.0+0.3", "4.0+3.0", "4.0+3.0+0.3", "4.0+3.0+1.0",
)
#: ND tolerance of the 3.0 filter (+-OD) inferred from the seed's 59.3 % (its tolerance table lacks it).
ND_3_TOLERANCE = 0.15


def _od(stack: str) -> float:
    return sum(float(x) for x in stack.split("+") if x)


def choose_nd_filters(rate: Callable[[str], np.ndarray], instrument: Any) -> str:
    """The seed's rule: the smallest OD whose brightest pixel stays unsaturated at the shortest exposure.

    ``rate(stack)`` is the light rate on the array (counts/s) through an ND stack; it scales
    with ``10**-OD``, so it is evaluated once.
    """
    cfg = instrument.config
    t0 = float(cfg.exposures_s[0])
    peak_unattenuated = float(np.max(rate(ND_STACKS[0])))
    for stack in ND_STACKS:
        if peak_unattenuated * 10 ** -_od(stack) * t0 + 2 * cfg.black_level.counts < 0.9 * cfg.full_scale:
            return stack
    raise ValueError(f"no ND stack up to OD {_od(ND_STACKS[-1])} keeps the brightest pixel unsaturated")


def _synthesize_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config", nargs="?", default=None, metavar="CONFIG",
        help="a simulate config naming the detector, model and frames (default: the packaged default job)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder for the measurement set")
    p.add_argument("--seed", type=int, default=0, help="noise seed (the same seed gives the same files)")
    p.add_argument(
        "--camera-seed", type=int, default=None, help="seed of the camera's fixed per-pixel maps (overrides the config)"
    )
    p.add_argument("--nd", default=None, metavar="STACK", help='sample ND filters, e.g. "3.0" (default: chosen by the seed\'s rule)')
    p.add_argument(
        "--instrument", default=None, metavar="TOML",
        help="instrument config: every effect's switch and parameters (see configs/instrument_seed.toml); "
        "default: the seed's instrument",
    )
    p.add_argument(
        "--without", default="", metavar="EFFECTS",
        help="comma-separated instrument effects to switch off (e.g. stray_light,ambient)",
    )


def load_instrument_config(path: str | os.PathLike | None, camera_seed: int | None = None) -> Any:
    """Read an instrument TOML into :class:`~brdfjax.instrument.synthetic.InstrumentConfig`.

    Raises :class:`~brdfjax.config.ConfigError` naming the file and the dotted key on a bad value or an
    unknown key.
    """
    import tomllib

    from pydantic import ValidationError

    from .config import ConfigError
    from .instrument.synthetic import InstrumentConfig

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


def _run_synthesize(args: argparse.Namespace) -> int:
    from rich.console import Console

    from .config import ConfigError, load_simulate_config
    from .instrument.raw import Calibration
    from .instrument.synthetic import EFFECTS, SyntheticInstrument

    prog = "brdfjax synthesize"
    try:
        cfg = load_simulate_config(args.config)
    except ConfigError as e:
        _error(prog, str(e))
        return EXIT_USAGE
    try:
        inst_cfg = load_instrument_config(args.instrument, args.camera_seed)
    except ConfigError as e:
        _error(prog, str(e))
        return EXIT_USAGE
    off = [x.strip() for x in args.without.split(",") if x.strip()]
    unknown = sorted(set(off) - set(EFFECTS))
    if unknown:
        _error(prog, f"--without: unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")
        return EXIT_USAGE
    if cfg.grid.step != 1 or cfg.roi:
        _error(prog, f"{cfg.source}: grid.step/grid.roi do not apply: the synthetic camera reads the whole array")
        return EXIT_USAGE
    console = Console(stderr=True, highlight=False, soft_wrap=True)
    detector = cfg.build_detector()
    # The seed instrument's beam footprint and stray-light offsets are sizes on the array: scale
    # them to this detector's pixels (a no-op on the seed camera).
    inst_cfg = inst_cfg.without(*off)
    inst_cfg = inst_cfg.for_pixel_pitch(float(detector.pixel_pitch))
    instrument = SyntheticInstrument(detector, inst_cfg, seed=args.seed)
    model = cfg.build_model()
    samples = {}
    t0 = time.perf_counter()
    for stem, frame in cfg.build_frames():
        brdf = instrument.render_brdf(model, frame)
        nd = args.nd if args.nd is not None else choose_nd_filters(
            lambda stack, b=brdf, f=frame: instrument.sample_flux(b, f, stack), instrument
        )
        samples[stem] = (brdf, frame, nd)
        console.print(f"{stem}: sample ND filters '{nd or 'none'}'", markup=False)
    console.print(
        f"brdfjax synthesize: {cfg.source} -> {args.out}: {len(samples)} sample(s), "
        f"effects on: {', '.join(inst_cfg.enabled_effects())}",
        markup=False,
    )
    beam_nd = choose_nd_filters(instrument.beam_flux, instrument)
    console.print(f"beam signature: ND filters '{beam_nd}'", markup=False)
    try:
        manifest = instrument.write_set(
            args.out, samples, beam_filters=beam_nd, calibration=Calibration(nd_tolerances={3.0: ND_3_TOLERANCE})
        )
    except (OSError, ValueError) as e:
        _error(prog, str(e))
        return EXIT_FAILURE
    console.print(f"wrote {manifest} ({time.perf_counter() - t0:.1f} s)", markup=False)
    return EXIT_OK


#: Subcommands by name; later issues add fit, sample, diagnose and capture here.
COMMANDS: dict[str, Command] = {
    "simulate": Command(
        "simulate",
        "render the frames of a config to OpenEXR + PNG + summary.json",
        _simulate_arguments,
        _run_simulate,
    ),
    "synthesize": Command(
        "synthesize",
        "measure a config's model with the synthetic instrument: raw OpenEXR stacks + manifest.toml",
        _synthesize_arguments,
        _run_synthesize,
    ),
    "reduce": Command(
        "reduce",
        "reduce a raw measurement set (manifest.toml) to calibrated BRDF frames with per-pixel uncertainty",
        _reduce_arguments,
        _run_reduce,
    ),
    "fit": Command(
        "fit",
        "fit a model to frames/tables from a TOML fit config: result.json (parameters, uncertainties, chi2) + figures",
        lambda p: __import__("brdfjax.fit.cli_fit", fromlist=["add_arguments"]).add_arguments(p),
        lambda a: __import__("brdfjax.fit.cli_fit", fromlist=["run"]).run(a),
    ),
    "diagnose": Command(
        "diagnose",
        "diagnose the gap between a base model and measured frames: where, which effect, how far it shrinks",
        lambda p: __import__("brdfjax.diagnose.cli", fromlist=["add_arguments"]).add_arguments(p),
        lambda a: __import__("brdfjax.diagnose.cli", fromlist=["run"]).run(a),
    ),
    "capture": Command(
        "capture",
        "run a capture plan (beam signature, alignment, samples) on the simulated bench or lab hardware: raw set",
        lambda p: __import__("brdfjax.devices.capture", fromlist=["capture_arguments"]).capture_arguments(p),
        lambda a: __import__("brdfjax.devices.capture", fromlist=["run_capture_command"]).run_capture_command(a),
    ),
    "sample": Command(
        "sample",
        "parameter posteriors with emcee from a fit config ([sample] table): chain.h5, posterior.json, corner/trace plots",
        lambda p: __import__("brdfjax.sample.cli", fromlist=["add_arguments"]).add_arguments(p),
        lambda a: __import__("brdfjax.sample.cli", fromlist=["run"]).run(a),
    ),
}


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="brdfjax",
        description="Differentiable near-specular BRDF models and CCD scatterometer frames in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"brdfjax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for cmd in COMMANDS.values():
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``brdfjax`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    return args._run(args)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
