"""Instrument layer: raw exposure stacks, synthetic CCD frames, reduction and uncertainty (seed Ch. III-IV)."""

from ..io.raw import (
    Exposure as Exposure,
    Manifest as Manifest,
    RawAttrs as RawAttrs,
    RawFormatError as RawFormatError,
    RawStack as RawStack,
    read_manifest as read_manifest,
    read_raw_exr as read_raw_exr,
    write_manifest as write_manifest,
    write_raw_exr as write_raw_exr,
)
from .reduce import (
    ReductionError as ReductionError,
    reduce_measurement as reduce_measurement,
    reduce_measurement_set as reduce_measurement_set,
)
from .synthetic import InstrumentConfig as InstrumentConfig, SyntheticInstrument as SyntheticInstrument
from .uncertainty import (
    brdf_uncertainty as brdf_uncertainty,
    geometry_uncertainty as geometry_uncertainty,
    optical_density_uncertainty as optical_density_uncertainty,
)
