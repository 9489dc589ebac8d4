"""Camera alignment on the arm (seed §3.4): roll from an arm slew, yaw and pitch from an axial translation.

The beam-signature geometry: no sample, the focused beam travels along +z of
the scatter frame and hits the array where the ray meets the (possibly
misaligned) array plane.  :func:`spot_pixel` gives that pixel for an arm
angle ``theta_c`` and a camera translated by ``axial`` metres along its
optical axis toward the source (the seed's micrometer stage), with the
misalignment convention of :class:`brdfjax.Detector` (Eq 105:
``R_CCD = Rz(roll) Ry(yaw) Rx(pitch)``, offsets ``m_h``, ``m_v`` in pixels).
With ``axial = 0`` it is ``Detector.pixel_of(0, 0, theta_c)``.

The procedure (:func:`run_alignment`), on any :class:`~brdfjax.devices.interfaces.Bench`:

1. sample out of the beam, arm at 0, the beam-safe ND stack (interlock), the
   shortest exposure; a background frame with the beam blocked;
2. spot centroids (background subtracted, iterated window of +-3 footprint
   radii) at the arm slewed to ``-slew, 0, +slew`` and, with the arm at 0,
   the camera advanced by ``translation`` along its axis;
3. the seed's formulas: roll = atan(vertical / horizontal spot shift over
   the slew), yaw = atan(horizontal shift / translation in pixels), pitch =
   atan(vertical shift / translation in pixels) (seed: 24 px over 1545 px ->
   0.89 deg; 46 and 12 px over 4618.2 px/inch -> 0.57 and 0.15 deg);
4. a refinement: ``(roll, yaw, pitch, m_h, m_v)`` fitted (Gauss-Newton) to
   every measured spot with the exact geometry of :func:`spot_pixel`; the
   fitted angles are what the capture writes into the raw files' ``roll``,
   ``yaw``, ``pitch``, ``m_h``, ``m_v`` attributes (the pixel mapping's
   misalignment) and into the manifest's ``[capture.alignment]`` table.

Signs follow the pixel mapping, so the seed formulas come with the signs that
make them agree with the fit to first order.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["spot_pixel", "spot_centroid", "AlignmentResult", "solve_alignment", "run_alignment"]


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def spot_pixel(
    *,
    theta_c: float,
    axial: float = 0.0,
    roll: float = 0.0,
    yaw: float = 0.0,
    pitch: float = 0.0,
    m_h: float = 0.0,
    m_v: float = 0.0,
    pixel_pitch: tuple[float, float],
    distance: float,
) -> tuple[float, float]:
    """Fractional pixel ``(n_h, n_v)`` hit by the direct beam (along +z), float64.

    ``theta_c``: arm angle (rad; any sign); ``axial``: camera advanced along
    its optical axis toward the source, m.  Returns NaN when the ray misses
    the plane.
    """
    d_h, d_v = pixel_pitch
    alpha = theta_c + m_h * d_h / distance
    w = _ry(-alpha) @ np.array([0.0, 0.0, 1.0])
    rc = _rz(roll) @ _ry(yaw) @ _rx(pitch)
    normal = rc[:, 2]
    anchor = np.array([0.0, m_v * d_v, distance]) - axial * normal
    w_c = rc.T @ w
    a_c = rc.T @ anchor
    if w_c[2] <= 0:
        return (math.nan, math.nan)
    t = a_c[2] / w_c[2]
    return (float((t * w_c[0] - a_c[0]) / d_h), float((t * w_c[1] - a_c[1]) / d_v))


def spot_centroid(
    signal: np.ndarray, index_origin: tuple[int, int], w_px: float, *, iterations: int = 4
) -> tuple[float, float, float]:
    """Centroid ``(n_h, n_v)`` of a background-subtracted spot image, and its summed signal.

    ``signal``: ``(rows, cols)`` counts with the background removed;
    ``index_origin``: ``(h_min, v_min)``, the pixel indices of column 0 and
    row 0; ``w_px``: the footprint's 1/e^2 radius in pixels (window
    half-width ``3 w + 2``).  Starts at the brightest pixel and re-centres the
    window on the centroid.
    """
    rows, cols = signal.shape
    r0, c0 = np.unravel_index(int(np.argmax(signal)), signal.shape)
    cy, cx = float(r0), float(c0)
    half = int(math.ceil(3.0 * w_px)) + 2
    total = 0.0
    for _ in range(iterations):
        ra, rb = max(0, int(round(cy)) - half), min(rows, int(round(cy)) + half + 1)
        ca, cb = max(0, int(round(cx)) - half), min(cols, int(round(cx)) + half + 1)
        win = np.asarray(signal[ra:rb, ca:cb], dtype=np.float64)
        total = float(win.sum())
        if not total > 0:
            raise ValueError("spot_centroid: no positive signal in the window around the brightest pixel")
        yy, xx = np.mgrid[ra:rb, ca:cb]
        cy, cx = float((win * yy).sum() / total), float((win * xx).sum() / total)
        if ra == 0 or ca == 0 or rb == rows or cb == cols:
            raise ValueError(
                f"spot_centroid: the spot at array (row, col) = ({cy:.1f}, {cx:.1f}) is within {half} px of the edge; "
                "centre the camera on the beam or reduce the slew"
            )
    return (cx + index_origin[0], cy + index_origin[1], total)


@dataclass(frozen=True)
class AlignmentResult:
    """Measured misalignment (radians, pixels), the seed-formula estimates and the spots behind them."""

    roll: float
    yaw: float
    pitch: float
    m_h: float
    m_v: float
    seed_roll: float
    seed_yaw: float
    seed_pitch: float
    rms_residual_px: float
    spots: tuple[tuple[float, float, float, float], ...]  # (theta_c rad, axial m, n_h, n_v)
    nd_filters: str = ""
    slew: float = 0.0
    translation: float = 0.0

    def degrees(self) -> dict[str, float]:
        return {
            "roll_deg": math.degrees(self.roll),
            "yaw_deg": math.degrees(self.yaw),
            "pitch_deg": math.degrees(self.pitch),
            "m_h_px": self.m_h,
            "m_v_px": self.m_v,
            "seed_roll_deg": math.degrees(self.seed_roll),
            "seed_yaw_deg": math.degrees(self.seed_yaw),
            "seed_pitch_deg": math.degrees(self.seed_pitch),
            "rms_residual_px": self.rms_residual_px,
        }

    def to_dict(self) -> dict:
        d = asdict(self)
        d["spots"] = [list(s) for s in self.spots]
        return d


def solve_alignment(
    spots: list[tuple[float, float, float, float]],
    *,
    pixel_pitch: tuple[float, float],
    distance: float,
    slew: float,
    translation: float,
) -> AlignmentResult:
    """Misalignment from measured spots ``[(theta_c, axial, n_h, n_v), ...]`` (see the module docstring).

    Needs the spots at ``theta_c = -slew, 0, +slew`` (axial 0) and at
    ``theta_c = 0, axial = translation``.
    """
    def find(tc: float, ax: float) -> tuple[float, float]:
        for t, a, h, v in spots:
            if abs(t - tc) < 1e-12 and abs(a - ax) < 1e-12:
                return h, v
        raise ValueError(f"solve_alignment: no spot measured at theta_c={tc!r} rad, axial={ax!r} m")

    h0, v0 = find(0.0, 0.0)
    hm, vm = find(-slew, 0.0)
    hp, vp = find(slew, 0.0)
    ht, vt = find(0.0, translation)
    d_h, d_v = pixel_pitch
    # Seed formulas.  Slewing the arm by +slew moves the spot toward -n_h; a roll tilts that path by
    # -roll (v = -tan(roll) h in the pixel frame); advancing the camera by L moves the spot by
    # (+L tan(yaw) / d_h, -L tan(pitch) / d_v) to first order.
    seed_roll = -math.atan((vp - vm) / (hp - hm))
    seed_yaw = math.atan((ht - h0) * d_h / translation)
    seed_pitch = -math.atan((vt - v0) * d_v / translation)

    def predict(p: np.ndarray) -> np.ndarray:
        out = []
        for t, a, _, _ in spots:
            out += list(
                spot_pixel(theta_c=t, axial=a, roll=p[0], yaw=p[1], pitch=p[2], m_h=p[3], m_v=p[4],
                           pixel_pitch=pixel_pitch, distance=distance)
            )
        return np.array(out)

    obs = np.array([x for _, _, h, v in spots for x in (h, v)])
    p = np.array([seed_roll, seed_yaw, seed_pitch, -h0, -v0], dtype=np.float64)
    steps = np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4])
    for _ in range(20):
        r = obs - predict(p)
        J = np.stack([(predict(p + np.eye(5)[k] * steps[k]) - predict(p - np.eye(5)[k] * steps[k])) / (2 * steps[k])
                      for k in range(5)], axis=1)
        dp, *_ = np.linalg.lstsq(J, r, rcond=None)
        p = p + dp
        if np.all(np.abs(dp) < np.array([1e-12, 1e-12, 1e-12, 1e-9, 1e-9])):
            break
    rms = float(np.sqrt(np.mean((obs - predict(p)) ** 2)))
    return AlignmentResult(
        float(p[0]), float(p[1]), float(p[2]), float(p[3]), float(p[4]),
        seed_roll, seed_yaw, seed_pitch, rms, tuple(tuple(map(float, s)) for s in spots),
        slew=float(slew), translation=float(translation),
    )


def run_alignment(
    bench,
    *,
    nd_filters: str,
    slew: float,
    translation: float,
    w_px: float,
    exposure_s: float,
    n_frames: int,
    check_safe: Callable[[str], None],
    seed_noise: Callable[[int], None] | None = None,
    log: Callable[[str], None] | None = None,
) -> AlignmentResult:
    """Run the §3.4 procedure on a bench (module docstring); ``check_safe(stack)`` is the damage interlock.

    ``slew``: arm slew (rad); ``translation``: axial camera travel (m);
    ``w_px``: the footprint radius in pixels (centroid window).  Leaves the
    arm at 0, the camera translation at 0 and the beam blocked.
    """
    cam = bench.camera
    n_v, n_h = cam.shape
    origin = (-(n_h // 2 - 1) if n_h % 2 == 0 else -(n_h // 2), -(n_v // 2 - 1) if n_v % 2 == 0 else -(n_v // 2))
    say = log or (lambda s: None)
    bench.shutter.close()
    bench.sample_mount.set_in_beam(False)
    bench.arm.move_to(0.0)
    bench.camera_axial.move_to(0.0)
    check_safe(nd_filters)
    bench.filters.set_filters(nd_filters)
    cam.set_exposure(exposure_s)
    cam.set_frame_averaging(n_frames)
    counter = iter(range(10**6))
    if seed_noise:
        seed_noise(next(counter))
    background = np.asarray(cam.read_frame().counts, dtype=np.float64)
    spots = []
    try:
        bench.shutter.open()
        for tc, ax in ((0.0, 0.0), (-slew, 0.0), (slew, 0.0), (0.0, translation)):
            bench.arm.move_to(tc)
            bench.camera_axial.move_to(ax)
            if seed_noise:
                seed_noise(next(counter))
            frame = cam.read_frame()
            if float(np.max(frame.counts)) >= frame.full_scale:
                raise ValueError(
                    f"alignment: the spot saturates at theta_c = {math.degrees(tc):.3f} deg through ND '{nd_filters}'"
                )
            h, v, _ = spot_centroid(np.asarray(frame.counts, np.float64) - background, origin, w_px)
            spots.append((tc, ax, h, v))
            say(f"alignment: theta_c = {math.degrees(tc):+.3f} deg, axial = {ax * 1e3:.2f} mm: spot at "
                f"(n_h, n_v) = ({h:.3f}, {v:.3f})")
    finally:
        bench.shutter.close()
        bench.arm.move_to(0.0)
        bench.camera_axial.move_to(0.0)
    d_h, d_v = bench.pixel_pitch
    res = solve_alignment(spots, pixel_pitch=(d_h, d_v), distance=bench.distance, slew=slew, translation=translation)
    return dataclasses.replace(res, nd_filters=nd_filters)
