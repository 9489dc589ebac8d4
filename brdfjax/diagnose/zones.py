"""WHERE the model misses the data: significant residual regions and named zones.

Input: per data block, the normalised residual ``r = (ln d - ln f) / sigma_ln``
(NaN where a point is not used) and the specular-relative coordinates
``(sx, sy)`` in degrees (:func:`specular_coordinates`): ``sx`` along the plane
of incidence (positive toward larger theta_s), ``sy`` out of the plane
(positive toward +y), both measured from the specular direction.

A *region* is a connected set of points whose smoothed residual is
significant: on frames the residual map is box-averaged over ``smooth`` x
``smooth`` points (NaNs excluded) and scaled by ``sqrt(count)``, so that pure
noise has ``z ~ N(0, 1)``; points with ``|z| > threshold`` are labelled into
4-connected components, positive and negative separately (a region has one
sign).  On goniometer tables the same is done along each incidence angle's
samples sorted by ``sx`` (runs of consecutive samples; the zones are then
angle intervals).  Labelling is a breadth-first search (SciPy is not a
runtime dependency).

Each region gets its centroid relative to the specular direction, its extent
(2-sigma half lengths along its principal axes, from the second moments of
the positions weighted by ``r^2``), its orientation (major axis, degrees from
``+sx`` toward ``+sy``, in [0, 180)), its sign, its share of the total misfit
(``sum r^2`` in the region over the total chi^2) and a zone name:

- ``far field`` first when the region covers 30 % or more of the block's
  points or is larger than the wings' diameter and half the block: a
  structure that spans the frame is a floor or far field whatever its
  centroid (named by extent and position together);
- ``peak core``: the centroid within the peak core (where the data are
  above half their maximum), the region not elongated and no larger than
  three core radii;
- ``band``: an elongated region (axis ratio > 3, longer than the peak core's
  diameter) whose axis passes through the peak: a band through the peak with
  its orientation (diffraction bars, anisotropy);
- ``peak wings``: the centroid within the wings (the data above 1e-3 of their
  maximum, at most 6 core radii) but outside the core;
- ``secondary lobe``: a compact region outside the wings (an offset peak,
  a stray-light sub-peak; "at the specular direction" when it sits there
  while the brightest peak is elsewhere);
- ``far field``: anything else (background, a diffuse floor).

Every description gives the region's extent and its distance from both the
brightest peak and the specular direction.

The remaining points form the ``background`` zone.  The peak is located at
the data's maximum (not the fitted model's: a base fit that absorbs a
missing effect by widening its peak must not widen the zones), so that a
sample whose brightest lobe is itself offset still has its core where the
light is.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "Region",
    "specular_coordinates",
    "smoothed_z",
    "label",
    "find_regions",
    "ZONE_KINDS",
]

ZONE_KINDS = ("peak core", "peak wings", "band", "secondary lobe", "far field", "background")


def _unit(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit vectors of zenith ``theta`` and azimuth ``phi`` measured from -x (brdfjax.core.geometry convention)."""
    st = np.sin(theta)
    return np.stack([-st * np.cos(phi), -st * np.sin(phi), np.cos(theta)], axis=-1)


def specular_coordinates(theta_s: Any, phi_s: Any, theta_i: Any, phi_i: Any = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(sx, sy)`` in degrees of scatter directions relative to the specular direction.

    The specular direction of incidence ``(theta_i, phi_i)`` has zenith
    ``theta_i`` and azimuth ``phi_i + pi``.  ``sx = asin(w . e_theta)``,
    ``sy = asin(w . e_phi)`` with ``e_theta``, ``e_phi`` the unit tangents at
    the specular direction (toward larger zenith, larger azimuth x -1: +y for
    the in-plane case ``phi_i = 0``).  All angles in radians in, degrees out.
    """
    theta_s, phi_s = np.asarray(theta_s, float), np.asarray(phi_s, float)
    theta_i = np.broadcast_to(np.asarray(theta_i, float), theta_s.shape)
    phi_spec = np.broadcast_to(np.asarray(phi_i, float), theta_s.shape) + np.pi
    w = _unit(theta_s, phi_s)
    ct, st = np.cos(theta_i), np.sin(theta_i)
    cp, sp = np.cos(phi_spec), np.sin(phi_spec)
    e_theta = np.stack([-ct * cp, -ct * sp, -st], axis=-1)
    e_phi = np.stack([sp, -cp, np.zeros_like(cp)], axis=-1)
    x = np.clip(np.sum(w * e_theta, axis=-1), -1, 1)
    y = np.clip(np.sum(w * e_phi, axis=-1), -1, 1)
    return np.degrees(np.arcsin(x)), np.degrees(np.arcsin(y))


def _box_sum(a: np.ndarray, size: int) -> np.ndarray:
    """Sum over a ``size``-wide centred box along every axis (zero outside), via cumulative sums."""
    h = size // 2
    out = a
    for ax in range(a.ndim):
        pad = [(0, 0)] * a.ndim
        pad[ax] = (h + 1, h)
        c = np.cumsum(np.pad(out, pad), axis=ax)
        n = out.shape[ax]
        hi = np.take(c, np.arange(size, size + n), axis=ax)
        lo = np.take(c, np.arange(0, n), axis=ax)
        out = hi - lo
    return out


def smoothed_z(r: np.ndarray, size: int) -> np.ndarray:
    """Box-averaged residual scaled to unit variance under pure noise: ``sum(r) / sqrt(count)``; NaN where no data."""
    r = np.asarray(r, float)
    ok = np.isfinite(r)
    if size <= 1:
        return np.where(ok, r, np.nan)
    s = _box_sum(np.where(ok, r, 0.0), size)
    n = _box_sum(ok.astype(float), size)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = s / np.sqrt(n)
    return np.where(ok & (n > 0), z, np.nan)


def label(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected components of a boolean array (4-connectivity in 2-D, runs in 1-D): ``(labels, n)``, 0 = none."""
    mask = np.asarray(mask, bool)
    labels = np.zeros(mask.shape, np.int32)
    n = 0
    shape = mask.shape
    offsets = [tuple(int(d == ax) * s for d in range(mask.ndim)) for ax in range(mask.ndim) for s in (-1, 1)]
    for start in zip(*np.nonzero(mask)):
        if labels[start]:
            continue
        n += 1
        labels[start] = n
        queue = deque([start])
        while queue:
            p = queue.popleft()
            for off in offsets:
                q = tuple(a + b for a, b in zip(p, off))
                if all(0 <= q[d] < shape[d] for d in range(len(shape))) and mask[q] and not labels[q]:
                    labels[q] = n
                    queue.append(q)
    return labels, n


@dataclass
class Region:
    """A significant residual structure in one block (see the module docstring)."""

    block: int
    name: str  # the zone kind, e.g. "band"
    sign: int  # +1: data above the model, -1: below
    share: float  # sum r^2 in the region / total chi^2 of all blocks
    chi2: float
    n_points: int
    center_deg: tuple[float, float]  # (sx, sy) centroid relative to specular
    extent_deg: tuple[float, float]  # (major, minor) 2-sigma half lengths
    orientation_deg: float  # major axis from +sx toward +sy, [0, 180)
    mask: np.ndarray = field(repr=False, default=None)  # boolean, the block's grid shape
    description: str = ""

    def to_dict(self, block_name: str | None = None) -> dict[str, Any]:
        return {
            "name": self.name,
            "block": block_name if block_name is not None else self.block,
            "share": float(self.share),
            "chi2": float(self.chi2),
            "n_points": int(self.n_points),
            "center_deg": [float(x) for x in self.center_deg],
            "extent_deg": [float(x) for x in self.extent_deg],
            "orientation_deg": float(self.orientation_deg),
            "sign": "positive" if self.sign > 0 else "negative" if self.sign < 0 else "none",
            "description": self.description,
        }


def _moments(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float, float, float, float]:
    w = w / w.sum()
    cx, cy = float(np.sum(w * x)), float(np.sum(w * y))
    dx, dy = x - cx, y - cy
    cov = np.array([[np.sum(w * dx * dx), np.sum(w * dx * dy)], [np.sum(w * dx * dy), np.sum(w * dy * dy)]])
    vals, vecs = np.linalg.eigh(cov)
    major = vecs[:, 1]
    ang = float(np.degrees(np.arctan2(major[1], major[0])) % 180.0)
    return cx, cy, 2 * float(np.sqrt(max(vals[1], 0))), 2 * float(np.sqrt(max(vals[0], 0))), ang


def peak_scales(model: np.ndarray, sx: np.ndarray, sy: np.ndarray, usable: np.ndarray) -> dict[str, float]:
    """The peak location of ``model`` (any BRDF values) and its core (> 50 % of max) and wing (> 1e-3 of max) radii, degrees."""
    m = np.where(usable & np.isfinite(model), model, -np.inf)
    if not np.isfinite(m).any():
        return {"px": 0.0, "py": 0.0, "core": 0.0, "wings": 0.0}
    k = int(np.argmax(m))
    px, py = float(sx.flat[k]), float(sy.flat[k])
    top = float(m.flat[k])
    d = np.hypot(sx - px, sy - py)
    core = float(np.max(d[m >= 0.5 * top])) if np.any(m >= 0.5 * top) else 0.0
    wings = float(np.max(d[m >= 1e-3 * top])) if np.any(m >= 1e-3 * top) else core
    # a peak narrower than the sampling: at least one grid spacing
    spacing = float(np.nanmedian(np.abs(np.diff(np.sort(np.unique(np.round(sx[usable], 6))))))) if usable.sum() > 2 else 0.0
    core = max(core, spacing)
    return {"px": px, "py": py, "core": core, "wings": max(min(wings, 6 * core), 2 * spacing, core)}


def _classify(cx, cy, major, minor, ang, scales, one_d: bool, cover: float = 0.0, span: float = math.inf) -> tuple[str, str]:
    """Zone kind and description from a region's position AND extent (named by the centroid alone, a
    floor spanning the whole region was called a peak core, and a lobe at the specular direction a secondary
    lobe of the brighter offset peak).

    ``cover``: the share of the block's usable points in the region; ``span``: the block's half-size (deg).
    """
    px, py, core, wings = scales["px"], scales["py"], scales["core"], scales["wings"]
    dc = float(np.hypot(cx - px, cy - py))
    ds = float(np.hypot(cx, cy))  # from the specular direction
    where = f"centre {dc:.3g} deg from the brightest peak, {ds:.3g} deg from the specular direction"
    size = f"extent {major:.3g} x {minor:.3g} deg"
    elong = major / max(minor, 1e-12)
    # distance from the peak to the region's major axis line
    ux, uy = np.cos(np.radians(ang)), np.sin(np.radians(ang))
    d_axis = abs((px - cx) * uy - (py - cy) * ux)
    # thin across (minor < a quarter of the block's half-size) it is a band even where it holds most of the usable
    # points: a frame masked to the pixels above the noise keeps little more than the fringes (measured: a bar band
    # covering 68 % of the usable points, 0.30 x 0.079 deg in a 0.41-deg block, was named far field)
    if (not one_d and elong > 3.0 and major > 2 * core and d_axis < max(core, 0.25 * major)
            and (cover < 0.5 or minor < 0.25 * span)):
        return "band", f"a band through the peak oriented {ang:.0f} deg from the plane of incidence ({size}, {where})"
    spread = major > max(2.0 * wings, 0.5 * span) if math.isfinite(span) else False
    if cover >= 0.3 or spread:
        # a region spanning much of the block is a floor or far-field structure whatever its centroid
        return "far field", f"spans {100 * cover:.0f} % of the block's points ({size}, {where}): a floor or far-field structure"
    if dc <= core and (one_d or elong <= 3.0 or major <= 2 * core) and (one_d or major <= 3.0 * core):
        return "peak core", f"the peak core: {size}, {where} (core radius {core:.3g} deg)"
    if dc <= wings:
        return "peak wings", f"{size}, {where} (wings extend to {wings:.3g} deg)"
    if major <= max(wings, 0.2 * dc) or elong <= 3.0 and major <= 0.5 * dc:
        what = "a lobe at the specular direction" if ds <= max(core, major) else "an isolated lobe"
        return "secondary lobe", f"{what}: {size}, {where}"
    return "far field", f"{size}, {where}, beyond the wings"


def find_regions(
    residuals: list[np.ndarray],
    geometry: list[dict[str, np.ndarray]],
    values: list[np.ndarray],
    *,
    groups: list[np.ndarray | None] | None = None,
    threshold: float = 4.0,
    smooth: int = 3,
    min_points: int = 4,
    max_regions: int = 12,
) -> list[Region]:
    """Significant regions of every block, largest share first (see the module docstring).

    ``values``: per block the BRDF that locates the peak and sets its core and
    wing radii (the engine passes the data: a distorted base fit must not move
    the zones).  ``groups``: per block, for tables, an integer group per row
    (one group per incidence angle); ``None`` for frames.
    """
    total = float(sum(np.nansum(np.square(r)) for r in residuals))
    total = total if total > 0 else 1.0
    out: list[Region] = []
    for bi, (r, geo, mv) in enumerate(zip(residuals, geometry, values)):
        r = np.asarray(r, float)
        usable = np.isfinite(r)
        sx, sy = np.asarray(geo["sx"], float), np.asarray(geo["sy"], float)
        grp = None if groups is None else groups[bi]
        one_d = r.ndim == 1
        masks: list[tuple[np.ndarray, int]] = []
        n_usable = max(int(usable.sum()), 1)
        span = 0.5 * float(np.hypot(np.ptp(sx[usable]), np.ptp(sy[usable]))) if usable.any() and not one_d else math.inf
        if not one_d:
            scales = peak_scales(np.asarray(mv, float), sx, sy, usable)
            z = smoothed_z(r, smooth)
            for sign in (1, -1):
                lab, n = label(np.nan_to_num(sign * z, nan=0.0) > threshold)
                masks.extend(((lab == k) & usable, sign) for k in range(1, n + 1))
        else:
            grp = np.zeros(r.shape, int) if grp is None else np.asarray(grp)
            scales_by = {}
            for g in np.unique(grp):
                idx = np.flatnonzero(grp == g)
                idx = idx[np.argsort(sx[idx])]
                zg = smoothed_z(r[idx], smooth)
                scales_by[g] = peak_scales(np.asarray(mv, float)[idx], sx[idx], sy[idx], usable[idx])
                for sign in (1, -1):
                    lab, n = label(np.nan_to_num(sign * zg, nan=0.0) > threshold)
                    for k in range(1, n + 1):
                        m = np.zeros(r.shape, bool)
                        m[idx[lab == k]] = True
                        masks.append((m & usable, sign))
        for m, sign in masks:
            npts = int(m.sum())
            if npts < min_points:
                continue
            w = np.square(r[m])
            chi2 = float(w.sum())
            if w.sum() <= 0:
                continue
            cx, cy, major, minor, ang = _moments(sx[m], sy[m], w)
            if one_d:
                sc = scales_by[int(np.bincount(grp[m]).argmax())]
                major, minor = 0.5 * float(np.ptp(sx[m])), 0.0
                ang = 0.0
            else:
                sc = scales
            name, desc = _classify(cx, cy, major, minor, ang, sc, one_d, npts / n_usable, span)
            out.append(Region(bi, name, sign, chi2 / total, chi2, npts, (cx, cy), (major, minor), ang, m, desc))
    out.sort(key=lambda z: -z.share)
    return out[:max_regions]


def zone_masks(regions: list[Region], residuals: list[np.ndarray]) -> dict[str, list[np.ndarray]]:
    """Per zone label (``"<kind> #k"``, plus ``"background"``): the per-block boolean masks.

    Used to measure every step of the explanation path on the same zones.
    """
    out: dict[str, list[np.ndarray]] = {}
    covered = [np.zeros(np.shape(r), bool) for r in residuals]
    for k, reg in enumerate(regions):
        ms = [np.zeros(np.shape(r), bool) for r in residuals]
        ms[reg.block] = reg.mask
        covered[reg.block] |= reg.mask
        out[zone_label(reg, k)] = ms
    out["background"] = [np.isfinite(np.asarray(r, float)) & ~c for r, c in zip(residuals, covered)]
    return out


def zone_label(reg: Region, k: int) -> str:
    return f"{reg.name} #{k + 1}"
