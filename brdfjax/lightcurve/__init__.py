"""Light curves of satellites made of facets with brdfjax models (an edge package: it imports the core, config, io).

``brdfjax lightcurve CONFIG --out DIR`` (:mod:`.cli`) runs a TOML config
(:mod:`.config`); :mod:`.ephemeris` places the satellite (SGP4), the Sun and
the observer; :mod:`.engine` is the JAX forward model (facets, attitude, the
solar disk, flux and magnitude), differentiable and vmappable over posterior
draws; :mod:`.models` adds the Phong baseline, the directional albedo and
models from fits and posteriors; :mod:`.glintmap` maps where a model glints
against a baseline.  ``brdfjax observe`` predicts real observations:
:mod:`.skygeometry` (the geometry of observed rows without a TLE),
:mod:`.attitude` (named attitude laws), :mod:`.photometry` (bands),
:mod:`.earthshine`, :mod:`.observe` and :mod:`.observe_config`.  See the
README's "Light curves" and docs/guides/sky.md.
"""

from .config import LightcurveConfig as LightcurveConfig, load_lightcurve_config as load_lightcurve_config
from .engine import (
    Attitude as Attitude,
    Facets as Facets,
    Geometry as Geometry,
    Satellite as Satellite,
    SunDisk as SunDisk,
    facet_flux as facet_flux,
    magnitude as magnitude,
)
from .glintmap import GlintMap as GlintMap, glint_map as glint_map
from .models import Phong as Phong, directional_albedo as directional_albedo, lumos_phong as lumos_phong
from .run import build_job as build_job, posterior_total_flux as posterior_total_flux, run_lightcurve as run_lightcurve
