"""Model presets for the seed's other materials (Chapter V): mirror, polished aluminium, Kapton.

The seed measured a broadband mirror, a circularly polished aluminium disk and
an unwrinkled Kapton sheet (§5.1-5.3) but fitted no model to them; it reports
their peak BRDF values and that the mirror's peak is symmetric and
beam-limited ("remarkably similar to the beam signature") while the
aluminium's and Kapton's are asymmetric (anisotropic, "more detailed
quantitative analysis ... saved for other work").  The presets below are
therefore *plausible* models, not fits: their shapes follow the seed's
descriptions and their weights ``rho_s`` are set so that the specular pixel's
BRDF after the beam footprint is of the order of the seed's peak values
(mirror 2.50e6 sr^-1 at theta_i = 20 deg, aluminium 4.57e5 at 40 deg, Kapton
1.63e5 at 60 deg); widths and orientations are assumptions (stated on each
builder).

Anisotropic distributions (``BeckmannAniso``, ``GGXAniso``) have their axes
along the sample's x and y; the orientation of a groove pattern is the
:class:`~brdfjax.core.terms.Oriented` wrapper's angle ``psi``, which turns any term about the
sample normal (the distribution's x axis lies at azimuth ``psi`` from +x
toward +y).  Fresnel and Q do not depend on the azimuth, so turning the
term is exactly turning its microfacet distribution.
"""

from __future__ import annotations

import numpy as np

from ..runtime.choices import check_choices
from .distributions import Beckmann, BeckmannAniso, GGXAniso
from .terms import SEED_FORM, Lambertian, Model, Oriented, Specular

__all__ = ["Oriented", "mirror", "polished_aluminium", "kapton", "MIRROR", "POLISHED_ALUMINIUM", "KAPTON"]


def _deg(x: float) -> float:
    return float(np.deg2rad(x))


#: Aluminium at 632.8 nm (complex index n + i k; Rakic 1995): the mirror's coating and the disk.
ALUMINIUM_INDEX = (1.37, 7.62)
#: Kapton (polyimide) at 632.8 nm, real index.
KAPTON_INDEX = 1.70

#: Mirror: a narrow isotropic Beckmann peak (slope width 5e-5, a scatter-angle 1/e half-width of
#: 1.4e-4 rad, narrower than the beam footprint's 2.1e-4 rad: beam-limited), aluminium coating.
MIRROR: dict[str, float] = {"m": 5e-5, "rho_s": 0.80, "n": ALUMINIUM_INDEX[0], "k": ALUMINIUM_INDEX[1]}
#: Polished aluminium: anisotropic Beckmann, slope widths 6e-4 across and 2e-4 along the grooves
#: (assumed), grooves turned 30 deg (assumed: the spot's position on the circular polish sets it).
POLISHED_ALUMINIUM: dict[str, float] = {
    "mx": 6e-4, "my": 2e-4, "psi": _deg(30.0), "rho_s": 0.63, "n": ALUMINIUM_INDEX[0], "k": ALUMINIUM_INDEX[1],
}
#: Kapton: anisotropic GGX (widths 5e-4 and 2e-4, orientation -20 deg: assumed) and a Lambertian
#: floor for the "more evenly diffuse pattern" the seed notes (rho_d 0.02, assumed).
KAPTON: dict[str, float] = {
    "alpha_x": 5e-4, "alpha_y": 2e-4, "psi": _deg(-20.0), "rho_s": 0.90, "n": KAPTON_INDEX, "rho_d": 0.02,
}


def _check(name: str, defaults: dict[str, float], overrides: dict[str, float]) -> dict[str, float]:
    check_choices("parameter", sorted(overrides), defaults, error=KeyError, prefix=f"{name}: ")
    return {**defaults, **overrides}


def mirror(**overrides: float) -> Model:
    """Broadband mirror (seed §5.1): one narrow isotropic Beckmann peak, beam-limited.

    Fit it with the beam footprint as instrument function (``FrameData.footprint``):
    the measured peak is mostly the beam's.  Parameters ``m, rho_s, n, k``.
    """
    p = _check("mirror", MIRROR, overrides)
    return Model(
        terms={"specular": Specular(Beckmann(p["m"]), rho_s=p["rho_s"], n=p["n"], k=p["k"], **SEED_FORM)},
        aliases=(("m", "specular.m"), ("rho_s", "specular.rho_s"), ("n", "specular.n"), ("k", "specular.k")),
    )


def polished_aluminium(**overrides: float) -> Model:
    """Circularly polished aluminium (seed §5.2): an anisotropic Beckmann peak turned by ``psi``.

    Parameters ``mx, my`` (rms slopes along the turned x and y axes), ``psi``
    (rad), ``rho_s, n, k``.
    """
    p = _check("polished_aluminium", POLISHED_ALUMINIUM, overrides)
    spec = Specular(BeckmannAniso(p["mx"], p["my"]), rho_s=p["rho_s"], n=p["n"], k=p["k"], **SEED_FORM)
    return Model(
        terms={"specular": Oriented(spec, psi=p["psi"])},
        aliases=tuple((k, f"specular.{k}") for k in ("mx", "my", "psi", "rho_s", "n", "k")),
    )


def kapton(**overrides: float) -> Model:
    """Unwrinkled Kapton (seed §5.3): an anisotropic GGX peak turned by ``psi`` plus a Lambertian floor.

    Parameters ``alpha_x, alpha_y, psi, rho_s, n, rho_d``.
    """
    p = _check("kapton", KAPTON, overrides)
    spec = Specular(GGXAniso(p["alpha_x"], p["alpha_y"]), rho_s=p["rho_s"], n=p["n"], **SEED_FORM)
    return Model(
        terms={"specular": Oriented(spec, psi=p["psi"]), "diffuse": Lambertian(p["rho_d"])},
        aliases=(
            ("alpha_x", "specular.alpha_x"), ("alpha_y", "specular.alpha_y"), ("psi", "specular.psi"),
            ("rho_s", "specular.rho_s"), ("n", "specular.n"), ("rho_d", "diffuse.rho_d"),
        ),
    )
