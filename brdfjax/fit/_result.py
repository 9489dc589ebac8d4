"""The result of a fit and its JSON form (the output contract of ``brdfjax fit``).

``FitResult.to_json()`` writes at least ``parameters`` (name -> ``{"value",
"sigma", "unit", "free"}`` in natural units: angles in degrees with unit
"deg"), ``chi2``, ``chi2_reduced``, ``dof``, ``converged``, ``message``,
``n_iterations`` and ``wall_s``; beside them the correlation matrix, the
loss, per-block statistics, whether the model was convolved with an
instrument function, warnings and versions.  Non-finite numbers are written
as ``null`` (JSON has no NaN); a fixed parameter's sigma is ``null``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..io import atomic_output
from ._common import natural_unit, to_natural

__all__ = ["ParameterEstimate", "BlockSummary", "FitResult"]


def _num(x: Any) -> Any:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _clean(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, float | np.floating):
        return _num(x)
    return x


@dataclass(frozen=True)
class ParameterEstimate:
    """One parameter in stored units (rad, m, 1, sr^-1); :meth:`natural` converts for reports."""

    value: float
    sigma: float | None  # None for fixed parameters
    unit: str
    free: bool
    initial: float

    def natural(self) -> dict[str, Any]:
        f = to_natural(self.unit)
        return {
            "value": _num(self.value * f),
            "sigma": None if self.sigma is None else _num(self.sigma * f),
            "unit": natural_unit(self.unit),
            "free": self.free,
            "initial": _num(self.initial * f),
        }


@dataclass(frozen=True)
class BlockSummary:
    """Fit statistics of one data block (a frame or a table), and of groups within it (tables: per theta_i)."""

    name: str
    kind: str  # "frame" or "table"
    n_points: int
    chi2: float
    log_rms: float  # rms of log(f_model) - log(d_data), natural log
    convolved: bool
    groups: tuple[dict[str, Any], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "n_points": self.n_points,
            "chi2": _num(self.chi2),
            "log_rms": _num(self.log_rms),
            "convolved": self.convolved,
            "groups": [{k: (_num(v) if isinstance(v, float) else v) for k, v in g.items()} for g in self.groups],
        }


@dataclass(frozen=True, eq=False)
class FitResult:
    """Everything a fit found; ``models``/``frames`` are the fitted core objects per block."""

    parameters: dict[str, ParameterEstimate]
    free_names: tuple[str, ...]
    covariance: np.ndarray  # stored units, free parameters
    correlation: np.ndarray
    chi2: float
    dof: int
    n_points: int
    converged: bool
    status: str  # a SolveStatus value
    message: str
    n_iterations: int
    wall_s: float
    solver: str
    loss: str
    loss_scale: float
    cost: float
    n_downweighted: int
    covariance_absolute: bool
    precision: str
    blocks: tuple[BlockSummary, ...]
    warnings: tuple[str, ...]
    versions: dict[str, str]
    timings: dict[str, float] = field(default_factory=dict)
    models: tuple[Any, ...] = ()
    frames: tuple[Any, ...] = ()
    residuals: tuple[np.ndarray, ...] = ()  # per block, raw (non-robust) weighted residuals
    weights: tuple[np.ndarray, ...] = ()  # per block, IRLS weights rho'(r)/r
    auto_init: dict[str, Any] = field(default_factory=dict)
    # The noise model: {"estimated": False} when every block has its uncertainties; else the estimated
    # log-normal scatter of ln BRDF (``sigma_ln``), the blocks and points it covers and how it was found.
    noise: dict[str, Any] = field(default_factory=lambda: {"estimated": False})
    # -2 ln L up to a data-only constant: chi2 with known uncertainties; with estimated noise the profile
    # ``chi2_other + N ln(RSS/N) + N`` (NaN: not computed -- then chi2 stands in).
    neg2_log_likelihood: float = math.nan
    # Parameters the data do not determine (an unresolved peak): name -> {"reason", "range", ...}.
    undetermined: dict[str, Any] = field(default_factory=dict)
    # Systematic errors as nuisance parameters: their priors and each parameter's conditional sigma
    # (nuisance held at the optimum); empty without nuisance parameters.
    nuisance: dict[str, Any] = field(default_factory=dict)

    @property
    def chi2_reduced(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    @property
    def sigma_estimated(self) -> bool:
        """Whether the noise of some block was estimated from the residuals (no uncertainties given)."""
        return bool(self.noise.get("estimated"))

    @property
    def m2ll(self) -> float:
        """``-2 ln L`` (up to a data-only constant): the information criteria's measure of misfit."""
        return self.chi2 if not math.isfinite(self.neg2_log_likelihood) else self.neg2_log_likelihood

    @property
    def convolved(self) -> bool:
        """Whether the model was convolved with an instrument function (footprint) in any block."""
        return any(b.convolved for b in self.blocks)

    def value(self, name: str) -> float:
        """A parameter's value in stored units (rad, m, ...)."""
        return self._get(name).value

    def sigma(self, name: str) -> float | None:
        return self._get(name).sigma

    def truth_warnings(self, truth: Mapping[str, float], n_sigma: float = 3.0) -> list[str]:
        """A warning for every free parameter whose ``truth`` (stored units) lies outside ``n_sigma`` of the estimate.

        For synthetic demos, where the truth is known: a truth that far out
        means the reported sigma misses an error the data carry (a model
        or instrument effect the fit does not describe), not bad luck
        (``n_sigma = 3``: 0.3 % of honest cases).  A name of a per-frame
        parameter (``phi_ref``) checks every frame's entry.
        """
        out = []
        for name, p in self.parameters.items():
            base = name.split("[")[0]
            t = truth.get(name, truth.get(base))
            if not p.free or t is None or p.sigma is None or not (p.sigma > 0 and math.isfinite(p.sigma)):
                continue
            pull = (p.value - float(t)) / p.sigma
            if abs(pull) > n_sigma:
                f, unit = to_natural(p.unit), natural_unit(p.unit)
                out.append(
                    f"the truth of '{name}' ({float(t) * f:.6g} {unit}) lies {pull:+.1f} sigma from the estimate "
                    f"({p.value * f:.6g} +- {p.sigma * f:.3g} {unit}): the sigma misses an error the data carry "
                    "(an effect the model or the reduction does not describe), not noise"
                )
        return out

    def _get(self, name: str) -> ParameterEstimate:
        if name not in self.parameters:
            raise KeyError(f"unknown parameter '{name}'; known: {', '.join(self.parameters)}")
        return self.parameters[name]

    def to_dict(self) -> dict[str, Any]:
        params = {k: p.natural() for k, p in self.parameters.items()}
        cond = self.nuisance.get("sigma_conditional", {}) if self.nuisance else {}
        for k, s in cond.items():
            f = to_natural(self.parameters[k].unit)
            params[k]["sigma_conditional"] = _num(s * f)
            marg = params[k]["sigma"]
            params[k]["sigma_systematic"] = None if marg is None or not math.isfinite(s) else _num(
                math.sqrt(max(marg**2 - (s * f) ** 2, 0.0))
            )
        out = {
            "parameters": params,
            "chi2": _num(self.chi2),
            "chi2_reduced": _num(self.chi2_reduced),
            "dof": int(self.dof),
            "n_points": int(self.n_points),
            "n_free": len(self.free_names) - len(self.nuisance.get("parameters", {}) if self.nuisance else {}),
            "n_nuisance": len(self.nuisance.get("parameters", {}) if self.nuisance else {}),
            "converged": bool(self.converged),
            "status": self.status,
            "message": self.message,
            "n_iterations": int(self.n_iterations),
            "wall_s": _num(self.wall_s),
            "timings_s": {k: _num(v) for k, v in self.timings.items()},
            "solver": self.solver,
            "loss": {
                "name": self.loss,
                "scale": _num(self.loss_scale),
                "cost": _num(self.cost),
                "n_downweighted": int(self.n_downweighted),
            },
            "covariance_absolute": self.covariance_absolute,
            "sigma_estimated": self.sigma_estimated,
            "noise": {k: (_num(v) if isinstance(v, float) else v) for k, v in self.noise.items()},
            "neg2_log_likelihood": _num(self.m2ll),
            "goodness_of_fit": (
                "not available: the noise was estimated from the residuals, so chi2_reduced is ~1 by construction"
                if self.sigma_estimated else "chi2_reduced (the data's own uncertainties)"
            ),
            "undetermined": _clean(self.undetermined),
            "correlation": {
                "names": list(self.free_names),
                "matrix": [[_num(x) for x in row] for row in np.asarray(self.correlation)],
            },
            "instrument_function": {
                "convolved": self.convolved,
                "blocks": [b.name for b in self.blocks if b.convolved],
            },
            "blocks": [b.to_dict() for b in self.blocks],
            "warnings": list(self.warnings),
            "precision": self.precision,
            "versions": dict(self.versions),
        }
        if self.nuisance:
            out["nuisance"] = {
                "parameters": self.nuisance.get("parameters", {}),
                "chi2_prior": _num(self.nuisance.get("chi2_prior")),
                "note": self.nuisance.get("note", ""),
            }
        return out

    def to_json(self, path: str | os.PathLike | None = None, indent: int = 2) -> str:
        """The JSON text; written (atomically) to ``path`` when given."""
        text = json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        if path is not None:
            with atomic_output(path) as tmp:
                tmp.write_text(text + "\n", encoding="utf-8")
        return text

    def summary(self) -> str:
        """A short human-readable table of the parameters in natural units."""
        if self.sigma_estimated:
            gof = (f"sigma ESTIMATED from the residuals: sigma_ln = {self.noise['sigma_ln']:.4g} (x{math.exp(self.noise['sigma_ln']):.3g}); "
                   f"-2 ln L = {self.m2ll:.6g}, dof = {self.dof} (chi2_reduced is 1 by construction, not a goodness of fit)")
        else:
            gof = f"chi2 = {self.chi2:.6g}, dof = {self.dof}, chi2_reduced = {self.chi2_reduced:.4g}"
        lines = [
            f"{'converged' if self.converged else 'NOT converged'}: {self.message}",
            f"{gof}, {self.n_iterations} iterations, {self.wall_s:.2f} s ({self.solver}, loss {self.loss})",
        ]
        for name, p in self.parameters.items():
            d = p.natural()
            sig = "fixed" if d["sigma"] is None and not p.free else f"+- {d['sigma']:.3g}" if d["sigma"] is not None else "+- inf"
            if name in self.undetermined:
                u = self.undetermined[name]
                sig = f"NOT determined: {u.get('range_text', '')}"
            cond = (self.nuisance or {}).get("sigma_conditional", {}).get(name)
            extra = "" if cond is None else f" (without systematics +- {cond * to_natural(p.unit):.3g})"
            lines.append(f"  {name:<22s} {d['value']:>14.6g} {sig:<14s} {d['unit']}{extra}")
        lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)
