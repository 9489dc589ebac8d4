"""Capture plans: what to measure, in which order, and the rules that keep the camera safe.

A plan is a list of :class:`Measurement` (beam signature, sample
measurements over ``(theta_i, phi_ref)`` with ``theta_c = theta_i``, and the
optional §3.4 alignment), each with its exposure bracket (1, 10, 100, 1000 ms
by default), frame averaging, ND stack (``"auto"``: chosen at the bench) and
a background (the same exposures with the beam blocked).

**OD selection** (:func:`probe_stack`): the seed's rule,
:func:`brdfjax.instrument.nd.select_stack` (the smallest OD that keeps the
brightest pixel unsaturated at the shortest exposure, ``peak rate x 10^-OD x
t_min + 2 x black level < 0.9 x full scale``), as ``brdfjax synthesize`` uses it.  At the bench the peak rate is measured,
not known: :func:`probe_stack` starts at the densest stack, takes a
shortest-exposure frame, and steps to thinner stacks only as far as the
measured peak (or, while it is buried in the noise, an upper bound of it)
proves safe, then applies the rule to the measured rate.

**Damage interlock** (:class:`Interlock`): the OD chosen for the beam
signature is the smallest OD at which the focused beam may reach the array.
Every step that exposes the array to the direct beam (sample out of the
beam: beam signature, alignment) is checked against it, and a thinner stack
is refused with :class:`InterlockError` unless the operator overrides it
explicitly (``[capture] override_interlock = true`` or
``--override-interlock``), which is logged and recorded in the manifest.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..instrument.nd import select_stack, stack_od
from ..runtime.errors import InputError

__all__ = [
    "DEFAULT_EXPOSURES_S",
    "Measurement",
    "InterlockError",
    "Interlock",
    "probe_stack",
    "ProbeResult",
]

#: The seed's exposure bracket, s.
DEFAULT_EXPOSURES_S: tuple[float, ...] = (1e-3, 1e-2, 1e-1, 1.0)
#: A probe peak is trusted once it is this many counts above the black level.
PROBE_MIN_SIGNAL = 200.0


@dataclass(frozen=True)
class Measurement:
    """One entry of a plan.  ``kind``: ``"beam"``, ``"sample"`` or ``"alignment"``; angles in radians."""

    name: str
    kind: str
    theta_i: float = 0.0
    phi_ref: float = 0.0
    theta_c: float = 0.0
    nd: str = "auto"
    exposures_s: tuple[float, ...] = DEFAULT_EXPOSURES_S
    n_frames: int = 32
    background: bool = True
    options: dict = field(default_factory=dict)

    @property
    def exposes_direct_beam(self) -> bool:
        """The sample is out of the beam and the arm looks into it: the focused beam reaches the array."""
        return self.kind in ("beam", "alignment")

    def files(self) -> tuple[str, str]:
        """The measurement file and its background file (names in the set's folder)."""
        if self.kind == "beam":
            return ("beam.exr", "beam_background.exr")
        return (f"{self.name}.exr", f"{self.name}_background.exr")


class InterlockError(InputError, RuntimeError):
    """A plan step refused by the damage interlock (the message says why and how to override); exit 2."""


class Interlock:
    """Refuses exposing the array to the focused beam through less OD than the seed's rule allows."""

    def __init__(self, *, override: bool = False, log: Callable[[str], None] | None = None):
        self.min_od: float | None = None
        self.min_stack: str | None = None
        self.evidence = ""
        self.override = bool(override)
        self.overridden: list[str] = []
        self._log = log or (lambda s: None)

    def establish(self, stack: str, evidence: str) -> None:
        self.min_stack, self.min_od, self.evidence = stack, stack_od(stack), evidence

    def check(self, stack: str, what: str) -> None:
        """Raise :class:`InterlockError` if ``stack`` is below the safe OD for a direct-beam step ``what``."""
        if self.min_od is None:
            raise InterlockError(
                f"interlock: refusing {what} through ND '{stack or 'none'}': the safe OD for the focused beam "
                "is not known yet (measure the beam signature with nd = \"auto\" first)"
            )
        od = stack_od(stack)
        if od + 1e-9 >= self.min_od:
            return
        msg = (
            f"interlock: refusing {what} through ND '{stack or 'none'}' (OD {od:g}): it would expose the array to "
            f"the focused beam below the smallest safe OD {self.min_od:g} ('{self.min_stack}'; {self.evidence}). "
            "Use nd = \"auto\" or a denser stack, or override explicitly with [capture] override_interlock = true "
            "or --override-interlock if the array can take it."
        )
        if not self.override:
            raise InterlockError(msg)
        note = f"OVERRIDDEN {msg}"
        self.overridden.append(note)
        self._log(note)


@dataclass(frozen=True)
class ProbeResult:
    stack: str
    peak_rate_unattenuated: float  # counts/s
    probes: tuple[tuple[str, float], ...]  # (stack, peak counts above black level)

    def evidence(self, t_min: float) -> str:
        s, p = self.probes[-1]
        return f"brightest pixel {p:.0f} counts above black at {t_min * 1e3:g} ms through '{s or 'none'}'"


def probe_stack(
    take_peak: Callable[[str], float],
    *,
    stacks: Sequence[str],
    t_min: float,
    black_level: float,
    full_scale: float,
) -> ProbeResult:
    """Choose a stack by measurement (module docstring).

    ``take_peak(stack)`` sets the stack, takes a frame at the shortest
    exposure and returns its brightest pixel minus the black level, counts.
    Never puts a stack in the beam that the measurements so far do not prove
    safe (predicted brightest pixel below 0.9 full scale).
    """
    ordered = sorted(stacks, key=stack_od)
    limit = 0.9 * full_scale - 2 * black_level
    i = len(ordered) - 1
    probes: list[tuple[str, float]] = []
    while True:
        stack = ordered[i]
        peak = float(take_peak(stack))
        probes.append((stack, peak))
        if peak + black_level >= 0.9 * full_scale and i == len(ordered) - 1:
            raise ValueError(
                f"the brightest pixel is saturated ({peak:.0f} counts above black) even through the densest stack "
                f"'{stack}'; add ND filters"
            )
        if peak >= PROBE_MIN_SIGNAL or i == 0:
            rate = max(peak, 1.0) / t_min * 10 ** stack_od(stack)
            chosen = select_stack(rate, t_min=t_min, black_level=black_level, full_scale=full_scale, stacks=stacks)
            return ProbeResult(chosen, rate, tuple(probes))
        # Buried or faint: the true peak is below max(peak, PROBE_MIN_SIGNAL); go as thin as that bound allows.
        bound = max(peak, PROBE_MIN_SIGNAL)
        j = i
        while j > 0 and bound * 10 ** (stack_od(stack) - stack_od(ordered[j - 1])) < limit:
            j -= 1
        if j == i:
            rate = bound / t_min * 10 ** stack_od(stack)
            chosen = select_stack(rate, t_min=t_min, black_level=black_level, full_scale=full_scale, stacks=stacks)
            return ProbeResult(chosen, rate, tuple(probes))
        i = j


def peak_above_black(counts: np.ndarray, black_level: float) -> float:
    """Brightest pixel minus the black level, counts (no filtering: a focused spot may be a few pixels wide)."""
    return float(np.max(np.asarray(counts, dtype=np.float32)) - black_level)

