"""Systematic errors as named nuisance parameters of the likelihood (seed Chapter IV).

A reduced frame's ``sigma_rel`` is the quadrature total of every contribution
of the seed's budget (Eq 71), but several of them are one error shared by
every pixel of a frame -- or of several frames: the ND filters' OD tolerances
(Eq 97), the incident flux's temporal fluctuation and non-linearity (Eq 93,
96), the common level of the camera's response curve.  Counted as
independent per-pixel noise they shrink by ``sqrt(n_pixels)``; left out they
vanish.  Here each is a parameter of the likelihood with a Gaussian prior from
the instrument's calibration, and every point of a frame moves with it:

======================  ==================================================  ============================
parameter               effect on ``log f`` of frame k                      prior (standard deviation)
======================  ==================================================  ============================
``nd[<OD>]``            ``ln(10) (n_beam,k - n_sample,k) delta``: one        the filter's OD tolerance
                        physical filter's OD error ``delta``; a filter in    (manifest ``[calibration]``,
                        both the beam-signature and the sample stack         seed §4.3; ``nd_tolerance =
                        cancels (Eq 87), frames sharing it share it          "rectangular"``: tol / sqrt 3)
``flux[<frame>]``       ``+ s``: the incident flux of that measurement       ``sqrt(u_temporal^2 +
                                                                            u_incident_nonlinearity^2)``
``nonlinearity``        ``+ s``, shared by every frame: the common level of  the curve's largest error,
                        the response curve (§4.2)                            times the residual fraction
                                                                            after a correction
======================  ==================================================  ============================

(a second physical filter of one nominal OD in a stack is ``nd[<OD>#2]``).
The data model is ``d = f exp(sum_j D_kj s_j)`` (``D`` the design above), so
the weighted log residual of a point gains ``(D s)_k / sigma_rel``; the priors
are extra residual rows ``s_j / sigma_j``: a Gauss-Newton solver, the
covariance, the sampler's likelihood (``-sum r^2 / 2``) and its gradient all
see the same function.  The per-pixel ``sigma_rel`` must then carry only what
is independent from pixel to pixel (``sigma = "noise"`` or ``"pixel"``, with
``sigma_floor`` for the per-pixel gain scatter), never ``"total"``.

:func:`conditional_sigma` gives each physical parameter's uncertainty with the
nuisance parameters held at their optimum (what the data alone say), beside the
marginal one (systematics included) from the full covariance.
"""

from __future__ import annotations

import difflib
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array
from pydantic import Field, PrivateAttr, field_validator

from ..config import StrictModel, check_choice
from ..instrument.nd import ND_3_TOLERANCE, SEED_ND_TOLERANCES, parse_nd_filters
from ..instrument.reduce import SEED_CURVE_RESIDUAL
from ._common import FitInputError

__all__ = [
    "ND_TOLERANCE_KINDS",
    "FrameSystematics",
    "NuisanceOptions",
    "NuisanceSpec",
    "NuisanceTerms",
    "systematics_from_attrs",
    "build_nuisance",
    "conditional_sigma",
    "default_nd_tolerances",
]

#: How an OD tolerance becomes a prior's standard deviation: the seed's Eq 97 takes it as one
#: ("standard"); "rectangular" takes it as the half-width of a uniform distribution (GUM: tol / sqrt 3).
ND_TOLERANCE_KINDS = ("standard", "rectangular")
LN10 = math.log(10.0)

#: The footprint's 1/e^2 width is known to about 4 %: the seed's 25 px focus (§3.3) against the 24 px that the
#: beam-signature peak of 3.82e6 sr^-1 implies (§3.8).
FOOTPRINT_REL_SIGMA = 0.04
#: ``[nuisance.alignment]`` key -> (Detector field, factor to stored units).  Misalignment of Eq 105.
ALIGNMENT_KEYS: dict[str, tuple[str, float]] = {
    "roll_deg": ("roll", math.pi / 180),
    "yaw_deg": ("yaw", math.pi / 180),
    "pitch_deg": ("pitch", math.pi / 180),
    "m_h_px": ("m_h", 1.0),
    "m_v_px": ("m_v", 1.0),
    "distance_m": ("distance", 1.0),
}
#: The seed's alignment accuracy: roll, yaw and pitch left after one alignment iteration (§3.4: 0.11, 0.062,
#: 0.025 deg); the peak offsets read from the peak pixel, to one pixel, per measurement (§4.4); the
#: sample-to-array distance to 5 mm (§4.4, Delta R).
SEED_ALIGNMENT: dict[str, float] = {
    "roll_deg": 0.11, "yaw_deg": 0.062, "pitch_deg": 0.025, "m_h_px": 1.0, "m_v_px": 1.0, "distance_m": 0.005,
}
#: Detector fields a misalignment nuisance parameter offsets, and whether it is per measurement (Eq 105: m_h, m_v
#: "vary independently for every specific measurement", the mounting's rotation and distance do not).
GEOMETRY_PER_FRAME = {"roll": False, "yaw": False, "pitch": False, "distance": False, "m_h": True, "m_v": True}
GEOMETRY_UNITS = {"roll": "rad", "yaw": "rad", "pitch": "rad", "distance": "m", "m_h": "px", "m_v": "px",
                  "footprint": "log-scale"}


def default_nd_tolerances() -> dict[float, float]:
    """The seed's OD tolerances (§4.3) plus the 3.0 OD filter's inferred one, as the synthetic manifest has."""
    return {**{round(float(k), 6): float(v) for k, v in SEED_ND_TOLERANCES.items()}, 3.0: float(ND_3_TOLERANCE)}


@dataclass(frozen=True)
class FrameSystematics:
    """What a reduced frame's header says about its frame-wide errors (relative, dimensionless)."""

    nd_beam: str
    nd_sample: str
    temporal: float
    incident_nonlinearity: float
    nonlinearity_level: float  # the response curve's common error left after the reduction

    @property
    def flux_sigma(self) -> float:
        return math.hypot(self.temporal, self.incident_nonlinearity)


def _curve_max(text: str) -> float:
    """Largest |error| of a curve written as ``"x:error,x:error"`` (the reduction's header attribute)."""
    out = 0.0
    for part in str(text).split(","):
        if ":" in part:
            try:
                out = max(out, abs(float(part.split(":")[1])))
            except ValueError:
                continue
    return out


def systematics_from_attrs(attrs: Mapping[str, Any]) -> FrameSystematics | None:
    """The frame-wide errors of a reduced frame (``None`` when its header has no ND stacks)."""
    if "nd_beam" not in attrs and "nd_sample" not in attrs:
        return None
    level = _curve_max(attrs.get("nonlinearity_curve", "") or "")
    if int(attrs.get("nonlinearity_corrected", 0) or 0):
        level *= SEED_CURVE_RESIDUAL
    return FrameSystematics(
        nd_beam=str(attrs.get("nd_beam", "") or ""),
        nd_sample=str(attrs.get("nd_sample", "") or ""),
        temporal=float(attrs.get("u_temporal", 0.0) or 0.0),
        incident_nonlinearity=float(attrs.get("u_incident_nonlinearity", 0.0) or 0.0),
        nonlinearity_level=float(level),
    )


class NuisanceOptions(StrictModel):
    """The ``[nuisance]`` table of a fit config (and :func:`brdfjax.fit.fit`'s ``nuisance`` option).

    ``enabled``: ``None`` (default) turns the nuisance parameters on when the
    frames carry their ND stacks (data through the instrument); ``nd``,
    ``flux``, ``nonlinearity``: which kinds; ``nd_tolerance``: how an OD
    tolerance becomes a standard deviation; ``nd_tolerances``: ``"OD" = +-OD``
    entries that replace or extend the manifest's ``[calibration]`` and the
    seed's table.
    """

    enabled: bool | None = Field(None, description="nuisance parameters on/off (default: on for frames with ND stacks)")
    nd: bool = Field(True, description="one OD offset per uncancelled physical ND filter")
    flux: bool = Field(True, description="one incident-flux scale per frame (temporal, incident non-linearity)")
    nonlinearity: bool = Field(True, description="the response curve's common level, shared by every frame")
    nd_tolerance: str = Field("standard", description=f"one of {', '.join(ND_TOLERANCE_KINDS)}")
    nd_tolerances: dict[str, float] = Field(default_factory=dict, description='"OD" = tolerance (+-OD, >= 0)')
    footprint: bool = Field(False, description="the beam footprint's width as a nuisance parameter (log-scale)")
    footprint_rel_sigma: float = Field(
        FOOTPRINT_REL_SIGMA, ge=0, description="prior sigma of the footprint width, relative (seed §3.3/§3.8: 24-25 px)"
    )
    misalignment: bool = Field(False, description="the detector's misalignment (Eq 105) as nuisance parameters")
    alignment: dict[str, float] = Field(
        default_factory=dict, description="alignment accuracies replacing the seed's: " + ", ".join(ALIGNMENT_KEYS)
    )
    # the calibration's table (a manifest's [calibration.nd_tolerances] over the seed's), set by with_calibration
    _calibration: dict[float, float] | None = PrivateAttr(default=None)

    def with_calibration(self, table: Mapping[float, float] | None) -> "NuisanceOptions":
        """A copy whose tolerances start from ``table`` (nominal OD -> +-OD) instead of the seed's."""
        out = self.model_copy()
        out._calibration = None if table is None else {round(float(k), 6): float(v) for k, v in table.items()}
        return out

    @field_validator("nd_tolerance")
    @classmethod
    def _kind(cls, v: str) -> str:
        return check_choice("nd_tolerance", v, ND_TOLERANCE_KINDS)

    @field_validator("nd_tolerances")
    @classmethod
    def _tolerances(cls, v: dict[str, float]) -> dict[str, float]:
        for k, tol in v.items():
            try:
                od = float(k)
            except ValueError:
                raise ValueError(f'key "{k}" is not a nominal OD like "3.0"') from None
            if not (math.isfinite(od) and od > 0):
                raise ValueError(f'key "{k}": the nominal OD must be a positive number')
            if not (math.isfinite(tol) and tol >= 0):
                raise ValueError(f'"{k}" = {tol!r}: an OD tolerance must be a finite number >= 0')
        return v

    @field_validator("alignment")
    @classmethod
    def _alignment(cls, v: dict[str, float]) -> dict[str, float]:
        for k, a in v.items():
            if k not in ALIGNMENT_KEYS:
                close = difflib.get_close_matches(k, ALIGNMENT_KEYS, n=1)
                hint = f"; did you mean '{close[0]}'?" if close else ""
                raise ValueError(f"unknown key '{k}'{hint} (known: {', '.join(ALIGNMENT_KEYS)})")
            if not (math.isfinite(a) and a >= 0):
                raise ValueError(f"{k} = {a!r}: an alignment accuracy must be a finite number >= 0 (0: not a parameter)")
        return v

    def alignment_sigmas(self) -> dict[str, float]:
        """Alignment accuracy per detector field, stored units (rad, px, m): the seed's, replaced by ``alignment``."""
        acc = {**SEED_ALIGNMENT, **self.alignment}
        return {ALIGNMENT_KEYS[k][0]: float(a) * ALIGNMENT_KEYS[k][1] for k, a in acc.items()}

    def tolerance_table(self, base: Mapping[float, float] | None = None) -> dict[float, float]:
        base = self._calibration if base is None else base
        table = default_nd_tolerances() if base is None else {round(float(k), 6): float(t) for k, t in base.items()}
        table.update({round(float(k), 6): float(t) for k, t in self.nd_tolerances.items()})
        return table


@dataclass(frozen=True)
class NuisanceSpec:
    """The nuisance parameters of one fit: names, priors and the design ``D`` (blocks x parameters)."""

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    prior_sigma: np.ndarray  # (q,) in the parameter's unit (OD for nd, log-scale otherwise)
    design: np.ndarray  # (n_blocks, q): d log f / d parameter
    notes: tuple[str, ...]
    # per parameter: the instrument quantity it offsets ("" for the log-scale ones above; "footprint" or a
    # Detector field), and (n_blocks, q) the blocks it acts on through that quantity
    geometry: tuple[str, ...] = ()
    acts_on: np.ndarray | None = None

    @property
    def size(self) -> int:
        return len(self.names)

    def geometry_of(self, j: int) -> str:
        return self.geometry[j] if self.geometry else ""

    def blocks_of(self, j: int) -> tuple[int, ...]:
        on = self.design[:, j] != 0
        if self.acts_on is not None:
            on = on | self.acts_on[:, j]
        return tuple(int(k) for k in np.flatnonzero(on))

    def unit_of(self, j: int) -> str:
        g = self.geometry_of(j)
        return GEOMETRY_UNITS[g] if g else ("OD" if self.kinds[j] == "nd" else "log-scale")

    def stored_unit(self, j: int) -> str:
        """The layout unit (radians are reported in degrees); "1" for the dimensionless ones."""
        u = self.unit_of(j)
        return u if u in ("rad", "m", "px") else "1"

    def describe(self) -> dict[str, Any]:
        out = {}
        for j, (n, k, s, note) in enumerate(zip(self.names, self.kinds, self.prior_sigma, self.notes)):
            u = self.unit_of(j)
            f = 180 / math.pi if u == "rad" else 1.0
            out[n] = {"kind": k, "prior": "normal", "prior_mu": 0.0, "prior_sigma": float(s) * f, "note": note,
                      "unit": "deg" if u == "rad" else u}
        return out


def _filters(spec: str) -> list[tuple[float, int]]:
    """Physical filters of a stack as (nominal OD, occurrence)."""
    seen: Counter = Counter()
    out = []
    for od in parse_nd_filters(spec or None):
        key = round(float(od), 6)
        out.append((key, seen[key]))
        seen[key] += 1
    return out


def _od_text(od: float) -> str:
    """``1.0`` -> ``"1.0"``, ``0.25`` -> ``"0.25"`` (as filters are written in stacks)."""
    text = f"{od:g}"
    return text if ("." in text or "e" in text) else text + ".0"


def _filter_name(key: tuple[float, int]) -> str:
    od, occ = key
    return f"nd[{_od_text(od)}]" if occ == 0 else f"nd[{_od_text(od)}#{occ + 1}]"


def build_nuisance(
    blocks: Sequence[Any],
    names: Sequence[str],
    options: NuisanceOptions,
    tolerances: Mapping[float, float] | None = None,
    *,
    source: str = "nuisance",
) -> NuisanceSpec | None:
    """The nuisance parameters of ``blocks`` (``None`` when there are none).

    ``tolerances``: nominal OD -> +-OD (default: the seed's plus the 3.0 OD
    filter's), extended by ``options.nd_tolerances``.  A tolerance in
    ``options.nd_tolerances`` for a filter no frame has, or a filter without a
    tolerance, raises :class:`FitInputError` naming ``source`` and the key.
    """
    systs = [getattr(b, "systematics", None) for b in blocks]
    if options.enabled is False or not any(s is not None for s in systs):
        return None
    table = options.tolerance_table(tolerances)
    n_blocks = len(blocks)
    cols: list[np.ndarray] = []
    out_names: list[str] = []
    kinds: list[str] = []
    sig: list[float] = []
    notes: list[str] = []
    factor = 1.0 if options.nd_tolerance == "standard" else 1.0 / math.sqrt(3.0)
    present: set[float] = set()
    for s in systs:
        if s is not None:
            present |= {od for od, _ in _filters(s.nd_beam)} | {od for od, _ in _filters(s.nd_sample)}
    for k in options.nd_tolerances:
        if round(float(k), 6) not in present:
            have = ", ".join(_od_text(od) for od in sorted(present)) or "none"
            raise FitInputError(
                f'{source}: nuisance.nd_tolerances."{k}": no frame\'s ND stacks have a {_od_text(float(k))} OD filter '
                f"(the beam and sample stacks have: {have}); remove the entry"
            )
    if options.nd:
        coef: dict[tuple[float, int], np.ndarray] = {}
        for k, s in enumerate(systs):
            if s is None:
                continue
            beam, sample = set(_filters(s.nd_beam)), set(_filters(s.nd_sample))
            for key in beam ^ sample:  # a filter in both stacks cancels (seed Eq 87, §4.3)
                coef.setdefault(key, np.zeros(n_blocks))[k] += LN10 * (1.0 if key in beam else -1.0)
        for key in sorted(coef):
            od = key[0]
            if od not in table:
                known = ", ".join(_od_text(x) for x in sorted(table))
                raise FitInputError(
                    f'{source}: the {_od_text(od)} OD filter has no tolerance (known: {known}); give it in the '
                    f'manifest\'s [calibration.nd_tolerances] or as nuisance.nd_tolerances."{_od_text(od)}"'
                )
            if table[od] == 0:
                continue
            cols.append(coef[key])
            out_names.append(_filter_name(key))
            kinds.append("nd")
            sig.append(table[od] * factor)
            notes.append(f"OD error of the {_od_text(od)} OD filter (tolerance +-{table[od]:g}, {options.nd_tolerance})")
    if options.flux:
        for k, s in enumerate(systs):
            if s is None or s.flux_sigma <= 0:
                continue
            c = np.zeros(n_blocks)
            c[k] = 1.0
            cols.append(c)
            out_names.append(f"flux[{names[k]}]")
            kinds.append("flux")
            sig.append(s.flux_sigma)
            notes.append("incident flux of the measurement: temporal fluctuation (Eq 96) and non-linearity (Eq 93)")
    if options.nonlinearity:
        levels = [s.nonlinearity_level for s in systs if s is not None]
        level = max(levels) if levels else 0.0
        if level > 0:
            cols.append(np.array([1.0 if s is not None else 0.0 for s in systs]))
            out_names.append("nonlinearity")
            kinds.append("nonlinearity")
            sig.append(level)
            notes.append("common level of the camera's response curve left after the reduction (§4.2)")
    geometry = [""] * len(cols)
    acts: list[np.ndarray] = [np.zeros(n_blocks, bool) for _ in cols]
    frames = [k for k, s in enumerate(systs) if s is not None]
    if options.footprint:
        with_fp = [k for k in frames if getattr(blocks[k], "footprint", None) is not None]
        if not with_fp:
            raise FitInputError(
                f"{source}: nuisance.footprint = true, but no frame with ND stacks has a beam footprint (data."
                "footprint_w_px, or the frame's footprint_w_px attribute); give the footprint or remove the key"
            )
        if options.footprint_rel_sigma > 0:
            on = np.zeros(n_blocks, bool)
            on[with_fp] = True
            cols.append(np.zeros(n_blocks))
            acts.append(on)
            geometry.append("footprint")
            out_names.append("footprint")
            kinds.append("footprint")
            sig.append(options.footprint_rel_sigma)
            notes.append("the beam footprint's 1/e^2 width, log-scale (w = w0 exp(s); seed §3.3, §3.8)")
    if options.misalignment:
        for field, sigma in options.alignment_sigmas().items():
            if sigma <= 0:
                continue
            groups = [[k] for k in frames] if GEOMETRY_PER_FRAME[field] else [frames]
            for g in groups:
                on = np.zeros(n_blocks, bool)
                on[g] = True
                cols.append(np.zeros(n_blocks))
                acts.append(on)
                geometry.append(field)
                out_names.append(f"{field}[{names[g[0]]}]" if GEOMETRY_PER_FRAME[field] else field)
                kinds.append("misalignment")
                sig.append(sigma)
                notes.append(f"detector misalignment: offset of {field} from nominal (Eq 105; seed §3.4, §4.4)")
    if not cols:
        return None
    return NuisanceSpec(tuple(out_names), tuple(kinds), np.array(sig, np.float64), np.stack(cols, axis=1), tuple(notes),
                        tuple(geometry), np.stack(acts, axis=1))


class NuisanceTerms(eqx.Module):
    """The nuisance parameters inside the traced problem: per-point offsets and prior rows."""

    index: Array  # (q,) positions of the nuisance parameters in the free vector
    design: Array  # (n_points, q) d log f / d parameter at every usable point, blocks in order
    inv_sigma: Array  # (n_points,) 1 / sigma_rel of every usable point
    prior_inv_sigma: Array  # (q,)

    @classmethod
    def build(cls, spec: NuisanceSpec, first: int, counts: Sequence[int], inv_sigma: Sequence[np.ndarray]) -> "NuisanceTerms":
        point_block = np.repeat(np.arange(len(counts)), counts)
        return cls(
            np.arange(first, first + spec.size, dtype=np.int32),
            spec.design[point_block],
            np.concatenate([np.asarray(s, np.float64) for s in inv_sigma]),
            1.0 / spec.prior_sigma,
        )

    @property
    def size(self) -> int:
        return int(self.index.shape[0])

    def apply(self, r: Array, x: Array) -> Array:
        """The data residuals with the nuisance offsets, followed by the prior rows."""
        s = x[self.index]
        shifted = r + (self.design @ s).astype(r.dtype) * self.inv_sigma.astype(r.dtype)
        return jnp.concatenate([shifted, (s * self.prior_inv_sigma).astype(r.dtype)])


def conditional_sigma(jac_v: np.ndarray, dx_dv: np.ndarray, keep: Sequence[int], factor: float = 1.0) -> np.ndarray:
    """Sigmas of the parameters ``keep`` with every other free parameter held at the optimum.

    The inverse of the ``keep`` block of ``J^T J`` (Gauss-Newton), in stored units.
    """
    keep = np.asarray(keep, int)
    if keep.size == 0:
        return np.zeros(0)
    J = np.asarray(jac_v, np.float64)[:, keep]
    d = np.asarray(dx_dv, np.float64)[keep]
    try:
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
    except np.linalg.LinAlgError:
        return np.full(keep.size, np.nan)
    return np.sqrt(np.clip(factor * np.diag(cov), 0.0, None)) * np.abs(d)


def check_sigma_choice(sigma: str, source: str) -> None:
    """``sigma = "total"`` already counts the frame-wide errors: with nuisance parameters it would count them twice."""
    if sigma == "total":
        raise FitInputError(
            f"{source}: data.sigma = 'total' carries the frame-wide errors (ND filters, incident flux) that the "
            "nuisance parameters model; use sigma = 'noise' or 'pixel' (with sigma_floor for the per-pixel gain "
            "scatter), or turn the nuisance parameters off with [nuisance] enabled = false"
        )
