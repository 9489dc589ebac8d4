"""Adapters from pylablib's Thorlabs classes onto the bench interfaces (``pip install brdfjax[lab]``).

**Untested on physical hardware.**  Each adapter is a thin mapping, tested
(``tests/devices/test_devices.py``) against pylablib 1.4's own classes with their
transport replaced: :class:`pylablib.devices.Thorlabs.KinesisMotor` talking
the APT protocol byte for byte to an emulated controller through a custom
pylablib comm backend, :class:`pylablib.devices.Thorlabs.PM160` talking SCPI
to an emulated meter the same way, and
:class:`pylablib.devices.Thorlabs.ThorlabsTLCamera` with the TSI SDK library
replaced (exposure, black level, sensor size and bit depth through the SDK
calls; frames from a stand-in for ``grab``).  Run them on the bench before
trusting them; report what differs.

=========================== =========================================== ======================
adapter                     pylablib class                              interface
=========================== =========================================== ======================
:class:`TLCameraAdapter`    ``Thorlabs.ThorlabsTLCamera`` (TSI cameras,  :class:`Camera`
                            e.g. the seed's 8051 CCD)
:class:`KinesisRotation`    ``Thorlabs.KinesisMotor`` with a rotation    :class:`RotationStage`
                            stage (scale in deg, e.g. ``"PRM1-Z8"``)
:class:`KinesisTranslation` ``Thorlabs.KinesisMotor`` with a linear      :class:`TranslationStage`
                            stage (scale in m, e.g. ``"MTS50-Z8"``)
:class:`PowerMeterAdapter`  ``Thorlabs.PM160`` (or any ``GenericPM``)    :class:`PowerMeter`
:class:`ManualFilters`,     an operator prompt (the seed changed ND     :class:`FilterChanger`,
:class:`ManualShutter`,     filters, blocked the beam, mounted the       :class:`Shutter`, ...
:class:`ManualMount`,       sample and set phi_ref by hand)
:class:`ManualRotation`
=========================== =========================================== ======================

pylablib is imported only when a lab bench is opened (:func:`open_lab_bench`).
pylablib errors become :class:`~brdfjax.devices.interfaces.DeviceError`:
timeouts and transport errors are ``retryable`` (every command the adapters
send is absolute -- move *to*, set exposure *to* -- so repeating it is safe),
any other device error (limit switch, motion error) is not.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from ..instrument.nd import ND_STACKS
from .interfaces import Bench, CameraFrame, DeviceError

__all__ = [
    "TLCameraAdapter",
    "KinesisRotation",
    "KinesisTranslation",
    "PowerMeterAdapter",
    "ManualFilters",
    "ManualShutter",
    "ManualMount",
    "ManualRotation",
    "ManualTranslation",
    "open_lab_bench",
]

_MOTION_FAULTS = ("motion_error", "hw_fw_lim", "hw_bk_lim", "overcurrent", "current_limit", "encoder_fault")


def _errors():
    from pylablib.core.devio.comm_backend import DeviceBackendError  # pylablib is optional: the [lab] extra
    from pylablib.devices.Thorlabs import ThorlabsError, ThorlabsTimeoutError  # the [lab] extra

    return ThorlabsTimeoutError, DeviceBackendError, ThorlabsError


def _wrap(what: str, fn: Callable, *args, **kwargs):
    """Call a pylablib method, mapping its errors to :class:`DeviceError` (timeouts/transport: retryable)."""
    timeout_err, backend_err, thorlabs_err = _errors()
    try:
        return fn(*args, **kwargs)
    except DeviceError:
        raise
    except (timeout_err, backend_err) as e:
        raise DeviceError(f"{what}: {type(e).__name__}: {e}", retryable=True) from e
    except thorlabs_err as e:
        raise DeviceError(f"{what}: {type(e).__name__}: {e}", retryable=False) from e


def _camera_errors():
    from pylablib.devices.Thorlabs import (  # pylablib is optional: the [lab] extra
        ThorlabsTLCameraError,
        ThorlabsTLCameraTimeoutError,
    )

    return ThorlabsTLCameraTimeoutError, ThorlabsTLCameraError


class TLCameraAdapter:
    """A Thorlabs TSI scientific camera (``ThorlabsTLCamera``) as a :class:`Camera`.

    Frame averaging is done here: :meth:`read_frame` grabs ``n_frames``
    frames and returns their mean and per-frame standard deviation (float32).
    ``full_scale`` is ``2**bit_depth - 1`` from the sensor info.
    """

    def __init__(self, cam, *, frame_timeout_s: float = 10.0):
        self.cam = cam
        self.frame_timeout_s = float(frame_timeout_s)
        self._n_frames = 1

    def _call(self, what, fn, *args, **kwargs):
        timeout_err, cam_err = _camera_errors()
        try:
            return fn(*args, **kwargs)
        except timeout_err as e:
            raise DeviceError(f"camera: {what}: {e}", retryable=True) from e
        except cam_err as e:
            raise DeviceError(f"camera: {what}: {e}", retryable=False) from e

    @property
    def shape(self) -> tuple[int, int]:
        width, height = self._call("detector size", self.cam.get_detector_size)
        return (int(height), int(width))

    @property
    def full_scale(self) -> float:
        info = self._call("sensor info", self.cam.get_sensor_info)
        return float(2 ** int(info.bit_depth) - 1)

    def set_exposure(self, exposure_s: float) -> float:
        self._call("set exposure", self.cam.set_exposure, float(exposure_s))
        return self.get_exposure()

    def get_exposure(self) -> float:
        return float(self._call("exposure", self.cam.get_exposure))

    def set_frame_averaging(self, n_frames: int) -> int:
        if int(n_frames) < 1:
            raise DeviceError(f"camera: frame averaging must be >= 1, got {n_frames!r}")
        self._n_frames = int(n_frames)
        return self._n_frames

    def get_frame_averaging(self) -> int:
        return self._n_frames

    def get_black_level(self) -> float:
        return float(self._call("black level", self.cam.get_black_level))

    def set_black_level(self, counts: float) -> float:
        return float(self._call("set black level", self.cam.set_black_level, int(round(counts))))

    def read_frame(self) -> CameraFrame:
        frames = self._call("grab", self.cam.grab, self._n_frames, frame_timeout=self.frame_timeout_s)
        stack = np.asarray(frames, dtype=np.float64)
        if stack.ndim == 2:
            stack = stack[None]
        if stack.shape[0] != self._n_frames:
            raise DeviceError(f"camera: grabbed {stack.shape[0]} of {self._n_frames} frames", retryable=True)
        std = stack.std(axis=0, ddof=1).astype(np.float32) if stack.shape[0] > 1 else None
        return CameraFrame(
            counts=stack.mean(axis=0).astype(np.float32), counts_std=std, exposure_s=self.get_exposure(),
            n_frames=self._n_frames, black_level=self.get_black_level(), full_scale=self.full_scale,
            metadata={"camera": "ThorlabsTLCamera"},
        )


class _Kinesis:
    _units = ""

    def __init__(self, motor, *, timeout_s: float = 60.0, label: str = "stage"):
        self.motor = motor
        self.timeout_s = float(timeout_s)
        self.label = label
        units = _wrap(f"{label}: scale units", motor.get_scale_units)
        if units != self._units:
            raise DeviceError(
                f"{label}: the KinesisMotor's position units are {units!r}, expected {self._units!r}; open it with "
                "the stage's name as scale (e.g. scale=\"PRM1-Z8\" for a rotation, \"MTS50-Z8\" for a translation)"
            )

    def _to_device(self, value: float) -> float:
        return value

    def _from_device(self, value: float) -> float:
        return value

    def move_to(self, value: float) -> None:
        target = self._to_device(value)
        _wrap(f"{self.label}: move_to", self.motor.move_to, target)
        _wrap(f"{self.label}: wait_move", self.motor.wait_move, timeout=self.timeout_s)
        status = _wrap(f"{self.label}: status", self.motor.get_status)
        bad = [s for s in status if s in _MOTION_FAULTS]
        if bad:
            raise DeviceError(f"{self.label}: motion to {value!r} ended with {bad}", retryable=False)

    def get_position(self) -> float:
        return self._from_device(float(_wrap(f"{self.label}: position", self.motor.get_position)))


class KinesisRotation(_Kinesis):
    """A Kinesis rotation stage (``KinesisMotor`` opened with a rotation stage's scale, degrees) in radians."""

    _units = "deg"

    def _to_device(self, value: float) -> float:
        return math.degrees(value)

    def _from_device(self, value: float) -> float:
        return math.radians(value)


class KinesisTranslation(_Kinesis):
    """A Kinesis linear stage (``KinesisMotor`` opened with a linear stage's scale, metres)."""

    _units = "m"


class PowerMeterAdapter:
    """A Thorlabs power meter (``PM160`` or any ``GenericPM``) as a :class:`PowerMeter`."""

    def __init__(self, pm):
        self.pm = pm

    def read_power(self) -> float:
        return float(_wrap("power meter: read", self.pm.get_power))

    def set_wavelength(self, wavelength_m: float) -> None:
        _wrap("power meter: wavelength", self.pm.set_wavelength, float(wavelength_m))


# --- operator prompts (what the seed did by hand) ---------------------------------------------------


class _Manual:
    def __init__(self, prompt: Callable[[str], str] = input):
        self._prompt = prompt

    def ask(self, text: str) -> None:
        self._prompt(f"[brdfjax capture] {text}; press Enter when done ")


class ManualFilters(_Manual):
    def __init__(self, stacks: Sequence[str] | None = None, prompt: Callable[[str], str] = input):
        super().__init__(prompt)
        self._stacks = tuple(stacks or ND_STACKS)
        self._current: str | None = None

    def available_stacks(self) -> tuple[str, ...]:
        return self._stacks

    def set_filters(self, stack: str) -> None:
        if stack != self._current:
            self.ask(f"put the ND stack '{stack or 'none'}' in front of the camera")
            self._current = stack

    def get_filters(self) -> str:
        return self._current or ""


class ManualShutter(_Manual):
    _open = False

    def open(self) -> None:
        if not self._open:
            self.ask("unblock the laser")
            self._open = True

    def close(self) -> None:
        if self._open:
            self.ask("block the laser")
            self._open = False

    def is_open(self) -> bool:
        return self._open


class ManualMount(_Manual):
    _in = True

    def set_in_beam(self, in_beam: bool) -> None:
        if bool(in_beam) != self._in:
            self.ask("mount the sample in the beam" if in_beam else "take the sample out of the beam")
            self._in = bool(in_beam)

    def in_beam(self) -> bool:
        return self._in


class ManualRotation(_Manual):
    def __init__(self, label: str, prompt: Callable[[str], str] = input):
        super().__init__(prompt)
        self.label, self._pos = label, 0.0

    def move_to(self, angle_rad: float) -> None:
        if angle_rad != self._pos:
            self.ask(f"set {self.label} to {math.degrees(angle_rad):.4f} deg")
            self._pos = float(angle_rad)

    def get_position(self) -> float:
        return self._pos


class ManualTranslation(ManualRotation):
    def move_to(self, position_m: float) -> None:  # type: ignore[override]
        if position_m != self._pos:
            self.ask(f"set {self.label} to {position_m * 1e3:.3f} mm")
            self._pos = float(position_m)


def open_lab_bench(lab, *, wavelength: float = 632.8e-9) -> Bench:
    """Open the seed's bench from an ``[instrument.lab]`` config (:class:`~brdfjax.devices.capture.LabConfig`)."""
    try:
        from pylablib.devices import Thorlabs  # pylablib is optional: the [lab] extra
    except ImportError as e:  # pragma: no cover - depends on the install
        raise DeviceError("the lab bench needs pylablib: pip install 'brdfjax[lab]'") from e

    def motor(st):
        return _wrap(f"Kinesis {st.serial}", Thorlabs.KinesisMotor, st.serial, scale=st.scale,
                     default_channel=st.channel)

    cam = TLCameraAdapter(Thorlabs.ThorlabsTLCamera(lab.camera_serial))
    pitch = lab.pixel_pitch_um * 1e-6
    return Bench(
        camera=cam,
        sample_theta=KinesisRotation(motor(lab.sample_theta), label="sample theta_i stage"),
        arm=KinesisRotation(motor(lab.arm), label="detector arm"),
        sample_phi=(KinesisRotation(motor(lab.sample_phi), label="sample phi_ref stage") if lab.sample_phi
                    else ManualRotation("phi_ref (sample rotation about its normal)")),
        camera_axial=(KinesisTranslation(motor(lab.camera_axial), label="camera axial stage") if lab.camera_axial
                      else ManualTranslation("the camera's axial micrometer")),
        filters=ManualFilters(),
        shutter=ManualShutter(),
        sample_mount=ManualMount(),
        power_meter=PowerMeterAdapter(Thorlabs.PM160(lab.power_meter)) if lab.power_meter else None,
        pixel_pitch=(pitch, pitch),
        distance=lab.distance_m,
        wavelength=wavelength,
        name="lab",
    )
