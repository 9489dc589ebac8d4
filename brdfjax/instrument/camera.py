"""The synthetic camera's per-pixel maps (dark signal, gain, non-linearity): one seeded draw per camera.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .config import (
    InstrumentConfig,
)
from .nd import parse_nd_filters

# --- the camera's per-pixel maps -------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """Per-pixel properties of one synthetic CCD (from ``camera_seed``), float32 ``(n_v, n_h)`` maps or None.

    ``nonlinearity``: signed per-pixel gain error g (fraction);
    ``ambient``: ambient rate map, counts/s; ``dark_pattern``: standard-normal
    fixed pattern; ``nd_offsets``: true minus nominal OD of each physical
    filter, keyed by ``(nominal OD, occurrence in a stack)``.
    """

    shape: tuple[int, int]
    nonlinearity: np.ndarray | None
    ambient: np.ndarray | None
    dark_pattern: np.ndarray | None
    nd_offsets: Mapping[tuple[float, int], float]

    @classmethod
    def build(cls, config: InstrumentConfig, shape: tuple[int, int]) -> "Camera":
        rng = np.random.default_rng([config.camera_seed, 0x5EED])
        rows, cols = shape
        nl = amb = dark = None
        c = config.nonlinearity
        if c.enabled:
            k_shape, theta = (c.gain_mean / c.gain_std) ** 2, c.gain_std**2 / c.gain_mean
            cap = max(c.outlier_threshold - c.common_max, 0.0)
            mag = rng.gamma(k_shape, theta, size=shape)
            bad = mag > cap
            while np.any(bad):  # truncated gamma by rejection: the tail beyond the threshold is the outliers'
                mag[bad] = rng.gamma(k_shape, theta, size=int(bad.sum()))
                bad = mag > cap
            outlier = rng.random(shape) < c.outlier_fraction
            n_out = int(outlier.sum())
            if n_out and c.outlier_max > c.outlier_threshold > 0:
                total = np.exp(rng.uniform(np.log(c.outlier_threshold), np.log(c.outlier_max), n_out))
                mag[outlier] = total - c.common_max
            sign = np.where(rng.random(shape) < 0.5, -1.0, 1.0)
            nl = (sign * mag).astype(np.float32)
        a = config.ambient
        if a.enabled:
            v = np.linspace(-1.0, 1.0, rows)[:, None]
            h = np.linspace(-1.0, 1.0, cols)[None, :]
            field = np.zeros(shape)
            for _ in range(4):  # a few smooth random waves across the array
                fx, fy = rng.uniform(0.2, 1.5, 2)
                ph1, ph2 = rng.uniform(0, 2 * np.pi, 2)
                field += np.cos(np.pi * fx * h + ph1) * np.cos(np.pi * fy * v + ph2)
            field = (field - field.mean()) / (field.std() or 1.0)
            pattern = np.clip(1.0 + a.nonuniformity * field, 0.0, None)
            amb = (a.rate_counts_per_s * pattern / pattern.mean()).astype(np.float32)
        if config.dark.enabled and config.dark.fixed_pattern_fraction > 0:
            dark = rng.standard_normal(shape).astype(np.float32)
        offsets: dict[tuple[float, int], float] = {}
        if config.nd_error.enabled:
            nd_rng = np.random.default_rng([config.camera_seed, 0x0D])
            for od, tol in sorted(config.nd_error.tolerances):
                for occ in range(4):
                    offsets[(round(od, 6), occ)] = float(nd_rng.uniform(-tol, tol))
        return cls((rows, cols), nl, amb, dark, offsets)

    def nonlinearity_map(self, config: InstrumentConfig) -> np.ndarray:
        """Each pixel's maximum response error relative to the array-average linear response, ``|g| + common_max``.

        This is the seed's ``dNL_s`` (§4.2, final method; Eq 92): what a
        characterised camera would hand the reduction as ``scatter_nonlinearity``.
        """
        if self.nonlinearity is None:
            return np.zeros(self.shape, np.float32)
        return (np.abs(self.nonlinearity) + np.float32(config.nonlinearity.common_max)).astype(np.float32)

    def true_od(self, nd_filters: str, config: InstrumentConfig) -> float:
        """The actual OD of a filter stack (nominal unless ``nd_error`` is on)."""
        filters = parse_nd_filters(nd_filters)
        if not config.nd_error.enabled:
            return float(sum(filters))
        seen: dict[float, int] = {}
        total = 0.0
        for od in filters:
            key = round(od, 6)
            occ = seen.get(key, 0)
            seen[key] = occ + 1
            if (key, occ) not in self.nd_offsets:
                known = sorted({k for k, _ in self.nd_offsets})
                raise ValueError(
                    f"nd_error: no tolerance for the {od:g} OD filter; known: {known}; add it to nd_error.tolerances"
                )
            total += od + self.nd_offsets[(key, occ)]
        return total
