"""The terms and model wrappers the effects add to a base model (pure JAX, differentiable).

- :class:`Oriented`: any term turned about the sample normal by its own angle
  ``psi`` (the orientation of diffraction bars or of an anisotropic lobe
  relative to the sample frame; the frame's ``phi_ref`` turns everything).
- :class:`SpectralDiffraction`: the Fraunhofer bars of
  :class:`brdfjax.core.terms.Diffraction` integrated over a source spectrum, so the
  diffraction orders smear into stripes.  The spectrum is a set of relative
  wavelength offsets ``x_k`` with weights ``w_k`` (sum 1) scaled by the
  relative rms width ``width``: ``lambda_k = lambda (1 + width x_k)``, with
  ``lambda`` the frame's (centroid) wavelength.  The default offsets are the
  Gauss-Hermite nodes of a Gaussian line (``width`` = sigma_lambda / lambda);
  :meth:`SpectralDiffraction.from_spectrum` takes any
  ``colour.SpectralDistribution`` (a broadband LED, a laser line of finite width).
- :class:`InstrumentResponse`: a :class:`~brdfjax.core.terms.Model` (same terms,
  same parameter names) with instrument-side responses switched on by
  ``features``; their parameters are named ``instrument.<name>``:

  ========================  ===============================================  ==========================
  feature                   measured BRDF                                     parameters
  ========================  ===============================================  ==========================
  ``misalignment``          ``f`` at the scatter direction turned by          ``rx, ry, rz`` (rad);
                            ``Rz(rz) Ry(ry) Rx(rx)`` about the axes of the     ``arm``, ``arm_phi`` (rad,
                            camera on its arm (``Rz(-arm_phi) Ry(arm)`` of     per frame, fixed: the
                            the sample's x, y, z): a detector offset           frame's arm angle and
                            ``m_h, m_v``                                       phi_ref)
                            (pixels * pitch / R) and roll to first order,
                            one turn for every frame
  ``aperture``              ``f`` averaged over a square angular footprint     ``aperture`` (rad, full
                            of each sample (midpoint rule on a grid of          width)
                            turned scatter directions)
  ``stray_light``           ``f + ghost f(turned by ghost_x, ghost_y about     ``ghost`` (1), ``ghost_x``,
                            the camera's axes) + background``: a faint          ``ghost_y`` (rad),
                            displaced copy (a sub-peak at a fixed offset on     ``background`` (sr^-1);
                            the array) and a uniform background                 ``arm`` as above
  ``flux_scale``            ``flux_scale f`` (an OD or incident-flux error)    ``flux_scale`` (1)
  ``nonlinearity``          ``f_ref (f / f_ref)^gamma`` (a power-law response   ``gamma`` (1); ``f_ref``
                            of the measured signal about ``f_ref``)            static (sr^-1)
  ========================  ===============================================  ==========================

  Applied in the order geometry (misalignment, aperture) -> optics (stray
  light) -> detector (flux scale, non-linearity).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ...core.fields import check_param, param
from ...core.geometry import Directions, Rx, Ry, Rz, rotate
from ...core.terms import AbstractTerm, Diffraction, Model, Oriented, param_fields
from ...fit import Param

__all__ = ["Oriented", "SpectralDiffraction", "InstrumentResponse", "FEATURES", "turn_scatter", "camera_axes", "block_camera", "camera_params", "response_features"]


def _gauss_hermite(n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    x, w = np.polynomial.hermite_e.hermegauss(n)
    w = w / w.sum()
    return tuple(float(v) for v in x), tuple(float(v) for v in w)


class SpectralDiffraction(AbstractTerm):
    """:class:`~brdfjax.core.terms.Diffraction` averaged over a spectrum: ``sum_k w_k Diffraction(lambda (1 + width x_k))``.

    It wraps the diffraction term (``diffraction``; its parameters keep their
    names: ``<bars>.rho``, ``.a``, ``.b``, ``.c``, then ``.width``) and
    evaluates it at each node's wavelength.
    """

    kind: ClassVar[str] = "spectral_diffraction"
    diffraction: Diffraction
    width: Array = param("1", "relative rms spectral width sigma_lambda / lambda")
    nodes: tuple[float, ...] = eqx.field(static=True, default=_gauss_hermite(15)[0])
    weights: tuple[float, ...] = eqx.field(static=True, default=_gauss_hermite(15)[1])

    def __check_init__(self):
        check_param("spectral_diffraction", "width", self.width, lambda v: v >= 0, "width >= 0 (relative)")
        if len(self.nodes) != len(self.weights) or not self.nodes:
            raise ValueError("SpectralDiffraction: nodes and weights must be non-empty and of equal length")

    @classmethod
    def from_diffraction(cls, d: Diffraction, width: float, n_nodes: int = 15) -> "SpectralDiffraction":
        """A Gaussian line of relative rms width ``width`` about the frame's wavelength."""
        x, w = _gauss_hermite(n_nodes)
        return cls(d, width, x, w)

    @classmethod
    def from_spectrum(cls, d: Diffraction, sd: Any, max_samples: int = 41) -> "SpectralDiffraction":
        """The bars under a source of spectral distribution ``sd`` (a ``colour.SpectralDistribution``, nm).

        The frame's wavelength is taken as the spectrum's centroid; ``width``
        is its relative rms width and the nodes the spectrum's samples in
        units of that width (resampled to at most ``max_samples``).
        """
        lam = np.asarray(sd.wavelengths, float)
        val = np.clip(np.asarray(sd.values, float), 0.0, None)
        if lam.size < 1 or val.sum() <= 0:
            raise ValueError("SpectralDiffraction.from_spectrum: the spectrum has no positive values")
        keep = val > 1e-6 * val.max()
        lam, val = lam[keep], val[keep]
        if lam.size > max_samples:
            edges = np.linspace(lam[0], lam[-1], max_samples + 1)
            idx = np.clip(np.digitize(lam, edges) - 1, 0, max_samples - 1)
            wsum = np.bincount(idx, val, max_samples)
            lsum = np.bincount(idx, val * lam, max_samples)
            ok = wsum > 0
            lam, val = lsum[ok] / wsum[ok], wsum[ok]
        w = val / val.sum()
        centre = float(np.sum(w * lam))
        sigma = float(np.sqrt(np.sum(w * (lam - centre) ** 2)))
        if sigma <= 0:
            return cls(d, 0.0, (0.0,), (1.0,))
        x = (lam / centre - 1.0) / (sigma / centre)
        return cls(d, sigma / centre, tuple(map(float, x)), tuple(map(float, w)))

    def __call__(self, dirs, wavelength):
        total = 0.0
        for x, w in zip(self.nodes, self.weights):
            total = total + w * self.diffraction(dirs, wavelength * (1.0 + self.width * x))
        return total


def turn_scatter(dirs: Directions, ax: Any, ay: Any, az: Any = 0.0, camera: Any = None) -> Directions:
    """Directions with only ``w_s`` turned by ``Rz(az) Ry(ay) Rx(ax)``; ``w_sum`` updated without cancellation.

    ``camera = (alpha, phi_ref)``: the frame's arm angle and sample rotation;
    the turn is then about the axes of the camera on that arm, as seen in the
    sample frame (``render.pixel_directions``: ``Rz(-phi_ref)`` of the
    scatter frame): ``C Rz(az) Ry(ay) Rx(ax) C^T`` with ``C = Rz(-phi_ref)
    Ry(alpha)``, so that one misaligned camera (pixel offsets m_h, m_v and a
    roll) is the same turn in every frame whatever its geometry.
    """
    R = Rz(az) @ Ry(ay) @ Rx(ax)
    if camera is not None:
        C = camera_axes(*camera)
        R = C @ R @ C.T
    dws = rotate(R - jnp.eye(3, dtype=R.dtype), dirs.w_s)
    return Directions(dirs.w_i, dirs.w_s + dws, dirs.w_sum + dws)


def camera_axes(arm: Any, phi_ref: Any) -> Array:
    """The camera's x, y, z axes (columns) in the sample frame of ``render.pixel_directions``:
    ``Rz(-phi_ref) Ry(arm)``; ``C.T @ w`` takes a sample-frame direction into the camera's frame."""
    return Rz(-phi_ref) @ Ry(arm)


def block_camera(block: Any) -> tuple[float, float]:
    """``(arm angle, phi_ref)`` (rad) of a data block's camera: its ``theta_c``
    (or the nominal ``theta_i`` when the camera sits on the peak) and the
    frame's nominal ``phi_ref``; ``(0, 0)`` for a goniometer table (no
    camera: camera turns are then in the sample frame)."""
    if not hasattr(block, "arm_detector"):
        return 0.0, 0.0
    return float(block.arm_detector().theta_c), float(block.phi_ref)


def camera_params(blocks: Sequence[Any]) -> dict[str, Any]:
    """The fixed per-frame ``instrument.arm`` / ``instrument.arm_phi`` parameter specs of ``blocks``."""
    cams = [block_camera(b) for b in blocks]
    return {
        "instrument.arm": Param.fixed([c[0] for c in cams], per_frame=True),
        "instrument.arm_phi": Param.fixed([c[1] for c in cams], per_frame=True),
    }


#: Feature -> its parameter fields on :class:`InstrumentResponse`.
FEATURES: dict[str, tuple[str, ...]] = {
    "misalignment": ("rx", "ry", "rz", "arm", "arm_phi"),
    "aperture": ("aperture",),
    "stray_light": ("ghost", "ghost_x", "ghost_y", "background", "arm", "arm_phi"),
    "flux_scale": ("flux_scale",),
    "nonlinearity": ("gamma",),
}


def _midpoints(n: int) -> tuple[float, ...]:
    return tuple(float(v) for v in (np.arange(n) + 0.5) / n - 0.5)


class InstrumentResponse(Model):
    """A :class:`~brdfjax.core.terms.Model` seen through instrument-side responses (module docstring).

    Build with :meth:`wrap` (keeps the terms, aliases and any response
    already switched on) and switch features on by name; parameters are
    addressed as ``instrument.<field>``.
    """

    kind: ClassVar[str] = "instrument_response"
    features: tuple[str, ...] = eqx.field(static=True, default=())
    flux_scale: Array = param("1", "global scale of the measured BRDF (flux/OD error)", default=1.0)
    gamma: Array = param("1", "power-law exponent of the signal response", default=1.0)
    f_ref: float = eqx.field(static=True, default=1.0)
    rx: Array = param("rad", "scatter-direction turn about the camera's x axis (sample frame when arm = 0)", default=0.0)
    ry: Array = param("rad", "scatter-direction turn about y (the arm's rotation axis)", default=0.0)
    rz: Array = param("rad", "scatter-direction turn about the camera's optical axis (sample z when arm = 0)", default=0.0)
    arm: Array = param("rad", "the frame's arm angle (the camera's axes; fixed per frame)", default=0.0)
    arm_phi: Array = param("rad", "the frame's phi_ref (the sample turned under the camera; fixed per frame)", default=0.0)
    ghost: Array = param("1", "relative amplitude of the stray-light copy", default=0.0)
    ghost_x: Array = param("rad", "turn of the copy about the camera's x axis", default=0.0)
    ghost_y: Array = param("rad", "turn of the copy about y (the arm's rotation axis)", default=0.0)
    background: Array = param("sr^-1", "uniform stray background", default=0.0)
    aperture: Array = param("rad", "full width of each sample's square angular footprint", default=0.0)
    aperture_n: tuple[int, int] = eqx.field(static=True, default=(21, 5))

    def __check_init__(self):
        unknown = [f for f in self.features if f not in FEATURES]
        if unknown:
            raise ValueError(f"InstrumentResponse: unknown feature(s) {unknown}; known: {', '.join(FEATURES)}")

    @classmethod
    def wrap(cls, model: Model, *features: str, **values: Any) -> "InstrumentResponse":
        """``model`` with ``features`` switched on and response fields set from ``values``."""
        fields = {}
        if isinstance(model, InstrumentResponse):
            fields = {f.name: getattr(model, f.name) for f in param_fields(model)}
            fields.update(features=model.features, f_ref=model.f_ref, aperture_n=model.aperture_n)
        fields.update(values)
        feats = tuple(fields.pop("features", ())) + tuple(f for f in features if f not in fields.get("features", ()))
        feats = tuple(dict.fromkeys(feats))
        return cls(terms=dict(model.terms), aliases=model.aliases, features=feats, **fields)

    def unwrap(self) -> Model:
        """The plain model (no instrument response)."""
        return Model(terms=dict(self.terms), aliases=self.aliases)

    def _paths(self):
        out = super()._paths()
        units = {f.name: f.metadata["unit"] for f in param_fields(self)}
        for feat in self.features:
            for name in FEATURES[feat]:
                out[f"instrument.{name}"] = ((name,), units[name])
        return out

    def _sum(self, dirs, wavelength):
        return Model.__call__(self, dirs, wavelength)

    def __call__(self, dirs, wavelength):
        on = self.features
        if "misalignment" in on:
            dirs = turn_scatter(dirs, self.rx, self.ry, self.rz, camera=(self.arm, self.arm_phi))
        if "aperture" in on:
            nx, ny = self.aperture_n
            gx, gy = np.meshgrid(_midpoints(nx), _midpoints(ny), indexing="ij")
            # in-plane (about y) along x-nodes, out-of-plane (about x) along y-nodes; vmapped (one compiled copy)
            vals = jax.vmap(lambda x, y: self._sum(turn_scatter(dirs, self.aperture * y, self.aperture * x), wavelength))(
                jnp.asarray(gx.ravel(), dirs.w_s.dtype), jnp.asarray(gy.ravel(), dirs.w_s.dtype)
            )
            f = jnp.mean(vals, axis=0)
        else:
            f = self._sum(dirs, wavelength)
        if "stray_light" in on:
            ghost = turn_scatter(dirs, self.ghost_x, self.ghost_y, camera=(self.arm, self.arm_phi))
            f = f + self.ghost * self._sum(ghost, wavelength) + self.background
        if "flux_scale" in on:
            f = self.flux_scale * f
        if "nonlinearity" in on:
            pos = f > 0
            f = jnp.where(pos, self.f_ref * jnp.exp(self.gamma * jnp.log(jnp.where(pos, f, 1.0) / self.f_ref)), 0.0)
        return f

    def term_values(self, dirs, wavelength):
        return Model.term_values(self, dirs, wavelength)


def response_features(model: Model) -> Sequence[str]:
    """The instrument-response features switched on in ``model`` (none for a plain model)."""
    return model.features if isinstance(model, InstrumentResponse) else ()
