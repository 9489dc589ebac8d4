"""Device interfaces of the scatterometer bench (typing Protocols, checked at run time).

The capture plans (:mod:`brdfjax.devices.plans`, :mod:`brdfjax.devices.capture`)
talk to the hardware only through these few interfaces, so the same plan
drives the simulated instrument (:mod:`brdfjax.devices.simulated`, the
default) and the pylablib adapters for the seed's Thorlabs hardware
(:mod:`brdfjax.devices.lab`).  Units are SI and radians throughout; every
motion call blocks until the motion is finished.

=================== ================================================================
interface           role on the seed's bench (seed Chapter III)
=================== ================================================================
:class:`Camera`     the CCD: exposure time, frame averaging, black level, one
                    averaged frame with its metadata
:class:`RotationStage`  sample incidence theta_i, detector arm theta_c, the sample's
                    rotation about its normal phi_ref (manual in the seed)
:class:`TranslationStage` the camera's stages: along its optical axis (yaw/pitch
                    alignment, seed §3.4) and across it (centring)
:class:`FilterChanger`  the ND filter stack in front of the camera (or a prompt)
:class:`Shutter`    the beam block: closed = laser blocked (background frames)
:class:`SpecimenMount` the sample in or out of the beam (out: beam signature)
:class:`PowerMeter` optical power, W (source monitoring)
=================== ================================================================

:class:`Bench` groups one of each; :func:`check_bench` names any device that
does not satisfy its interface.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ..core.detector import Detector
from ..runtime.errors import InputError

__all__ = [
    "CameraFrame",
    "Camera",
    "RotationStage",
    "TranslationStage",
    "FilterChanger",
    "Shutter",
    "SpecimenMount",
    "PowerMeter",
    "Bench",
    "DeviceError",
    "check_bench",
    "bench_detector",
]


class DeviceError(InputError, RuntimeError):
    """A device failed.  ``retryable`` says whether repeating the same call is safe (e.g. a read timeout).

    A refusal of the bench, not a bug: the command exits 2 with the message (``brdfjax.runtime.errors``).
    """

    def __init__(self, message: str, *, retryable: bool = False):
        super().__init__(message)
        self.retryable = retryable


@dataclass(frozen=True)
class CameraFrame:
    """One frame as the camera returns it (the average of ``n_frames`` frames).

    ``counts``: float32 ``(n_v, n_h)`` mean digital counts, black level
    included; ``counts_std``: per-frame standard deviation or ``None``;
    ``exposure_s``, ``n_frames``, ``black_level`` (counts), ``full_scale``
    (counts); ``metadata``: anything else the camera reports (timestamps,
    frame counters, temperature).
    """

    counts: np.ndarray
    exposure_s: float
    n_frames: int
    black_level: float
    full_scale: float
    counts_std: np.ndarray | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    """The CCD.  ``shape`` is ``(n_v rows, n_h columns)``; ``pixel_pitch`` in metres."""

    @property
    def shape(self) -> tuple[int, int]: ...

    @property
    def full_scale(self) -> float: ...

    def set_exposure(self, exposure_s: float) -> float:
        """Set the exposure (integration) time, s; returns the time actually set."""
        ...

    def get_exposure(self) -> float: ...

    def set_frame_averaging(self, n_frames: int) -> int:
        """Set how many frames each :meth:`read_frame` averages; returns the number set."""
        ...

    def get_frame_averaging(self) -> int: ...

    def get_black_level(self) -> float: ...

    def set_black_level(self, counts: float) -> float: ...

    def read_frame(self) -> CameraFrame:
        """Acquire and return one averaged frame (blocks)."""
        ...


@runtime_checkable
class RotationStage(Protocol):
    """A rotation stage, angles in radians."""

    def move_to(self, angle_rad: float) -> None:
        """Move to an absolute angle and wait until the motion has finished."""
        ...

    def get_position(self) -> float: ...


@runtime_checkable
class TranslationStage(Protocol):
    """A linear stage, positions in metres."""

    def move_to(self, position_m: float) -> None: ...

    def get_position(self) -> float: ...


@runtime_checkable
class FilterChanger(Protocol):
    """The ND filters in front of the camera, as a stack of nominal ODs, e.g. ``"4.0+1.0+0.2"`` (``""``: none)."""

    def available_stacks(self) -> tuple[str, ...]:
        """The stacks this changer can put in the beam, in increasing OD."""
        ...

    def set_filters(self, stack: str) -> None: ...

    def get_filters(self) -> str: ...


@runtime_checkable
class Shutter(Protocol):
    """The beam block.  ``close()`` blocks the laser (background frames), ``open()`` lets it through."""

    def open(self) -> None: ...

    def close(self) -> None: ...

    def is_open(self) -> bool: ...


@runtime_checkable
class SpecimenMount(Protocol):
    """Whether the sample is in the beam (out: the beam goes straight to the arm, beam signature)."""

    def set_in_beam(self, in_beam: bool) -> None: ...

    def in_beam(self) -> bool: ...


#: The older name of :class:`SpecimenMount` ("sample" is also the posterior package).
SampleMount = SpecimenMount


@runtime_checkable
class PowerMeter(Protocol):
    """An optical power meter: power in W at the set wavelength (m)."""

    def read_power(self) -> float: ...

    def set_wavelength(self, wavelength_m: float) -> None: ...


#: Bench slot -> the interface its device must satisfy.
SLOTS: dict[str, type] = {
    "camera": Camera,
    "sample_theta": RotationStage,
    "arm": RotationStage,
    "sample_phi": RotationStage,
    "camera_axial": TranslationStage,
    "camera_vertical": TranslationStage,
    "filters": FilterChanger,
    "shutter": Shutter,
    "sample_mount": SpecimenMount,
    "power_meter": PowerMeter,
}


@dataclass
class Bench:
    """One device per role.  ``pixel_pitch`` (m, ``(d_h, d_v)``) and ``distance`` (R, m) describe the camera
    on the arm; ``wavelength`` (m) the source.  ``power_meter`` and ``camera_vertical`` may be ``None``."""

    camera: Camera
    sample_theta: RotationStage
    arm: RotationStage
    sample_phi: RotationStage
    camera_axial: TranslationStage
    filters: FilterChanger
    shutter: Shutter
    sample_mount: SpecimenMount
    pixel_pitch: tuple[float, float]
    distance: float
    wavelength: float = 632.8e-9
    camera_vertical: TranslationStage | None = None
    power_meter: PowerMeter | None = None
    name: str = "bench"

    def describe(self) -> dict[str, str]:
        return {slot: type(getattr(self, slot)).__name__ for slot in SLOTS if getattr(self, slot) is not None}


def check_bench(bench: Bench) -> list[str]:
    """Problems with a bench: every device that does not satisfy its interface, by slot (empty when fine)."""
    out = []
    for slot, proto in SLOTS.items():
        dev = getattr(bench, slot)
        if dev is None:
            if slot in ("power_meter", "camera_vertical"):
                continue
            out.append(f"{slot}: missing (needs a {proto.__name__})")
        elif not isinstance(dev, proto):
            missing = [m for m in _members(proto) if not hasattr(dev, m)]
            out.append(f"{slot}: {type(dev).__name__} is not a {proto.__name__} (missing: {', '.join(missing)})")
    return out


def _members(proto: type) -> list[str]:
    return sorted(n for n in vars(proto) if not n.startswith("_"))


def bench_detector(bench: Bench, alignment: Mapping[str, Any] | None, shape: tuple[int, int], theta_c: Any = None) -> Detector:
    """The :class:`~brdfjax.Detector` of ``bench``'s camera: its pitch and distance, the arm at ``theta_c``.

    ``alignment`` (the capture's ``roll_deg``, ``yaw_deg``, ``pitch_deg``,
    ``m_h_px``, ``m_v_px``; missing ones 0) gives the misalignment.
    """
    al = alignment or {}
    return Detector(
        shape=(int(shape[0]), int(shape[1])), pixel_pitch=bench.pixel_pitch[0], pixel_pitch_v=bench.pixel_pitch[1],
        distance=bench.distance, theta_c=theta_c,
        roll=math.radians(al.get("roll_deg", 0.0)), yaw=math.radians(al.get("yaw_deg", 0.0)),
        pitch=math.radians(al.get("pitch_deg", 0.0)), m_h=al.get("m_h_px", 0.0), m_v=al.get("m_v_px", 0.0),
    )
