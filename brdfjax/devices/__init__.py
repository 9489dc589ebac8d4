"""The device layer: bench interfaces, the simulated bench (default), pylablib lab adapters, capture plans.

* :mod:`.interfaces` -- Protocols for the camera, rotation/translation stages, ND filters, beam block,
  sample mount and power meter; :class:`~.interfaces.Bench` groups them.
* :mod:`.simulated` -- :class:`~.simulated.SimulatedBench`, every interface driven by the synthetic instrument.
* :mod:`.lab` -- thin adapters onto pylablib's Thorlabs classes (``pip install brdfjax[lab]``; imported lazily;
  untested on physical hardware).
* :mod:`.plans` -- plan entries, the seed's OD rule and the damage interlock.
* :mod:`.alignment` -- the seed §3.4 alignment (roll, yaw, pitch).
* :mod:`.capture` -- ``brdfjax capture``: durable, resumable capture into the raw format.
* :mod:`.liveview` -- the live BRDF preview (window or PNG/HTML) .
"""

from .interfaces import (
    Bench,
    Camera,
    CameraFrame,
    DeviceError,
    FilterChanger,
    PowerMeter,
    RotationStage,
    Shutter,
    SpecimenMount,
    TranslationStage,
    bench_detector,
    check_bench,
)
from .plans import Interlock, InterlockError, Measurement
from .simulated import SimulatedBench

__all__ = [
    "Bench",
    "Camera",
    "CameraFrame",
    "DeviceError",
    "FilterChanger",
    "PowerMeter",
    "RotationStage",
    "SpecimenMount",
    "Shutter",
    "TranslationStage",
    "bench_detector",
    "check_bench",
    "Interlock",
    "InterlockError",
    "Measurement",
    "SimulatedBench",
]
