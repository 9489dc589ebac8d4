"""A fused numba kernel of the solar-cell frame: the baseline of ``benchmark_frame.py``.

The same formulas as ``brdfjax.render(brdfjax.solar_cell(), ...)`` in float32
(``brdfjax/detector.py``'s pixel mapping, ``terms.Specular`` with the seed's
Eq 70 normalisation and ``fresnel.q_factor`` for the centre and the offset
peak, ``terms.Diffraction`` for the bars), written as one loop over the
pixels with ``numba.njit(parallel=True)`` over the rows (IEEE arithmetic, no
fast-math): what a hand-written fused CPU kernel of this model costs.
Everything that depends only on the frame (the incident direction and its
Fresnel parts, the rotations, ``1/m^2``) is computed once on the host in
float64 and passed as float32, as the compiled JAX program does it once per
call.  Needs ``numba`` (``pip install "brdfjax[bench]"``).
"""

from __future__ import annotations

import math

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - the benchmark skips the numba row
    numba = None

F = np.float32


def _csqrt_np(a: float, b: float) -> tuple[float, float, float]:
    r = math.hypot(a, b)
    big = math.sqrt(0.5 * (r + abs(a)))
    small = 0.5 * b / big if big > 0 else 0.0
    if a >= 0:
        return big, small, r
    return abs(small), (-big if b < 0 else big), r


def _incident_constants(w_i: np.ndarray, n: float, k: float) -> list[float]:
    """Per-frame parts of the Q factor of one specular term (float64 on the host)."""
    n2r, n2i = n * n - k * k, 2.0 * n * k
    ix, iy, ci = (float(c) for c in w_i)
    si2 = ix * ix + iy * iy
    air, aii, ai2 = _csqrt_np(n2r - si2, n2i)
    den_s = (ci + air) ** 2 + aii**2
    den_p = (n2r * ci + air) ** 2 + (n2i * ci + aii) ** 2
    num2 = (n2r - 1.0) ** 2 + n2i**2
    return [ix, iy, ci, si2, air, aii, ai2, den_s, den_p, n2r, n2i, num2]


def _rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def frame_constants(theta_i: float, phi_ref: float = 0.0, wavelength: float = 632.8e-9, *, pitch: float = 5.5e-6,
                    distance: float = 0.325, **params: float) -> np.ndarray:
    """The float32 constants of one aligned seed-detector frame of ``solar_cell(**params)``."""
    from brdfjax.core.terms import SOLAR_CELL_SEED  # noqa: PLC0415 - only the parameter defaults

    p = {**SOLAR_CELL_SEED, **params}
    alpha = theta_i  # arm centred on the peak, no misalignment
    hs, hd = 0.5 * (alpha + theta_i), 0.5 * (alpha - theta_i)
    c2 = 2.0 * math.cos(hs)
    cr, sr = math.cos(-phi_ref), math.sin(-phi_ref)
    w_i = np.array([-math.sin(theta_i), 0.0, math.cos(theta_i)])
    w_i = _rot_z(-phi_ref) @ w_i  # sample frame
    ro = _rot_y(-p["dtheta"]) @ _rot_z(-p["dphi0"])
    w_i2 = ro @ w_i
    centre = _incident_constants(w_i, p["n1"], 0.0) + [1.0 / p["m1"] ** 2, p["rho_s1"]]
    offset = _incident_constants(w_i2, p["n2"], 0.0) + [1.0 / p["m2"] ** 2, p["rho_s2"]]
    kk = 2.0 * w_i[2] / wavelength
    geo = [pitch, pitch, distance, math.sin(alpha), math.cos(alpha), c2 * math.sin(hd), c2 * math.cos(hd), cr, sr]
    bars = [p["rho_s3"], math.pi * p["a"] * kk, p["b"] * kk, distance / p["c"]]
    return np.array(geo + centre + offset + list(ro.ravel()) + bars, dtype=F)


if numba is not None:
    _jit = numba.njit(inline="always", fastmath=False, cache=True)

    @_jit
    def _specular(c, o, sx, sy, sz, tx, ty, tz):
        """Specular(Beckmann) of Eq 70 for one pixel; ``c[o:o+14]`` the term's per-frame constants."""
        ix, iy, ci, si2 = c[o], c[o + 1], c[o + 2], c[o + 3]
        air, aii, ai2, den_s, den_p = c[o + 4], c[o + 5], c[o + 6], c[o + 7], c[o + 8]
        n2r, n2i, num2, inv_m2, rho = c[o + 9], c[o + 10], c[o + 11], c[o + 12], c[o + 13]
        zero, one, half = F(0.0), F(1.0), F(0.5)
        if not (ci > zero and sz > zero and tz > zero):
            return zero
        inv_z = one / tz
        t2 = (tx * inv_z) ** 2 + (ty * inv_z) ** 2
        d = math.exp(-t2 * inv_m2) * (one + t2) ** 2 * (inv_m2 / F(math.pi))
        ss2 = sx * sx + sy * sy
        rr2 = si2 * ss2
        dot = ix * sx + iy * sy
        crs = ix * sy - iy * sx
        # csqrt(n^2 - ss2) and its modulus
        a = n2r - ss2
        r = math.sqrt(a * a + n2i * n2i)
        big = math.sqrt(half * (r + abs(a)))
        small = half * n2i / big if big > zero else zero
        if a >= zero:
            asr, asi = big, small
        else:
            asr, asi = abs(small), (-big if n2i < zero else big)
        den_ss = (sz + asr) ** 2 + asi**2
        den_ps = (n2r * sz + asr) ** 2 + (n2i * sz + asi) ** 2
        pr, pim = air * asr - aii * asi, air * asi + aii * asr
        if rr2 > zero:
            inv_rr2 = one / rr2
            cos2, sin2 = dot * dot * inv_rr2, crs * crs * inv_rr2
            pp = ((pr * dot + n2r * rr2) ** 2 + (pim * dot + n2i * rr2) ** 2) * inv_rr2
        else:
            cos2, sin2, pp = one, zero, pr * pr + pim * pim
        numer = (cos2 * den_p + ai2 * sin2 * den_s) * den_ps + (r * sin2 * den_p + pp * den_s) * den_ss
        q = num2 * numer / (den_s * den_ss * den_p * den_ps)
        return rho * d * q * (half / (ci + sz) ** 2)

    @numba.njit(parallel=True, fastmath=False, cache=True)
    def _frame(n_h, n_v, c, out):
        dh, dv, R, sa, ca, bx, bz, cr, sr = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8]
        ci = c[9 + 2]
        m = c[37:46]
        rho3, ka, kb, kc = c[46], c[47], c[48], c[49]
        zero, one, two = F(0.0), F(1.0), F(2.0)
        pi = F(math.pi)
        for row in numba.prange(n_v.shape[0]):
            y = n_v[row] * dv
            for col in range(n_h.shape[0]):
                x = n_h[col] * dh
                px, py, pz = x, y, zero * x  # aligned: R_CCD = 1, m_v = 0
                q = px * px + py * py + pz * pz + two * R * pz
                nu = math.sqrt(R * R + q)
                inv = one / (nu * (nu + R))
                inv_u = (nu + R) * inv
                ex, ey, ez = px * inv_u, py * inv_u, pz * inv_u - q * inv
                erx, erz = ca * ex + sa * ez, ca * ez - sa * ex
                sx, sy, sz = sa + erx, ey, ca + erz
                tx, ty, tz = bx + erx, ey, bz + erz
                # sample frame: Rz(-phi_ref)
                sx, sy = cr * sx - sr * sy, sr * sx + cr * sy
                tx, ty = cr * tx - sr * ty, sr * tx + cr * ty
                if not (ci > zero and sz > zero):
                    out[row, col] = zero
                    continue
                f = _specular(c, 9, sx, sy, sz, tx, ty, tz)
                # offset normal: Ry(-dtheta) Rz(-dphi0)
                s2x = m[0] * sx + m[1] * sy + m[2] * sz
                s2y = m[3] * sx + m[4] * sy + m[5] * sz
                s2z = m[6] * sx + m[7] * sy + m[8] * sz
                t2x = m[0] * tx + m[1] * ty + m[2] * tz
                t2y = m[3] * tx + m[4] * ty + m[5] * tz
                t2z = m[6] * tx + m[7] * ty + m[8] * tz
                f += _specular(c, 23, s2x, s2y, s2z, t2x, t2y, t2z)
                # diffraction by the bars
                n2 = tx * tx + ty * ty + tz * tz
                inv_n = one / math.sqrt(n2) if n2 > zero else one
                hx, hy = tx * inv_n, ty * inv_n
                ub = hy * kb
                sinc = one if ub == zero else math.sin(pi * ub) / (pi * ub)
                f += rho3 * math.cos(hy * ka) ** 2 * sinc * sinc * math.exp(-((hx * kc) ** 2))
                out[row, col] = f


def solar_cell_frame(theta_i: float, step: int = 1, phi_ref: float = 0.0, out: np.ndarray | None = None) -> np.ndarray:
    """The seed solar-cell frame (float32, sr^-1) on every ``step``-th pixel of the seed detector."""
    if numba is None:
        raise ImportError("fused_numba needs numba: pip install 'brdfjax[bench]'")
    n_h = (np.arange(3296)[::step] - 1647).astype(F)
    n_v = (np.arange(2472)[::step] - 1235).astype(F)
    if out is None:
        out = np.empty((n_v.size, n_h.size), F)
    _frame(n_h, n_v, frame_constants(theta_i, phi_ref), out)
    return out
