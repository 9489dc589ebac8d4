"""The simulated scatterometer bench: every device interface, driven by the synthetic instrument.

:class:`SimulatedBench` wraps a :class:`brdfjax.instrument.synthetic.SyntheticInstrument`
(camera noise, non-linearity, dark, ambient, stray light, ND filters, beam
footprint) and a brdfjax model for the sample, and exposes the bench's
devices (:mod:`brdfjax.devices.interfaces`): the camera, the sample's
theta_i and phi_ref rotations, the detector arm, the camera's axial and
vertical translation stages, the ND filter changer, the beam block, the
sample mount and a power meter.  What the camera sees follows the bench's
state:

* beam blocked: ambient light only (a background frame);
* sample in the beam: the model rendered on the *true* detector (its
  misalignment included) at the arm's angle, through the ND stack
  (:meth:`SyntheticInstrument.sample_flux`);
* sample out: the focused beam (Gaussian footprint) where the direct beam
  meets the array (:func:`brdfjax.devices.alignment.spot_pixel`, so an arm
  slew or an axial translation moves the spot as the misalignment says),
  plus stray light and ambient.

It is the embedded default backend of ``brdfjax capture``.  Noise: every
frame draws from ``numpy.random.default_rng([seed, *key, n])`` where ``key``
is set by :meth:`SimulatedBench.seed_noise` (the capture passes the
measurement index and the exposure) and ``n`` counts frames since, so a
measurement's data do not depend on what ran before it -- a resumed capture
is bit-identical to an uninterrupted one.  ``faults`` injects device errors
for tests; ``frame_delay_s`` slows acquisition down (to interrupt a capture
mid-plan in tests).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence

import equinox as eqx
import numpy as np

from ..core.detector import Detector
from ..core.render import Conditions
from ..instrument.nd import ND_STACKS, parse_nd_filters
from ..instrument.synthetic import (
    InstrumentConfig,
    SyntheticInstrument,
    beam_flux_image,
)
from .alignment import spot_pixel
from .interfaces import Bench, CameraFrame, DeviceError

__all__ = ["SimulatedBench"]


class SimulatedBench:
    """A simulated bench (module docstring).  ``detector`` is the true camera geometry (``theta_c`` ignored).

    ``model``: the sample's brdfjax model; ``config``: the synthetic
    instrument's effects (use :meth:`InstrumentConfig.for_pixel_pitch` /
    ``coarse`` for a binned camera); ``seed``: noise seed.
    """

    def __init__(
        self,
        model,
        detector: Detector,
        config: InstrumentConfig | None = None,
        *,
        seed: int = 0,
        wavelength: float = 632.8e-9,
        stacks: Sequence[str] = ND_STACKS,
        source_power_w: float = 15e-3,
        frame_delay_s: float = 0.0,
        faults: Mapping[str, Sequence[int]] | None = None,
    ):
        self.model = model
        self.true_detector = detector.at(None)
        self.instrument = SyntheticInstrument(self.true_detector, config, seed=seed)
        self.seed = int(seed)
        self.wavelength = float(wavelength)
        self.stacks = tuple(stacks)
        self.source_power_w = float(source_power_w)
        self.frame_delay_s = float(frame_delay_s)
        self.faults = {k: set(v) for k, v in (faults or {}).items()}
        self.calls: dict[str, int] = {}
        # state
        self.theta_i = 0.0
        self.phi_ref = 0.0
        self.theta_c = 0.0
        self.axial = 0.0
        self.vertical = 0.0
        self.filters = self.stacks[-1]
        self.shutter_open = False
        self.sample_in = True
        self.exposure_s = float(self.instrument.config.exposures_s[0])
        self._noise_key: tuple[int, ...] = ()
        self._frame_no = 0
        self._brdf_cache: dict[tuple, np.ndarray] = {}
        self.frames_read = 0
        self.camera = _Camera(self)
        self.sample_theta = _Rotation(self, "theta_i", (0.0, math.radians(89.0)))
        self.arm = _Rotation(self, "theta_c", (math.radians(-10.0), math.radians(89.0)))
        self.sample_phi = _Rotation(self, "phi_ref", (-2 * math.pi, 2 * math.pi))
        self.camera_axial = _Translation(self, "axial", (0.0, 0.0254))
        self.camera_vertical = _Translation(self, "vertical", (-0.0127, 0.0127))
        self.filter_changer = _Filters(self)
        self.beam_block = _Shutter(self)
        self.sample_mount = _Mount(self)
        self.power_meter = _PowerMeter(self)

    # -- the bench ---------------------------------------------------------------------------
    def bench(self) -> Bench:
        d = self.true_detector
        return Bench(
            camera=self.camera,
            sample_theta=self.sample_theta,
            arm=self.arm,
            sample_phi=self.sample_phi,
            camera_axial=self.camera_axial,
            camera_vertical=self.camera_vertical,
            filters=self.filter_changer,
            shutter=self.beam_block,
            sample_mount=self.sample_mount,
            power_meter=self.power_meter,
            pixel_pitch=(float(d.pixel_pitch), float(d.pixel_pitch_v)),
            distance=float(d.distance),
            wavelength=self.wavelength,
            name="simulated",
        )

    def seed_noise(self, *key: int) -> None:
        """Seed the noise of the following frames from ``(seed, *key)`` (module docstring)."""
        self._noise_key = tuple(int(k) for k in key)
        self._frame_no = 0

    def _fault(self, what: str) -> None:
        n = self.calls.get(what, 0) + 1
        self.calls[what] = n
        if n in self.faults.get(what, ()):
            raise DeviceError(f"simulated {what} failure (call {n})", retryable=what == "read_frame")

    # -- light -------------------------------------------------------------------------------
    def _detector_now(self) -> Detector:
        d = self.true_detector
        if self.vertical:
            d = eqx.tree_at(lambda x: x.m_v, d, d.m_v + self.vertical / d.pixel_pitch_v)
        return d

    def light_rate(self) -> np.ndarray:
        """Counts/s reaching every pixel in the bench's current state, float32 ``(n_v, n_h)``."""
        ins = self.instrument
        shape = ins.shape
        if not self.shutter_open:
            flux = np.zeros(shape, np.float32)
            if ins.config.ambient.enabled:
                flux += ins.camera.ambient
            return flux
        det = self._detector_now()
        if self.sample_in:
            if not 0.0 <= self.theta_c < math.pi / 2:
                raise DeviceError(f"simulated arm at {math.degrees(self.theta_c):.3f} deg: no sample frame there")
            # Arrays, not Python floats: jitted code would recompile for every new angle.
            f64 = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
            frame = Conditions(f64(self.theta_i), f64(self.phi_ref), f64(self.wavelength))
            key = (self.theta_i, self.phi_ref, self.theta_c, self.vertical)
            ins.detector = det.at(f64(self.theta_c))
            if key not in self._brdf_cache:
                self._brdf_cache.clear()
                self._brdf_cache[key] = ins.render_brdf(self.model, frame)
            return ins.sample_flux(self._brdf_cache[key], frame, self.filters)
        d_h, d_v = float(det.pixel_pitch), float(det.pixel_pitch_v)
        n_h, n_v = spot_pixel(
            theta_c=self.theta_c, axial=self.axial, roll=float(det.roll), yaw=float(det.yaw),
            pitch=float(det.pitch), m_h=float(det.m_h), m_v=float(det.m_v),
            pixel_pitch=(d_h, d_v), distance=float(det.distance),
        )
        h_min, _, v_min, _ = det.index_range
        flux = ins.incident_flux(self.filters) * ins.drift()
        if math.isfinite(n_h) and ins.config.footprint.enabled:
            phi = beam_flux_image(shape, (n_v - v_min, n_h - h_min), ins.config.footprint.w_px, flux)
        else:
            phi = np.zeros(shape, np.float32)
        return ins.add_stray_and_ambient(phi)

    def read(self) -> CameraFrame:
        self._fault("read_frame")
        ins = self.instrument
        ins.rng = np.random.default_rng([self.seed, *self._noise_key, self._frame_no])
        self._frame_no += 1
        flux = self.light_rate()
        e = ins.expose(flux, self.exposure_s)
        self.frames_read += 1
        if self.frame_delay_s:
            time.sleep(self.frame_delay_s)
        cfg = ins.config
        return CameraFrame(
            counts=e.counts,
            counts_std=e.counts_std,
            exposure_s=self.exposure_s,
            n_frames=e.n_frames,
            black_level=cfg.black_level.counts if cfg.black_level.enabled else 0.0,
            full_scale=cfg.full_scale,
            metadata={
                "software": "brdfjax.devices.simulated",
                "synthetic_effects": ",".join(cfg.enabled_effects()),
                "frame_index": self.frames_read,
            },
        )


class _Device:
    def __init__(self, sim: SimulatedBench):
        self._sim = sim


class _Camera(_Device):
    @property
    def shape(self) -> tuple[int, int]:
        return self._sim.instrument.shape

    @property
    def full_scale(self) -> float:
        return self._sim.instrument.config.full_scale

    def set_exposure(self, exposure_s: float) -> float:
        if not exposure_s > 0:
            raise DeviceError(f"simulated camera: exposure must be positive, got {exposure_s!r} s")
        self._sim.exposure_s = float(exposure_s)
        return self._sim.exposure_s

    def get_exposure(self) -> float:
        return self._sim.exposure_s

    def set_frame_averaging(self, n_frames: int) -> int:
        ins = self._sim.instrument
        if int(n_frames) < 1:
            raise DeviceError(f"simulated camera: frame averaging must be >= 1, got {n_frames!r}")
        ins.config = ins.config.model_copy(update={"n_frames": int(n_frames)})
        return int(n_frames)

    def get_frame_averaging(self) -> int:
        return self._sim.instrument.config.n_frames

    def get_black_level(self) -> float:
        c = self._sim.instrument.config
        return c.black_level.counts if c.black_level.enabled else 0.0

    def set_black_level(self, counts: float) -> float:
        ins = self._sim.instrument
        ins.config = ins.config.model_copy(
            update={"black_level": ins.config.black_level.model_copy(update={"counts": float(counts)})}
        )
        return self.get_black_level()

    def read_frame(self) -> CameraFrame:
        return self._sim.read()

    def seed_noise(self, *key: int) -> None:
        self._sim.seed_noise(*key)


class _Rotation(_Device):
    def __init__(self, sim: SimulatedBench, attr: str, limits: tuple[float, float]):
        super().__init__(sim)
        self._attr, self._limits = attr, limits

    def move_to(self, angle_rad: float) -> None:
        self._sim._fault(f"move_{self._attr}")
        lo, hi = self._limits
        if not lo <= angle_rad <= hi:
            raise DeviceError(
                f"simulated {self._attr} stage: {math.degrees(angle_rad):.4f} deg is outside its travel "
                f"[{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg"
            )
        setattr(self._sim, self._attr, float(angle_rad))

    def get_position(self) -> float:
        return float(getattr(self._sim, self._attr))


class _Translation(_Rotation):
    def move_to(self, position_m: float) -> None:  # type: ignore[override]
        lo, hi = self._limits
        if not lo - 1e-12 <= position_m <= hi + 1e-12:
            raise DeviceError(
                f"simulated {self._attr} stage: {position_m * 1e3:.3f} mm is outside its travel "
                f"[{lo * 1e3:.1f}, {hi * 1e3:.1f}] mm"
            )
        setattr(self._sim, self._attr, float(position_m))


class _Filters(_Device):
    def available_stacks(self) -> tuple[str, ...]:
        return self._sim.stacks

    def set_filters(self, stack: str) -> None:
        if stack not in self._sim.stacks:
            raise DeviceError(f"simulated filter changer: no stack {stack!r}; available: {self._sim.stacks}")
        parse_nd_filters(stack)
        self._sim.filters = stack

    def get_filters(self) -> str:
        return self._sim.filters


class _Shutter(_Device):
    def open(self) -> None:
        self._sim.shutter_open = True

    def close(self) -> None:
        self._sim.shutter_open = False

    def is_open(self) -> bool:
        return self._sim.shutter_open


class _Mount(_Device):
    def set_in_beam(self, in_beam: bool) -> None:
        self._sim.sample_in = bool(in_beam)

    def in_beam(self) -> bool:
        return self._sim.sample_in


class _PowerMeter(_Device):
    def read_power(self) -> float:
        """The source power, W (15 mW HeNe, seed §3.1), when the beam is not blocked; 0 otherwise."""
        return self._sim.source_power_w if self._sim.shutter_open else 0.0

    def set_wavelength(self, wavelength_m: float) -> None:
        self._sim.wavelength = float(wavelength_m)
