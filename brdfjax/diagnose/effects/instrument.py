"""Instrument-side effects: what the measurement does to the surface's BRDF.

``instrument_function`` (the beam's footprint, data side),
``flux_scale``, ``pixel_nonlinearity``, ``misalignment``,
``spectral_bandwidth`` (a source of finite bandwidth smears the diffraction
orders), ``stray_light`` and ``angular_sampling`` (a goniometer sample's
angular footprint).  The responses they add are the features of
:class:`~brdfjax.diagnose.effects.terms.InstrumentResponse`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...core.distributions import Beckmann
from ...core.terms import Diffraction, Model, Specular
from ...fit import FrameData, Param, TableData
from ...fit.internal import lobe_fwhm, lobe_parameters, lobe_term, table_step
from ...instrument.synthetic import footprint_kernel
from .base import (
    Effect,
    Extension,
    Signature,
    best_by_linear_chi2,
    golden,
    is_free,
    log_sf_chi2_even,
    log_sf_normal,
    no_frames,
    profiled_chi2,
    public_name,
    robust_mean_z,
    sample_ws,
    score_from_logp,
    template_z,
    weight_names,
    with_terms,
    ws_turn,
)
from .tables import tables_only
from .terms import (
    InstrumentResponse,
    Oriented,
    SpectralDiffraction,
    block_camera,
    camera_axes,
    camera_params,
    response_features,
)

__all__ = [
    "InstrumentFunctionEffect",
    "FluxScaleEffect",
    "PixelNonlinearityEffect",
    "MisalignmentEffect",
    "SpectralBandwidthEffect",
    "StrayLightEffect",
    "AngularSamplingEffect",
]


class InstrumentFunctionEffect(Effect):
    side = "instrument"
    name = "instrument_function"
    title = "convolution with the beam signature (instrument function)"
    doc = (
        "Data side: every frame gets a footprint (FrameData.footprint), the pixel-integrated Gaussian "
        "exp(-2 r^2 / w^2) of the focused beam (Eq 73), with which the fit convolves the model.  No new "
        "model parameter; the 1/e^2 radius w (0.5-11 grid pixels, then a golden-section search) is the one with the lowest "
        "chi^2 profiled over the main lobe's width (golden-section search) and a global log scale; n_new = 1 (w).  Signature: the score test "
        "z = r . t_perp / |t_perp| at that width (the symmetric shoulder: core down, wings up).  The width is "
        "rescanned on the candidate's refit and on every committed set that holds it, and refitted there while "
        "the chi^2 falls (``refine``)."
    )
    widths = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.5, 6.0, 8.0, 11.0)

    def present_in(self, model):
        return False

    def identifiable(self, model, params, blocks):
        frames = [b for b in blocks if isinstance(b, FrameData)]
        if not frames:
            return "needs detector frames (the instrument function is a 2-D convolution)"
        if all(b.footprint is not None for b in frames):
            return "every frame already carries an instrument function (footprint)"
        return None

    @staticmethod
    def _with_footprint(blocks, w, replace: bool = False):
        """``blocks`` with the footprint of width ``w`` on each frame (``replace``: also where one is already)."""
        ker = footprint_kernel(w)
        return [dataclasses.replace(b, footprint=ker) if isinstance(b, FrameData) and (replace or b.footprint is None)
                else b for b in blocks]

    def _blocks(self, ctx, w):
        return self._with_footprint(ctx.blocks, w)

    def _best_width(self, ctx, blocks_at) -> float:
        """The width of lowest profiled chi^2 on ``blocks_at(w)``: the grid ``widths``, then a golden-section search."""
        def prof(w):
            return profiled_chi2(ctx, lambda m: m, ctx.frames(), blocks_at(w))

        _, w = min((prof(w), w) for w in self.widths)
        lw, _ = golden(lambda x: prof(math.exp(x)), math.log(w / 1.4), math.log(w * 1.4), 14)
        return float(math.exp(lw))

    def _scan(self, ctx):
        w = self._best_width(ctx, lambda w: self._blocks(ctx, w))
        z = template_z(ctx, lambda m: m, ctx.frames(), self._blocks(ctx, w))
        return z, w

    def signature(self, ctx):
        z, w = self._scan(ctx)
        logp = math.log(len(self.widths) / 2.0) + log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"matched filter z = {z:.1f} for a footprint of 1/e^2 radius {w:g} grid pixels")

    def extend(self, ctx):
        z, w = self._scan(ctx)
        return Extension(ctx.model, dict(ctx.params), 1, blocks=self._blocks(ctx, w), fit_kwargs={"use_footprint": True},
                         note=f"footprint 1/e^2 radius {w:.3g} grid pixels (matched-filter z {z:.1f})")

    def refine(self, ctx, bare_blocks) -> tuple[list, float]:
        """The footprint's width scanned again on a fit that holds it: ``(blocks, w)``, ``bare_blocks`` the frames
        without a footprint.  The width is a data-side parameter the fit cannot move; scanned on the model it
        extends, it takes up what that model lacks (measured with diffraction withheld with it: 1.44 grid pixels
        scanned on the base, 1.29 rescanned on the fit with diffraction, truth 1.27; that fit's reduced chi^2
        34.7 -> 6.4).  :func:`~brdfjax.diagnose.refits.refine_data_side` refits at the new width."""
        w = self._best_width(ctx, lambda w: self._with_footprint(bare_blocks, w, replace=True))
        return self._with_footprint(bare_blocks, w, replace=True), w

    @staticmethod
    def _variance(k) -> float:
        g = np.asarray(k, np.float64).sum(axis=0)
        n = np.arange(g.size) - (g.size - 1) / 2.0
        return float(np.sum(g * n**2) / np.sum(g))

    def width_of(self, blocks) -> float | None:
        """The footprint width the frames of ``blocks`` carry, or None without one: the width whose kernel has
        the same second moment (a bisection in log width; the moment rises with the width, and for widths
        near a pixel it is not w^2 / 4 + 1/12, the kernel being sampled at whole pixels)."""
        for b in blocks:
            k = getattr(b, "footprint", None) if isinstance(b, FrameData) else None
            if k is not None:
                var = self._variance(k)
                lo, hi = math.log(0.05), math.log(64.0)
                for _ in range(60):
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if self._variance(footprint_kernel(math.exp(mid))) < var else (lo, mid)
                return math.exp(0.5 * (lo + hi))
        return None

    def with_width(self, bare_blocks, w: float) -> list:
        """``bare_blocks`` with the footprint of width ``w`` on every frame."""
        return self._with_footprint(bare_blocks, w, replace=True)


class FluxScaleEffect(Effect):
    side = "instrument"
    generic = True
    name = "flux_scale"
    title = "global flux scale (OD / incident-flux error)"
    needs_2d = False
    doc = (
        "Instrument side: the measured BRDF is flux_scale times the model (InstrumentResponse feature "
        "'flux_scale', parameter instrument.flux_scale in [0.1, 10]).  Initialised as exp of the median "
        "log residual.  Not identifiable when every term's weight is free (they absorb any global "
        "scale); fix the weights by calibration to test it.  Signature: a constant offset of the residual: "
        "the smaller (same sign) of the robust mean-residual z of the bright and the faint half of the points."
    )

    def present_in(self, model):
        return "flux_scale" in response_features(model)

    def identifiable(self, model, params, blocks):
        if (why := tables_only(blocks, self.name)) is not None:
            return why
        w = weight_names(model)
        if w and all(is_free(params, n) for _, n in w):
            names = ", ".join(n for _, n in w)
            return (f"flux_scale multiplies every term and every term's weight is free ({names}): a global scale "
                    "is absorbed by them; fix the weights (calibration) to test a flux error")
        return None

    def _halves(self, ctx):
        bright, faint, all_ = [], [], []
        for k in range(len(ctx.blocks)):
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            ok = np.isfinite(r)
            if not ok.any():
                continue
            med = np.median(f[ok])
            bright.append(r[ok & (f >= med)]); faint.append(r[ok & (f < med)])
            all_.append((r * ctx.sigma(k))[ok])
        cat = lambda x: np.concatenate(x) if x else np.zeros(0)  # noqa: E731
        return cat(bright), cat(faint), cat(all_)

    def signature(self, ctx):
        b, f, a = self._halves(ctx)
        zb, zf = robust_mean_z(b), robust_mean_z(f)
        z = min(abs(zb), abs(zf)) if zb * zf > 0 else 0.0
        return Signature(float(np.median(a)) if a.size else 0.0, score_from_logp(log_sf_normal(z) + math.log(2)),
                         f"residual offset: bright half z = {zb:.1f}, faint half z = {zf:.1f}")

    def extend(self, ctx):
        _, _, a = self._halves(ctx)
        s = float(np.clip(np.exp(np.median(a)), 0.2, 5.0)) if a.size else 1.0
        model = InstrumentResponse.wrap(ctx.model, "flux_scale", flux_scale=s)
        params = dict(ctx.params)
        params["instrument.flux_scale"] = Param(s, lower=0.1, upper=10.0)
        return Extension(model, params, 1, note=f"flux scale start {s:.4g}")


class PixelNonlinearityEffect(Effect):
    side = "instrument"
    generic = True
    name = "pixel_nonlinearity"
    title = "non-linear signal response (power law)"
    needs_2d = False
    # with the scale freed beside gamma (a weight fixed by calibration), gamma = 1 is a flux scale.  Measured:
    # in two withheld-effect trials (flux_scale with diffraction or with spectral_bandwidth) flux_scale was not
    # retried at step 2 (neither among step 1's best nor step 2's best signatures) and pixel_nonlinearity took
    # its place on the path with gamma = 1.0010
    nests = ("flux_scale",)
    doc = (
        "Instrument side: the measured BRDF is f_ref (s f / f_ref)^gamma (InstrumentResponse features "
        "'nonlinearity' and 'flux_scale': instrument.gamma in [0.5, 1.5], f_ref the geometric mean of the "
        "fitted model over the points, held).  The level at which the response is exact is not known, so "
        "the scale s (instrument.flux_scale in [0.1, 10]) is freed with gamma whenever a global scale is "
        "identifiable (some term's weight fixed by calibration) and not already in the model; with f_ref "
        "at the geometric mean, s and gamma are nearly uncorrelated.  (Measured: with gamma alone, a "
        "response exact at 1 sr^-1 was ranked behind flux_scale in 2 of 3 withheld-effect trials and "
        "needed both on the path.)  A power law of a lone Beckmann lobe is a narrower lobe times a "
        "scale; frames at different incident angles separate them only to second order (the geometric "
        "factor 1 / (cos theta_i cos theta_s) raised to gamma), so a lone Beckmann lobe of free width is "
        "reported as not identifiable.  Initialised by regressing the log residual on ln f (slope: gamma - 1, "
        "intercept at f_ref: ln s).  Signature: the t-statistic of that slope over the points where the "
        "model is above 1e-3 of its maximum (a residual correlated with the log signal)."
    )

    def present_in(self, model):
        return "nonlinearity" in response_features(model)

    def identifiable(self, model, params, blocks):
        if (why := tables_only(blocks, self.name)) is not None:
            return why
        terms = list(model.terms.values())
        if len(terms) == 1 and isinstance(terms[0], Specular) and isinstance(terms[0].distribution, Beckmann):
            (tname, _), = weight_names(model)
            width = public_name(model, f"{tname}.m")
            # the scale comes with gamma where a weight is fixed (extend), so a free weight is not needed for this
            if is_free(params, width):
                return (f"a power law f^gamma of a lone Beckmann lobe is the same lobe with m / sqrt(gamma) and another "
                        f"scale: with {width} free the data cannot tell it from a flux scale or a weight (measured: "
                        f"flux_scale alone reached the true model's chi^2); fix the width or add a term of another "
                        f"shape with a calibrated weight (a diffuse floor)")
        return None

    def _regress(self, ctx):
        X, Y, W = [], [], []
        for k in range(len(ctx.blocks)):
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            s = ctx.sigma(k)
            ok = np.isfinite(r) & (f > 0)
            if not ok.any():
                continue
            ok &= f > 1e-3 * f[ok].max()
            X.append(np.log(f[ok])); Y.append(r[ok] * s[ok]); W.append(1.0 / s[ok] ** 2)
        if not X:
            return 0.0, 0.0, 1.0, 0.0
        x, y, w = np.concatenate(X), np.concatenate(Y), np.concatenate(W)
        xm = np.sum(w * x) / np.sum(w)
        ym = float(np.sum(w * y) / np.sum(w))
        sxx = np.sum(w * (x - xm) ** 2)
        if sxx <= 0:
            return 0.0, 0.0, float(np.exp(xm)), ym
        beta = float(np.sum(w * (x - xm) * (y - ym)) / sxx)
        return beta, beta * math.sqrt(sxx), float(np.exp(xm)), ym

    def signature(self, ctx):
        beta, z, _, _ = self._regress(ctx)
        return Signature(beta, score_from_logp(log_sf_normal(abs(z)) + math.log(2)), f"slope of the log residual on ln f: {beta:.4f} (t = {z:.1f})")

    def extend(self, ctx):
        beta, _, fref, ym = self._regress(ctx)
        g = float(np.clip(1.0 + beta, 0.6, 1.4))
        params = dict(ctx.params)
        params["instrument.gamma"] = Param(g, lower=0.5, upper=1.5)
        scale = ("flux_scale" not in response_features(ctx.model)
                 and FluxScaleEffect().identifiable(ctx.model, ctx.params, ctx.blocks) is None)
        if not scale:
            model = InstrumentResponse.wrap(ctx.model, "nonlinearity", gamma=g, f_ref=fref)
            return Extension(model, params, 1, note=f"gamma start {g:.4f} about f_ref {fref:.3g} sr^-1")
        # the response's exact level is unknown: a scale with it (s^gamma at f_ref: the residual's mean there)
        s = float(np.clip(np.exp(ym / g), 0.2, 5.0))
        model = InstrumentResponse.wrap(ctx.model, "flux_scale", "nonlinearity", gamma=g, f_ref=fref, flux_scale=s)
        params["instrument.flux_scale"] = Param(s, lower=0.1, upper=10.0)
        return Extension(model, params, 2, note=f"gamma start {g:.4f} about f_ref {fref:.3g} sr^-1, with scale start {s:.4g}")


class MisalignmentEffect(Effect):
    side = "instrument"
    name = "misalignment"
    title = "detector misalignment (roll/yaw/pitch, m_h, m_v)"
    doc = (
        "Instrument side, as a model-side wrapper (brdfjax.fit has no detector parameters): the model is "
        "evaluated at scatter directions turned by Rz(rz) Ry(ry) Rx(rx) about the camera's axes "
        "(InstrumentResponse feature 'misalignment'; instrument.rx, .ry, .rz shared by all frames, start 0; "
        "instrument.arm, .arm_phi fixed per frame at the frame's arm angle and phi_ref).  An offset of the array by m_h, m_v "
        "pixels is a turn of m * pitch / R, a roll a turn about the optical axis; yaw and pitch of the "
        "array about its centre change the pixel directions only to second order.  One camera, one turn: "
        "the same turn predicts frames not fitted (held-out frames).  Signature: the dipole of the residual at the peak: the residual regressed on the "
        "model's log gradient (-d ln f / d row, -d ln f / d col) over the peak (chi^2, 2 dof per frame); "
        "the fitted shift in grid pixels is reported."
    )

    def present_in(self, model):
        return "misalignment" in response_features(model)

    def identifiable(self, model, params, blocks):
        if no_frames(blocks):
            return "needs detector frames (a goniometer table has no detector mapping)"
        return None

    def _dipole(self, ctx):
        chi2, n, shifts = 0.0, 0, []
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            s = ctx.sigma(k)
            ok = np.isfinite(r) & (f > 0)
            if ok.sum() < 10:
                continue
            L = np.log(np.maximum(f, 1e-300))
            gr, gc = np.gradient(L)
            sel = ok & (f > 1e-3 * f[ok].max()) & np.isfinite(gr) & np.isfinite(gc)
            A = np.stack([-gr[sel] / s[sel], -gc[sel] / s[sel]], axis=1)
            AtA = A.T @ A
            if np.linalg.cond(AtA) > 1e12:
                continue
            beta = np.linalg.solve(AtA, A.T @ r[sel])
            chi2 += float(beta @ AtA @ beta)
            n += 1
            shifts.append(beta)
        return chi2, n, shifts

    def signature(self, ctx):
        chi2, n, shifts = self._dipole(ctx)
        if n == 0:
            return Signature(0.0, 0.0, "no peak to test")
        sh = "; ".join(f"({b[0]:+.2f}, {b[1]:+.2f})" for b in shifts)
        return Signature(chi2, score_from_logp(log_sf_chi2_even(chi2, 2 * n)), f"dipole chi^2 = {chi2:.1f} ({2 * n} dof); shift (rows, cols) per frame: {sh}")

    def extend(self, ctx):
        model = InstrumentResponse.wrap(ctx.model, "misalignment")
        params = dict(ctx.params)
        for p in ("rx", "ry", "rz"):
            params[f"instrument.{p}"] = Param(0.0, per_frame=False, scale=2e-3)
        params.update(camera_params(ctx.blocks))
        return Extension(model, params, 3, note="camera turns rx, ry, rz (shared by all frames) from 0")


class SpectralBandwidthEffect(Effect):
    side = "instrument"
    name = "spectral_bandwidth"
    title = "finite source bandwidth (smeared diffraction orders)"
    doc = (
        "Replaces the base's Diffraction term by SpectralDiffraction: the bars averaged over a Gaussian "
        "line of relative rms width <bars>.width = sigma_lambda / lambda (15 Gauss-Hermite nodes), free in "
        "[0, 0.3]; higher orders smear into stripes.  Needs a diffraction term in the base.  Initialised "
        "at the width (0.2 %-8 %) whose linearised refit lowers chi^2 most; signature: the score test "
        "z = r . t_perp / |t_perp| of that smearing (t_perp: its change in ln f less what the base absorbs)."
    )
    widths = (0.002, 0.005, 0.01, 0.02, 0.04, 0.08)

    def present_in(self, model):
        return any(isinstance(t.term if isinstance(t, Oriented) else t, SpectralDiffraction) for t in model.terms.values())

    def _bars(self, model):
        return [n for n, t in model.terms.items() if isinstance(t.term if isinstance(t, Oriented) else t, Diffraction)]

    def identifiable(self, model, params, blocks):
        if not self._bars(model):
            return "the base model has no diffraction term: a source bandwidth shows through diffraction only"
        return None

    def _transform(self, width):
        def tr(m: Model) -> Model:
            terms = dict(m.terms)
            for n in self._bars(m):
                t = terms[n]
                if isinstance(t, Oriented):
                    terms[n] = dataclasses.replace(t, term=SpectralDiffraction.from_diffraction(t.term, width))
                else:
                    terms[n] = SpectralDiffraction.from_diffraction(t, width)
            return with_terms(m, terms)

        return tr

    def _scan(self, ctx):
        z, w, _ = best_by_linear_chi2(ctx, self.widths, lambda w: (self._transform(w),))
        return z, w

    def signature(self, ctx):
        z, w = self._scan(ctx)
        logp = math.log(len(self.widths) / 2.0) + log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"matched filter z = {z:.1f} for a relative line width {w:g}")

    def extend(self, ctx):
        z, w = self._scan(ctx)
        names = self._bars(ctx.model)
        model = self._transform(w)(ctx.model)
        params = dict(ctx.params)
        for n in names:
            params[f"{n}.width"] = Param(w, lower=0.0, upper=0.3)
        return Extension(model, params, len(names), note=f"line width start {w:g} (sigma_lambda / lambda) for {', '.join(names)}")


class StrayLightEffect(Effect):
    side = "instrument"
    name = "stray_light"
    title = "stray light (displaced sub-peak and background)"
    doc = (
        "Instrument side: the measured BRDF is f + ghost f(turned) (InstrumentResponse "
        "feature 'stray_light': instrument.ghost and the copy's turn .ghost_x, .ghost_y about "
        "the camera's axes, shared by all frames: a ghost sits at a fixed offset on the array; the response's "
        "uniform .background is held at 0: a floor is the 'lambertian' candidate's, one floor, not two).  Initialised from the cross-correlation of the residual with the base model's peak "
        "footprint (the model above 10 % of its maximum): its maximum away from zero shift gives the copy's "
        "offset (turned into ghost_x, ghost_y) and the excess there its relative amplitude.  Signature: "
        "that matched filter's maximum z over the shifts searched."
    )

    def present_in(self, model):
        return "stray_light" in response_features(model)

    def identifiable(self, model, params, blocks):
        if no_frames(blocks):
            return "needs detector frames (sub-peaks are displaced images on the array)"
        return None

    def _xcorr(self, ctx):
        best, n_shift = None, 0
        for k in ctx.frames():
            r = np.asarray(ctx.residuals[k], float)
            f = np.asarray(ctx.model_values[k], float)
            ok = np.isfinite(r)
            if not ok.any():
                continue
            T = (f > 0.1 * np.nanmax(f)).astype(float)
            rows, cols = r.shape
            shape = (2 * rows, 2 * cols)
            R0 = np.where(ok, r, 0.0)
            F = np.fft.rfft2(R0, shape) * np.conj(np.fft.rfft2(T, shape))
            num = np.fft.irfft2(F, shape)
            N = np.fft.irfft2(np.fft.rfft2(ok.astype(float), shape) * np.conj(np.fft.rfft2(T * T, shape)), shape)
            with np.errstate(invalid="ignore", divide="ignore"):
                z = num / np.sqrt(np.maximum(N, 1e-12))
            z[N < 0.5 * T.sum()] = -np.inf
            # exclude small shifts (the peak itself): within the footprint's extent
            rr, cc = np.nonzero(T)
            ext_r = (rr.max() - rr.min()) if rr.size else 1
            ext_c = (cc.max() - cc.min()) if cc.size else 1
            dr = np.fft.fftfreq(shape[0], 1.0 / shape[0])[:, None]
            dc = np.fft.fftfreq(shape[1], 1.0 / shape[1])[None, :]
            z[(np.abs(dr) <= max(ext_r // 2 + 1, 2)) & (np.abs(dc) <= max(ext_c // 2 + 1, 2))] = -np.inf
            n_shift += int(np.isfinite(z).sum())
            i = np.unravel_index(int(np.argmax(z)), z.shape)
            if best is None or z[i] > best[0]:
                best = (float(z[i]), k, int(dr[i[0], 0]), int(dc[0, i[1]]))
        return best, n_shift

    def applicable(self, ctx):
        best, _ = self._xcorr(ctx)
        if best is None or not math.isfinite(best[0]):
            return "no room for a displaced copy in the frames (no shift outside the peak's footprint)"
        return None

    def signature(self, ctx):
        best, n = self._xcorr(ctx)
        if best is None or not math.isfinite(best[0]):
            return Signature(0.0, 0.0, "no room for a displaced copy in the frames")
        z, k, dr, dc = best
        logp = math.log(max(n, 1) / 4.0) + log_sf_normal(z)
        return Signature(z, score_from_logp(logp), f"displaced-copy matched filter z = {z:.1f} at a shift of ({dr}, {dc}) grid pixels (block {k})")

    def extend(self, ctx):
        best, _ = self._xcorr(ctx)
        if best is None or not math.isfinite(best[0]):
            raise ValueError("stray_light: no displaced copy to start from (the frames leave no room for a shift "
                             "outside the peak's footprint)")
        _, k0, dr, dc = best
        gx, gy, ratio = [], [], []
        for k in ctx.frames():
            b, fr = ctx.blocks[k], ctx.block_frame(k)
            f = np.asarray(ctx.model_values[k], float)
            ws = sample_ws(b, fr)
            pr, pc = np.unravel_index(int(np.nanargmax(f)), f.shape)
            qr, qc = int(np.clip(pr + dr, 0, f.shape[0] - 1)), int(np.clip(pc + dc, 0, f.shape[1] - 1))
            # the turn about the camera's axes (one offset on the array is one turn in every frame)
            to_cam = np.asarray(camera_axes(*block_camera(b)), float).T
            ax, ay = ws_turn(to_cam @ ws[qr, qc], to_cam @ ws[pr, pc])
            gx.append(ax); gy.append(ay)
            r = np.asarray(ctx.residuals[k], float)
            if np.isfinite(r[qr, qc]):
                ratio.append(f[qr, qc] * (math.exp(r[qr, qc] * float(ctx.sigma(k)[qr, qc])) - 1.0) / f[pr, pc])
        g0 = float(np.clip(np.median(ratio), 1e-7, 0.5)) if ratio else 1e-4
        # no free background: a uniform floor is the diffuse floor's (lambertian) component, and two candidates
        # carrying the same free component competed for it (measured: 18 apart in delta BIC out of 3.6e8)
        bg = 0.0
        gx0, gy0 = float(np.median(gx)), float(np.median(gy))
        model = InstrumentResponse.wrap(ctx.model, "stray_light", ghost=g0, ghost_x=gx0, ghost_y=gy0, background=bg)
        params = dict(ctx.params)
        params["instrument.ghost"] = Param(g0, lower=0.0, upper=1.0)
        params["instrument.ghost_x"] = Param(gx0, per_frame=False, scale=2e-3)
        params["instrument.ghost_y"] = Param(gy0, per_frame=False, scale=2e-3)
        params["instrument.background"] = Param.fixed(bg)
        params.update(camera_params(ctx.blocks))
        return Extension(model, params, 3, note=f"copy shifted by ({dr}, {dc}) grid pixels at {g0:.3g} of the peak")


class AngularSamplingEffect(Effect):
    side = "instrument"
    name = "angular_sampling"
    title = "angular footprint of each goniometer sample"
    needs_2d = False
    doc = (
        "Model averaged over each sample's square angular footprint of full width instrument.aperture "
        "(InstrumentResponse feature 'aperture': 21 x 5 midpoints, in-plane x out-of-plane turns of the "
        "scatter direction), for goniometer tables whose step can straddle a narrow peak.  Initialised at "
        "the aperture (0.05-3 deg, refined to 10 %) with the lowest chi^2 profiled over the main lobe's "
        "width (x 0.05-1.5, golden section) and a global log scale; signature: that profiled chi^2 decrease "
        "against no aperture, as sqrt (1 dof) with the look-elsewhere factor of the apertures (a lobe "
        "narrower than the footprint gives a flat-topped, box-like measured peak that no lobe width fits).  Frames only: pixels are far smaller than "
        "any feature, so it is not identifiable there."
    )
    apertures_deg = (0.05, 0.1, 0.2, 0.4, 0.8, 1.5, 3.0)

    def present_in(self, model):
        return "aperture" in response_features(model)

    def identifiable(self, model, params, blocks):
        if not any(isinstance(b, TableData) for b in blocks):
            return "concerns goniometer tables; a detector pixel's footprint is far below any feature of the model"
        return None

    def _tr(self, a):
        return lambda m: InstrumentResponse.wrap(m, "aperture", aperture=a)

    def _scan(self, ctx):
        tables = [k for k, b in enumerate(ctx.blocks) if isinstance(b, TableData)]
        none = profiled_chi2(ctx, lambda m: m, tables, lo=0.05, hi=1.5)
        rows = [(profiled_chi2(ctx, self._tr(np.deg2rad(a)), tables, lo=0.05, hi=1.5), a) for a in self.apertures_deg]
        chi, a = min(rows)
        rows = [(profiled_chi2(ctx, self._tr(np.deg2rad(a * f)), tables, lo=0.05, hi=1.5), a * f) for f in (0.8, 0.9, 1.0, 1.12, 1.25)]
        chi, a = min(rows)
        return max(none - chi, 0.0), float(a)

    def unresolved(self, ctx) -> tuple[float, str] | None:
        """A peak the sampling does not resolve: ``(z, text)`` or None.

        The fitted narrowest lobe's FWHM is below the table's angular step at its highest sample, and that
        sample stands out of its two in-plane neighbours by more than a lobe one step wide allows (a
        Gaussian of FWHM = step falls to 1/16 one step away): ``z`` is that excess of ln(peak /
        neighbour) over ln 16 in units of the noise of ln BRDF.  The width and weight of such a lobe are
        not determined by the data (the fit reports the range they allow).
        """
        lobes = lobe_parameters(ctx.model)
        if not lobes:
            return None
        best = None
        for k, b in enumerate(ctx.blocks):
            if not isinstance(b, TableData):
                continue
            st = table_step(b)
            if st is None:
                continue
            step, ti = st
            wl = float(np.mean(np.asarray(b.wavelength, float)))
            # the narrowest lobe (each lobe of a multi_lobe term on its own)
            widths = [lobe_fwhm(lobe_term(ctx.block_model(k), t, w), ti, wl, 3.0 * step) for t, w, _ in lobes]
            widths = [x for x in widths if math.isfinite(x)]
            fwhm = min(widths) if widths else math.nan
            if not (math.isfinite(fwhm) and fwhm < step):
                continue
            d = np.asarray(b.brdf, float)
            tis = np.asarray(b.theta_i, float)
            sl = np.flatnonzero((np.abs(tis - ti) < 1e-6) & np.isfinite(d) & (d > 0))
            signed = np.where(np.abs(np.mod(np.asarray(b.phi_s, float)[sl] - np.asarray(b.phi_i, float)[sl], 2 * math.pi) - math.pi) < 1e-3,
                              np.asarray(b.theta_s, float)[sl], -np.asarray(b.theta_s, float)[sl])
            order = np.argsort(signed)
            vals = d[sl][order]
            i = int(np.argmax(vals))
            nb = [vals[j] for j in (i - 1, i + 1) if 0 <= j < vals.size]
            if not nb:
                continue
            excess = math.log(vals[i] / max(nb)) - math.log(16.0)
            s = float(np.nanmedian(ctx.sigma(k)))
            z = max(excess, 0.0) / max(s, 1e-12)
            text = (
                f"peak unresolved: the fitted lobe's FWHM ({math.degrees(fwhm):.3g} deg) is below the angular sampling "
                f"({math.degrees(step):.3g} deg) and the peak sample is x{vals[i] / max(nb):.3g} above its neighbours "
                f"(theta_i = {math.degrees(ti):.4g} deg): the lobe's width and weight are not determined by these data"
            )
            if best is None or z > best[0]:
                best = (z, text)
        return best

    def signature(self, ctx):
        un = self.unresolved(ctx)
        if un is not None:
            z, text = un
            return Signature(z, score_from_logp(log_sf_normal(z)), text, detection=z > 0)
        d, a = self._scan(ctx)
        z = math.sqrt(d)
        logp = math.log(len(self.apertures_deg) / 2.0) + log_sf_normal(z)
        return Signature(d, score_from_logp(logp), f"profiled chi^2 decrease {d:.1f} for an aperture of {a:.3g} deg")

    def extend(self, ctx):
        un = self.unresolved(ctx)
        if un is not None:
            # an unresolved peak: every aperture fits the one sample alike (the scan would find nothing to
            # gain); start at the table's step
            steps = [st[0] for b in ctx.blocks if isinstance(b, TableData) and (st := table_step(b)) is not None]
            a = float(np.degrees(min(steps)))
        else:
            _, a = self._scan(ctx)
        a = float(np.deg2rad(a))
        model = InstrumentResponse.wrap(ctx.model, "aperture", aperture=a)
        params = dict(ctx.params)
        params["instrument.aperture"] = Param(a, lower=0.0, upper=float(np.deg2rad(10.0)))
        note = f"aperture start {np.degrees(a):.3g} deg"
        if un is not None:
            note = f"{un[1]}; {note}"
        return Extension(model, params, 1, note=note)
