"""Data containers of a fit: detector frames and goniometer tables (NumPy, at the edge).

:class:`FrameData` is one BRDF frame on a pixel grid with its per-pixel
relative uncertainty and mask, as the instrument reduction produces it (a
later step reads them from frame EXRs).  :class:`TableData` is a list of
goniometer samples ``(theta_i, phi_i, theta_s, phi_s[, wavelength], brdf[,
sigma_rel])``; :mod:`brdfjax.io.tables` reads them from files.

Both are frozen and validated on construction (shapes, finiteness, units);
validation never changes the values.  :meth:`usable` is the boolean selection
of points a fit uses: inside the mask, finite and positive BRDF, finite and
positive ``sigma_rel``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.detector import Detector, PixelGrid
from ..runtime.errors import FitInputError

__all__ = ["FrameData", "TableData"]


def _array(owner: str, field: str, value: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise FitInputError(f"{owner}: '{field}' is not a numeric array ({err})") from None
    if shape is not None and a.shape != shape and a.ndim != 0:
        raise FitInputError(f"{owner}: '{field}' has shape {a.shape}, expected {shape} (or a scalar)")
    return a


def _describe_unusable(owner: str, n: int, in_mask: np.ndarray, brdf: np.ndarray, sigma: np.ndarray | None) -> str:
    n_mask = int(in_mask.sum())
    if n_mask == 0:
        return f"{owner}: no usable points: the mask selects none of the {n} points"
    b = brdf[in_mask]
    parts = [f"{int((~np.isfinite(b)).sum())} have NaN/inf brdf", f"{int((np.isfinite(b) & (b <= 0)).sum())} have brdf <= 0"]
    if sigma is not None:
        s = np.broadcast_to(sigma, brdf.shape)[in_mask]
        parts.append(f"{int((~(np.isfinite(s) & (s > 0))).sum())} have sigma_rel that is not a positive number")
    return f"{owner}: no usable points: of the {n_mask} points in the mask, " + ", ".join(parts)


@dataclass(frozen=True, eq=False)
class FrameData:
    """One measured BRDF frame on a detector pixel grid.

    ``brdf`` (sr^-1) and ``sigma_rel`` (relative 1-sigma uncertainty of the
    BRDF, a scalar or per pixel) are ``(rows, cols) = grid.shape`` arrays,
    ``mask`` (True: use the pixel; ``None``: all) likewise.  ``theta_i``,
    ``phi_ref`` (rad) and ``wavelength`` (m) are the frame's nominal
    conditions; ``detector`` the camera it was taken with (if its ``theta_c``
    is ``None``, the arm is taken to sit at the nominal ``theta_i``, so that a
    fit that frees ``theta_i`` moves the incidence, not the camera).
    ``footprint``: the instrument function, a 2-D kernel sampled on the
    grid's pixel spacing (odd sides, centred, normalised to sum 1 by the fit)
    with which the model is convolved before comparison; ``None``: none.
    ``systematics``: the frame-wide errors a fit may model as nuisance
    parameters (:mod:`brdfjax.fit._nuisance`); ``None``: none known.
    """

    brdf: Any
    sigma_rel: Any
    theta_i: float
    detector: Detector
    grid: PixelGrid
    mask: Any = None
    phi_ref: float = 0.0
    wavelength: float = 632.8e-9
    footprint: Any = None
    name: str = "frame"
    # The frame-wide errors of a frame that came through the instrument (ND stacks, incident flux,
    # non-linearity level; brdfjax.fit._nuisance.FrameSystematics), read from a reduced frame's header.
    systematics: Any = None

    def __post_init__(self):
        owner = f"frame '{self.name}'"
        if not isinstance(self.detector, Detector):
            raise FitInputError(f"{owner}: 'detector' must be a brdfjax Detector, got {type(self.detector).__name__}")
        if not isinstance(self.grid, PixelGrid):
            raise FitInputError(f"{owner}: 'grid' must be a PixelGrid (Detector.grid(step, roi)), got {type(self.grid).__name__}")
        shape = self.grid.shape
        b = _array(owner, "brdf", self.brdf)
        if b.shape != shape:
            raise FitInputError(f"{owner}: 'brdf' has shape {b.shape}, but the grid is {shape} (rows, cols)")
        _array(owner, "sigma_rel", self.sigma_rel, shape)
        if self.mask is not None and np.shape(self.mask) != shape:
            raise FitInputError(f"{owner}: 'mask' has shape {np.shape(self.mask)}, but the grid is {shape}")
        for f, ok, what in (
            ("theta_i", lambda v: 0 <= v < np.pi / 2, "0 <= theta_i < pi/2 (radians)"),
            ("phi_ref", np.isfinite, "a finite angle in radians"),
            ("wavelength", lambda v: v > 0, "a positive wavelength in metres"),
        ):
            v = getattr(self, f)
            if np.ndim(v) != 0 or not np.isfinite(float(v)) or not ok(float(v)):
                raise FitInputError(f"{owner}: '{f}' = {v!r} is invalid; expected {what}")
        if self.footprint is not None:
            k = _array(owner, "footprint", self.footprint)
            if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
                raise FitInputError(f"{owner}: 'footprint' must be a 2-D kernel with odd sides, got shape {k.shape}")
            if not np.all(np.isfinite(k)) or k.sum() <= 0 or np.any(k < 0):
                raise FitInputError(f"{owner}: 'footprint' must be finite, non-negative and not all zero")
        b = np.asarray(self.brdf, dtype=np.float64)
        if b.size and np.all(np.isnan(b)):
            raise FitInputError(f"{owner}: 'brdf' is all NaN")

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape

    def usable(self) -> np.ndarray:
        """Boolean (rows, cols): in the mask, finite positive BRDF, finite positive sigma_rel."""
        b = np.asarray(self.brdf, dtype=np.float64)
        s = np.broadcast_to(np.asarray(self.sigma_rel, dtype=np.float64), b.shape)
        m = np.ones(b.shape, bool) if self.mask is None else np.asarray(self.mask, dtype=bool)
        with np.errstate(invalid="ignore"):
            return m & np.isfinite(b) & (b > 0) & np.isfinite(s) & (s > 0)

    def check_usable(self) -> np.ndarray:
        """:meth:`usable`, raising :class:`FitInputError` (saying why) when it selects nothing."""
        u = self.usable()
        if not u.any():
            m = np.ones(self.shape, bool) if self.mask is None else np.asarray(self.mask, dtype=bool)
            raise FitInputError(
                _describe_unusable(f"frame '{self.name}'", u.size, m, np.asarray(self.brdf, float), np.asarray(self.sigma_rel, float))
            )
        return u

    def arm_detector(self) -> Detector:
        """The detector with its arm fixed at the nominal ``theta_i`` when it follows the peak."""
        return self.detector.with_arm(np.float64(self.theta_i))


@dataclass(frozen=True, eq=False)
class TableData:
    """Goniometer samples: one row per (incident, scattered) direction pair.

    Angles in radians, azimuths from -x as in :mod:`brdfjax.core.geometry`
    (``phi_i = 0`` puts the source at -x; the mirror direction is then
    ``phi_s = pi``); ``brdf`` in sr^-1; ``sigma_rel`` the relative 1-sigma
    uncertainty (``None``: unknown, every point weighted 1 and the covariance
    scaled by the residual variance); ``wavelength`` in metres (a scalar or
    per row); ``mask`` True where a row is used.  ``source`` names the file it
    came from, for messages; ``lines`` the file's line number of each row
    (``None``: not read from a line-oriented file).
    """

    theta_i: Any
    phi_i: Any
    theta_s: Any
    phi_s: Any
    brdf: Any
    sigma_rel: Any = None
    wavelength: Any = 632.8e-9
    mask: Any = None
    name: str = "table"
    source: str = ""
    lines: Any = None  # the file's line number of each row (for messages), or None
    screening: Any = None  # the reader's record of the rows it dropped and of its checks (a dict), or None

    def __post_init__(self):
        owner = f"table '{self.name}'" + (f" ({self.source})" if self.source else "")
        b = _array(owner, "brdf", self.brdf)
        if b.ndim != 1:
            raise FitInputError(f"{owner}: 'brdf' must be 1-D (one value per row), got shape {b.shape}")
        n = b.shape
        for f in ("theta_i", "phi_i", "theta_s", "phi_s"):
            a = _array(owner, f, getattr(self, f), n)
            if not np.all(np.isfinite(a)):
                raise FitInputError(f"{owner}: '{f}' has {int((~np.isfinite(a)).sum())} non-finite values")
        ti = _array(owner, "theta_i", self.theta_i, n)
        ts = _array(owner, "theta_s", self.theta_s, n)
        if np.any(ti < 0) or np.any(ts < 0):
            raise FitInputError(
                f"{owner}: negative zenith angles; zeniths are >= 0 with the side given by the azimuth "
                "(for signed in-plane angles, read the file with signed_inplane=True)"
            )
        if np.any(ti > np.pi / 2 + 1e-9) or np.any(ts > np.pi / 2 + 1e-9):
            raise FitInputError(
                f"{owner}: zenith angles beyond 90 deg (max |theta_i| = {np.degrees(np.abs(ti).max()):.4g} deg, "
                f"|theta_s| = {np.degrees(np.abs(ts).max()):.4g} deg); are they in degrees? give radians"
            )
        if self.sigma_rel is not None:
            _array(owner, "sigma_rel", self.sigma_rel, n)
        w = _array(owner, "wavelength", self.wavelength, n)
        if not np.all(np.isfinite(w) & (w > 0)) or np.any(w > 1e-3):
            raise FitInputError(f"{owner}: 'wavelength' must be positive and in metres (e.g. 632.8e-9)")
        if self.mask is not None and np.shape(self.mask) != n:
            raise FitInputError(f"{owner}: 'mask' has shape {np.shape(self.mask)}, expected {n}")
        if b.size and np.all(np.isnan(b)):
            raise FitInputError(f"{owner}: 'brdf' is all NaN")

    def __len__(self) -> int:
        return int(np.asarray(self.brdf).shape[0])

    def usable(self) -> np.ndarray:
        b = np.asarray(self.brdf, dtype=np.float64)
        m = np.ones(b.shape, bool) if self.mask is None else np.asarray(self.mask, dtype=bool)
        ok = m & np.isfinite(b) & (b > 0)
        if self.sigma_rel is not None:
            s = np.broadcast_to(np.asarray(self.sigma_rel, dtype=np.float64), b.shape)
            with np.errstate(invalid="ignore"):
                ok &= np.isfinite(s) & (s > 0)
        return ok

    def check_usable(self) -> np.ndarray:
        u = self.usable()
        if not u.any():
            m = np.ones(u.shape, bool) if self.mask is None else np.asarray(self.mask, dtype=bool)
            sig = None if self.sigma_rel is None else np.asarray(self.sigma_rel, float)
            owner = f"table '{self.name}'" + (f" ({self.source})" if self.source else "")
            raise FitInputError(_describe_unusable(owner, u.size, m, np.asarray(self.brdf, float), sig))
        return u

    def select(self, rows: Any, name: str | None = None) -> "TableData":
        """A table of some rows (boolean or index array)."""

        def take(x):
            return x if np.ndim(x) == 0 or x is None else np.asarray(x)[rows]

        return TableData(
            take(self.theta_i), take(self.phi_i), take(self.theta_s), take(self.phi_s), take(self.brdf),
            None if self.sigma_rel is None else take(self.sigma_rel), take(self.wavelength),
            None if self.mask is None else take(self.mask), name or self.name, self.source,
            None if self.lines is None else take(self.lines), self.screening,
        )

    def incident_angles(self, decimals: int = 6) -> np.ndarray:
        """The distinct incident zenith angles (rad), rounded to ``decimals``."""
        return np.unique(np.round(np.asarray(self.theta_i, float), decimals))
