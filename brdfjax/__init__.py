"""brdfjax: differentiable near-specular BRDF models and CCD scatterometer frames in JAX.

Public names are re-exported here from their modules; see the README for a tour.
"""

from ._compat import MOVED as _MOVED_MODULES, install as _install_moved_module_paths
from .core import distributions as distributions, shadowing as shadowing
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
    Frame as Frame,
    evaluate_pixels as evaluate_pixels,
    pixel_directions as pixel_directions,
    render as render,
)
from .core.terms import (
    SOLAR_CELL_SEED as SOLAR_CELL_SEED,
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

__version__ = "0.1.0"

#: Public names that moved: still served (for one release) with a DeprecationWarning naming the new spelling.
_MOVED_NAMES = {
    "render_frame": ("render", 'bj.render(model, frame, detector, outputs="all")'),
    "render_geometry": ("render_geometry", 'bj.render(None, frame, detector, outputs=("theta_s", "phi_s", "omega"))'),
    "render_sharded": ("render_sharded", 'bj.render(model, frame, detector, devices="all")'),
    "sample_directions": ("pixel_directions", "bj.pixel_directions"),
}


def __getattr__(name: str):
    if name in _MOVED_NAMES:
        import warnings  # noqa: PLC0415 -- only a deprecated name pays for it

        from .core import render as _render  # noqa: PLC0415 -- served on first use of a deprecated name

        warnings.warn(f"brdfjax.{name} is deprecated: use {_MOVED_NAMES[name][1]}", DeprecationWarning, stacklevel=2)
        return getattr(_render, name)
    if f"brdfjax.{name}" in _MOVED_MODULES:  # bj.terms etc.: the moved module, through the finder (which warns)
        import importlib  # noqa: PLC0415 -- only a deprecated name pays for it

        return importlib.import_module(f"brdfjax.{name}")
    raise AttributeError(f"module 'brdfjax' has no attribute {name!r}")

_install_moved_module_paths()
