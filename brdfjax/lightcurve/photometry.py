"""Magnitude systems and bands for predicted satellite brightness (NumPy).

A prediction is an irradiance ``E`` at the observer in units of the solar
irradiance at 1 AU (what :func:`~brdfjax.lightcurve.engine.facet_flux`
returns).  A band turns it into a magnitude::

    m = m_sun(band) - 2.5 log10(E / E_sun(1 AU))

with ``m_sun`` the apparent magnitude of the Sun at 1 AU in that band
(:data:`BANDS`).  Whether ``E`` carries the ``(AU / d_sun)^2`` factor of the
Sun's true distance is the photometric *convention*
(:class:`Photometry`): ``"physical"`` keeps it (the Sun is 3 % brighter in
January than in July); ``"lumos"`` drops it, as lumos-sat does (its
irradiance is a constant 1360 W m^-2 everywhere), to reproduce predictions
made with lumos-sat.

Solar magnitudes (Willmer 2018, ApJS 236, 47, table 3: apparent magnitudes of
the Sun at 1 AU):

=========  ======  ============================================================
band       m_sun   meaning
=========  ======  ============================================================
V          -26.76  Johnson V, Vega system
CLEAR      -26.76  an unfiltered CMOS/CCD magnitude reported on the V scale
                   (SCORE's ``CLEAR`` filter, MMT-9 magnitudes): taken as V
VISUAL     -26.76  a naked-eye estimate against V comparison stars: taken as V
G          -26.90  Gaia G (Vega)
g          -26.52  SDSS g (AB)
r          -26.96  SDSS r (AB)
i          -27.05  SDSS i (AB)
AB532      -27.056 lumos-sat's "AB magnitude": the irradiance of a 1360 W m^-2
                   Sun taken as monochromatic at 532 nm (``F_nu = E lambda /
                   c`` with ``c = 3e8``) against 3631 Jy
AB         -27.056 the same (the Slingshot set's ``measured_ab`` is on it)
=========  ======  ============================================================

``CLEAR`` and ``VISUAL`` as V is an approximation (an unfiltered silicon
sensor is redder than V; the colour term of a grey satellite is ~0.1-0.3
mag): the bands say how the comparison is made, they do not remove it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..runtime.errors import InputError

__all__ = ["BANDS", "BandError", "Band", "Photometry", "lumos_ab_sun_magnitude", "band"]

#: lumos-sat's constants: solar irradiance (W m^-2), wavelength (m), speed of light (m/s).
LUMOS_SUN_IRRADIANCE, LUMOS_WAVELENGTH, LUMOS_C = 1360.0, 532e-9, 3.0e8


def lumos_ab_sun_magnitude() -> float:
    """lumos-sat's AB magnitude of the Sun at 1 AU: ``-2.5 log10(1360 * 532e-9 / (3e8 * 3631e-26))``."""
    return -2.5 * math.log10(LUMOS_SUN_IRRADIANCE * LUMOS_WAVELENGTH / (LUMOS_C * 3631e-26))


@dataclass(frozen=True)
class Band:
    name: str
    sun_magnitude: float
    system: str  # "Vega" or "AB"
    note: str


BANDS: dict[str, Band] = {
    b.name: b
    for b in (
        Band("V", -26.76, "Vega", "Johnson V (Willmer 2018)"),
        Band("CLEAR", -26.76, "Vega", "unfiltered magnitudes reported on the V scale, taken as V"),
        Band("VISUAL", -26.76, "Vega", "visual estimates against V comparison stars, taken as V"),
        Band("G", -26.90, "Vega", "Gaia G (Willmer 2018)"),
        Band("g", -26.52, "AB", "SDSS g (Willmer 2018)"),
        Band("r", -26.96, "AB", "SDSS r (Willmer 2018)"),
        Band("i", -27.05, "AB", "SDSS i (Willmer 2018)"),
        Band("AB532", lumos_ab_sun_magnitude(), "AB", "lumos-sat's AB: 1360 W m^-2 at 532 nm against 3631 Jy"),
        Band("AB", lumos_ab_sun_magnitude(), "AB", "as AB532 (lumos-sat's AB convention)"),
    )
}


class BandError(InputError):
    """An unknown band name; the message names where it came from and the known bands."""


def band(name: str, where: str = "band") -> Band:
    """The :class:`Band` called ``name`` (exact, then case-insensitive); :class:`BandError` naming ``where``."""
    if name in BANDS:
        return BANDS[name]
    up = name.strip().upper()
    if up in BANDS and up != "G":  # 'v', 'clear', 'ab' ...; the one-letter SDSS/Gaia names stay case-sensitive
        return BANDS[up]
    raise BandError(f"{where}: unknown band '{name}'; known: {', '.join(BANDS)} (map others with the config's 'bands' table)")


@dataclass(frozen=True)
class Photometry:
    """How irradiance becomes magnitude: ``convention`` "physical" (with ``(AU/d_sun)^2``) or "lumos" (without)."""

    convention: str = "physical"

    def __post_init__(self):
        if self.convention not in ("physical", "lumos"):
            raise InputError(f"photometry.convention = '{self.convention}'; expected 'physical' or 'lumos'")

    def magnitude(self, flux: np.ndarray, sun_magnitudes: np.ndarray) -> np.ndarray:
        """Magnitudes of ``flux`` (units of E_sun(1 AU), already with or without the distance factor)."""
        with np.errstate(divide="ignore"):
            return np.asarray(sun_magnitudes) - 2.5 * np.log10(np.asarray(flux))
