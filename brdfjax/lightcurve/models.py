"""Facet models beyond the core's: a Phong baseline, the directional albedo, models from fits and posteriors.

:func:`lumos_phong` builds lumos-sat's ``PHONG(Kd, Ks, n)`` baseline
(``Kd / pi + Ks (n + 2) / (2 pi) max(r . w_s, 0)^n``, ``r`` the mirror
direction of ``w_i``) from the core's one :class:`~brdfjax.core.terms.Phong`
and a Lambertian term (``Phong`` here is that core class, re-exported).
:func:`directional_albedo` integrates any model over the scattered hemisphere
in half-vector coordinates, fine enough for the seed's 2e-4 rad peaks, to
give a baseline "of the same albedo".  :func:`params_from_fit_result` and
:func:`posterior_samples` read a ``brdfjax fit`` result.json and a
``brdfjax sample`` chain.h5.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import jax
import jax.numpy as jnp
import numpy as np

from ..core.geometry import Directions
from ..core.terms import AbstractTerm, Lambertian, Model, Phong
from ..runtime.errors import InputError

__all__ = ["Phong", "lumos_phong", "directional_albedo", "params_from_fit_result", "posterior_samples", "ModelSourceError"]


class ModelSourceError(InputError):
    """A fit result or posterior chain that cannot give a facet's model; the message names the file and key."""


def lumos_phong(kd: float, ks: float, n: float) -> Model:
    """lumos-sat's ``PHONG(Kd, Ks, n)``: ``Kd / pi + Ks (n + 2) / (2 pi) max(r . w_s, 0)^n`` as a core model.

    The core's :class:`~brdfjax.core.terms.Phong` (``rho (k + 2) / (2 pi)
    max(cos alpha, 0)^k``, alpha from the mirror direction) with ``rho = Ks``,
    ``k = n``, plus a :class:`~brdfjax.core.terms.Lambertian` of ``rho_d = Kd``.
    """
    return Model({"diffuse": Lambertian(kd), "phong": Phong(ks, n)})


def directional_albedo(model: AbstractTerm, theta_i: float, wavelength: float = 550e-9,
                       n_theta: int = 1200, n_phi: int = 4096) -> float:
    """``int f(w_i, w_s) cos(theta_s) d w_s`` over the hemisphere (the directional-hemispherical reflectance).

    Integrated over half vectors ``h`` (``w_s`` = the mirror of ``w_i`` about
    ``h``, ``d w_s = 4 (w_i . h) d w_h``) on a grid log-spaced in the half
    vector's zenith from 1e-7 rad (resolving 2e-4 rad peaks and the offset
    peak 0.5 deg away) and uniform in azimuth (4096 steps resolve the
    diffraction streak, 1.2e-4 rad wide, out to 0.1 rad).  Directions below
    the horizon contribute nothing.
    """
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    t_edges = np.concatenate([[0.0], np.geomspace(1e-7, np.pi / 2, n_theta)])
    t = 0.5 * (t_edges[1:] + t_edges[:-1])
    dt = np.diff(t_edges)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    wi = np.array([-np.sin(theta_i), 0.0, np.cos(theta_i)])

    def row(args):
        tk, dtk = args
        st, ct = jnp.sin(tk), jnp.cos(tk)
        h = jnp.stack([st * jnp.cos(phi), st * jnp.sin(phi), jnp.broadcast_to(ct, phi.shape)], -1).astype(dtype)
        wih = jnp.sum(h * wi, -1)
        ws = 2 * wih[:, None] * h - wi
        dirs = Directions.from_vectors(jnp.broadcast_to(jnp.asarray(wi, dtype), ws.shape), ws)
        f = model(dirs, wavelength)
        integrand = f * jnp.maximum(ws[:, 2], 0) * 4 * jnp.maximum(wih, 0) * st
        return jnp.sum(integrand) * dtk * (2 * np.pi / n_phi)

    rows = jax.jit(lambda a, b: jax.lax.map(row, (a, b), batch_size=16))(jnp.asarray(t, dtype), jnp.asarray(dt, dtype))
    return float(jnp.sum(rows))


def _natural_to_stored(value: float, unit: str) -> float:
    return float(np.deg2rad(value)) if unit == "deg" else float(value)


def params_from_fit_result(path: str | Path, model: Model, where: str) -> dict[str, float]:
    """Parameter values (stored units) of a ``brdfjax fit`` result.json for ``model``.

    Every parameter of the result must be one of the model's; ``where`` is the
    config key that named the file (for messages).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        params = data["parameters"]
        if not isinstance(params, dict):
            raise TypeError("'parameters' is not a table")
    except FileNotFoundError:
        raise ModelSourceError(f"{where}: fit result {path} not found") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ModelSourceError(f"{where}: {path} is not a brdfjax fit result.json ({type(e).__name__}: {e})") from None
    known = model.parameter_units()
    out = {}
    for name, entry in params.items():
        if name not in known:
            raise ModelSourceError(
                f"{where}: {path}: parameters.{name} is not a parameter of the facet's model; known: {', '.join(known)}"
            )
        if not isinstance(entry, dict) or entry.get("value") is None:
            raise ModelSourceError(f"{where}: {path}: parameters.{name} has no finite 'value'")
        out[name] = _natural_to_stored(entry["value"], entry.get("unit", ""))
    return out


def posterior_samples(path: str | Path, model: Model, where: str, n: int, burn: int | None, seed: int = 0
                      ) -> tuple[tuple[str, ...], np.ndarray]:
    """``n`` draws (stored units) from a ``brdfjax sample`` chain.h5: parameter names and an (n, p) array.

    The file is emcee's HDF5 backend (group ``mcmc``) with the names in the
    ``brdfjax`` group's ``meta`` (JSON); ``burn`` steps are discarded (default:
    half the chain); draws are taken without replacement when the chain has
    enough, with a fixed ``seed``.
    """
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            meta = json.loads(f["brdfjax"].attrs["meta"])
            g = f["mcmc"]
            it = int(g.attrs["iteration"])
            chain = np.asarray(g["chain"][:it], np.float64)  # (steps, walkers, p)
    except FileNotFoundError:
        raise ModelSourceError(f"{where}: posterior chain {path} not found") from None
    except (OSError, KeyError, ValueError) as e:
        raise ModelSourceError(f"{where}: {path} is not a brdfjax chain.h5 ({type(e).__name__}: {e})") from None
    names = tuple(meta.get("names", ()))
    if not names or chain.ndim != 3 or chain.shape[-1] != len(names):
        raise ModelSourceError(f"{where}: {path}: the chain's parameter names do not match its shape {chain.shape}")
    known = model.parameter_units()
    bad = [nm for nm in names if nm not in known]
    if bad:
        raise ModelSourceError(
            f"{where}: {path}: chain parameter(s) {bad} are not parameters of the facet's model; known: {', '.join(known)}"
        )
    burn = it // 2 if burn is None else burn
    if burn >= it:
        raise ModelSourceError(f"{where}: {path}: burn = {burn} discards the whole chain ({it} steps)")
    flat = chain[burn:].reshape(-1, len(names))
    rng = np.random.default_rng(seed)
    idx = rng.choice(flat.shape[0], size=n, replace=flat.shape[0] < n)
    return names, flat[idx]

