"""brdfjax: differentiable near-specular BRDF models and CCD scatterometer frames in JAX.

Public names are re-exported here from their modules; see the README for a tour.
"""

from ._compat import install as _install_moved_module_paths
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
    Frame as Frame,
    evaluate_pixels as evaluate_pixels,
    render as render,
    render_frame as render_frame,
    render_geometry as render_geometry,
    render_sharded as render_sharded,
    sample_directions as sample_directions,
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

_install_moved_module_paths()
