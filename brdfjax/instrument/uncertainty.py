"""Per-pixel relative uncertainty of a CCD BRDF frame (seed Chapter IV, Eq 71-110).

A BRDF frame is reduced with Eq 45, ``f_r = Phi_s / (Phi_i cos(theta_s) Omega_d)``,
and its first-order relative uncertainty is Eq 71::

    df/f = [ (dPhi_s/Phi_s)^2 + (dPhi_i/Phi_i)^2 + (dOmega_d/Omega_d)^2 + (dtheta_s tan(theta_s))^2 ]^(1/2)

with each term itself a quadrature sum of independent contributions:

=====================  ====================================================  ==========
term (key)             contributions (keys)                                  seed
=====================  ====================================================  ==========
``scatter_flux``       ``scatter_nonlinearity`` (per pixel), ``scatter_noise``  Eq 92
``incident_flux``      ``incident_nonlinearity``, ``temporal``, ``nd``       Eq 93-98
``scatter_angle``      ``theta_R``, ``theta_d``, ``theta_c``,                 Eq 99-101,
                       ``theta_misalignment``                                105-106a
``solid_angle``        ``solid_angle_R``, ``solid_angle_d``,                 Eq 107-110
                       ``solid_angle_misalignment``
``total``              the four terms above                                  Eq 71
=====================  ====================================================  ==========

Every value under those keys is a **relative** standard uncertainty, a
dimensionless fraction (0.0308 means 3.08 %, the seed prints percent).  The
scatter-azimuth uncertainties of Eq 102-104 and 106b are returned as well, as
*absolute* angles in radians under ``dphi_s_*`` keys (``phi_s`` does not enter
Eq 45; the seed's relative values are these divided by ``phi_s`` in radians),
together with the absolute ``dtheta_s`` (rad).

How the geometric terms are computed
------------------------------------
No partial derivative is written out by hand.  For every pixel the core
mapping ``(R, d, theta_c) -> (theta_s, phi_s, Omega_d)`` of
:meth:`brdfjax.Detector.angles` and :meth:`brdfjax.Detector.solid_angle` is
differentiated with :func:`jax.jacfwd` (``d`` shifts the horizontal and the
vertical pitch together, seed ``d_h = d_v = d``), and Eq 45 itself is
differentiated with :func:`jax.grad` to get the sensitivities of ``ln f_r`` to
``theta_s`` (``tan theta_s``, the scaling Eq 71 applies) and to ``Omega_d``
(``-1/Omega_d``).  A term is then ``|d ln f/d x| |dx/dp| dp``.  The
misalignment terms are the differences between the nominal mapping and a
misaligned one (Eq 105, 109), scaled by the same Eq 45 sensitivities (seed
§4.4-4.5).  An independent analytic implementation of Eq 99-104 and 107-108
lives in ``tests/instrument/test_uncertainty.py`` and checks this to 1e-6.

As in the seed, the terms of Eq 71 are combined as if independent, although
``theta_s`` and ``Omega_d`` both depend on ``R`` and ``d``.

Seed inputs (module constants)
------------------------------
``dR = 5 mm``, ``dd = 4e-9 m``, ``dtheta_c = 0.5 deg`` (§4.4); incident-flux
non-linearity 0.018 % (Eq 93); temporal fluctuation 1.01 % (Eq 96); ND-filter
tolerances (§4.3): 0.1, 0.2, 0.3 OD +-0.01 and 4.0 OD +-0.2 as printed.  The
1.0 OD filter's tolerance is not printed; +-0.06 is inferred from two
independent seed results that it alone fixes: 14.2 % for beam 4.0+1.0+0.2 vs
sample 4.0+0.1 (§4.6) and 14.0 % for 4.0+1.0+0.2 vs 4.0 (§6, solar cell at
60 deg).  The per-pixel scatter non-linearity map of §4.2 is a measurement
the seed does not publish; only its summary (mean 2.18 %, std 0.50 %,
max 16.32 %, min 1.05 %) is given, in :data:`SEED_SCATTER_NONLINEARITY`.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ..core.detector import Detector, PixelGrid
from ..core.render import cast, map_rows, resolve_dtype
from .nd import SEED_ND_TOLERANCES, NDSpec, parse_nd_filters
from .radiometry import brdf_from_flux

__all__ = [
    "SEED_DISTANCE_UNCERTAINTY",
    "SEED_PITCH_UNCERTAINTY",
    "SEED_ARM_ANGLE_UNCERTAINTY",
    "SEED_INCIDENT_NONLINEARITY",
    "SEED_TEMPORAL",
    "SEED_SCATTER_NONLINEARITY",
    "brdf_eq45",
    "eq45_log_sensitivities",
    "uncancelled_filters",
    "optical_density_uncertainty",
    "incident_flux_uncertainty",
    "scatter_flux_uncertainty",
    "geometry_uncertainty",
    "brdf_uncertainty",
]

#: Uncertainty of the sample-to-array distance R, m (seed §4.4).
SEED_DISTANCE_UNCERTAINTY = 5e-3
#: Uncertainty of the pixel pitch d, m (seed §4.4).
SEED_PITCH_UNCERTAINTY = 4e-9
#: Uncertainty of the detector arm angle theta_c, rad (0.5 deg, seed §4.4).
SEED_ARM_ANGLE_UNCERTAINTY = float(np.deg2rad(0.5))
#: Array-average pixel non-linearity for the summed beam signature, relative (Eq 93: 0.018 %).
SEED_INCIDENT_NONLINEARITY = 1.8e-4
#: Temporal fluctuation of the incident flux, relative (Eq 96: 1.01 %).
SEED_TEMPORAL = 0.0101
#: Summary of the seed's per-pixel scatter non-linearity map (§4.2, Table 5), relative.  The map is unpublished.
SEED_SCATTER_NONLINEARITY: Mapping[str, float] = MappingProxyType(
    {"mean": 0.0218, "std": 0.0050, "max": 0.1632, "min": 0.0105}
)

Precision = Literal["float32", "float64"]


# -- Eq 45 and its sensitivities ----------------------------------------------------------


#: Eq 45 under its older name (the one definition is :func:`brdfjax.instrument.radiometry.brdf_from_flux`).
brdf_eq45 = brdf_from_flux


def eq45_log_sensitivities(theta_s: ArrayLike, solid_angle: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """``d ln f_r / d(Phi_s, Phi_i, theta_s, Omega_d)`` at ``Phi_s = Phi_i = 1``, by :func:`jax.grad` of Eq 45.

    Analytically ``(1, -1, tan theta_s, -1/Omega_d)``: multiplied by the
    relative flux uncertainties, the absolute ``dtheta_s`` (rad) and the
    absolute ``dOmega_d`` (sr), they give the four terms of Eq 71.  Works
    elementwise on arrays of any (common broadcast) shape.
    """
    theta_s, solid_angle = jnp.broadcast_arrays(jnp.asarray(theta_s), jnp.asarray(solid_angle))
    one = jnp.ones_like(theta_s)

    def log_f(phi_s, phi_i, th, om):
        return jnp.log(brdf_from_flux(phi_s, phi_i, th, om))

    grad = jax.grad(log_f, argnums=(0, 1, 2, 3))
    for _ in range(theta_s.ndim):
        grad = jax.vmap(grad)
    return grad(one, one, theta_s, solid_angle)


# -- incident flux: ND filters (Eq 97) and Eq 98 -------------------------------------------


def _od_key(od: float) -> float:
    return round(float(od), 6)


def _tolerance_table(tolerances: Mapping[Any, float] | None) -> dict[float, float]:
    table = SEED_ND_TOLERANCES if tolerances is None else tolerances
    if not isinstance(table, Mapping):
        raise ValueError(f"nd_tolerances must be a mapping nominal OD -> +-OD tolerance, got {table!r}")
    out = {}
    for k, v in table.items():
        try:
            key, tol = _od_key(k), float(v)
        except (TypeError, ValueError):
            raise ValueError(f"nd_tolerances: entry {k!r}: {v!r} is not a number -> number pair") from None
        if not (math.isfinite(tol) and tol >= 0):
            raise ValueError(f"nd_tolerances: tolerance of the {k!r} OD filter is {v!r}; expected a finite value >= 0")
        out[key] = tol
    return out


def uncancelled_filters(nd_beam: NDSpec, nd_sample: NDSpec) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Filters of the beam-signature and the sample stacks that do not cancel in Eq 87.

    A filter present in both stacks is the same physical filter, so its OD
    error cancels in ``OD_b - OD_m`` (seed §4.3); stacks are compared as
    multisets of nominal ODs.  Returns ``(beam_only, sample_only)``.
    """
    beam = Counter(_od_key(v) for v in parse_nd_filters(nd_beam))
    sample = Counter(_od_key(v) for v in parse_nd_filters(nd_sample))
    return tuple(sorted((beam - sample).elements())), tuple(sorted((sample - beam).elements()))


def optical_density_uncertainty(
    nd_beam: NDSpec, nd_sample: NDSpec, tolerances: Mapping[Any, float] | None = None
) -> float:
    """Relative incident-flux uncertainty from ND-filter OD tolerances (seed Eq 97), dimensionless.

    ``dPhi_OD / Phi_OD = ln(10) sqrt(sum of dOD^2 over the filters that differ)``
    between the beam-signature stack ``nd_beam`` and the sample stack
    ``nd_sample`` (see :func:`uncancelled_filters`).  ``tolerances`` maps nominal
    OD to its +- tolerance and replaces the seed's table
    :data:`SEED_ND_TOLERANCES` (extend it with ``{**SEED_ND_TOLERANCES, 0.5: ...}``).

    Seed mirror case: ``optical_density_uncertainty("4.0+1.0+0.2", "4.0+1.0")``
    is ``ln(10) * 0.01 = 0.0230`` (2.30 %).
    """
    table = _tolerance_table(tolerances)
    beam_only, sample_only = uncancelled_filters(nd_beam, nd_sample)
    total = 0.0
    for which, spec, filters in (("nd_beam", nd_beam, beam_only), ("nd_sample", nd_sample, sample_only)):
        for od in filters:
            if od not in table:
                known = ", ".join(f"{k:g}" for k in sorted(table)) or "none"
                raise ValueError(
                    f"ND filter {od:g} OD (in {which} {spec!r}) has no tolerance; known filters: {known}; "
                    f"pass nd_tolerances={{..., {od:g}: tolerance}}"
                )
            total += table[od] ** 2
    return math.log(10.0) * math.sqrt(total)


def _check_nonnegative(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {value!r}; expected a finite number >= 0") from None
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} = {value!r}; expected a finite number >= 0")
    return v


def incident_flux_uncertainty(
    nd: float, nonlinearity: float = SEED_INCIDENT_NONLINEARITY, temporal: float = SEED_TEMPORAL
) -> float:
    """Relative incident-flux uncertainty (seed Eq 98), dimensionless.

    ``sqrt(dNL_i^2 + (dPhi_T/Phi_T)^2 + (dPhi_OD/Phi_OD)^2)`` with the ND term
    ``nd`` from :func:`optical_density_uncertainty` (Eq 97), the array-average
    non-linearity (Eq 93, 0.018 %) and the temporal fluctuation (Eq 96, 1.01 %).
    """
    nd = _check_nonnegative("nd", nd)
    nonlinearity = _check_nonnegative("incident_nonlinearity", nonlinearity)
    temporal = _check_nonnegative("temporal", temporal)
    return math.sqrt(nonlinearity**2 + temporal**2 + nd**2)


def scatter_flux_uncertainty(nonlinearity: ArrayLike, noise: ArrayLike = 0.0) -> np.ndarray:
    """Relative scatter-flux uncertainty per pixel, dimensionless (seed Eq 92, plus counts noise).

    ``sqrt(dNL_s^2 + noise^2)``: ``nonlinearity`` is the seed's signed
    per-pixel maximum non-linear error relative to the array-wide linear
    response (§4.2; the root of the square makes it positive), ``noise`` the
    relative standard deviation of the stitched counts (``counts_std /
    counts``, >= 0).  The seed leaves noise out of Eq 92 and masks pixels near
    the noise floor instead; pass ``noise=0`` for its budget.  Scalars or
    arrays that broadcast together; NaN marks an unknown pixel and propagates.
    """
    nl = np.asarray(nonlinearity, dtype=np.float64)
    nz = np.asarray(noise, dtype=np.float64)
    if np.any(nz < 0) or np.any(np.isinf(nz)):
        raise ValueError(f"scatter_noise: relative standard deviations must be finite and >= 0, got min {np.nanmin(nz)!r}")
    if np.any(np.isinf(nl)):
        raise ValueError("scatter_nonlinearity: values must be finite (NaN marks an unknown pixel)")
    try:
        return np.sqrt(np.square(nl) + np.square(nz))
    except ValueError:
        raise ValueError(
            f"scatter_nonlinearity shape {nl.shape} and scatter_noise shape {nz.shape} do not broadcast together"
        ) from None


# -- geometry: scatter angle and solid angle ----------------------------------------------

_PARAMS = ("R", "d", "c")  # distance, pitch shift, arm angle


def _perturbed(detector: Detector, distance, pitch_shift) -> Detector:
    return eqx.tree_at(
        lambda x: (x.distance, x.pixel_pitch, x.pixel_pitch_v),
        detector,
        (distance, detector.pixel_pitch + pitch_shift, detector.pixel_pitch_v + pitch_shift),
    )


def _wrap(a):
    return jnp.mod(a + jnp.pi, 2 * jnp.pi) - jnp.pi


def _geometry_row(args, n_h_row, n_v):
    detector, theta_c, mis_angles, mis_theta_c, mis_omega, deltas = args

    def one(h):
        def mapping(p):
            det = _perturbed(detector, p[0], p[1])
            th, ph = det.angles(h, n_v, p[2])
            return jnp.stack([th, ph, det.solid_angle(h, n_v)])

        p0 = jnp.stack([jnp.asarray(detector.distance), jnp.zeros_like(theta_c), theta_c])
        values = mapping(p0)
        jac = jax.jacfwd(mapping)(p0)  # (output: theta_s, phi_s, Omega) x (param: R, d, theta_c)
        th, ph, om = values[0], values[1], values[2]
        _, _, s_theta, s_omega = eq45_log_sensitivities(th, om)
        out = {}
        for j, name in enumerate(_PARAMS):
            out[f"theta_{name}"] = jnp.abs(s_theta * jac[0, j]) * deltas[j]
            out[f"dphi_s_{name}"] = jnp.abs(jac[1, j]) * deltas[j]
            if name != "c":
                out[f"solid_angle_{name}"] = jnp.abs(s_omega * jac[2, j]) * deltas[j]
        if mis_angles is None:
            out["theta_misalignment"] = jnp.zeros_like(th)
            out["dphi_s_misalignment"] = jnp.zeros_like(th)
        else:
            th_m, ph_m = mis_angles.angles(h, n_v, mis_theta_c)
            out["theta_misalignment"] = jnp.abs(s_theta * (th_m - th))
            out["dphi_s_misalignment"] = jnp.abs(_wrap(ph_m - ph))
        if mis_omega is None:
            out["solid_angle_misalignment"] = jnp.zeros_like(om)
        else:
            out["solid_angle_misalignment"] = jnp.abs(s_omega * (mis_omega.solid_angle(h, n_v) - om))
        dtheta = [jnp.abs(jac[0, j]) * deltas[j] for j in range(3)]
        dtheta.append(jnp.zeros_like(th) if mis_angles is None else jnp.abs(th_m - th))
        out["dtheta_s"] = jnp.sqrt(sum(jnp.square(x) for x in dtheta))
        return out

    return jax.vmap(one)(n_h_row)


def _rows_per_chunk(n_rows: int, n_cols: int, chunk_pixels: int) -> int:
    """At most ``chunk_pixels`` pixels a chunk, balanced so that the last chunk pads less than one row per chunk."""
    rows = max(1, min(chunk_pixels // max(n_cols, 1), n_rows))
    n_chunks = -(-n_rows // rows)
    return -(-n_rows // n_chunks)


def _check_detector(name: str, det: Any, reference: Detector) -> None:
    if det is None:
        return
    if not isinstance(det, Detector):
        raise ValueError(f"{name} must be a brdfjax Detector or None, got {type(det).__name__}")
    if det.shape != reference.shape:
        raise ValueError(f"{name} has array shape {det.shape}; expected the nominal detector's {reference.shape}")


def geometry_uncertainty(
    detector: Detector,
    theta_i: float,
    grid: PixelGrid | None = None,
    *,
    dR: float = SEED_DISTANCE_UNCERTAINTY,
    dd: float = SEED_PITCH_UNCERTAINTY,
    dtheta_c: float = SEED_ARM_ANGLE_UNCERTAINTY,
    misaligned: Detector | None = None,
    misaligned_solid_angle: Detector | None = None,
    precision: Precision = "float32",
    chunk_pixels: int = 1 << 18,
) -> dict[str, np.ndarray]:
    """Per-pixel scatter-angle and solid-angle terms of Eq 71 (seed §4.4-4.5), arrays ``(rows, cols)``.

    ``detector`` is the nominal mapping used to reduce the frame (normally
    aligned); its arm angle is ``detector.theta_c`` or, if that is None,
    ``theta_i`` (rad).  ``dR`` (m), ``dd`` (m, applied to both pitches) and
    ``dtheta_c`` (rad) are standard uncertainties.  ``misaligned`` is the
    best estimate of the real geometry for the scatter angles (Eq 105; the
    measurement's peak offsets ``m_h, m_v`` and the CCD rotation) and
    ``misaligned_solid_angle`` that for the solid angle (Eq 109; the seed takes
    ``m_h, m_v`` from the beam signature there); the latter defaults to the
    former, and None leaves the misalignment terms at zero.  A misaligned
    detector's own ``theta_c`` is used if set.

    Keys (relative, dimensionless): ``theta_R``, ``theta_d``, ``theta_c``,
    ``theta_misalignment`` (Eq 99-101 and §4.4, each ``dtheta_s tan(theta_s)``),
    ``scatter_angle`` (Eq 106a); ``solid_angle_R``, ``solid_angle_d``,
    ``solid_angle_misalignment`` (Eq 107-109), ``solid_angle`` (Eq 110).
    Absolute, radians: ``dtheta_s`` (Eq 106a without the tan), ``dphi_s_R``,
    ``dphi_s_d``, ``dphi_s_c``, ``dphi_s_misalignment`` (Eq 102-104, §4.4)
    and ``dphi_s`` (Eq 106b times phi_s).

    ``precision="float32"`` gives the sensitivity terms to about 1e-5
    relative and the misalignment terms, differences of nearly equal angles
    and solid angles, to about 1 %; use ``"float64"`` (with 64-bit JAX
    enabled) for reference numbers.
    """
    if not isinstance(detector, Detector):
        raise ValueError(f"detector must be a brdfjax Detector, got {type(detector).__name__}")
    _check_detector("misaligned", misaligned, detector)
    _check_detector("misaligned_solid_angle", misaligned_solid_angle, detector)
    theta_i = float(theta_i)
    if not (0 <= theta_i < np.pi / 2):
        raise ValueError(f"theta_i = {theta_i!r} rad; expected 0 <= theta_i < pi/2")
    deltas = tuple(
        _check_nonnegative(n, v) for n, v in (("dR", dR), ("dd", dd), ("dtheta_c", dtheta_c))
    )
    if not (isinstance(chunk_pixels, int | np.integer) and chunk_pixels >= 1):
        raise ValueError(f"chunk_pixels = {chunk_pixels!r}; expected a positive integer")
    grid = detector.grid() if grid is None else grid
    if not isinstance(grid, PixelGrid):
        raise ValueError(f"grid must be a PixelGrid (see Detector.grid), got {type(grid).__name__}")
    dtype = resolve_dtype(precision)
    if misaligned_solid_angle is None:
        misaligned_solid_angle = misaligned

    theta_c = float(np.asarray(detector.arm_angle(theta_i)))
    mis_theta_c = theta_c
    if misaligned is not None and misaligned.theta_c is not None:
        mis_theta_c = float(np.asarray(misaligned.theta_c))
    args = cast(
        (detector, jnp.asarray(theta_c), misaligned, jnp.asarray(mis_theta_c), misaligned_solid_angle,
         jnp.asarray(deltas)),
        dtype,
    )
    rows = _rows_per_chunk(grid.n_v.size, grid.n_h.size, chunk_pixels)
    out = map_rows(_geometry_row, args, jnp.asarray(grid.n_h, dtype), jnp.asarray(grid.n_v, dtype), rows)
    res = {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}
    res["scatter_angle"] = np.sqrt(sum(np.square(res[f"theta_{k}"]) for k in ("R", "d", "c", "misalignment")))
    res["dphi_s"] = np.sqrt(sum(np.square(res[f"dphi_s_{k}"]) for k in ("R", "d", "c", "misalignment")))
    res["solid_angle"] = np.sqrt(sum(np.square(res[f"solid_angle_{k}"]) for k in ("R", "d", "misalignment")))
    return res


# -- the whole budget ---------------------------------------------------------------------


def _per_pixel(name: str, value: ArrayLike, shape: tuple[int, int]) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim != 0 and a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape}; expected a scalar or the grid shape (rows, cols) = {shape}")
    return a


def brdf_uncertainty(
    detector: Detector,
    theta_i: float,
    grid: PixelGrid | None = None,
    *,
    scatter_nonlinearity: ArrayLike,
    scatter_noise: ArrayLike = 0.0,
    nd_beam: NDSpec = None,
    nd_sample: NDSpec = None,
    nd_tolerances: Mapping[Any, float] | None = None,
    nd: float | None = None,
    incident_nonlinearity: float = SEED_INCIDENT_NONLINEARITY,
    temporal: float = SEED_TEMPORAL,
    dR: float = SEED_DISTANCE_UNCERTAINTY,
    dd: float = SEED_PITCH_UNCERTAINTY,
    dtheta_c: float = SEED_ARM_ANGLE_UNCERTAINTY,
    misaligned: Detector | None = None,
    misaligned_solid_angle: Detector | None = None,
    precision: Precision = "float32",
    chunk_pixels: int = 1 << 18,
) -> dict[str, np.ndarray]:
    """Relative uncertainty of every pixel of a CCD BRDF frame, by term (seed Eq 71).

    Parameters (angles in radians, lengths in metres, uncertainties standard):

    - ``detector``, ``theta_i``, ``grid``: the nominal pixel mapping, the
      incidence angle (the arm sits at ``theta_c = theta_i`` unless
      ``detector.theta_c`` is set) and the pixels (default: the full array;
      use ``detector.grid(step)`` for a decimated frame).  Rows are evaluated
      in chunks of about ``chunk_pixels`` pixels, so the full 8.1-Mpixel
      frame runs in bounded memory.
    - ``scatter_nonlinearity``: per-pixel non-linearity dNL_s (Eq 92), a
      scalar or an array of the grid's shape (signed values allowed);
      ``scatter_noise``: relative std of the stitched counts, same shapes.
    - ND filters (Eq 97): the beam-signature stack ``nd_beam`` and the sample
      stack ``nd_sample`` (``"4.0+1.0+0.2"``, a sequence of ODs, or None for
      no filter), with ``nd_tolerances`` (default :data:`SEED_ND_TOLERANCES`);
      or ``nd``, the relative ND term itself (e.g. 0 after characterising the
      filters).  Give the stacks or ``nd``, not both.
    - ``incident_nonlinearity`` (Eq 93), ``temporal`` (Eq 96): relative.
    - ``dR``, ``dd``, ``dtheta_c``, ``misaligned``, ``misaligned_solid_angle``:
      see :func:`geometry_uncertainty`.

    Returns NumPy float64 values, every one a relative (dimensionless)
    standard uncertainty except the ``dtheta_s*`` / ``dphi_s*`` angles (rad):
    ``total`` (Eq 71), ``scatter_flux`` (Eq 92) with ``scatter_nonlinearity``
    and ``scatter_noise``; ``incident_flux`` (Eq 98) with ``nd`` (Eq 97),
    ``incident_nonlinearity`` and ``temporal``; ``scatter_angle`` (Eq 106a)
    with ``theta_R``, ``theta_d``, ``theta_c``, ``theta_misalignment``;
    ``solid_angle`` (Eq 110) with ``solid_angle_R``, ``solid_angle_d``,
    ``solid_angle_misalignment``; and ``dtheta_s``, ``dphi_s``,
    ``dphi_s_R``, ``dphi_s_d``, ``dphi_s_c``, ``dphi_s_misalignment``.
    Per-pixel values have the grid's shape ``(rows, cols)``; the incident-flux
    terms (and scatter-flux terms given as scalars) are 0-d arrays that
    broadcast against it.
    """
    grid = detector.grid() if grid is None and isinstance(detector, Detector) else grid
    shape = grid.shape if isinstance(grid, PixelGrid) else None
    if shape is None:
        raise ValueError(f"grid must be a PixelGrid (see Detector.grid), got {type(grid).__name__}")
    nl = _per_pixel("scatter_nonlinearity", scatter_nonlinearity, shape)
    noise = _per_pixel("scatter_noise", scatter_noise, shape)
    scatter = scatter_flux_uncertainty(nl, noise)

    stacks_given = nd_beam is not None or nd_sample is not None
    if nd is not None and (stacks_given or nd_tolerances is not None):
        raise ValueError("give either the ND stacks (nd_beam, nd_sample, nd_tolerances) or the ND term nd, not both")
    if nd is None:
        if not stacks_given:
            raise ValueError(
                "the ND-filter term needs nd_beam and nd_sample (e.g. '4.0+1.0+0.2' and '4.0+1.0'), "
                "or nd (0 if the stacks are identical or the filters characterised)"
            )
        nd = optical_density_uncertainty(nd_beam, nd_sample, nd_tolerances)
    nd = _check_nonnegative("nd", nd)
    incident = incident_flux_uncertainty(nd, incident_nonlinearity, temporal)

    res = geometry_uncertainty(
        detector,
        theta_i,
        grid,
        dR=dR,
        dd=dd,
        dtheta_c=dtheta_c,
        misaligned=misaligned,
        misaligned_solid_angle=misaligned_solid_angle,
        precision=precision,
        chunk_pixels=chunk_pixels,
    )
    res.update(
        scatter_flux=scatter,
        scatter_nonlinearity=np.abs(nl),
        scatter_noise=noise,
        incident_flux=np.asarray(incident),
        nd=np.asarray(nd),
        incident_nonlinearity=np.asarray(float(incident_nonlinearity)),
        temporal=np.asarray(float(temporal)),
    )
    res["total"] = np.sqrt(
        np.square(scatter) + incident**2 + np.square(res["scatter_angle"]) + np.square(res["solid_angle"])
    )
    return res
