"""brdfjax: differentiable near-specular BRDF models and CCD scatterometer frames in JAX.

Public names are re-exported here from their modules (``bj.Specular``, ``bj.render``, ...); see the README
for a tour.  They are imported on first use (PEP 562 module ``__getattr__``): ``import brdfjax`` and the
command line's ``brdfjax --help`` / ``--version`` do not load JAX.
"""

from __future__ import annotations

import importlib
import warnings
from typing import TYPE_CHECKING, Any

from ._compat import MOVED as _MOVED, install as _install_moved_module_paths

__version__ = "0.1.0"

#: Public name -> (module, attribute); attribute ``None``: the module itself.
_EXPORTS: dict[str, tuple[str, str | None]] = {
    "distributions": (".core.distributions", None),
    "shadowing": (".core.shadowing", None),
    "Detector": (".core.detector", "Detector"),
    "PixelGrid": (".core.detector", "PixelGrid"),
    "incident_direction": (".core.detector", "incident_direction"),
    "GGX": (".core.distributions", "GGX"),
    "GTR": (".core.distributions", "GTR"),
    "AbstractDistribution": (".core.distributions", "AbstractDistribution"),
    "AshikhminShirley": (".core.distributions", "AshikhminShirley"),
    "BeardMaxwell": (".core.distributions", "BeardMaxwell"),
    "Beckmann": (".core.distributions", "Beckmann"),
    "BeckmannAniso": (".core.distributions", "BeckmannAniso"),
    "CosineLobe": (".core.distributions", "CosineLobe"),
    "GGXAniso": (".core.distributions", "GGXAniso"),
    "HyperCauchy": (".core.distributions", "HyperCauchy"),
    "Ribardiere": (".core.distributions", "Ribardiere"),
    "StudentT": (".core.distributions", "StudentT"),
    "StudentTAniso": (".core.distributions", "StudentTAniso"),
    "fresnel": (".core.fresnel", "fresnel"),
    "q_factor": (".core.fresnel", "q_factor"),
    "Directions": (".core.geometry", "Directions"),
    "direction": (".core.geometry", "direction"),
    "zenith_azimuth": (".core.geometry", "zenith_azimuth"),
    "Conditions": (".core.conditions", "Conditions"),
    "OUTPUTS": (".core.render", "OUTPUTS"),
    "evaluate_pixels": (".core.render", "evaluate_pixels"),
    "pixel_directions": (".core.render", "pixel_directions"),
    "render": (".core.render", "render"),
    "SEED_FORM": (".core.terms", "SEED_FORM"),
    "SOLAR_CELL_SEED": (".core.terms", "SOLAR_CELL_SEED"),
    "STANDARD_FORM": (".core.terms", "STANDARD_FORM"),
    "ABg": (".core.terms", "ABg"),
    "AbstractTerm": (".core.terms", "AbstractTerm"),
    "Binomial": (".core.terms", "Binomial"),
    "Diffraction": (".core.terms", "Diffraction"),
    "Lambertian": (".core.terms", "Lambertian"),
    "Lobe": (".core.terms", "Lobe"),
    "Model": (".core.terms", "Model"),
    "MultiLobeSpecular": (".core.terms", "MultiLobeSpecular"),
    "OffsetNormal": (".core.terms", "OffsetNormal"),
    "Oriented": (".core.terms", "Oriented"),
    "Phong": (".core.terms", "Phong"),
    "Specular": (".core.terms", "Specular"),
    "solar_cell": (".core.terms", "solar_cell"),
}

__all__ = ["__version__", *_EXPORTS]

#: Public names that moved: still served (for one release) with a DeprecationWarning naming the new spelling.
_DEPRECATED: dict[str, tuple[str, str]] = {
    "render_frame": ("render_frame", 'bj.render(model, frame, detector, outputs="all")'),
    "render_geometry": ("render_geometry", 'bj.render(None, frame, detector, outputs=("theta_s", "phi_s", "omega"))'),
    "render_sharded": ("render_sharded", 'bj.render(model, frame, detector, devices="all")'),
    "sample_directions": ("sample_directions", "bj.pixel_directions"),
}


def __getattr__(name: str) -> Any:
    """Import a public name (or a subpackage, ``bj.fit``) on first use and keep it on the package."""
    if name == "Frame":  # the measurement conditions' old name (a "frame" is an image everywhere else)
        warnings.warn("brdfjax.Frame is deprecated: use bj.Conditions (the measurement conditions: theta_i, phi_ref, "
                      "wavelength)", DeprecationWarning, stacklevel=2)
        return importlib.import_module(".core.conditions", __name__).Conditions
    if name in _DEPRECATED:  # not kept on the package: every use warns
        warnings.warn(f"brdfjax.{name} is deprecated: use {_DEPRECATED[name][1]}", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(".core.render", __name__), _DEPRECATED[name][0])
    if name in _EXPORTS:
        module, attr = _EXPORTS[name]
        value = importlib.import_module(module, __name__)
        if attr is not None:
            value = getattr(value, attr)
    elif f"{__name__}.{name}" in _MOVED:  # a module's old flat path as an attribute: its new place
        value = importlib.import_module(_MOVED[f"{__name__}.{name}"])
    elif not name.startswith("_"):
        try:
            value = importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # the same names, eagerly, for type checkers and IDEs
    from .core import distributions as distributions, shadowing as shadowing
    from .core.conditions import Conditions as Conditions
    from .core.detector import Detector as Detector, PixelGrid as PixelGrid, incident_direction as incident_direction
    from .core.distributions import (
        GGX as GGX,
        GTR as GTR,
        AbstractDistribution as AbstractDistribution,
        AshikhminShirley as AshikhminShirley,
        BeardMaxwell as BeardMaxwell,
        Beckmann as Beckmann,
        BeckmannAniso as BeckmannAniso,
        CosineLobe as CosineLobe,
        GGXAniso as GGXAniso,
        HyperCauchy as HyperCauchy,
        Ribardiere as Ribardiere,
        StudentT as StudentT,
        StudentTAniso as StudentTAniso,
    )
    from .core.fresnel import fresnel as fresnel, q_factor as q_factor
    from .core.geometry import Directions as Directions, direction as direction, zenith_azimuth as zenith_azimuth
    from .core.render import (
        OUTPUTS as OUTPUTS,
        evaluate_pixels as evaluate_pixels,
        pixel_directions as pixel_directions,
        render as render,
    )
    from .core.terms import (
        SEED_FORM as SEED_FORM,
        SOLAR_CELL_SEED as SOLAR_CELL_SEED,
        STANDARD_FORM as STANDARD_FORM,
        ABg as ABg,
        AbstractTerm as AbstractTerm,
        Binomial as Binomial,
        Diffraction as Diffraction,
        Lambertian as Lambertian,
        Lobe as Lobe,
        Model as Model,
        MultiLobeSpecular as MultiLobeSpecular,
        OffsetNormal as OffsetNormal,
        Oriented as Oriented,
        Phong as Phong,
        Specular as Specular,
        solar_cell as solar_cell,
    )

_install_moved_module_paths()
