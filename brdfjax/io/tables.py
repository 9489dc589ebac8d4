"""Goniometer tables: readers (whitespace/CSV with a column mapping, ASTM E1392-style, MERL in-plane,
Cornell ``.brdf``) and export of a model to a table on any angle grid.

Every reader returns :class:`~brdfjax.fit.TableData` in brdfjax's conventions
(radians; azimuths from -x, the source at ``phi_i = 0`` and the mirror
direction at ``phi_s = pi``; wavelengths in metres) and names the file, line
and column in every error (:class:`~brdfjax.fit.FitInputError`).

Angle conventions differ between sources; the readers take:

- ``columns``: canonical name -> the file's column (header name or 0-based
  index).  Canonical names: ``theta_i``, ``phi_i``, ``theta_s``, ``phi_s``,
  ``brdf``, ``sigma_rel`` (relative 1-sigma), ``sigma`` (absolute, sr^-1),
  ``wavelength``.  ``phi_i`` defaults to 0.
- ``angle_unit``: ``deg`` or ``rad`` (a header such as ``theta_s(rad)``
  overrides it for that column).
- ``signed_inplane``: zeniths are signed in-plane angles (negative: the
  source side); they become ``|theta|`` with the azimuth turned by 180 deg.
  Without a ``phi_s`` column this is required, and ``phi_s`` is the forward
  half of the plane of incidence (pi) for positive angles.
- ``azimuth_offset``: added to both azimuths (the file's unit), for sources
  whose azimuth zero is elsewhere (MERL: -180).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np

from ..core.geometry import Directions
from ..core.terms import AbstractTerm
from ..runtime.errors import FitInputError
from . import atomic_output
from .blocks import TableData

__all__ = [
    "Screen",
    "make_table",
    "check_mirror",
    "read_table",
    "read_astm_e1392",
    "read_merl_inplane",
    "read_cornell_brdf",
    "export_table",
    "CANONICAL_COLUMNS",
]

CANONICAL_COLUMNS = ("theta_i", "phi_i", "theta_s", "phi_s", "brdf", "sigma_rel", "sigma", "wavelength")
_ANGLES = ("theta_i", "phi_i", "theta_s", "phi_s")
_WAVELENGTH_UNITS = {"nm": 1e-9, "um": 1e-6, "µm": 1e-6, "m": 1.0}


def _path(path: str | os.PathLike) -> Path:
    p = Path(path)
    if p.is_dir():
        raise FitInputError(f"{p}: is a directory, not a table file; name the file itself")
    if not p.is_file():
        raise FitInputError(f"{p}: no such file")
    return p


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is not None:
        return [t.strip() for t in line.split(delimiter)]
    if "," in line:
        return [t.strip() for t in line.split(",")]
    if "\t" in line:
        return [t.strip() for t in line.split("\t") if t.strip()]
    return line.split()


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


_UNIT_RE = re.compile(r"^(.*?)\s*[\(\[]\s*([^\)\]]*)\s*[\)\]]\s*$")


def _header_name(token: str) -> tuple[str, str | None]:
    """``'theta_s(deg)'`` -> ``('theta_s', 'deg')``; names are compared case-insensitively."""
    m = _UNIT_RE.match(token)
    if m:
        return m.group(1).strip().lower(), m.group(2).strip().lower() or None
    return token.strip().lower(), None


def _read_numeric(path: Path, comment: str, delimiter: str | None) -> tuple[list[str] | None, np.ndarray, list[int]]:
    """Header tokens (or None), the numeric rows and their line numbers."""
    header: list[str] | None = None
    last_comment: list[str] | None = None
    rows: list[list[float]] = []
    lines: list[int] = []
    with path.open() as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.strip()
            if not line:
                continue
            if comment and line.startswith(comment):
                body = line[len(comment) :].strip()
                if body:
                    last_comment = _split(body, delimiter)
                continue
            tokens = _split(line, delimiter)
            if not rows and header is None and not all(_is_number(t) for t in tokens):
                header = tokens
                continue
            try:
                values = [float(t) for t in tokens]
            except ValueError:
                bad = next(t for t in tokens if not _is_number(t))
                raise FitInputError(f"{path}:{lineno}: '{bad}' is not a number") from None
            if rows and len(values) != len(rows[0]):
                raise FitInputError(f"{path}:{lineno}: {len(values)} columns, but the first data row has {len(rows[0])}")
            rows.append(values)
            lines.append(lineno)
    if not rows:
        raise FitInputError(f"{path}: no data rows")
    data = np.array(rows, dtype=np.float64)
    if header is None and last_comment is not None and len(last_comment) == data.shape[1]:
        header = last_comment
    return header, data, lines


def _angle_factor(path: Path, column: str, unit: str | None) -> float:
    if unit in ("deg", "degree", "degrees"):
        return math.pi / 180.0
    if unit in ("rad", "radian", "radians"):
        return 1.0
    raise FitInputError(f"{path}: column '{column}': unknown angle unit {unit!r}; use 'deg' or 'rad'")


def _columns_to_table(
    path: Path,
    header: list[str] | None,
    data: np.ndarray,
    columns: Mapping[str, str | int],
    angle_unit: str,
    signed_inplane: bool,
    azimuth_offset: float,
    wavelength: float | None,
    wavelength_unit: str,
    name: str | None,
    lines: Sequence[int] | None = None,
    screen: "Screen | None" = None,
) -> TableData:
    unknown = set(columns) - set(CANONICAL_COLUMNS)
    if unknown:
        raise FitInputError(f"{path}: unknown column role(s) {sorted(unknown)}; known: {', '.join(CANONICAL_COLUMNS)}")
    for need in ("theta_i", "theta_s", "brdf"):
        if need not in columns:
            raise FitInputError(f"{path}: the column mapping needs '{need}' (give columns={{'{need}': <name or index>}})")
    if "sigma" in columns and "sigma_rel" in columns:
        raise FitInputError(f"{path}: give 'sigma' (absolute) or 'sigma_rel', not both")
    names = [_header_name(t) for t in header] if header is not None else None
    n_cols = data.shape[1]

    def column(role: str) -> tuple[np.ndarray, str | None]:
        key = columns[role]
        if isinstance(key, int | np.integer):
            if not 0 <= int(key) < n_cols:
                raise FitInputError(f"{path}: column index {key} for '{role}' is out of range (the file has {n_cols} columns)")
            unit = names[int(key)][1] if names is not None and len(names) == n_cols else None
            return data[:, int(key)], unit
        if names is None:
            raise FitInputError(f"{path}: no header row to find column '{key}' for '{role}'; map it by index instead")
        wanted = str(key).strip().lower()
        hits = [i for i, (n, _) in enumerate(names) if n == wanted]
        if not hits:
            raise FitInputError(
                f"{path}: no column '{key}' for '{role}'; the header has: {', '.join(n for n, _ in names)}"
            )
        if len(names) != n_cols:
            raise FitInputError(f"{path}: the header names {len(names)} columns but the data have {n_cols}")
        return data[:, hits[0]], names[hits[0]][1]

    out: dict[str, np.ndarray] = {}
    for role in _ANGLES:
        if role not in columns:
            continue
        values, unit = column(role)
        f = _angle_factor(path, f"{columns[role]} ({role})", unit or angle_unit)
        offset = azimuth_offset if role.startswith("phi") else 0.0
        out[role] = (values + offset) * f
    for role in ("theta_i", "theta_s"):
        th = out[role]
        lim = math.pi / 2 + 1e-9
        with np.errstate(invalid="ignore"):
            beyond = np.abs(th) > lim
        if np.any(beyond):
            bad = float(np.degrees(np.nanmax(np.abs(th))))
            raise FitInputError(
                f"{path}: column '{columns[role]}' ({role}) has zenith angles up to {bad:.4g} deg (> 90); "
                f"check angle_unit ('{angle_unit}') and which column is the zenith"
            )
    n = data.shape[0]
    phi_i = out.get("phi_i", np.zeros(n))
    if "phi_s" in out:
        phi_s = out["phi_s"]
    elif signed_inplane:
        phi_s = np.full(n, math.pi)  # forward half of the plane of incidence for positive angles
    else:
        raise FitInputError(
            f"{path}: no 'phi_s' column; for in-plane data with signed scatter angles pass signed_inplane=True"
        )
    theta_i, theta_s = out["theta_i"], out["theta_s"]
    if signed_inplane:
        phi_i = np.where(theta_i < 0, phi_i + math.pi, phi_i)
        phi_s = np.where(theta_s < 0, phi_s + math.pi, phi_s)
        theta_i, theta_s = np.abs(theta_i), np.abs(theta_s)
    elif np.any(np.nan_to_num(theta_i) < 0) or np.any(np.nan_to_num(theta_s) < 0):
        raise FitInputError(
            f"{path}: negative zenith angles in '{columns['theta_i']}'/'{columns['theta_s']}'; if they are signed "
            "in-plane angles pass signed_inplane=True"
        )
    brdf, _ = column("brdf")
    sigma_rel = None
    if "sigma_rel" in columns:
        sigma_rel, _ = column("sigma_rel")
    elif "sigma" in columns:
        sigma_abs, _ = column("sigma")
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma_rel = sigma_abs / brdf
    if wavelength_unit not in _WAVELENGTH_UNITS:
        raise FitInputError(f"{path}: unknown wavelength unit '{wavelength_unit}'; known: {', '.join(_WAVELENGTH_UNITS)}")
    if "wavelength" in columns:
        wl_values, unit = column("wavelength")
        wl = wl_values * _WAVELENGTH_UNITS.get(unit or wavelength_unit, np.nan)
        if wavelength is not None:
            stated = float(wavelength) * _WAVELENGTH_UNITS[wavelength_unit]
            _check_stated_wavelength(path, f"column '{columns['wavelength']}'", wl, stated)
    elif wavelength is not None:
        wl = float(wavelength) * _WAVELENGTH_UNITS.get(wavelength_unit, np.nan)
    else:
        wl = 632.8e-9
    return make_table(
        path, theta_i, phi_i, theta_s, phi_s, brdf, sigma_rel, wl, name=name or path.stem, lines=lines, screen=screen,
    )


def read_table(
    path: str | os.PathLike,
    columns: Mapping[str, str | int],
    *,
    angle_unit: str = "deg",
    signed_inplane: bool = False,
    azimuth_offset: float = 0.0,
    wavelength: float | None = None,
    wavelength_unit: str = "nm",
    delimiter: str | None = None,
    comment: str = "#",
    name: str | None = None,
    screen: "Screen | None" = None,
) -> TableData:
    """A whitespace- or comma-separated table with a column mapping (module docstring).

    The header is the first non-numeric line, or else the last comment line
    with as many names as the data have columns.  ``wavelength`` (in
    ``wavelength_unit``) applies to every row when there is no wavelength
    column (default 632.8 nm); with a wavelength column it must agree with
    it.  ``screen``: the checks of the rows and of the mirror direction
    (:class:`Screen`; default: drop bad rows, check the mirror).
    """
    p = _path(path)
    if angle_unit not in ("deg", "rad"):
        raise FitInputError(f"{p}: angle_unit must be 'deg' or 'rad', got {angle_unit!r}")
    header, data, lines = _read_numeric(p, comment, delimiter)
    screen = screen or Screen()
    if not screen.convention:
        screen = dataclasses.replace(
            screen, convention=f"azimuth_offset (now {azimuth_offset:g}) or signed_inplane (now {str(signed_inplane).lower()})"
        )
    return _columns_to_table(
        p, header, data, columns, angle_unit, signed_inplane, azimuth_offset, wavelength, wavelength_unit, name, lines, screen
    )


MERL_COLUMNS = {"theta_i": "phi_in", "phi_i": "theta_in", "theta_s": "phi_out", "phi_s": "theta_out", "brdf": "brdf"}
#: lumos-sat's own header for the same layout (``phi_*`` zenith angles, ``theta_*`` azimuths)
LUMOS_COLUMNS = {"theta_i": "phi_i", "phi_i": "theta_i", "theta_s": "phi_o", "phi_s": "theta_o", "brdf": "brdf"}
_LAYOUT_ORDER = ("theta_i", "phi_i", "theta_s", "phi_s", "brdf")  # the layout's column order (zenith first)


def _inplane_mapping(path: Path, header: list[str] | None, n_cols: int) -> dict[str, str | int]:
    """The column mapping of a file of the MERL/lumos-sat layout, from its header.

    MERL's names (``phi_in theta_in phi_out theta_out brdf``) or lumos-sat's
    (``phi_i theta_i phi_o theta_o brdf``), in any order and case; a file
    without a header and with five columns is read in the layout's order.
    """
    if header is None:
        if n_cols == len(_LAYOUT_ORDER):
            return {role: i for i, role in enumerate(_LAYOUT_ORDER)}
        raise FitInputError(
            f"{path}: no header and {n_cols} columns; the MERL/lumos-sat layout has 5 "
            "(zenith_in azimuth_in zenith_out azimuth_out brdf), or give columns"
        )
    names = {_header_name(t)[0] for t in header}
    for mapping in (MERL_COLUMNS, LUMOS_COLUMNS):
        if {mapping[role] for role in _ANGLES} <= names:  # the angle names tell the layouts apart
            return dict(mapping)
    raise FitInputError(
        f"{path}: the header ({', '.join(_header_name(t)[0] for t in header)}) is neither MERL's "
        f"({' '.join(MERL_COLUMNS.values())}) nor lumos-sat's ({' '.join(LUMOS_COLUMNS.values())}); "
        "map the columns with columns = {theta_i = ..., phi_i = ..., theta_s = ..., phi_s = ..., brdf = ...} "
        "(theta: zenith, phi: azimuth, in brdfjax's names)"
    )


def read_merl_inplane(
    path: str | os.PathLike,
    name: str | None = None,
    *,
    columns: Mapping[str, str | int] | None = None,
    signed_inplane: bool = True,
    azimuth_offset: float = -180.0,
    wavelength: float | None = None,
    screen: "Screen | None" = None,
) -> TableData:
    """In-plane slices in the lumos-sat layout (MERL's slices as lumos-sat ships them, lumos-sat's own tables).

    Columns ``phi_in theta_in phi_out theta_out brdf`` (MERL's names, as in
    ``tests/data/real/merl_aluminium_inplane.txt``) or ``phi_i theta_i phi_o
    theta_o brdf`` (lumos-sat's), where ``phi`` is the ZENITH (degrees;
    signed in-plane for the outgoing direction, negative on the source side)
    and ``theta`` the azimuth, the source at azimuth 180 (or -180) and the
    mirror direction at 0 (checked on the file: each slice peaks at
    ``phi_out = phi_in``, ``theta_out = 0``).  Either header is recognised,
    as a first line or as the last comment line before the data; a file
    without a header and with five columns is read in this order.  No
    uncertainties.  ``columns`` renames any role (canonical role -> the
    file's header name or index) for files of this layout with other names;
    roles not given keep the recognised header's names.  ``wavelength``
    (nm): the layout states none; default 632.8 nm.
    """
    p = _path(path)
    header, data, lines = _read_numeric(p, "#", None)
    if columns and set(columns) >= set(_LAYOUT_ORDER):
        mapping: dict[str, str | int] = {}
    elif columns:
        try:
            mapping = _inplane_mapping(p, header, data.shape[1])
        except FitInputError:
            mapping = dict(MERL_COLUMNS)  # the error then names the first role the mapping misses
    else:
        mapping = _inplane_mapping(p, header, data.shape[1])
    mapping.update(columns or {})
    screen = screen or Screen()
    if not screen.convention:
        screen = dataclasses.replace(
            screen, convention=f"azimuth_offset (now {azimuth_offset:g}) or signed_inplane (now {str(signed_inplane).lower()})"
        )
    return _columns_to_table(
        p, header, data, mapping, "deg", signed_inplane, azimuth_offset, wavelength, "nm", name, lines, screen
    )


def read_cornell_brdf(
    path: str | os.PathLike, wavelength_nm: float | str = "mean", name: str | None = None, *, screen: "Screen | None" = None
) -> TableData:
    """A Cornell gonioreflectometer ``.brdf`` file (pbrt-v2 ``scenes/brdfs``).

    Format: ``#`` comments; the number of wavelengths; the wavelengths (nm);
    records ``theta_i phi_i theta_s phi_s`` (radians, ``phi_i = 0``, mirror
    direction at ``phi_s = pi``: brdfjax's convention) followed by one BRDF
    per wavelength.  ``wavelength_nm``: one of the file's wavelengths, or
    ``"mean"`` for the average over all of them (reported at the mean
    wavelength).  No uncertainties.
    """
    p = _path(path)
    tokens: list[str] = []
    with p.open() as fh:
        for raw in fh:
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            tokens.extend(line.split())
    try:
        values = np.array([float(t) for t in tokens])
    except ValueError:
        bad = next(t for t in tokens if not _is_number(t))
        raise FitInputError(f"{p}: '{bad}' is not a number") from None
    if values.size < 2 or values[0] != int(values[0]) or values[0] < 1:
        raise FitInputError(f"{p}: expected the number of wavelengths first, got {values[:1].tolist()}")
    n_wl = int(values[0])
    wls = values[1 : 1 + n_wl]
    rest = values[1 + n_wl :]
    width = 4 + n_wl
    if wls.size != n_wl or rest.size == 0 or rest.size % width:
        raise FitInputError(
            f"{p}: {rest.size} numbers after the {n_wl} wavelengths do not form records of 4 angles + {n_wl} values"
        )
    rec = rest.reshape(-1, width)
    spectra = rec[:, 4:]
    if isinstance(wavelength_nm, str):
        if wavelength_nm != "mean":
            raise FitInputError(f"{p}: wavelength_nm must be a number (nm) or 'mean', got {wavelength_nm!r}")
        brdf = spectra.mean(axis=1)
        wl = float(wls.mean()) * 1e-9
        suffix = "mean"
    else:
        idx = np.nonzero(np.isclose(wls, float(wavelength_nm)))[0]
        if idx.size == 0:
            raise FitInputError(
                f"{p}: no wavelength {wavelength_nm} nm; the file has {', '.join(f'{w:g}' for w in wls)} nm or 'mean'"
            )
        brdf = spectra[:, idx[0]]
        wl = float(wls[idx[0]]) * 1e-9
        suffix = f"{wls[idx[0]]:g}nm"
    theta_i, phi_i, theta_s, phi_s = rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3]
    with np.errstate(invalid="ignore"):
        beyond = (np.abs(theta_i) > math.pi / 2 + 1e-6) | (np.abs(theta_s) > math.pi / 2 + 1e-6)
    if np.any(beyond):
        raise FitInputError(f"{p}: zenith angles beyond pi/2: the file's angles should be in radians")
    screen = screen or Screen()
    if not screen.convention:
        screen = dataclasses.replace(screen, convention="the file's azimuths (Cornell: phi_i = 0, mirror at phi_s = pi)")
    return make_table(
        p, np.abs(theta_i), phi_i, np.abs(theta_s), phi_s, brdf, None, wl, name=name or f"{p.stem}_{suffix}",
        lines=None, screen=screen, row_label="record",
    )


# --- row screening and the mirror-angle check -------------------------------------------------


@dataclass(frozen=True)
class Screen:
    """What a reader checks in the rows of a table (see :func:`make_table`).

    ``on_bad_rows``: ``"drop"`` (report and drop them, the count in the
    table's ``screening`` record) or ``"error"`` (refuse the file, listing
    them).  Bad rows: a non-finite angle or BRDF (NaN rows named by line),
    ``theta_s`` or ``theta_i`` at 90 deg (the model is exactly 0 there),
    BRDF <= 0, constant placeholder runs: ``placeholder_run`` or more
    consecutive rows of one slice with the identical BRDF value (a slice made
    only of them is always an error), and floor placeholders, isolated or not:
    one exact BRDF value in ``floor_repeats`` or more rows (0: no such check)
    that is the lowest value of every slice it occurs in and is written more
    coarsely than the next larger values, by two or more decimal places or
    significant digits (a provider's
    ``1e-4`` written where a measurement fell below its detection limit, among
    values such as ``0.000113``); see :func:`_floor_rows` for why real noise
    floors, quantised or printed to fixed decimals, are not taken.
    ``check_mirror``: each slice's peak
    must lie within ``mirror_tolerance_deg`` (or twice the distance of the
    slice's nearest sample to the mirror direction, if larger) of the mirror
    direction, in most slices with a clear peak (max / median >= 3); else the
    azimuth convention is wrong and the error names ``convention`` (the keys
    to change).
    """

    on_bad_rows: str = "drop"
    placeholder_run: int = 10
    floor_repeats: int = 3
    check_mirror: bool = True
    mirror_tolerance_deg: float = 10.0
    convention: str = ""


def _check_stated_wavelength(path: Path, where: str, stated_m: np.ndarray, wanted_m: float) -> None:
    w = np.asarray(stated_m, float)
    w = w[np.isfinite(w)]
    if w.size and np.any(np.abs(w - wanted_m) > 0.5e-9 + 1e-6 * wanted_m):
        have = ", ".join(f"{x:g}" for x in np.unique(np.round(w * 1e9, 4))[:5])
        raise FitInputError(
            f"{path}: wavelength_nm = {wanted_m * 1e9:g} disagrees with the file ({where} states {have} nm); "
            "drop wavelength_nm or correct it"
        )


def _slices(theta_i: np.ndarray, phi_i: np.ndarray) -> list[np.ndarray]:
    """Row indices of each (theta_i, phi_i) slice, in file order."""
    key = np.round(np.nan_to_num(theta_i, nan=-1.0), 6) * 1000.0 + np.round(np.nan_to_num(phi_i, nan=-1.0), 6)
    _, inv = np.unique(key, return_inverse=True)
    return [np.flatnonzero(inv == k) for k in range(int(inv.max()) + 1)] if inv.size else []


def _fmt_lines(label: str, where: np.ndarray, limit: int = 12) -> str:
    items = ", ".join(str(int(x)) for x in where[:limit])
    more = f" and {where.size - limit} more" if where.size > limit else ""
    return f"{label}s {items}{more}"


def _placeholder_rows(brdf: np.ndarray, rows: np.ndarray, run: int) -> np.ndarray:
    """Rows (of ``rows``, in order) inside runs of >= ``run`` identical BRDF values."""
    b = brdf[rows]
    out = np.zeros(rows.size, bool)
    start = 0
    for i in range(1, rows.size + 1):
        if i == rows.size or not (b[i] == b[start]):
            if i - start >= run:
                out[start:i] = True
            start = i
    return out


def _last_decimal(v: float) -> int:
    """The decimal exponent of ``v``'s last significant digit as written (12 digits at most): 0.000113 -> -6,
    0.0001 -> -4, 1040 -> 1."""
    exponent = Decimal(format(float(v), ".12g")).normalize().as_tuple().exponent
    return int(exponent) if isinstance(exponent, int) else 0


def _digits(v: float) -> int:
    """The number of significant digits of ``v`` as written (12 at most): 0.000113 -> 3, 0.0001 -> 1, 1040 -> 3."""
    return int(math.floor(math.log10(abs(v)))) - _last_decimal(v) + 1 if v else 1


def _floor_rows(b: np.ndarray, ok: np.ndarray, slices: list[np.ndarray], min_count: int, k: int = 6) -> np.ndarray:
    """Rows holding a floor placeholder: a value written in place of a measurement (see :class:`Screen`).

    A value ``v`` is one when (1) it occurs in ``min_count`` or more usable
    rows (``ok``), (2) it is the lowest usable value of every slice it occurs
    in (nothing lies below a floor that replaced what fell below it), and (3)
    it is written more coarsely than the ``k`` next larger usable values of
    the table: its last significant digit lies two or more decimal places
    above their median last digit (``1e-4`` below ``0.000113, 0.000117``), or
    it has two or more significant digits fewer than their median (``1e-4``
    below ``0.00101, 0.00102``).  (3) keeps real noise floors: a table printed
    to 3 significant digits repeats its lowest values (the V2 Mini mirror
    film's 0.000113, four times) and one printed to fixed decimals repeats
    them more (Cornell Cayman at 550 nm: 1e-06, sixteen times), but the values
    just above them are written to the same last digit.  A margin of one
    decimal place would drop real rows (measured in
    ``experiments/table_floor_screening.py``: Cornell Cayman, tables printed to
    2 significant digits or 5 fixed decimals).
    """
    out = np.zeros(b.shape, bool)
    if min_count < 1 or not ok.any():
        return out
    usable = np.sort(b[ok])
    lowest = [(r, float(np.min(b[r]))) for rows in slices if (r := rows[ok[rows]]).size]
    for v in sorted({m for _, m in lowest}):
        hits = np.flatnonzero(ok & (b == v))
        if hits.size < min_count:
            continue
        if any(np.any(b[r] == v) and m < v for r, m in lowest):
            continue  # below it elsewhere in one of its slices: not a floor
        above = usable[np.searchsorted(usable, v, side="right") :][:k]
        if not above.size:
            continue
        coarser = _last_decimal(v) - float(np.median([_last_decimal(x) for x in above]))
        fewer = float(np.median([_digits(x) for x in above])) - _digits(v)
        if coarser >= 2 or fewer >= 2:
            out[hits] = True
    return out


def _angle_between(t1, p1, t2, p2):
    c = np.cos(t1) * np.cos(t2) + np.sin(t1) * np.sin(t2) * np.cos(p1 - p2)
    return np.arccos(np.clip(c, -1.0, 1.0))


def _broad_forward_peak(ti, pi_, ts, ps, b, ok, k, d_peak, d_retro, tol) -> bool:
    """Whether an off-mirror peak is a broad lobe's forward (off-specular) peak.

    A rough surface's lobe peaks beyond the mirror direction, toward grazing in
    the plane of incidence (the shadowing/Fresnel/normalisation factors grow
    there), by an amount that grows with the lobe's breadth: Beckmann m = 0.145
    at 60 deg incidence peaks at theta_s ~ 70 deg.  Such a peak (1) is nearer
    the mirror direction than the source direction, (2) lies in the plane of
    incidence on the mirror's side, beyond the mirror (theta_s > theta_i), and
    (3) is broad enough to reach it: ``d_peak <= tol + 2 w``, with ``w`` the
    breadth of its half-maximum region toward the mirror (the largest distance
    from the peak of a sample with BRDF >= peak / 2 that is nearer the mirror
    than the peak is).  A wrong azimuth convention puts the peak on the source
    side (fails 1) or out of the plane (fails 2); a narrow peak far from the
    mirror fails 3.
    """
    if not d_peak < d_retro or ts[k] <= ti[k]:
        return False
    mirror = (ti[k], pi_[k] + math.pi)
    if float(_angle_between(ts[k], ps[k], ts[k], mirror[1])) > tol:
        return False
    half = ok[(b[ok] >= 0.5 * b[k]) & (_angle_between(ts[ok], ps[ok], *mirror) < d_peak)]
    w = float(np.max(_angle_between(ts[half], ps[half], ts[k], ps[k]))) if half.size else 0.0
    return d_peak <= tol + 2.0 * w


def check_mirror(
    path: Path | str, theta_i, phi_i, theta_s, phi_s, brdf, tolerance_deg: float = 10.0, convention: str = ""
) -> dict[str, Any]:
    """The mirror-angle check of :class:`Screen` (radians, brdfjax's convention); returns its record.

    Raises :class:`FitInputError` naming the file and ``convention`` when the
    clear peaks of most slices are off the mirror direction.  A broad lobe's
    forward-shifted peak (:func:`_broad_forward_peak`) counts as at the mirror
    (the record's ``forward_shifted``).
    """
    ti, pi_, ts, ps, b = (np.asarray(a, float) for a in (theta_i, phi_i, theta_s, phi_s, brdf))
    clear, off, forward = 0, [], 0
    for rows in _slices(ti, pi_):
        ok = rows[np.isfinite(b[rows]) & (b[rows] > 0)]
        if ok.size < 5:
            continue
        k = ok[int(np.argmax(b[ok]))]
        if b[k] < 3.0 * float(np.median(b[ok])):
            continue
        clear += 1
        mirror = (ti[k], pi_[k] + math.pi)
        d_peak = float(_angle_between(ts[k], ps[k], *mirror))
        d_near = float(np.min(_angle_between(ts[ok], ps[ok], *mirror)))
        tol = max(math.radians(tolerance_deg), 2.0 * d_near)
        if d_peak > tol:
            d_retro = float(_angle_between(ts[k], ps[k], ti[k], pi_[k]))
            if _broad_forward_peak(ti, pi_, ts, ps, b, ok, k, d_peak, d_retro, tol):
                forward += 1
                continue
            off.append((ti[k], ts[k], ps[k], pi_[k], d_peak, d_retro))
    record = {"slices_with_a_clear_peak": clear, "off_mirror": len(off), "forward_shifted": forward}
    if clear and len(off) > clear / 2:
        t0, t1, p1, pi0, d_peak, d_retro = off[0]
        side = " (on the backscatter side, next to the source)" if d_retro < d_peak else ""
        raise FitInputError(
            f"{path}: the BRDF peak of {len(off)} of {clear} slices is not at the mirror direction{side}: e.g. "
            f"theta_i = {math.degrees(t0):.4g} deg: peak at theta_s = {math.degrees(t1):.4g}, "
            f"phi_s = {math.degrees(p1) % 360:.4g} deg, {math.degrees(d_peak):.3g} deg from the mirror direction "
            f"(theta_s = {math.degrees(t0):.4g}, phi_s = {math.degrees(pi0 + math.pi) % 360:.4g} deg in brdfjax's "
            f"convention); the file's angle convention is probably another: change {convention or 'the azimuths'}"
            " (or set check_mirror = false for a surface whose peak is off-specular)"
        )
    return record


def make_table(
    path: Path | str,
    theta_i: Any,
    phi_i: Any,
    theta_s: Any,
    phi_s: Any,
    brdf: Any,
    sigma_rel: Any,
    wavelength: Any,
    *,
    name: str,
    lines: Any = None,
    screen: Screen | None = None,
    row_label: str = "line",
) -> TableData:
    """Screen the rows (:class:`Screen`) and build the :class:`TableData` of the kept rows (angles in radians).

    The table's ``screening`` record: rows read, kept, dropped per reason
    (with their line numbers), and the mirror check's result.
    """
    screen = screen or Screen()
    if screen.on_bad_rows not in ("drop", "error"):
        raise FitInputError(f"{path}: on_bad_rows must be 'drop' or 'error', got {screen.on_bad_rows!r}")
    arrays = [np.asarray(a, np.float64) for a in (theta_i, phi_i, theta_s, phi_s, brdf)]
    n = arrays[4].shape[0]
    ti, pi_, ts, ps, b = (np.broadcast_to(a, (n,)).copy() for a in arrays)
    where = np.arange(1, n + 1) if lines is None else np.asarray(lines, int)
    label = row_label if lines is not None or row_label != "line" else "row"
    sig = None if sigma_rel is None else np.broadcast_to(np.asarray(sigma_rel, np.float64), (n,))
    wl = np.asarray(wavelength, np.float64)
    finite = np.isfinite(ti) & np.isfinite(pi_) & np.isfinite(ts) & np.isfinite(ps) & np.isfinite(b)
    if wl.ndim:
        finite &= np.isfinite(wl)
    with np.errstate(invalid="ignore"):
        grazing = finite & ((np.abs(ts) >= math.pi / 2 - 1e-9) | (np.abs(ti) >= math.pi / 2 - 1e-9))
        non_pos = finite & ~grazing & (b <= 0)
    placeholder = np.zeros(n, bool)
    all_placeholder = []
    for rows in _slices(ti, pi_):
        cand = rows[finite[rows] & ~grazing[rows] & ~non_pos[rows]]
        if cand.size == 0:
            continue
        ph = _placeholder_rows(b, cand, max(2, int(screen.placeholder_run)))
        placeholder[cand[ph]] = True
        if ph.all() and cand.size >= 2:
            all_placeholder.append((ti[rows[0]], cand))
    if all_placeholder:
        t0, rows = all_placeholder[0]
        raise FitInputError(
            f"{path}: the slice at theta_i = {math.degrees(t0):.4g} deg holds only a constant placeholder value "
            f"(BRDF = {b[rows[0]]:.6g} in all its {rows.size} rows, {label}s {where[rows[0]]}-{where[rows[-1]]}); "
            "remove it from the file or select other incident angles (theta_i_deg)"
        )
    floor = _floor_rows(b, finite & ~grazing & ~non_pos & ~placeholder, _slices(ti, pi_), int(screen.floor_repeats))
    floor_values = ", ".join(f"{v:.6g}" for v in np.unique(b[floor]))
    reasons = {
        "non_finite": ~finite,
        "theta_90deg": grazing,
        "non_positive": non_pos,
        "placeholder": placeholder,
        "placeholder_floor": floor,
    }
    texts = {
        "non_finite": "NaN/non-finite angle or BRDF",
        "theta_90deg": "at theta = 90 deg (the model is 0 there)",
        "non_positive": "BRDF <= 0",
        "placeholder": f"constant placeholder runs (>= {screen.placeholder_run} identical values)",
        "placeholder_floor": f"floor placeholder value(s) {floor_values} (the lowest of their slices, written more "
        f"coarsely than the next larger values, >= {screen.floor_repeats} rows)",
    }
    dropped = {k: {"count": int(m.sum()), f"{label}s": where[m][:50].tolist()} for k, m in reasons.items() if m.any()}
    if floor.any():
        dropped["placeholder_floor"]["values"] = np.unique(b[floor]).tolist()
    bad = ~finite | grazing | non_pos | placeholder | floor
    if bad.any() and screen.on_bad_rows == "error":
        parts = [f"{int(m.sum())} {texts[k]} ({_fmt_lines(label, where[m])})" for k, m in reasons.items() if m.any()]
        raise FitInputError(f"{path}: bad rows: " + "; ".join(parts) + " (on_bad_rows = 'error'; 'drop' drops them)")
    keep = ~bad
    if not keep.any():
        raise FitInputError(f"{path}: no usable rows: all {n} are bad (" + ", ".join(f"{v['count']} {texts[k]}" for k, v in dropped.items()) + ")")
    mirror = None
    if screen.check_mirror:
        mirror = check_mirror(path, ti[keep], pi_[keep], ts[keep], ps[keep], b[keep], screen.mirror_tolerance_deg, screen.convention)
    record = {"n_rows": n, "n_kept": int(keep.sum()), "dropped": dropped, "mirror_check": mirror}
    return TableData(
        theta_i=ti[keep], phi_i=np.mod(pi_[keep], 2 * math.pi), theta_s=ts[keep], phi_s=np.mod(ps[keep], 2 * math.pi),
        brdf=b[keep], sigma_rel=None if sig is None else sig[keep], wavelength=wl if wl.ndim == 0 else wl[keep],
        name=name, source=str(path), lines=where[keep] if lines is not None else None, screening=record,
    )


# --- ASTM E1392-style files -----------------------------------------------------------------

_ASTM_KEYS = {
    "wavelength": "wavelength",
    "lambda": "wavelength",
    "incident angle": "theta_i",
    "angle of incidence": "theta_i",
    "theta_i": "theta_i",
    "incident azimuth": "phi_i",
    "phi_i": "phi_i",
    "angle unit": "angle_unit",
    "angle units": "angle_unit",
    "units": "angle_unit",
    "sample": "sample",
    "polarization": "polarization",
    "polarisation": "polarization",
}
_ASTM_COLUMNS = {
    "theta_s": "theta_s", "scatter_angle": "theta_s", "scatter angle": "theta_s", "theta_r": "theta_s", "polar": "theta_s",
    "phi_s": "phi_s", "scatter_azimuth": "phi_s", "azimuth": "phi_s", "phi_r": "phi_s",
    "brdf": "brdf", "bsdf": "brdf",
    "sigma": "sigma", "uncertainty": "sigma", "u": "sigma", "sigma_rel": "sigma_rel",
}
_KEY_RE = re.compile(r"^\s*([A-Za-z_ ]+?)\s*[:=]\s*(.+?)\s*$")


def _value_unit(path: Path, lineno: int, key: str, text: str) -> tuple[float, str | None]:
    parts = text.split()
    try:
        v = float(parts[0])
    except (ValueError, IndexError):
        raise FitInputError(f"{path}:{lineno}: '{key}' needs a number, got '{text}'") from None
    return v, (parts[1].lower() if len(parts) > 1 else None)


def read_astm_e1392(
    path: str | os.PathLike, name: str | None = None, *, wavelength: float | None = None, screen: "Screen | None" = None
) -> TableData:
    """An ASTM E1392-style scatter file: keyword header, then columns; several sections allowed.

    ASTM E1392 says what a BRDF report must state (wavelength, incident
    angle, scatter angles, BRDF) rather than a file layout; this reader takes
    the common layout of scatterometer exports::

        # comments
        Sample: ...                    (optional; free text)
        Wavelength: 632.8 nm           (nm, um or m; required)
        Angle unit: deg                (deg or rad; default deg)
        Incident angle: 20             (starts a section; required)
        Incident azimuth: 0            (optional, default 0)
        theta_s  phi_s  BRDF  sigma    (column header)
        ...numbers...
        Incident angle: 40             (next section, same columns unless a new header follows)
        ...

    Column names (case-insensitive, units in parentheses allowed):
    ``theta_s``/``scatter_angle``, ``phi_s``/``azimuth`` (optional: without it
    ``theta_s`` is a signed in-plane angle, negative on the source side),
    ``brdf``/``bsdf``, ``sigma`` (absolute, sr^-1) or ``sigma_rel``.
    ``wavelength`` (nm, optional): the wavelength the caller expects; it must
    agree with the file's ``Wavelength:`` line.
    """
    p = _path(path)
    meta: dict[str, Any] = {"angle_unit": "deg", "phi_i": 0.0}
    header: list[tuple[str, str | None]] | None = None
    sections: list[dict[str, Any]] = []
    current: dict[str, Any] | None = None
    with p.open() as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            m = _KEY_RE.match(line)
            if m and not _is_number(line.split()[0]):
                key = m.group(1).strip().lower()
                if key not in _ASTM_KEYS:
                    raise FitInputError(
                        f"{p}:{lineno}: unknown header key '{m.group(1).strip()}'; known: {', '.join(sorted(_ASTM_KEYS))}"
                    )
                role = _ASTM_KEYS[key]
                text = m.group(2)
                if role in ("sample", "polarization"):
                    meta[role] = text
                elif role == "angle_unit":
                    if text.lower() not in ("deg", "rad"):
                        raise FitInputError(f"{p}:{lineno}: angle unit must be 'deg' or 'rad', got '{text}'")
                    meta["angle_unit"] = text.lower()
                elif role == "wavelength":
                    v, unit = _value_unit(p, lineno, key, text)
                    if (unit or "nm") not in _WAVELENGTH_UNITS:
                        raise FitInputError(f"{p}:{lineno}: unknown wavelength unit '{unit}'; known: nm, um, m")
                    meta["wavelength"] = v * _WAVELENGTH_UNITS[unit or "nm"]
                else:
                    v, unit = _value_unit(p, lineno, key, text)
                    f = _angle_factor(p, key, unit or meta["angle_unit"])
                    meta[role] = v * f
                    if role == "theta_i":
                        current = {"theta_i": meta["theta_i"], "phi_i": meta["phi_i"], "rows": [], "header": header, "line": lineno}
                        sections.append(current)
                continue
            tokens = _split(line, None)
            if not all(_is_number(t) for t in tokens):
                header = [_header_name(t) for t in tokens]
                for n, _ in header:
                    if n not in _ASTM_COLUMNS:
                        raise FitInputError(
                            f"{p}:{lineno}: unknown column '{n}'; known: {', '.join(sorted(_ASTM_COLUMNS))}"
                        )
                if current is not None and not current["rows"]:
                    current["header"] = header
                continue
            if current is None:
                raise FitInputError(f"{p}:{lineno}: data before any 'Incident angle:' line")
            if current["header"] is None:
                current["header"] = header
            if current["header"] is None:
                raise FitInputError(f"{p}:{lineno}: data before a column header (e.g. 'theta_s phi_s BRDF')")
            if len(tokens) != len(current["header"]):
                raise FitInputError(f"{p}:{lineno}: {len(tokens)} values, but the header names {len(current['header'])} columns")
            current["rows"].append([float(t) for t in tokens])
            current.setdefault("lines", []).append(lineno)
    if "wavelength" not in meta:
        raise FitInputError(f"{p}: no 'Wavelength:' line")
    if not sections or not any(s["rows"] for s in sections):
        raise FitInputError(f"{p}: no data (each section starts with 'Incident angle:' and a column header)")
    if wavelength is not None:
        _check_stated_wavelength(p, "its 'Wavelength:' line", np.asarray(meta["wavelength"]), float(wavelength) * 1e-9)
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("theta_i", "phi_i", "theta_s", "phi_s", "brdf", "sigma_rel", "lines")}
    any_sigma = False
    for s in sections:
        if not s["rows"]:
            continue
        data = np.array(s["rows"], np.float64)
        roles = {_ASTM_COLUMNS[n]: (i, u) for i, (n, u) in enumerate(s["header"])}
        if "theta_s" not in roles or "brdf" not in roles:
            raise FitInputError(f"{p}:{s['line']}: the section needs a theta_s and a BRDF column")
        i, u = roles["theta_s"]
        ts = data[:, i] * _angle_factor(p, "theta_s", u or meta["angle_unit"])
        if "phi_s" in roles:
            j, uj = roles["phi_s"]
            ps = data[:, j] * _angle_factor(p, "phi_s", uj or meta["angle_unit"])
        else:
            ps = np.where(ts < 0, 0.0, math.pi) + s["phi_i"]
            ts = np.abs(ts)
        brdf = data[:, roles["brdf"][0]]
        if "sigma_rel" in roles:
            sr = data[:, roles["sigma_rel"][0]]
            any_sigma = True
        elif "sigma" in roles:
            with np.errstate(divide="ignore", invalid="ignore"):
                sr = data[:, roles["sigma"][0]] / brdf
            any_sigma = True
        else:
            sr = np.full(brdf.shape, np.nan)
        n = brdf.size
        with np.errstate(invalid="ignore"):
            out_of_range = np.any(ts < 0) or np.any(ts > math.pi / 2 + 1e-9)
        if out_of_range or not (0 <= s["theta_i"] <= math.pi / 2):
            raise FitInputError(f"{p}:{s['line']}: zenith angles outside [0, 90] deg; check 'Angle unit'")
        cols["theta_i"].append(np.full(n, s["theta_i"]))
        cols["phi_i"].append(np.full(n, s["phi_i"]))
        cols["theta_s"].append(ts)
        cols["phi_s"].append(ps)
        cols["brdf"].append(brdf)
        cols["sigma_rel"].append(sr)
        cols["lines"].append(np.asarray(s["lines"]))
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    if any_sigma and np.any(np.isnan(cat["sigma_rel"])):
        raise FitInputError(f"{p}: some sections have an uncertainty column and some do not")
    screen = screen or Screen()
    if not screen.convention:
        screen = dataclasses.replace(screen, convention="the file's azimuth columns (brdfjax: mirror at phi_s = phi_i + 180 deg)")
    return make_table(
        p, cat["theta_i"], cat["phi_i"], cat["theta_s"], cat["phi_s"], cat["brdf"],
        cat["sigma_rel"] if any_sigma else None, meta["wavelength"], name=name or p.stem, lines=cat["lines"], screen=screen,
    )


# --- export ---------------------------------------------------------------------------------


def export_table(
    model: AbstractTerm,
    theta_i: Sequence[float] | float,
    phi_i: Sequence[float] | float,
    theta_s: Sequence[float] | float,
    phi_s: Sequence[float] | float,
    *,
    wavelength_nm: float = 632.8,
    angle_unit: str = "deg",
    grid: bool = True,
    path: str | os.PathLike | None = None,
) -> dict[str, np.ndarray]:
    """A model evaluated on an angle grid, as columns (and a CSV file when ``path`` is given).

    ``grid=True``: every combination of the four angle lists; ``False``: the
    lists broadcast against each other (one row per element).  Angles in
    ``angle_unit`` (azimuths from -x: the mirror direction of ``phi_i = 0``
    is ``phi_s = 180`` deg).  Columns: ``theta_i_deg, phi_i_deg, theta_s_deg,
    phi_s_deg, wavelength_nm, brdf_per_sr``.
    """
    if angle_unit not in ("deg", "rad"):
        raise FitInputError(f"export_table: angle_unit must be 'deg' or 'rad', got {angle_unit!r}")
    f = math.pi / 180 if angle_unit == "deg" else 1.0
    arrays = [np.atleast_1d(np.asarray(a, np.float64)) * f for a in (theta_i, phi_i, theta_s, phi_s)]
    if grid:
        arrays = [a.ravel() for a in np.meshgrid(*arrays, indexing="ij")]
    else:
        try:
            arrays = [a.ravel() for a in np.broadcast_arrays(*arrays)]
        except ValueError:
            raise FitInputError(
                "export_table: with grid=False the four angle arrays must broadcast against each other"
            ) from None
    for label, a in (("theta_i", arrays[0]), ("theta_s", arrays[2])):
        if np.any(a < 0) or np.any(a > math.pi / 2):
            raise FitInputError(f"export_table: {label} must lie in [0, 90] deg")
    dirs = Directions.from_angles(*arrays)
    brdf = np.asarray(model(dirs, wavelength_nm * 1e-9), np.float64)
    cols = {
        "theta_i_deg": np.degrees(arrays[0]),
        "phi_i_deg": np.degrees(arrays[1]),
        "theta_s_deg": np.degrees(arrays[2]),
        "phi_s_deg": np.degrees(arrays[3]),
        "wavelength_nm": np.full(brdf.shape, float(wavelength_nm)),
        "brdf_per_sr": brdf,
    }
    if path is not None:
        table = np.stack(list(cols.values()), -1)
        with atomic_output(path) as tmp:
            np.savetxt(tmp, table, delimiter=",", header=",".join(cols), comments="", fmt="%.10g")
    return cols
