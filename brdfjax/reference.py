"""Independent NumPy float64 reference implementation (the "oracle").

This module is deliberately kept apart from the JAX core of brdfjax: it imports
nothing but NumPy and nothing from the rest of the package, and it was derived
directly from the dissertation (``shared/seed``) and the cleaned-up conventions
in ``shared/design/physics.md``, not from the JAX code.  The distributions are
written in their plain textbook form (``tan``, ``cos``; no log-space or other
numerical hardening), zenith angles come from ``atan2(hypot(x, y), z)``, and
everything is float64, so that it can serve

* the tests, as an independent check of the JAX core, and
* ``experiments/benchmark_frame.py``, as the straightforward vectorised NumPy
  baseline (:func:`solar_cell_frame`).

Conventions (physics.md):

* scatter frame (x, y, z): +z the macro-surface normal, +x in the plane of
  incidence toward forward scatter, +y out of plane ("downward");
* all directions point away from the surface;
* azimuths are measured from the **-x** direction, so a direction with zenith
  ``theta`` and azimuth ``phi`` is
  ``(sin t cos(p - pi), sin t sin(p - pi), cos t)``; the default incidence is
  ``phi_i = 0`` and forward specular is ``phi_s = pi``;
* angles in radians, lengths in metres;
* standard right-handed rotation matrices ``Rx``, ``Ry``, ``Rz``.

Equation numbers refer to the seed dissertation.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "N_H",
    "N_V",
    "PIXEL_PITCH",
    "R_NOMINAL",
    "rot_x",
    "rot_y",
    "rot_z",
    "pixel_indices",
    "scatter_vectors",
    "pixel_angles",
    "solid_angle",
    "inverse_map",
    "direction",
    "zenith_azimuth",
    "beckmann",
    "beckmann_aniso",
    "ggx",
    "ggx_aniso",
    "gtr",
    "hyper_cauchy",
    "student_t",
    "student_t_aniso",
    "cosine_lobe",
    "ashikhmin_shirley",
    "beard_maxwell_norm",
    "beard_maxwell",
    "ribardiere",
    "fresnel",
    "q_factor",
    "half_vector_angles",
    "specular",
    "smith_lambda_beckmann",
    "smith_lambda_ggx",
    "smith_lambda_numeric",
    "specular_shadowed",
    "abg",
    "phong",
    "lambertian",
    "solar_cell",
    "solar_cell_frame",
]

TWO_PI = 2.0 * np.pi

#: Detector array size (horizontal, vertical) in pixels (seed §3.3/§3.5).
N_H = 3296
N_V = 2472
#: Pixel pitch in metres (the seed writes "5.5 x 10^-6 um"; it means metres).
PIXEL_PITCH = 5.5e-6
#: Nominal sample-to-detector distance in metres.
R_NOMINAL = 0.325


# ---------------------------------------------------------------------------
# Rotations and directions
# ---------------------------------------------------------------------------


def rot_x(a: float) -> np.ndarray:
    """Right-handed rotation matrix about +x by angle ``a`` (scalar)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=np.float64)


def rot_y(a: float) -> np.ndarray:
    """Right-handed rotation matrix about +y (Eq 77): [[c,0,s],[0,1,0],[-s,0,c]]."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=np.float64)


def rot_z(a: float) -> np.ndarray:
    """Right-handed rotation matrix about +z by angle ``a`` (scalar)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float64)


def direction(theta, phi) -> np.ndarray:
    """Unit vector(s) with zenith ``theta`` and azimuth ``phi`` measured from -x.

    ``(sin t cos(p - pi), sin t sin(p - pi), cos t)`` stacked on a trailing axis
    of length 3 (Eq 81 without the length).
    """
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    st = np.sin(theta)
    return np.stack(
        np.broadcast_arrays(st * np.cos(phi - np.pi), st * np.sin(phi - np.pi), np.cos(theta)),
        axis=-1,
    )


def zenith_azimuth(v) -> tuple[np.ndarray, np.ndarray]:
    """Zenith and azimuth (from -x, in [0, 2 pi)) of (not necessarily unit) vectors.

    Eq 80 in the well-conditioned form: ``theta = atan2(hypot(x, y), z)``,
    ``phi = atan2(y, x) + pi`` wrapped into ``[0, 2 pi)``.
    """
    v = np.asarray(v, dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    theta = np.arctan2(np.hypot(x, y), z)
    phi = np.mod(np.arctan2(y, x) + np.pi, TWO_PI)
    # np.mod can return exactly 2 pi for inputs a hair below 0; fold it back.
    phi = np.where(phi >= TWO_PI, phi - TWO_PI, phi)
    return theta, phi


# ---------------------------------------------------------------------------
# Detector pixel mapping (§3.5, §4.4, §4.5)
# ---------------------------------------------------------------------------


def pixel_indices(n_h: int = N_H, n_v: int = N_V, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Pixel index grids ``(nh, nv)`` with the seed's convention (§3.5).

    The alignment pixel is the (n//2)-th pixel counted from 1 along each axis
    and gets index 0, so ``index = arange(n) - (n//2 - 1)``: for the default
    3296 x 2472 array the top-left pixel is (-1647, -1235) and the bottom-right
    (1648, 1236).  Every ``step``-th pixel is kept, starting from the top-left.

    Returns two int64 arrays shaped ``(rows, cols) = (ceil(n_v/step), ceil(n_h/step))``;
    rows run along ``nv``, columns along ``nh``.
    """
    h = np.arange(n_h, dtype=np.int64)[::step] - (n_h // 2 - 1)
    v = np.arange(n_v, dtype=np.int64)[::step] - (n_v // 2 - 1)
    nh, nv = np.meshgrid(h, v, indexing="xy")
    return nh, nv


def _ccd_rotation(roll: float, yaw: float, pitch: float) -> np.ndarray:
    """R_CCD = Rz(roll) Ry(yaw) Rx(pitch) (Tait-Bryan series of §4.4)."""
    return rot_z(roll) @ rot_y(yaw) @ rot_x(pitch)


def scatter_vectors(
    nh,
    nv,
    theta_c,
    R: float = R_NOMINAL,
    d_h: float = PIXEL_PITCH,
    d_v: float = PIXEL_PITCH,
    roll: float = 0.0,
    yaw: float = 0.0,
    pitch: float = 0.0,
    m_h: float = 0.0,
    m_v: float = 0.0,
) -> np.ndarray:
    """Un-normalised pixel scatter vectors r_s, shape ``(..., 3)`` (Eq 105).

    ``r_s = Ry(theta_c + dtheta_cm) (R_CCD r_p + R z) + dy y`` with
    ``r_p = (nh d_h, nv d_v, 0)`` (Eq 75), ``R_CCD = Rz(roll) Ry(yaw) Rx(pitch)``,
    ``dtheta_cm = m_h d_h / R`` (m_h times the angle subtended by one pixel
    near the centre, 9.70e-4 deg in the seed) and ``dy = m_v d_v``.
    With no misalignment this is Eq 78:
    ``(nh d cos tc + R sin tc, nv d, R cos tc - nh d sin tc)``.

    ``nh``, ``nv`` and ``theta_c`` broadcast; the misalignment parameters are
    scalars.
    """
    nh = np.asarray(nh, dtype=np.float64)
    nv = np.asarray(nv, dtype=np.float64)
    theta_c = np.asarray(theta_c, dtype=np.float64)
    px = nh * d_h
    py = nv * d_v
    M = _ccd_rotation(roll, yaw, pitch)
    # v = R_CCD r_p + R z   (r_p has no z component)
    vx = M[0, 0] * px + M[0, 1] * py
    vy = M[1, 0] * px + M[1, 1] * py
    vz = M[2, 0] * px + M[2, 1] * py + R
    a = theta_c + m_h * d_h / R
    ca, sa = np.cos(a), np.sin(a)
    x = ca * vx + sa * vz
    y = vy + m_v * d_v
    z = -sa * vx + ca * vz
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def pixel_angles(
    nh,
    nv,
    theta_c,
    R: float = R_NOMINAL,
    d_h: float = PIXEL_PITCH,
    d_v: float = PIXEL_PITCH,
    roll: float = 0.0,
    yaw: float = 0.0,
    pitch: float = 0.0,
    m_h: float = 0.0,
    m_v: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Scatter angles ``(theta_s, phi_s)`` of pixels (Eq 80 applied to Eq 105).

    ``theta_s = atan2(hypot(x, y), z)``; ``phi_s = atan2(y, x) + pi`` wrapped into
    ``[0, 2 pi)`` (azimuth from -x).
    """
    r = scatter_vectors(nh, nv, theta_c, R, d_h, d_v, roll, yaw, pitch, m_h, m_v)
    return zenith_azimuth(r)


def solid_angle(
    nh,
    nv,
    R: float = R_NOMINAL,
    d_h: float = PIXEL_PITCH,
    d_v: float = PIXEL_PITCH,
    roll: float = 0.0,
    yaw: float = 0.0,
    pitch: float = 0.0,
    m_h: float = 0.0,
    m_v: float = 0.0,
) -> np.ndarray:
    """Pixel solid angle in sr, Eq 109 (reduces to Eq 86 when aligned).

    ``Omega = d_h d_v (r0 . R_CCD z) / |r0|^3`` with ``r0`` the Eq 105 scatter
    vector evaluated at ``theta_c = 0`` (the misalignment offsets ``m_h``,
    ``m_v`` included, as the seed writes it).  With no misalignment
    ``r0 = (nh d_h, nv d_v, R)`` and ``R_CCD z = z``, which is Eq 86:
    ``d_h d_v R / (nh^2 d_h^2 + nv^2 d_v^2 + R^2)^(3/2)``.  The solid angle does
    not depend on ``theta_c``.

    Note: the seed dots ``r0`` with ``R_CCD z`` literally; the in-plane offset
    rotation ``Ry(dtheta_cm)`` is applied to ``r0`` but not to the pixel normal.
    For pixel-sized offsets the difference is far below any printed digit.
    """
    r0 = scatter_vectors(nh, nv, 0.0, R, d_h, d_v, roll, yaw, pitch, m_h, m_v)
    normal = _ccd_rotation(roll, yaw, pitch)[:, 2]
    dot = r0 @ normal
    norm = np.sqrt(np.sum(r0 * r0, axis=-1))
    return d_h * d_v * dot / norm**3


def inverse_map(
    theta_s,
    phi_s,
    theta_c,
    R: float = R_NOMINAL,
    d_h: float = PIXEL_PITCH,
    d_v: float = PIXEL_PITCH,
) -> tuple[np.ndarray, np.ndarray]:
    """Fractional pixel indices ``(n_h, n_v)`` of scatter directions (Eq 82).

    Eq 82 (perfect alignment),

        n_h = (R/d_h) (cot tc sin ts cos(ps - pi) - cos ts) / (cot tc cos ts + sin ts cos(ps - pi))
        n_v = (R/d_v) sin ts sin(ps - pi) / (cos tc cos ts + sin tc sin ts cos(ps - pi)),

    is evaluated in the algebraically identical form obtained by multiplying
    the n_h fraction through by ``sin tc``: with ``u`` the unit direction and
    ``u' = Ry(-theta_c) u``, ``n_h = (R/d_h) u'_x / u'_z`` and
    ``n_v = (R/d_v) u'_y / u'_z``.  This form is finite at both limits and
    reproduces Eq 83 (theta_c -> 0) and Eq 84 (theta_c -> 90 deg) exactly.
    """
    theta_c = np.asarray(theta_c, dtype=np.float64)
    u = direction(theta_s, phi_s)
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    cc, sc = np.cos(theta_c), np.sin(theta_c)
    xp = cc * ux - sc * uz
    zp = sc * ux + cc * uz
    return (R / d_h) * xp / zp, (R / d_v) * uy / zp


# ---------------------------------------------------------------------------
# Microfacet distributions (§2.3, Eq 54-68)
#
# All are functions of the half-vector zenith th (and azimuth ph, from -x;
# only cos^2 ph and sin^2 ph enter, so the azimuth origin does not matter) and
# are normalised so that  int_0^2pi int_0^pi/2 D cos(th) sin(th) dth dph = 1.
# The substitution u = tan^2(th) gives cos(th) sin(th) dth = cos^4(th) du / 2,
# which makes every normalisation below a one-line integral.
# ---------------------------------------------------------------------------


def beckmann(th, m):
    """Isotropic Beckmann (Eq 64): exp(-tan^2 th / m^2) / (pi m^2 cos^4 th)."""
    th = np.asarray(th, dtype=np.float64)
    t2 = np.tan(th) ** 2
    c4 = np.cos(th) ** 4
    return np.exp(-t2 / m**2) / (np.pi * m**2 * c4)


def beckmann_aniso(th, ph, mx, my):
    """Anisotropic Beckmann (Eq 65, re-normalised).

    ``exp(-tan^2 th (cos^2 ph / mx^2 + sin^2 ph / my^2)) / (pi mx my cos^4 th)``.
    Normalisation: the u-integral gives 1/(2 A(ph)) with
    ``A = cos^2/mx^2 + sin^2/my^2`` and ``int dph / A = 2 pi mx my``.
    """
    th = np.asarray(th, dtype=np.float64)
    ph = np.asarray(ph, dtype=np.float64)
    t2 = np.tan(th) ** 2
    a = np.cos(ph) ** 2 / mx**2 + np.sin(ph) ** 2 / my**2
    return np.exp(-t2 * a) / (np.pi * mx * my * np.cos(th) ** 4)


def ggx(th, alpha):
    """Trowbridge-Reitz / GGX: alpha^2 / (pi cos^4 th (alpha^2 + tan^2 th)^2).

    Seed Eq 59 normalised as Eq 60 with gamma = 2, c = alpha.
    """
    th = np.asarray(th, dtype=np.float64)
    t2 = np.tan(th) ** 2
    return alpha**2 / (np.pi * np.cos(th) ** 4 * (alpha**2 + t2) ** 2)


def ggx_aniso(th, ph, ax, ay):
    """Anisotropic GTR at gamma = 2 (Eq 62).

    ``1 / (pi ax ay (cos^2 th + sin^2 th (cos^2 ph / ax^2 + sin^2 ph / ay^2))^2)``.
    """
    th = np.asarray(th, dtype=np.float64)
    ph = np.asarray(ph, dtype=np.float64)
    a = np.cos(ph) ** 2 / ax**2 + np.sin(ph) ** 2 / ay**2
    den = np.cos(th) ** 2 + np.sin(th) ** 2 * a
    return 1.0 / (np.pi * ax * ay * den**2)


def gtr(th, c, gamma):
    """Generalized-Trowbridge-Reitz (Eq 60; Eq 61 at gamma = 1).

    ``D = K / (c^2 cos^2 th + sin^2 th)^gamma`` with
    ``K = (gamma - 1)(c^2 - 1) / (pi (1 - c^(2 - 2 gamma)))`` and, at gamma = 1,
    ``K = (c^2 - 1) / (pi ln c^2)``.  (With x = cos^2 th the normalisation
    integral is pi int_0^1 (1 + (c^2 - 1) x)^-gamma dx.)  ``c = 1`` (uniform,
    D = 1/pi) is a removable singularity of K and is not special-cased here.
    """
    th = np.asarray(th, dtype=np.float64)
    c2 = c * c
    if gamma == 1:
        k = (c2 - 1.0) / (np.pi * np.log(c2))
    else:
        k = (gamma - 1.0) * (c2 - 1.0) / (np.pi * (1.0 - c2 ** (1.0 - gamma)))
    return k / (c2 * np.cos(th) ** 2 + np.sin(th) ** 2) ** gamma


def hyper_cauchy(th, sigma, gamma):
    """Hyper-Cauchy (Eq 63), gamma > 1.

    ``(gamma - 1) sigma^(2 gamma - 2) / (pi cos^4 th (sigma^2 + tan^2 th)^gamma)``.
    """
    th = np.asarray(th, dtype=np.float64)
    t2 = np.tan(th) ** 2
    return (gamma - 1.0) * sigma ** (2.0 * gamma - 2.0) / (
        np.pi * np.cos(th) ** 4 * (sigma**2 + t2) ** gamma
    )


def student_t(th, sigma, gamma):
    """Ribardiere's normalised Student's t (Eq 67), gamma > 1.

    ``(gamma - 1)^gamma sigma^(2 gamma - 2) / (pi cos^4 th ((gamma - 1) sigma^2 + tan^2 th)^gamma)``
    (Eq 66 with B = 1/(sigma^2 (gamma - 1)), C = gamma).
    """
    th = np.asarray(th, dtype=np.float64)
    t2 = np.tan(th) ** 2
    g1 = gamma - 1.0
    return g1**gamma * sigma ** (2.0 * gamma - 2.0) / (
        np.pi * np.cos(th) ** 4 * (g1 * sigma**2 + t2) ** gamma
    )


def student_t_aniso(th, ph, sx, sy, gamma):
    """Anisotropic Student's t (Eq 68), gamma > 1.

    ``1 / (pi sx sy cos^4 th (1 + tan^2 th / (gamma - 1) (cos^2 ph / sx^2 + sin^2 ph / sy^2))^gamma)``.
    The seed leaves its normalisation open; it is normalised as printed: the
    u-integral gives 1/(2 A(ph)) and ``int dph / A = 2 pi sx sy``.  It reduces
    to Eq 67 when sx = sy.
    """
    th = np.asarray(th, dtype=np.float64)
    ph = np.asarray(ph, dtype=np.float64)
    t2 = np.tan(th) ** 2
    a = np.cos(ph) ** 2 / sx**2 + np.sin(ph) ** 2 / sy**2
    return 1.0 / (np.pi * sx * sy * np.cos(th) ** 4 * (1.0 + t2 * a / (gamma - 1.0)) ** gamma)


def cosine_lobe(th, k):
    """Normalised Blinn-Phong cosine lobe (Eq 57): (k + 2)/(2 pi) cos^k th."""
    th = np.asarray(th, dtype=np.float64)
    return (k + 2.0) / TWO_PI * np.cos(th) ** k


def ashikhmin_shirley(th, ph, kx, ky):
    """Anisotropic cosine lobe (Eq 58).

    ``sqrt((kx + 2)(ky + 2)) / (2 pi) cos(th)^(kx cos^2 ph + ky sin^2 ph)``.
    Exactly normalised for the cos-weighted measure: the th-integral gives
    1/(k(ph) + 2) and ``int dph / ((kx+2) cos^2 + (ky+2) sin^2) = 2 pi / sqrt((kx+2)(ky+2))``.
    """
    th = np.asarray(th, dtype=np.float64)
    ph = np.asarray(ph, dtype=np.float64)
    k = kx * np.cos(ph) ** 2 + ky * np.sin(ph) ** 2
    return np.sqrt((kx + 2.0) * (ky + 2.0)) / TWO_PI * np.cos(th) ** k


def beard_maxwell_norm(s):
    """Normalisation constant B of the modified Beard-Maxwell Cauchy (Eq 56).

    Derivation.  Eq 54 for ``D = B / (cos th (s^2 + tan^2 th))`` reads

        1 = 2 pi B I,   I = int_0^{pi/2} sin th / (s^2 + tan^2 th) dth.

    Multiply through by cos^2 th and use sin^2 = 1 - cos^2:
    ``sin th cos^2 th / (1 + (s^2 - 1) cos^2 th)``; with x = cos th
    (dx = -sin th dth) and k = s^2 - 1,

        I = int_0^1 x^2 / (1 + k x^2) dx = (1/k) (1 - int_0^1 dx / (1 + k x^2)).

    * s > 1 (k > 0):  int_0^1 dx/(1 + k x^2) = arctan(sqrt k)/sqrt k, so
      ``I = (1 - arctan(sqrt k)/sqrt k) / k``.
    * s < 1 (q = 1 - s^2 in (0, 1)):  int_0^1 dx/(1 - q x^2) = artanh(sqrt q)/sqrt q, so
      ``I = (artanh(sqrt q)/sqrt q - 1) / q``, evaluated with
      ``artanh(sqrt q) = ln((1 + sqrt q)/s)`` so tiny s keeps its digits.
    * s = 1: I = 1/3 (both branches tend to it: I = sum_n (-k)^n / (2n + 3)).

    Hence ``B = 1 / (2 pi I)``.  As s -> 0, I ~ ln(2/s) - 1 grows only
    logarithmically (the 1/theta tail of the Cauchy), so B -> 0 slowly; as
    s -> inf, I ~ 1/s^2 and B ~ s^2/(2 pi).  Near s = 1 (|k| < 0.05) the series
    is used to avoid cancellation.
    """
    s = np.asarray(s, dtype=np.float64)
    k = s * s - 1.0
    small = np.abs(k) < 0.05
    # series branch (0.05^24 / 51 is far below double precision)
    ks = np.where(small, k, 0.0)
    i_series = sum((-ks) ** n / (2 * n + 3) for n in range(24))
    # s > 1 branch
    kp = np.where((k > 0) & ~small, k, 1.0)
    rk = np.sqrt(kp)
    i_pos = (1.0 - np.arctan(rk) / rk) / kp
    # s < 1 branch
    # artanh(sqrt q) = ln((1 + sqrt q) / s), written in s to avoid 1 - sqrt(1 - s^2)
    neg = (k < 0) & ~small
    q = np.where(neg, -k, 0.5)
    rq = np.sqrt(q)
    atanh_rq = np.log((1.0 + rq) / np.where(neg, s, np.sqrt(0.5)))
    i_neg = (atanh_rq / rq - 1.0) / q
    i = np.where(small, i_series, np.where(k > 0, i_pos, i_neg))
    return 1.0 / (TWO_PI * i)


def beard_maxwell(th, s):
    """Modified Beard-Maxwell Cauchy distribution (Eq 56), normalised.

    ``D = B(s) / (cos th (s^2 + tan^2 th))`` with B from
    :func:`beard_maxwell_norm` (see its docstring for the derivation).
    """
    th = np.asarray(th, dtype=np.float64)
    t2 = np.tan(th) ** 2
    return beard_maxwell_norm(s) / (np.cos(th) * (s**2 + t2))


def ribardiere(th, B, C):
    """Ribardiere's family (Eq 66), C > 1: (C - 1) B / (pi cos^4 th (1 + B tan^2 th)^C).

    Normalised: the u-integral int_0^inf (1 + B u)^-C du = 1/(B (C - 1)).
    """
    th = np.asarray(th, dtype=np.float64)
    t2 = np.tan(th) ** 2
    return (C - 1.0) * B / (np.pi * np.cos(th) ** 4 * (1.0 + B * t2) ** C)


# ---------------------------------------------------------------------------
# Fresnel, Q factor, specular term (Eq 24-27, 52, 69-70)
# ---------------------------------------------------------------------------


def fresnel(n, theta):
    """Fresnel power reflectances ``(F_s, F_p)`` from air onto index ``n`` (Eq 25-26).

    ``r_s = (cos t - A) / (cos t + A)``, ``r_p = (n^2 cos t - A) / (n^2 cos t + A)``,
    ``A = sqrt(n^2 - sin^2 t)`` (principal complex square root; ``n`` may be
    complex).  The unpolarised reflectance of Eq 27 is ``(F_s + F_p)/2``.
    """
    n = np.asarray(n, dtype=np.complex128)
    theta = np.asarray(theta, dtype=np.float64)
    n2 = n * n
    c = np.cos(theta)
    a = np.sqrt(n2 - np.sin(theta) ** 2)
    rs = (c - a) / (c + a)
    rp = (n2 * c - a) / (n2 * c + a)
    return np.abs(rs) ** 2, np.abs(rp) ** 2


def q_factor(n, theta_i, phi_i, theta_s, phi_s):
    """Polarisation factor Q = Q_ss + Q_sp + Q_ps + Q_pp (Eq 69, physics.md).

    With ``A(t) = sqrt(n^2 - sin^2 t)`` and ``dphi = phi_s - phi_i`` (forward
    specular has dphi = pi), the four terms are the squared moduli of

        Q_ss: (n^2-1) cos(dphi-pi) / ((cos ti + A_i)(cos ts + A_s))
        Q_sp: (n^2-1) A_s sin(dphi-pi) / ((cos ti + A_i)(n^2 cos ts + A_s))
        Q_ps: (n^2-1) A_i sin(dphi-pi) / ((n^2 cos ti + A_i)(cos ts + A_s))
        Q_pp: (n^2-1)(A_i A_s cos(dphi-pi) - n^2 sin ti sin ts) / ((n^2 cos ti + A_i)(n^2 cos ts + A_s))
    """
    n = np.asarray(n, dtype=np.complex128)
    theta_i = np.asarray(theta_i, dtype=np.float64)
    theta_s = np.asarray(theta_s, dtype=np.float64)
    dphi = np.asarray(phi_s, dtype=np.float64) - np.asarray(phi_i, dtype=np.float64)
    n2 = n * n
    ci, si = np.cos(theta_i), np.sin(theta_i)
    cs, ss = np.cos(theta_s), np.sin(theta_s)
    ai = np.sqrt(n2 - si * si)
    a_s = np.sqrt(n2 - ss * ss)
    cd = np.cos(dphi - np.pi)
    sd = np.sin(dphi - np.pi)
    num = n2 - 1.0
    qss = np.abs(num * cd / ((ci + ai) * (cs + a_s))) ** 2
    qsp = np.abs(num * a_s * sd / ((ci + ai) * (n2 * cs + a_s))) ** 2
    qps = np.abs(num * ai * sd / ((n2 * ci + ai) * (cs + a_s))) ** 2
    qpp = np.abs(num * (ai * a_s * cd - n2 * si * ss) / ((n2 * ci + ai) * (n2 * cs + a_s))) ** 2
    return qss + qsp + qps + qpp


def half_vector_angles(theta_i, phi_i, theta_s, phi_s) -> tuple[np.ndarray, np.ndarray]:
    """Half-vector zenith and azimuth (from -x) of w_h = (w_i + w_s)/|w_i + w_s| (Eq 52)."""
    h = direction(theta_i, phi_i) + direction(theta_s, phi_s)
    return zenith_azimuth(h)


def specular(theta_i, phi_i, theta_s, phi_s, D, rho_s, n):
    """Specular term of Eq 70: rho_s D(th, ph) Q / (2 (cos ti + cos ts)^2).

    ``D`` is a callable of the half-vector angles ``(theta_h, phi_h)``, e.g.
    ``lambda th, ph: beckmann(th, 2e-4)``.
    """
    th, ph = half_vector_angles(theta_i, phi_i, theta_s, phi_s)
    q = q_factor(n, theta_i, phi_i, theta_s, phi_s)
    return rho_s * D(th, ph) * q / (2.0 * (np.cos(theta_i) + np.cos(theta_s)) ** 2)


# ---------------------------------------------------------------------------
# Beyond the seed: shadowing-masking (physics.md), ABg and Phong lobes
# ---------------------------------------------------------------------------


def smith_lambda_beckmann(theta, m):
    """Smith Lambda of Beckmann(m) at zenith ``theta``: ``(erf(a) - 1)/2 + exp(-a^2)/(2 a sqrt(pi))``, a = 1/(m tan)."""
    theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
    out = np.zeros_like(theta)
    for i, t in enumerate(theta):
        if t <= 0:
            continue
        a = 1.0 / (m * math.tan(t))
        out[i] = (math.erf(a) - 1.0) / 2.0 + math.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
    return out


def smith_lambda_ggx(theta, alpha):
    """Smith Lambda of GGX(alpha) at zenith ``theta``: ``(-1 + sqrt(1 + alpha^2 tan^2))/2``."""
    t = alpha * np.tan(np.asarray(theta, dtype=np.float64))
    return (-1.0 + np.sqrt(1.0 + t * t)) / 2.0


def smith_lambda_numeric(D, theta_o, phi_o=np.pi, n_theta=3000, n_phi=720):
    """Smith Lambda of any D from the projected-area identity (Heitz 2014 Eq 17-18).

    ``cos(theta_o) (1 + Lambda) = integral max(0, w_o . w_m) D(w_m) dw_m`` over
    the hemisphere of microfacet normals, by the midpoint rule on a
    (theta_m, phi_m) grid.  ``D`` is a callable of ``(theta_m, phi_m)`` (azimuth
    from -x) normalised per Eq 54.  Accurate to about 1e-5 for widths >= 0.1
    (not meant for narrow lobes).
    """
    th = (np.arange(n_theta) + 0.5) * (np.pi / 2) / n_theta
    ph = (np.arange(n_phi) + 0.5) * (2 * np.pi) / n_phi
    T, P = np.meshgrid(th, ph, indexing="ij")
    wm = direction(T, P)
    dw = np.sin(T) * (np.pi / 2 / n_theta) * (2 * np.pi / n_phi)
    dm = D(T, P) * dw
    out = []
    for t in np.atleast_1d(theta_o):
        wo = direction(t, phi_o)
        proj = np.maximum(wm @ wo, 0.0)
        out.append(np.sum(proj * dm) / np.cos(t) - 1.0)
    return np.asarray(out)


def specular_shadowed(theta_i, phi_i, theta_s, phi_s, D, rho_s, n, lam=None, normalisation="seed"):
    """Specular term with Smith G2 = 1/(1 + Lambda(ti) + Lambda(ts)) (``lam``: a callable of theta; None: G = 1).

    ``normalisation='seed'``: ``rho_s D G Q / (2 (cos ti + cos ts)^2)`` (Eq 70);
    ``'torrance_sparrow'``: ``rho_s D G (Q/2) / (4 cos ti cos ts)``.  Isotropic D only (Lambda of the zenith).
    """
    th, ph = half_vector_angles(theta_i, phi_i, theta_s, phi_s)
    q = q_factor(n, theta_i, phi_i, theta_s, phi_s)
    g = 1.0 if lam is None else 1.0 / (1.0 + lam(theta_i) + lam(theta_s))
    ci, cs = np.cos(theta_i), np.cos(theta_s)
    if normalisation == "seed":
        geo = 1.0 / (2.0 * (ci + cs) ** 2)
    elif normalisation == "torrance_sparrow":
        geo = 1.0 / (8.0 * ci * cs)
    else:
        raise ValueError(f"unknown normalisation {normalisation!r}")
    return rho_s * D(th, ph) * g * q * geo


def _mirror_offset(theta_i, phi_i, theta_s, phi_s):
    """``|beta - beta0|`` and the angle between the scattered and mirror directions."""
    wi = direction(theta_i, phi_i)
    ws = direction(theta_s, phi_s)
    wr = wi * np.array([-1.0, -1.0, 1.0])
    beta = np.hypot(ws[..., 0] - wr[..., 0], ws[..., 1] - wr[..., 1])
    cos_a = np.clip(np.sum(wr * ws, -1), -1.0, 1.0)
    return beta, cos_a


def abg(theta_i, phi_i, theta_s, phi_s, A, B, g):
    """Harvey-Shack ABg: ``A / (B + |beta - beta0|^g)``, beta the projection of the direction on the surface."""
    beta, _ = _mirror_offset(theta_i, phi_i, theta_s, phi_s)
    return A / (B + beta**g)


def phong(theta_i, phi_i, theta_s, phi_s, rho, k):
    """Normalised Phong lobe ``rho (k + 2)/(2 pi) max(cos alpha, 0)^k`` about the mirror direction."""
    _, cos_a = _mirror_offset(theta_i, phi_i, theta_s, phi_s)
    return rho * (k + 2.0) / (2.0 * np.pi) * np.maximum(cos_a, 0.0) ** k


def lambertian(rho_d):
    """Lambertian term rho_d / pi (Eq 50)."""
    return np.asarray(rho_d, dtype=np.float64) / np.pi


# ---------------------------------------------------------------------------
# Solar-cell model (Chapter VI, Eq 111-115)
# ---------------------------------------------------------------------------


def _specular_beckmann(theta_i, phi_i, theta_s, phi_s, theta_h, m, rho_s, n):
    """Eq 70 with Beckmann(m), given the angles and the half-vector zenith."""
    q = q_factor(n, theta_i, phi_i, theta_s, phi_s)
    return rho_s * beckmann(theta_h, m) * q / (2.0 * (np.cos(theta_i) + np.cos(theta_s)) ** 2)


def solar_cell(
    theta_i,
    theta_s,
    phi_s,
    phi_ref=0.0,
    wavelength=632.8e-9,
    m1=2e-4,
    rho_s1=0.015,
    n1=3.6,
    m2=2e-4,
    rho_s2=0.7,
    n2=1.4,
    dtheta=np.deg2rad(0.5),
    dphi0=np.deg2rad(45.0),
    a=8e-4,
    b=1e-5,
    c=4e-5,
    rho_s3=300.0,
    R=R_NOMINAL,
    terms=False,
    grating_factor=True,
):
    """Three-term solar-cell BRDF of Chapter VI (sr^-1), incidence at phi_i = 0.

    1. Centre specular peak (Eq 111): Eq 70 with Beckmann(m1), rho_s1, n1.
    2. Offset specular peak (Eq 112-113): both unit directions are rotated by
       ``Ry(-dtheta) Rz(-dphi0 - phi_ref)`` (which takes the tilted normal
       ``(sin dtheta cos(dphi0 + phi_ref), sin dtheta sin(dphi0 + phi_ref), cos dtheta)``
       onto +z); theta_i2, theta_s2, theta_h2 and the azimuth difference are
       recomputed in the rotated frame; then Eq 70 with Beckmann(m2), rho_s2, n2.
    3. Diffraction by the metal bars (Eq 114-115), from the UNrotated half
       vector (theta_h, phi_h from -x):
       ``xbar = R sin th cos(ph - phi_ref + pi)``, ``ybar = R sin th sin(ph - phi_ref + pi)``,
       ``zbar = R``,
       ``f3 = rho_s3 cos^2(pi a g ybar/(lambda zbar)) sinc^2(b g ybar/(lambda zbar)) exp(-xbar^2/c^2)``
       with the normalised sinc (``np.sinc``) and ``g = 2 cos(theta_i)``
       (``g = 1`` when ``grating_factor=False``, the plain Fraunhofer form).
       R cancels in the cos^2 and sinc^2 but not in the Gaussian, where it is
       the nominal 0.325 m.

    Inputs broadcast.  Returns the summed BRDF, or with ``terms=True`` a dict
    with keys ``"center"``, ``"offset"``, ``"diffraction"`` and ``"total"``.
    """
    theta_i = np.asarray(theta_i, dtype=np.float64)
    theta_s = np.asarray(theta_s, dtype=np.float64)
    phi_s = np.asarray(phi_s, dtype=np.float64)
    wi = direction(theta_i, 0.0)  # incident direction, phi_i = 0
    ws = direction(theta_s, phi_s)
    th, ph = zenith_azimuth(wi + ws)  # half vector (Eq 52), unrotated frame

    # 1. centre specular peak (Eq 111)
    f1 = _specular_beckmann(theta_i, 0.0, theta_s, phi_s, th, m1, rho_s1, n1)

    # 2. offset specular peak (Eq 112-113): rotate into the second normal's frame
    M = rot_y(-dtheta) @ rot_z(-dphi0 - phi_ref)
    wi2 = wi @ M.T
    ws2 = ws @ M.T
    ti2, pi2 = zenith_azimuth(wi2)
    ts2, ps2 = zenith_azimuth(ws2)
    th2, _ = zenith_azimuth(wi2 + ws2)
    f2 = _specular_beckmann(ti2, pi2, ts2, ps2, th2, m2, rho_s2, n2)

    # 3. diffraction pattern (Eq 114-115) from the unrotated half vector
    sth = np.sin(th)
    xbar = R * sth * np.cos(ph - phi_ref + np.pi)
    ybar = R * sth * np.sin(ph - phi_ref + np.pi)
    zbar = R
    g = 2.0 * np.cos(theta_i) if grating_factor else 1.0
    u = g * ybar / (wavelength * zbar)
    f3 = rho_s3 * np.cos(np.pi * a * u) ** 2 * np.sinc(b * u) ** 2 * np.exp(-(xbar**2) / c**2)

    total = f1 + f2 + f3
    if terms:
        return {"center": f1, "offset": f2, "diffraction": f3, "total": total}
    return total


def solar_cell_frame(
    theta_i,
    phi_ref=0.0,
    wavelength=632.8e-9,
    step=1,
    rows_per_chunk=128,
    n_h=N_H,
    n_v=N_V,
    d_h=PIXEL_PITCH,
    d_v=PIXEL_PITCH,
    **params,
):
    """Solar-cell BRDF over the seed detector with theta_c = theta_i (sr^-1).

    Returns a float64 array shaped ``(ceil(n_v/step), ceil(n_h/step))`` (rows
    along n_v, see :func:`pixel_indices`).  Pixels are mapped with Eq 78/80 at
    the distance ``params.get("R", 0.325)`` (the same R is passed on to the
    model's Gaussian), and the model is evaluated ``rows_per_chunk`` rows at a
    time so that peak memory stays bounded.  ``params`` are passed on to
    :func:`solar_cell` (m1, rho_s1, ..., R, grating_factor).

    This is the plain vectorised NumPy float64 baseline of the frame
    benchmark: no compilation, no caching, no tricks.
    """
    R = params.get("R", R_NOMINAL)
    # the same indices as pixel_indices(n_h, n_v, step), built row chunk by row chunk
    h = np.arange(n_h, dtype=np.int64)[::step] - (n_h // 2 - 1)
    v = np.arange(n_v, dtype=np.int64)[::step] - (n_v // 2 - 1)
    out = np.empty((v.size, h.size), dtype=np.float64)
    for r0 in range(0, v.size, rows_per_chunk):
        r1 = min(r0 + rows_per_chunk, v.size)
        nh, nv = np.meshgrid(h, v[r0:r1], indexing="xy")
        ts, ps = pixel_angles(nh, nv, theta_i, R=R, d_h=d_h, d_v=d_v)
        out[r0:r1] = solar_cell(theta_i, ts, ps, phi_ref, wavelength, **params)
    return out
