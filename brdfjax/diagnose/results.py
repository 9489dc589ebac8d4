"""The results of a diagnosis: :class:`Diagnosis` (the ``diagnosis.json`` contract and the reports),
:class:`Candidate` (one effect at one step) and :class:`Step` (one step of the explanation path).

The engine (:mod:`brdfjax.diagnose.engine`) builds them; :mod:`brdfjax.diagnose.report`
renders them (it imports this module only for type names).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..fit import FitResult
from ..io import atomic_output
from .report import html_report, markdown_report, noise_line, truth_line
from .zones import Region, zone_label

__all__ = ["Candidate", "Step", "Diagnosis", "json_ready", "finite_or_none"]



def finite_or_none(x: Any) -> Any:
    """``x`` as a float, or None when it is missing, not a number or not finite (JSON has no NaN)."""
    if x is None:
        return None
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def json_ready(obj: Any) -> Any:
    """``obj`` with every value JSON can hold (numbers finite or None, keys strings, tuples lists)."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_ready(v) for v in obj]
    if isinstance(obj, bool | str) or obj is None:
        return obj
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return finite_or_none(obj)
    return str(obj)


@dataclass
class Candidate:
    """One candidate effect at one step: applicability, signature and the refit with it."""

    effect: str
    title: str
    status: str  # "ranked", "skipped", "not identifiable", "failed", "not retried", "not refitted"
    note: str = ""
    side: str = "material"  # "material" (the surface) or "instrument" (the measurement)
    # reasons a ranked candidate may not enter the path (a new parameter on its bound, another term driven to
    # zero, its signature below the presence threshold); empty: admissible
    flags: list[str] = field(default_factory=list)
    parameters: dict[str, Any] = field(default_factory=dict)  # the effect's own parameters after the refit
    signature: dict[str, Any] = field(default_factory=dict)  # value, score, detail
    n_new: int = 0
    delta_chi2: float = math.nan
    delta_bic: float = math.nan
    gap_after: dict[str, float] = field(default_factory=dict)
    zones_after: dict[str, dict[str, float]] = field(default_factory=dict)
    wall_s: float = 0.0
    # "delta_bic" (the refit's BIC gain), "detection" (the effect's own detection, e.g. an unresolved peak),
    # "explanation" (held by the search's final explanation: ranked before the candidates it does without) or
    # "specific" (a specific effect the data require beside the generic one that gains most: ranked before it)
    ranked_by: str = "delta_bic"
    # "warm" (refitted from the model it extends, at its optimum) or "fresh" (from the fresh starts: kept because
    # it ended lower; the engine does it where the fit moved far from its starts)
    refit_start: str = "warm"
    # whether the refit was retried from a second start (its first attempt failed)
    retried: bool = False
    # not serialised: the refit's state, to continue the path from it
    state: Any = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        return json_ready(
            {
                "effect": self.effect,
                "title": self.title,
                "status": self.status,
                "note": self.note,
                "side": self.side,
                "admissible": self.status == "ranked" and not self.flags,
                "flags": self.flags,
                "ranked_by": self.ranked_by,
                "refit_start": self.refit_start,
                "retried": self.retried,
                "parameters": self.parameters,
                "delta_chi2": self.delta_chi2,
                "delta_bic": self.delta_bic,
                "signature": self.signature,
                "n_new": self.n_new,
                "chi2_reduced_after": self.gap_after.get("chi2_reduced"),
                "rms_log10_after": self.gap_after.get("rms_log10"),
                "zones_after": {k: v["chi2_reduced"] for k, v in self.zones_after.items()},
                "wall_s": self.wall_s,
            }
        )


@dataclass
class Step:
    """One step of the explanation path (the base, then each accepted effect)."""

    effect: str
    gap: dict[str, float]
    zones: dict[str, dict[str, float]]
    heldout: dict[str, float] | None
    delta_bic: float = math.nan
    parameters: dict[str, Any] = field(default_factory=dict)  # every parameter: {value, sigma, unit, free, initial}
    action: str = "add"  # "base", "add" (the effect entered) or "remove" (backward elimination took it out)
    side: str = ""  # "material" or "instrument" (empty for the base)
    flags: list[str] = field(default_factory=list)  # e.g. the held-out gap grew at this step
    notes: list[str] = field(default_factory=list)  # the joint refit from fresh starts, the close alternatives
    alternatives: list[dict[str, Any]] = field(default_factory=list)  # runners-up: effect, delta_bic, margin

    def to_dict(self) -> dict[str, Any]:
        return json_ready(
            {
                "effect": self.effect,
                "action": self.action,
                "side": self.side,
                "flags": self.flags,
                "notes": self.notes,
                "alternatives": self.alternatives,
                "chi2": self.gap["chi2"],
                "chi2_reduced": self.gap["chi2_reduced"],
                "rms_log10": self.gap["rms_log10"],
                "bic": self.gap["bic"],
                "n_free": self.gap["n_free"],
                "delta_bic": self.delta_bic,
                "heldout_rms_log10": None if self.heldout is None else self.heldout["rms_log10"],
                "heldout_chi2_reduced": None if self.heldout is None else self.heldout["chi2_reduced"],
                # free parameters the fitted data do not determine on which the held-out prediction depends
                "heldout_undetermined": None if self.heldout is None else self.heldout.get("undetermined"),
                "zones": {k: v["chi2_reduced"] for k, v in self.zones.items()},
                "parameters": self.parameters,
            }
        )


@dataclass
class Diagnosis:
    """Everything a diagnosis found; :meth:`to_dict` is the ``diagnosis.json`` contract, :meth:`write` the reports."""

    gap: dict[str, Any]
    regions: list[Region]
    block_names: list[str]
    ranking: list[Candidate]  # ranked candidates at the first step, best first
    skipped: list[Candidate]  # not applicable / not identifiable / failed, with the reason
    path: list[Step]
    significant: bool
    bic_threshold: float
    notes: list[str]
    timings: dict[str, float]
    settings: dict[str, Any]
    context: Any = field(default=None, repr=False)  # the base fit's Context
    final_context: Any = field(default=None, repr=False)
    path_rankings: list[list[Candidate]] = field(default_factory=list, repr=False)
    base_result: FitResult | None = field(default=None, repr=False)
    final_result: FitResult | None = field(default=None, repr=False)
    stop_reason: str = ""  # why the path stopped adding effects
    final_effects: list[tuple[str, str]] = field(default_factory=list)  # (effect, side) in the final model
    final_config: str | None = None  # the final model as a fit config (TOML), where the config path knows it
    final_params: dict[str, Any] = field(default_factory=dict, repr=False)  # the final fit's spec (bounds)
    # the generator's truth evaluated on the fitted frames (nothing fitted), where the truth is known (a config's
    # [diagnose.truth], a benchmark's generator): chi2_reduced, rms_log10, n_points, final_over_truth
    truth_gap: dict[str, Any] | None = None

    def set_truth_gap(self, gap: dict[str, Any], source: str = "") -> None:
        """Record the truth's own gap on the fitted frames and the final model's reduced chi^2 relative to it."""
        g = dict(gap)
        final = self.path[-1].gap["chi2_reduced"] if self.path else math.nan
        t = float(g.get("chi2_reduced", math.nan))
        g["final_chi2_reduced"] = final
        g["final_over_truth"] = final / t if t > 0 and math.isfinite(t) else math.nan
        g["within_20pct"] = bool(abs(g["final_over_truth"] - 1.0) <= 0.2) if math.isfinite(g["final_over_truth"]) else None
        if source:
            g["source"] = source
        self.truth_gap = g

    @property
    def zones(self) -> list[dict[str, Any]]:
        return [r.to_dict(self.block_names[r.block]) | {"label": zone_label(r, k)} for k, r in enumerate(self.regions)]

    @property
    def explained_by(self) -> list[str]:
        """The effects of the final model, in the order they entered (effects removed again are left out)."""
        return [e for e, _ in self.final_effects]

    def effects_by_side(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {"material": [], "instrument": []}
        for e, side in self.final_effects:
            out.setdefault(side, []).append(e)
        return out

    def to_dict(self) -> dict[str, Any]:
        return json_ready(
            {
                "gap": self.gap,
                "sigma_estimated": bool(self.gap.get("sigma_estimated")),
                "noise": noise_line(self.gap),
                "zones": self.zones,
                "ranking": [c.to_dict() for c in self.ranking],
                "skipped": [c.to_dict() for c in self.skipped],
                "path": [s.to_dict() for s in self.path],
                "path_rankings": [[c.to_dict() for c in r] for r in self.path_rankings],
                "significant": self.significant,
                "explained_by": self.explained_by,
                "explained_by_side": self.effects_by_side(),
                "stop_reason": self.stop_reason,
                "truth": self.truth_gap,
                "bic_threshold": self.bic_threshold,
                "blocks": self.block_names,
                "notes": self.notes,
                "timings_s": self.timings,
                "settings": self.settings,
            }
        )

    def to_json(self, path: str | os.PathLike | None = None, indent: int = 2) -> str:
        text = json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        if path is not None:
            _atomic_write(Path(path), text + "\n")
        return text

    def summary(self) -> str:
        lines = [
            f"base: chi2_reduced {self.gap['chi2_reduced']:.4g}, rms_log10 {self.gap['rms_log10']:.4g}"
            + ("" if self.gap.get("heldout_rms_log10") is None else f", held-out rms_log10 {self.gap['heldout_rms_log10']:.4g}")
        ]
        lines.append(noise_line(self.gap))
        for _k, z in enumerate(self.zones[:6]):
            lines.append(f"  zone {z['label']}: share {z['share']:.1%}, centre {z['center_deg'][0]:+.3g}/{z['center_deg'][1]:+.3g} deg, {z['sign']}")
        for c in self.ranking[:6]:
            by = ("  (ranked by its detection: " + str(c.signature.get("detail", "")) + ")" if c.ranked_by == "detection"
                  else "  (required beside the generic effect of larger gain: ranked before it)"
                  if c.ranked_by == "specific" else "  (in the final model: ranked before the effects it does without)"
                  if c.ranked_by == "explanation" else "")
            lines.append(f"  {c.effect:<22s} dBIC {c.delta_bic:12.1f}  dchi2 {c.delta_chi2:12.1f}  signature {c.signature.get('score', math.nan):.3g}{by}")
        lines.append("path: " + " -> ".join(f"{_step_name(s)} ({s.gap['chi2_reduced']:.3g})" for s in self.path))
        by = self.effects_by_side()
        lines.append(f"material effects: {', '.join(by['material']) or 'none'}; instrument effects: {', '.join(by['instrument']) or 'none'}")
        lines.append(f"stopped: {self.stop_reason}")
        if self.truth_gap is not None:
            lines.append(truth_line(self.truth_gap))
        for s in self.path:
            for f in s.flags:
                lines.append(f"  flag at {_step_name(s)}: {f}")
        lines.append(f"significant: {self.significant}")
        return "\n".join(lines)

    def write(self, out_dir: str | os.PathLike, *, figures: bool = True) -> dict[str, Path]:
        """Write ``diagnosis.json``, ``report.md`` and ``report.html`` (figures embedded) into ``out_dir``, atomically."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {"json": out / "diagnosis.json", "md": out / "report.md", "html": out / "report.html"}
        self.to_json(paths["json"])
        if self.final_config is not None:
            paths["config"] = out / "final_model.toml"
            _atomic_write(paths["config"], self.final_config)
        _atomic_write(paths["md"], markdown_report(self))
        _atomic_write(paths["html"], html_report(self, figures=figures))
        return paths


def _step_name(s: Step) -> str:
    return {"base": "base", "add": f"+{s.effect}", "remove": f"-{s.effect}"}.get(s.action, s.effect)


def _atomic_write(path: Path, text: str) -> None:
    with atomic_output(path) as tmp:
        tmp.write_text(text)
