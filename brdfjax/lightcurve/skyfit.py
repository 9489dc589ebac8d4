"""Learning from observations: a differentiable likelihood of observed magnitudes over facet parameters.

A :class:`SkyProblem` holds one observation set's fixed geometry (the Sun
and the observer in the body frame of the attitude law, the distance scale
and each row's solar magnitude) and a facet model (areas, normals, cant and
yaw offsets, each facet's BRDF model).  Every quantity that may be learned is
a named entry of one parameter vector (:class:`Param`): facet areas, cant and
yaw offsets, BRDF parameters of the facets' models, an extra magnitude
scatter, and the parameters of additive *effects* (:mod:`.skygap` uses them:
earthshine, a missing facet, a lobe beyond the measured incidence, an
out-of-plane offset peak).  Each is bounded and fitted in an unconstrained
coordinate ``u``: ``x = lo + (hi - lo) sigmoid(u)`` (in log space for
positive parameters), so a value that ends at a bound is seen as such
(:meth:`SkyFit.on_bound`).

The predicted magnitude of row ``i`` is ``m_sun(band_i) - 2.5 log10(sum_j
F_ij + effects_i)`` with ``F_ij = A_j f_j(w_i, w_s) cos_i cos_s (AU/d_sun)^2
/ d_obs^2`` (a point Sun; the rows kept by :func:`~.skygeometry.sky_geometry`
are sunlit), the same as :func:`~brdfjax.lightcurve.engine.facet_flux` with
a point Sun (a test compares them).

The likelihood (``-2 ln L``, what the fits minimise)::

    sum_{rows with sigma} r_i^2 / (sigma_i^2 + s^2) + ln(sigma_i^2 + s^2)
      + N0 ln(RSS0 / N0) + N0                      (rows without sigma: scatter profiled out)
      + sum_{lab tables} n ln(RSS_lab / n) + n      (joint fits: log-space residuals of each facet family's table)

with ``r = observed - predicted`` magnitude and ``s`` the ``scatter`` parameter
(off unless freed).  Rows enter with weights (0 or 1), so held-out folds of a
cross-validation reuse one compiled function.  Fits: optimistix BFGS on
``u`` (the free entries; the others held).  Posterior: blackjax NUTS with
window adaptation on the free ``u`` (flat prior in ``u``, i.e. the sigmoid's
Jacobian acts as a weak prior that keeps draws inside the bounds).

Cross-validation (:func:`group_folds`, :func:`cross_validate`) holds out
whole groups: local nights (absolute rows: the UTC time shifted by the
observer's longitude, a night running from local noon to noon), satellites,
or for sets without times contiguous blocks of rows; never single rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..config.base import read_toml
from ..core.geometry import Directions
from ..core.terms import Model
from ..fit import read_merl_inplane
from ..io import toml
from ..io.observations import Observations
from ..runtime.errors import InputError
from .attitude import lumos_normal_to_body, offset_facets
from .engine import Attitude, Facets, shadow_mask, to_facet_frames
from .observe import FacetSpec
from .photometry import band
from .skygeometry import SkyGeometry, sky_geometry

__all__ = ["Param", "SkyData", "SkyProblem", "SkyFit", "sky_data", "group_folds", "night_groups", "block_groups",
           "cross_validate", "nuts_posterior", "laplace_covariance", "predictive_band", "LabTable", "lab_table", "write_observe_config"]

AU_M = 1.495978707e11
_EDGE = 1e-3  # a parameter within this fraction of its range of a bound is "on the bound"


@dataclass
class Param:
    """One named, bounded entry of the parameter vector.

    ``kind``: ``area`` (facet ``index``, m^2), ``cant``/``yaw`` (facet, rad),
    ``model`` (family ``target``, parameter ``name`` of the model), ``scatter``
    (mag), ``effect`` (``target`` an effect's name, its ``name``).  ``log``:
    bounded in log space (positive parameters).
    """

    key: str
    kind: str
    value: float
    lo: float
    hi: float
    log: bool = False
    index: int = -1
    target: str = ""
    name: str = ""

    def __post_init__(self):
        if not (self.lo < self.hi) or (self.log and self.lo <= 0):
            raise InputError(f"parameter '{self.key}': bounds [{self.lo}, {self.hi}] are not valid"
                             + (" (a log parameter needs lo > 0)" if self.log else ""))
        if not (self.lo <= self.value <= self.hi):
            raise InputError(f"parameter '{self.key}': value {self.value} outside its bounds [{self.lo}, {self.hi}]")

    def to_u(self, x: float) -> float:
        a, b, v = (np.log(self.lo), np.log(self.hi), np.log(x)) if self.log else (self.lo, self.hi, x)
        p = np.clip((v - a) / (b - a), 1e-9, 1 - 1e-9)
        return float(np.log(p) - np.log1p(-p))


@dataclass
class SkyData:
    """One observation set's fixed geometry and magnitudes (kept rows)."""

    name: str
    obs: Observations
    geometry: SkyGeometry
    s_b: np.ndarray  # (N, 3) unit satellite -> Sun, body frame
    o_b: np.ndarray  # (N, 3) unit satellite -> observer, body frame
    scale: np.ndarray  # (N,) (AU / d_sun)^2 / d_obs^2
    sun_mag: np.ndarray  # (N,)
    mag: np.ndarray
    mag_err: np.ndarray  # NaN where none
    phase_deg: np.ndarray
    sun_obs_az_deg: np.ndarray  # azimuth of the observer from the Sun about body z at the satellite
    engine: object = None  # the light-curve engine's Geometry of these rows (earthshine needs it); None after take()
    rpy: tuple = (0.0, 0.0, 0.0)  # the attitude's roll, pitch, yaw offsets (deg)
    disk: dict | None = None  # solar-disk nodes: "nodes_b" (N, K, 3) body frame, "vis" (N, K), "weights" (K,)

    def __len__(self) -> int:
        return int(self.mag.shape[0])

    def take(self, idx) -> "SkyData":
        idx = np.asarray(idx)
        obs = self.obs.take(idx)
        disk = None if self.disk is None else {"nodes_b": self.disk["nodes_b"][idx], "vis": self.disk["vis"][idx],
                                               "weights": self.disk["weights"]}
        return SkyData(self.name, obs, self.geometry, self.s_b[idx], self.o_b[idx], self.scale[idx], self.sun_mag[idx],
                       self.mag[idx], self.mag_err[idx], self.phase_deg[idx], self.sun_obs_az_deg[idx], None, self.rpy,
                       disk)

    def with_mag(self, mag, mag_err=None) -> "SkyData":
        """The same rows with other magnitudes (synthetic sets)."""
        return SkyData(self.name, self.obs, self.geometry, self.s_b, self.o_b, self.scale, self.sun_mag,
                       np.asarray(mag, float), self.mag_err if mag_err is None else np.asarray(mag_err, float),
                       self.phase_deg, self.sun_obs_az_deg, self.engine, self.rpy, self.disk)

    def with_disk(self, disk) -> "SkyData":
        """The same rows with the solar-disk nodes of ``disk`` (a :class:`~.engine.SunDisk`; the engine's own node
        directions and Earth-shadow mask, so that a fit with the disk reproduces ``facet_flux`` with it)."""
        if self.engine is None:
            raise InputError(f"{self.name}: the solar disk needs the rows' engine geometry (lost by take(); build the "
                             "rows with sky_data)")
        g = self.engine
        nodes = disk.directions(g.s)
        vis = shadow_mask(g.r_hat * g.r[:, None], g.r, nodes, self.geometry.earth_radius)
        M = Attitude.nadir(*np.deg2rad(self.rpy)).matrix(g.r_hat, g.v_hat)
        nodes_b = jnp.einsum("tij,tki->tkj", M, nodes)
        return SkyData(self.name, self.obs, self.geometry, self.s_b, self.o_b, self.scale, self.sun_mag, self.mag,
                       self.mag_err, self.phase_deg, self.sun_obs_az_deg, self.engine, self.rpy,
                       {"nodes_b": np.asarray(nodes_b), "vis": np.asarray(vis), "weights": np.asarray(disk.weights)})


def sky_data(name: str, obs: Observations, *, yaw_law: str = "sun_yaw", convention: str = "physical",
             band_map: dict[str, str] | None = None, earth_radius: float | None = None, roll_deg: float = 0.0,
             pitch_deg: float = 0.0, yaw_deg: float = 0.0, min_altitude_deg: float = 0.0) -> SkyData:
    """The fixed part of a problem: geometry (rows below the horizon or in shadow dropped), body-frame directions."""
    geo = sky_geometry(obs, yaw_law=yaw_law, earth_radius=earth_radius, min_altitude_deg=min_altitude_deg)
    kept = obs.take(geo.keep)
    g = geo.engine_geometry(sun_distance_factor=(convention == "physical"))
    M = np.asarray(Attitude.nadir(np.deg2rad(roll_deg), np.deg2rad(pitch_deg), np.deg2rad(yaw_deg))
                   .matrix(g.r_hat, g.v_hat))
    s_b = np.einsum("tij,ti->tj", M, np.asarray(g.s))
    o_b = np.einsum("tij,ti->tj", M, np.asarray(g.o))
    scale = np.square(AU_M / np.asarray(g.d_sun)) / np.square(np.asarray(g.d_obs))
    band_map = band_map or {}
    sun_mag = np.array([band(band_map.get(str(b), str(b)), where=obs.source).sun_magnitude for b in kept.band])
    az = np.rad2deg(np.arctan2(o_b[:, 1], o_b[:, 0]) - np.arctan2(s_b[:, 1], s_b[:, 0]))
    az = (az + 180.0) % 360.0 - 180.0
    return SkyData(name, kept, geo, s_b, o_b, scale, sun_mag, np.asarray(kept.mag, float),
                   np.asarray(kept.mag_err, float), geo.phase_angle_deg(), az, g, (roll_deg, pitch_deg, yaw_deg))


# --- grouping for cross-validation ---------------------------------------------------------------------------


def night_groups(obs: Observations) -> np.ndarray:
    """Each absolute row's local night (an integer): UTC time + longitude / 15 h, nights running noon to noon."""
    if obs.time is None or obs.lon_deg is None:
        raise InputError(f"{obs.source}: rows have no time and site: hold out blocks (block_groups) instead of nights")
    t = obs.time.astype("datetime64[s]").astype(np.int64) / 86400.0 + np.asarray(obs.lon_deg, float) / 360.0 - 0.5
    return np.floor(t).astype(np.int64)


def block_groups(n: int, n_blocks: int) -> np.ndarray:
    """Contiguous blocks of rows (for sets without times: neighbouring rows are one pass)."""
    return np.minimum(np.arange(n) * n_blocks // max(n, 1), n_blocks - 1)


def group_folds(groups: np.ndarray, k: int, seed: int = 0) -> list[np.ndarray]:
    """``k`` held-out masks, each holding out whole groups (shuffled, balanced by row count)."""
    groups = np.asarray(groups)
    uniq, counts = np.unique(groups, return_counts=True)
    if uniq.size < 2:
        raise InputError(f"cross-validation needs at least 2 groups of rows; got {uniq.size}")
    k = min(k, uniq.size)
    order = np.random.default_rng(seed).permutation(uniq.size)
    load = np.zeros(k)
    fold_of = {}
    for i in sorted(order, key=lambda i: -counts[i]):
        f = int(np.argmin(load))
        fold_of[uniq[i]] = f
        load[f] += counts[i]
    fid = np.array([fold_of[g] for g in groups])
    return [fid == f for f in range(k)]


# --- lab tables for joint fits ----------------------------------------------------------------------------------


@dataclass
class LabTable:
    """A lab BRDF table as fixed arrays: directions and values (rows with data > 0)."""

    family: str
    dirs: Directions
    value: np.ndarray
    floor: float = 1e-6
    weight: float = 1.0


def lab_table(family: str, path, fmt: str = "lumos-sat", columns: dict | None = None, weight: float = 1.0,
              every: int = 1) -> LabTable:
    """Read a lab table (as :func:`~brdfjax.lightcurve.observe.lab_coverage` does) into a :class:`LabTable`."""
    t = read_merl_inplane(path, columns=columns)
    keep = (np.ones(len(t), bool) if t.mask is None else np.asarray(t.mask, bool)) & (np.asarray(t.brdf) > 0)
    idx = np.flatnonzero(keep)[::every]
    d = Directions.from_angles(jnp.asarray(np.asarray(t.theta_i)[idx]), jnp.asarray(np.asarray(t.phi_i)[idx]),
                               jnp.asarray(np.asarray(t.theta_s)[idx]), jnp.asarray(np.asarray(t.phi_s)[idx]))
    return LabTable(family, d, np.asarray(t.brdf, float)[idx], weight=weight)


# --- the problem ---------------------------------------------------------------------------------------------------


@dataclass
class SkyFit:
    """A fit's result: ``u`` (all entries), the free mask, ``-2 ln L``, the parameter values and which sit on a bound."""

    problem: "SkyProblem"
    u: np.ndarray
    free: np.ndarray
    m2ll: float
    n: int
    steps: int = 0
    w: np.ndarray | None = None  # the rows' weights of the fit (None: all 1)
    joint: float = 1.0

    @property
    def k(self) -> int:
        return int(self.free.sum())

    @property
    def bic(self) -> float:
        return self.m2ll + self.k * np.log(max(self.n, 1))

    def values(self) -> dict[str, float]:
        x = np.asarray(self.problem.x_of_u(jnp.asarray(self.u)))
        return {p.key: float(x[i]) for i, p in enumerate(self.problem.params)}

    def on_bound(self) -> list[str]:
        p = 0.5 * (1.0 + np.tanh(0.5 * self.u))  # the sigmoid, without overflow
        return [q.key for i, q in enumerate(self.problem.params) if self.free[i] and (p[i] < _EDGE or p[i] > 1 - _EDGE)]

    def predict(self, data: SkyData | None = None) -> np.ndarray:
        return self.problem.predict(self.u, data)


@dataclass
class SkyProblem:
    """Facets, their models and the parameter vector over one :class:`SkyData` (see the module docstring).

    ``effects``: name -> (kind, facet index, ...) evaluated by :mod:`.skygap`
    through ``effect_flux``; a problem without effects is the plain facet model.
    """

    data: SkyData
    facets: list[FacetSpec]
    models: dict[str, Model]  # family -> Model (each facet uses families[0])
    params: list[Param]
    normals: str = "body"
    wavelength: float = 550e-9
    labs: list[LabTable] = field(default_factory=list)
    effect_flux: object = None  # callable(problem, x, w_c, w_s, cos) -> (N,) extra flux, or None
    _fns: dict = field(default_factory=dict, repr=False)

    def __setattr__(self, name, value):
        # the compiled functions hold the rows as constants: new rows (a synthetic set's magnitudes, the solar
        # disk's nodes) drop them
        if name == "data" and "_fns" in self.__dict__:
            self.__dict__["_fns"].clear()
        object.__setattr__(self, name, value)

    # --- construction helpers
    @classmethod
    def build(cls, data: SkyData, facets: list[FacetSpec], models: dict[str, Model], *, normals: str = "body",
              free_areas: bool = True, area_range: float = 20.0, cant: list[str] = (), yaw: list[str] = (),
              offset_deg: float = 30.0, model_params: dict[str, list[str]] | None = None, model_range: float = 30.0,
              scatter: bool = False, wavelength: float = 550e-9, labs: list[LabTable] = ()) -> "SkyProblem":
        """A problem with the usual parameters: every facet's area (log, within ``area_range`` of the config's), cant
        and yaw of the named facets (+- ``offset_deg``), the named model parameters (positive ones log within
        ``model_range``; signed ones +- (10 |v| + 1)), and an extra scatter (0.001-3 mag)."""
        names = [f.name for f in facets]
        for f in facets:
            if f.families[0] not in models:
                raise InputError(f"facet '{f.name}': model '{f.families[0]}' is not among the models")
        ps: list[Param] = []
        for j, f in enumerate(facets):
            ps.append(Param(f"area.{f.name}", "area", f.area, f.area / area_range, f.area * area_range, True, j))
        lim = np.deg2rad(offset_deg)
        for kind, which in (("cant", cant), ("yaw", yaw)):
            for nm in which:
                if nm not in names:
                    raise InputError(f"{kind}: no facet '{nm}'; facets: {', '.join(names)}")
                j = names.index(nm)
                v = np.deg2rad(facets[j].cant_deg if kind == "cant" else facets[j].yaw_deg)
                ps.append(Param(f"{kind}.{nm}", kind, float(v), -lim + min(v, 0), lim + max(v, 0), False, j))
        for fam, pnames in (model_params or {}).items():
            if fam not in models:
                raise InputError(f"model_params: no model '{fam}'")
            vals = models[fam].params()
            for pn in pnames:
                if pn not in vals:
                    raise InputError(f"model_params: model '{fam}' has no parameter '{pn}'; known: {', '.join(vals)}")
                v = float(vals[pn])
                if v > 0:
                    ps.append(Param(f"{fam}.{pn}", "model", v, v / model_range, v * model_range, True, target=fam,
                                    name=pn))
                else:
                    w = 10 * abs(v) + 1
                    ps.append(Param(f"{fam}.{pn}", "model", v, v - w, v + w, False, target=fam, name=pn))
        ps.append(Param("scatter", "scatter", 1e-3 if not scatter else 0.3, 1e-3, 3.0, True))
        prob = cls(data, facets, models, ps, normals, wavelength, list(labs))
        prob._scatter_default = scatter
        return prob

    def add(self, params: list[Param]) -> None:
        self.params.extend(params)
        self._fns.clear()

    def index(self, key: str) -> int:
        for i, p in enumerate(self.params):
            if p.key == key:
                return i
        raise KeyError(f"no parameter '{key}'; known: {', '.join(p.key for p in self.params)}")

    def u0(self) -> np.ndarray:
        return np.array([p.to_u(p.value) for p in self.params])

    def default_free(self, *keys: str) -> np.ndarray:
        """Mask: the areas, the named keys (prefix match: ``"cant."`` frees every cant) and the scatter if it was asked."""
        m = np.array([p.kind == "area" for p in self.params])
        for k in keys:
            m |= np.array([p.key == k or (k.endswith(".") and p.key.startswith(k)) for p in self.params])
        if getattr(self, "_scatter_default", False):
            m[self.index("scatter")] = True
        return m

    # --- the forward model (JAX)
    def x_of_u(self, u):
        lo = np.array([np.log(p.lo) if p.log else p.lo for p in self.params])
        hi = np.array([np.log(p.hi) if p.log else p.hi for p in self.params])
        lg = np.array([p.log for p in self.params])
        t = lo + (hi - lo) * jax.nn.sigmoid(u)
        return jnp.where(lg, jnp.exp(t), t)

    def _facets(self, x):
        conv = lumos_normal_to_body if self.normals == "lumos" else (lambda v: np.asarray(v, float))
        f = self.facets
        base = Facets.build([q.name for q in f], [q.area for q in f], [conv(q.normal) for q in f],
                            x_axis=[None if q.x_axis is None else conv(q.x_axis) for q in f],
                            tracking=[q.tracking for q in f])
        area = jnp.asarray(base.area)
        cant = jnp.deg2rad(jnp.asarray([q.cant_deg for q in f], float))
        yaw = jnp.deg2rad(jnp.asarray([q.yaw_deg for q in f], float))
        for i, p in enumerate(self.params):
            if p.kind == "area":
                area = area.at[p.index].set(x[i])
            elif p.kind == "cant":
                cant = cant.at[p.index].set(x[i])
            elif p.kind == "yaw":
                yaw = yaw.at[p.index].set(x[i])
        fac = offset_facets(Facets(area, base.normal, base.x_axis, base.phi_ref, base.tracking, base.side, base.names),
                            cant, yaw)
        return fac

    def _models(self, x) -> dict[str, Model]:
        upd: dict[str, dict] = {}
        for i, p in enumerate(self.params):
            if p.kind == "model":
                upd.setdefault(p.target, {})[p.name] = x[i]
        return {k: (m.with_params(upd[k]) if k in upd else m) for k, m in self.models.items()}

    def facet_terms(self, x, s_b, o_b):
        """Facet-frame Sun and observer directions (N, J, 3) and each facet's BRDF x cos_i x cos_s (N, J)."""
        fac = self._facets(x)
        xa, ya, na = fac.frames(s_b)

        def to_facet(v):
            vv = v[:, None]
            return jnp.stack([jnp.sum(vv * xa, -1), jnp.sum(vv * ya, -1), jnp.sum(vv * na, -1)], -1)

        w_c, w_s = to_facet(s_b), to_facet(o_b)
        models = self._models(x)
        fams = [f.families[0] for f in self.facets]
        cols = [None] * len(fams)
        for fam in dict.fromkeys(fams):
            idx = [j for j, q in enumerate(fams) if q == fam]
            vals = models[fam](Directions.from_vectors(w_c[:, idx], w_s[:, idx]), self.wavelength)
            for q, j in enumerate(idx):
                cols[j] = vals[:, q]
        f = jnp.stack(cols, 1)
        cos = jnp.maximum(w_c[..., 2], 0.0) * jnp.maximum(w_s[..., 2], 0.0)
        return w_c, w_s, jnp.nan_to_num(f * cos), fac.area

    def disk_terms(self, x, d: SkyData):
        """Each facet's BRDF x cos_i x cos_s integrated over the solar disk (N, J): the rule of ``d.disk``, as
        :func:`~.engine.facet_flux` integrates it (node weights, the Earth's shadow per node)."""
        fac = self._facets(x)
        s_b = jnp.asarray(d.s_b)
        xa, ya, na = fac.frames(s_b)
        w_i = to_facet_frames(jnp.asarray(d.disk["nodes_b"]), xa, ya, na)  # (N, J, K, 3)
        w_s = to_facet_frames(jnp.asarray(d.o_b), xa, ya, na)  # (N, J, 3)
        models = self._models(x)
        fams = [f.families[0] for f in self.facets]
        cols = [None] * len(fams)
        for fam in dict.fromkeys(fams):
            idx = [j for j, q in enumerate(fams) if q == fam]
            ii = np.asarray(idx)
            vals = models[fam](Directions.from_vectors(w_i[:, ii], w_s[:, ii][:, :, None, :]), self.wavelength)
            for q, j in enumerate(idx):
                cols[j] = vals[:, q]
        fv = jnp.stack(cols, 1)  # (N, J, K)
        wts = jnp.asarray(d.disk["weights"]) * jnp.asarray(d.disk["vis"])[:, None, :]
        integral = jnp.sum(wts * fv * jnp.maximum(w_i[..., 2], 0.0), -1)
        return jnp.nan_to_num(integral * jnp.maximum(w_s[..., 2], 0.0))

    def disk_at(self, u, free: np.ndarray | None = None) -> bool | None:
        """Whether the solar disk is on at ``u``: a Python bool that the compiled functions specialise on (the
        switch ``disk.on`` is a fixed entry), or None where the problem has no disk or the switch is free (then a
        ``lax.cond`` chooses inside, and under a gradient that costs about 20 times an evaluation without the disk:
        the disk branch's residuals are carried whether taken or not)."""
        if self.data.disk is None or not any(p.key == "disk.on" for p in self.params):
            return None
        i = self.index("disk.on")
        if free is not None and bool(np.asarray(free)[i]) or isinstance(u, jax.core.Tracer):
            return None
        return bool(float(np.asarray(self.x_of_u(jnp.asarray(u)))[i]) > 0.5)

    def flux(self, x, d: SkyData | None = None, disk: bool | None = None):
        """Per-facet flux (N, J) and the effects' flux (N,), in units of the solar irradiance at 1 AU.  ``disk``:
        the solar disk on or off (None: by ``x``'s switch, :meth:`disk_at`)."""
        d = d or self.data
        s_b, o_b, scale = jnp.asarray(d.s_b), jnp.asarray(d.o_b), jnp.asarray(d.scale)
        w_c, w_s, fc, area = self.facet_terms(x, s_b, o_b)
        if d.disk is not None and any(p.key == "disk.on" for p in self.params):
            if disk is None and not isinstance(x, jax.core.Tracer):
                disk = bool(float(np.asarray(x)[self.index("disk.on")]) > 0.5)
            if disk is None:
                on = x[self.index("disk.on")] > 0.5
                fc = jax.lax.cond(on, lambda: self.disk_terms(x, d), lambda: fc)
            elif disk:
                fc = self.disk_terms(x, d)
        per = fc * area[None, :] * scale[:, None]
        extra = (self.effect_flux(self, x, d, w_c, w_s) if self.effect_flux is not None
                 else jnp.zeros(per.shape[0]))
        return per, extra

    def mag_of_x(self, x, d: SkyData | None = None, disk: bool | None = None):
        d = d or self.data
        per, extra = self.flux(x, d, disk)
        total = per.sum(-1) + extra
        return jnp.asarray(d.sun_mag) - 2.5 * jnp.log10(jnp.maximum(total, 1e-300))

    def predict(self, u, data: SkyData | None = None) -> np.ndarray:
        if data is not None:
            return np.asarray(self.mag_of_x(self.x_of_u(jnp.asarray(u)), data))
        disk = self.disk_at(u)
        key = ("predict", disk)
        if key not in self._fns:  # compiled once per problem (the fit's own rows), as the solve
            self._fns[key] = jax.jit(lambda v: self.mag_of_x(self.x_of_u(v), None, disk))
        return np.asarray(self._fns[key](jnp.asarray(u, float)))

    # --- the likelihood
    def _m2ll(self, u, w, joint, disk: bool | None = None):
        x = self.x_of_u(u)
        d = self.data
        r = jnp.asarray(d.mag) - self.mag_of_x(x, d, disk)
        err = np.asarray(d.mag_err)
        has = np.isfinite(err) & (err > 0)
        s2 = jnp.square(x[self.index("scatter")])
        var = jnp.where(has, np.where(has, err, 1.0) ** 2 + s2, 1.0)
        wh = w * has
        out = jnp.sum(wh * (jnp.square(r) / var + jnp.log(var)))
        w0 = w * (~has)
        n0 = jnp.sum(w0)
        rss0 = jnp.sum(w0 * jnp.square(r))
        out = out + jnp.where(n0 > 0, n0 * jnp.log(jnp.maximum(rss0, 1e-300) / jnp.maximum(n0, 1.0)) + n0, 0.0)
        if self.labs:
            models = self._models(x)
            for lab in self.labs:
                f = models[lab.family](lab.dirs, self.wavelength)
                rr = jnp.log(f + lab.floor) - jnp.log(jnp.asarray(lab.value) + lab.floor)
                n = rr.shape[0]
                out = out + joint * lab.weight * (n * jnp.log(jnp.sum(jnp.square(rr)) / n) + n)
        return out

    def m2ll(self, u, w=None, joint: float = 1.0) -> float:
        w = np.ones(len(self.data)) if w is None else np.asarray(w, float)
        return float(self._compiled(self.disk_at(u))["m2ll"](jnp.asarray(u), jnp.asarray(w), jnp.asarray(joint)))

    def _compiled(self, disk: bool | None = None):
        """The compiled solve and ``-2 ln L``, one pair per solar-disk state (a static choice: see :meth:`disk_at`).
        The free mask, start, weights and joint factor are arguments, so every refit and held-out fold of a problem
        reuses one compilation."""
        key = ("fns", disk)
        if key not in self._fns:
            def obj(v, args):
                u0, free, w, joint = args
                return self._m2ll(jnp.where(free, v, u0), w, joint, disk)

            solver = optx.BFGS(rtol=1e-7, atol=1e-7)

            @jax.jit
            def solve(u0, free, w, joint):
                sol = optx.minimise(obj, solver, u0, args=(u0, free, w, joint), max_steps=4000, throw=False)
                u = jnp.where(free, sol.value, u0)
                return u, self._m2ll(u, w, joint, disk), sol.stats["num_steps"]

            self._fns[key] = {"solve": solve, "m2ll": jax.jit(lambda u, w, joint: self._m2ll(u, w, joint, disk))}
        return self._fns[key]

    def fit(self, free: np.ndarray | None = None, u0: np.ndarray | None = None, w: np.ndarray | None = None,
            joint: float = 1.0, starts: list[np.ndarray] | None = None) -> SkyFit:
        """Minimise ``-2 ln L`` over the ``free`` entries from ``u0`` (and from each of ``starts``; the best is kept)."""
        free = self.default_free() if free is None else np.asarray(free, bool)
        w = np.ones(len(self.data)) if w is None else np.asarray(w, float)
        best = None
        for start in [self.u0() if u0 is None else u0] + list(starts or []):
            fn = self._compiled(self.disk_at(start, free))["solve"]
            u, m, steps = fn(jnp.asarray(start, float), jnp.asarray(free), jnp.asarray(w), jnp.asarray(joint))
            m = float(m)
            if np.isfinite(m) and (best is None or m < best.m2ll):
                best = SkyFit(self, np.asarray(u), free, m, int(np.sum(w > 0)), int(steps), w, float(joint))
        if best is None:
            raise InputError("sky fit: the likelihood is not finite at any start (check the facets' models and rows)")
        return best


# --- cross-validation --------------------------------------------------------------------------------------------


def cross_validate(problem: SkyProblem, free: np.ndarray, folds: list[np.ndarray], u0: np.ndarray | None = None,
                   joint: float = 1.0, band_draws: int = 0, seed: int = 0) -> dict:
    """Refit on all but each held-out fold; the held-out residuals (observed - predicted) of every row.

    Returns ``rms``, ``bias``, ``n``, the per-row held-out ``pred`` (N,) and
    ``sigma`` (N,): the training fit's predictive sigma of each held-out row
    (``sqrt(sigma_i^2 + s^2)`` where the row has an uncertainty, else the
    training rows' residual RMS), the fractions of held-out rows within
    +-0.9945 and +-1.96 of it (the Gaussian 68 and 95 % bands; the fit's own
    parameter uncertainty is not added), and per fold the RMS and the rows.
    ``band_draws`` > 0: also each held-out row's :func:`predictive_band` from
    its training fit (parameter uncertainty and the row's noise):
    ``band`` (N, 5) and ``band_coverage_68``/``band_coverage_95``, the
    fractions of held-out rows inside its 16-84 and 2.5-97.5 % ranges.
    """
    d = problem.data
    pred = np.full(len(d), np.nan)
    sig = np.full(len(d), np.nan)
    has = np.isfinite(d.mag_err) & (d.mag_err > 0)
    per_fold = []
    band = np.full((len(d), 5), np.nan)
    for q, hold in enumerate(folds):
        f = problem.fit(free, u0=u0, w=(~hold).astype(float), joint=joint)
        p = f.predict()
        pred[hold] = p[hold]
        if band_draws > 0:
            band[hold] = predictive_band(f, band_draws, seed + q)["band"][hold]
        r = d.mag - p
        train0 = ~hold & ~has
        s0 = np.sqrt(np.mean(r[train0] ** 2)) if train0.any() else np.nan
        s = f.values()["scatter"]
        sig[hold] = np.where(has, np.sqrt(np.where(has, d.mag_err, 0.0) ** 2 + s**2), s0)[hold]
        per_fold.append({"n": int(hold.sum()), "rms": float(np.sqrt(np.mean(r[hold] ** 2)))})
    r = d.mag - pred
    ok = np.isfinite(r)
    z = np.abs(r[ok]) / sig[ok]
    out = {"rms": float(np.sqrt(np.mean(r[ok] ** 2))), "bias": float(np.mean(r[ok])), "n": int(ok.sum()),
           "pred": pred, "sigma": sig, "coverage_68": float(np.mean(z <= 0.9945)),
           "coverage_95": float(np.mean(z <= 1.96)), "folds": per_fold}
    if band_draws > 0:
        m = d.mag[ok]
        out.update(band=band, band_coverage_68=float(np.mean((m >= band[ok, 1]) & (m <= band[ok, 3]))),
                   band_coverage_95=float(np.mean((m >= band[ok, 0]) & (m <= band[ok, 4]))))
    return out


def laplace_covariance(fit: SkyFit, max_sd_u: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The free entries' indices and their covariance in ``u`` from the Hessian of ``-2 ln L`` at the fit
    (``(H / 2)^-1``, the fit's own weights and joint factor).  Directions the rows do not constrain (a flat or
    negative curvature: an area of a facet no row sees, an amplitude on its bound) would get an unbounded spread;
    each eigenvalue of ``H / 2`` is floored at ``1 / max_sd_u^2``, so no direction spreads by more than
    ``max_sd_u`` in ``u`` (one logistic unit: a parameter in the middle of its range moves by about a quarter of
    it)."""
    prob = fit.problem
    idx = np.flatnonzero(fit.free)
    w = jnp.asarray(np.ones(len(prob.data)) if fit.w is None else fit.w)
    ufull = jnp.asarray(fit.u)
    disk = prob.disk_at(fit.u, fit.free)
    H = np.asarray(jax.hessian(lambda z: prob._m2ll(ufull.at[idx].set(z), w, fit.joint, disk))(ufull[idx]))
    # a non-finite second derivative (a parameter saturated on its bound: sigmoid' underflows) says nothing about
    # that direction: it gets the floor below
    H = np.nan_to_num(H, nan=0.0, posinf=0.0, neginf=0.0)
    H = 0.25 * (H + H.T)  # H / 2, symmetrised
    ev, V = np.linalg.eigh(H)
    ev = np.maximum(np.nan_to_num(ev, nan=0.0), 1.0 / max_sd_u**2)
    return idx, (V / ev) @ V.T


def predictive_band(fit: SkyFit, n_draws: int = 200, seed: int = 0, data: SkyData | None = None) -> dict:
    """Each row's predictive band with the fit's parameter uncertainty (the Laplace approximation of
    :func:`laplace_covariance`, drawn in ``u`` so that draws stay inside the bounds) and the row's noise (its
    uncertainty and the fitted scatter, or the fit's residual RMS over rows without one).

    Returns ``band`` (N, 5): the 2.5, 16, 50, 84 and 97.5 percentiles of the predicted observation (mag);
    ``param_sd`` (N,): the standard deviation of the predicted magnitude from the parameters alone; ``noise``
    (N,): the noise sigma used.
    """
    prob = fit.problem
    d = data or prob.data
    rng = np.random.default_rng(seed)
    idx, cov = laplace_covariance(fit)
    ev, V = np.linalg.eigh(cov)
    L = V * np.sqrt(np.clip(ev, 0, None))
    u = np.tile(fit.u, (n_draws, 1))
    u[:, idx] += rng.standard_normal((n_draws, idx.size)) @ L.T
    disk = prob.disk_at(fit.u, fit.free)
    mags = np.asarray(jax.lax.map(lambda v: prob.mag_of_x(prob.x_of_u(v), d, disk), jnp.asarray(u), batch_size=16))
    mags = np.nan_to_num(mags, nan=np.inf)
    has = np.isfinite(d.mag_err) & (d.mag_err > 0)
    s = fit.values()["scatter"]
    p = fit.predict(d)
    w = np.ones(len(d)) if (fit.w is None or data is not None) else fit.w
    train0 = (w > 0) & ~has
    s0 = float(np.sqrt(np.mean((d.mag - p)[train0] ** 2))) if train0.any() else 0.0
    noise = np.where(has, np.sqrt(np.where(has, d.mag_err, 0.0) ** 2 + s**2), s0)
    obs = mags + noise[None, :] * rng.standard_normal(mags.shape)
    return {"band": np.percentile(obs, [2.5, 16, 50, 84, 97.5], axis=0).T,
            "param_sd": np.std(np.where(np.isfinite(mags), mags, np.nan), 0), "noise": noise}


# --- posterior ---------------------------------------------------------------------------------------------------


def nuts_posterior(fit: SkyFit, n_draws: int = 300, n_warmup: int = 300, seed: int = 0, joint: float = 1.0
                   ) -> dict:
    """NUTS draws (blackjax, Stan's window adaptation) of the free parameters around a fit.

    The log-density is ``-0.5 (-2 ln L)`` in the unconstrained ``u`` (a flat
    prior in ``u``).  Returns the draws in natural units per free parameter
    key, the acceptance rate and the divergent transitions.
    """
    import blackjax  # optional dependency (the sample extra): imported only when a posterior is asked for

    prob = fit.problem
    free = np.asarray(fit.free, bool)
    idx = np.flatnonzero(free)
    ufull = jnp.asarray(fit.u)
    w = jnp.ones(len(prob.data))

    disk = prob.disk_at(fit.u, fit.free)

    def logdensity(z):
        return -0.5 * prob._m2ll(ufull.at[idx].set(z), w, joint, disk)

    key = jax.random.PRNGKey(seed)
    k1, k2 = jax.random.split(key)
    warm = blackjax.window_adaptation(blackjax.nuts, logdensity, target_acceptance_rate=0.8)
    (state, params), _ = warm.run(k1, jnp.asarray(fit.u[idx]), num_steps=n_warmup)
    kernel = blackjax.nuts(logdensity, **params).step

    @jax.jit
    def run(state, key):
        def one(st, k):
            st, info = kernel(k, st)
            return st, (st.position, info.is_divergent, info.acceptance_rate)
        return jax.lax.scan(one, state, jax.random.split(key, n_draws))

    _, (pos, div, acc) = run(state, k2)
    pos = np.asarray(pos)
    full = np.tile(np.asarray(fit.u), (pos.shape[0], 1))
    full[:, idx] = pos
    x = np.asarray(jax.vmap(prob.x_of_u)(jnp.asarray(full)))
    keys = [prob.params[i].key for i in idx]
    return {"keys": keys, "draws": x[:, idx], "u_draws": full, "acceptance": float(np.mean(acc)),
            "divergent": int(np.sum(div)), "step_size": float(params["step_size"])}


# --- the fitted model as an observe config -------------------------------------------------------------------------

_PATH_KEYS = ("path", "terms_file", "fit_result", "posterior")


def write_observe_config(fit: SkyFit, config_path, out_path, *, sections: dict | None = None,
                         effects_written: bool = False, header: str | None = None) -> Path:
    """The fitted facet model as an observe config: ``config_path`` with each facet's area, cant and yaw and each
    refitted model's parameters replaced by the fit's values, every facet predicted by the family the fit used (no
    alternatives; a refitted model's ``fit_result`` dropped: its covariance belongs to the lab fit), relative paths
    made absolute, and any ``[earthshine]`` table dropped (the problem has none of its own).  ``sections``: top-level
    tables set as given (``brdfjax skygap`` writes ``[effects]``, ``[earthshine]`` and ``[sun]`` of the diagnosed
    effects there).  ``brdfjax observe`` on it reproduces :meth:`SkyFit.predict` (a test).  A fit with effects of
    :mod:`.skygap` freed raises :class:`InputError` unless ``effects_written`` (the caller wrote them in
    ``sections``)."""
    prob = fit.problem
    free_effects = [p.key for i, p in enumerate(prob.params) if p.kind == "effect" and fit.free[i]]
    if free_effects and not effects_written:
        raise InputError(f"write_observe_config: effects {free_effects} have no observe-config form here "
                         "(brdfjax skygap writes them as [effects])")
    src = Path(config_path)
    data = read_toml(src, "observe config")

    def absolute(node):
        if isinstance(node, dict):
            return {k: (str((src.parent / v).resolve()) if k in _PATH_KEYS and isinstance(v, str)
                        and not Path(v).is_absolute() else absolute(v)) for k, v in node.items()}
        if isinstance(node, list):
            return [absolute(x) for x in node]
        return node

    data = absolute(data)
    data.pop("earthshine", None)  # the problem's facets carry no earthshine (skygap's candidate is written by it)
    data.pop("effects", None)
    vals = fit.values()
    for f in prob.facets:
        fc = data["facets"][f.name]
        fc["area_m2"] = vals[f"area.{f.name}"]
        for kind in ("cant", "yaw"):
            if f"{kind}.{f.name}" in vals:
                fc[f"{kind}_deg"] = float(np.rad2deg(vals[f"{kind}.{f.name}"]))
        fc["model"] = f.families[0]
        fc["alternatives"] = []
    changed: dict[str, dict] = {}
    for i, p in enumerate(prob.params):
        if p.kind == "model" and fit.free[i]:
            changed.setdefault(p.target, {})[p.name] = vals[p.key]
    for fam, upd in changed.items():
        m = data["models"][fam]
        terms = m.pop("terms", None) or read_toml(m.pop("terms_file"), f"terms file of models.{fam}")["terms"]
        m.pop("terms_file", None)
        m.pop("fit_result", None)
        for name, v in upd.items():
            term, par = name.split(".", 1)
            terms[term].setdefault("params", {})[par] = v
        m["terms"] = terms
    for k, v in (sections or {}).items():
        data[k] = v
    out = Path(out_path)
    return toml.write(out, data, header=header or f"{src.name} with the facet model fitted to observations "
                      "(brdfjax.lightcurve.skyfit.write_observe_config)")
