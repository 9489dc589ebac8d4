"""Numerics of frame evaluation: seed Figure 33 numbers, float32 vs float64, gradients, oracle, bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import brdfjax as bj
from brdfjax import reference as ref

DET = bj.Detector.seed()


def _offset_peak_pixel(theta_i_deg: float, phi_ref_deg: float = 0.0) -> tuple[int, int]:
    """Pixel where the second surface normal mirrors the beam (from the inverse map)."""
    p = bj.SOLAR_CELL_SEED
    ti, pr = np.deg2rad(theta_i_deg), np.deg2rad(phi_ref_deg)
    az = p["dphi0"] + pr
    n2 = np.array([np.sin(p["dtheta"]) * np.cos(az), np.sin(p["dtheta"]) * np.sin(az), np.cos(p["dtheta"])])
    w_i = np.array([-np.sin(ti), 0.0, np.cos(ti)])
    w = 2 * w_i.dot(n2) * n2 - w_i
    th, ph = bj.zenith_azimuth(jnp.asarray(w))
    h, v = DET.at(ti).pixel_of(th, ph)
    return int(round(float(h))), int(round(float(v)))


@pytest.mark.parametrize(
    "theta_i, centre_max, offset_max", [(20.0, 1.11e4, 4.44e4), (60.0, 3.91e4, 4.19e5)]
)
def test_figure_33_peak_values(theta_i, centre_max, offset_max):
    """Seed Fig 33: the maxima near the centre and offset peaks (full-resolution pixels, local windows)."""
    model = bj.solar_cell()
    frame = bj.Conditions.from_degrees(theta_i)
    centre = np.asarray(bj.render(model, frame, DET, roi=(-20, 20, -20, 20)))
    # The seed prints 3.91e4 at 60 deg; these formulas give 3.9188e4 (the printed value is 0.22% low).
    assert centre.max() == pytest.approx(centre_max, rel=3e-3)
    assert centre.argmax() == centre.size // 2  # exactly at the alignment pixel (0, 0)
    h, v = _offset_peak_pixel(theta_i)
    off = np.asarray(bj.render(model, frame, DET, roi=(h - 20, h + 20, v - 20, v + 20)))
    assert off.max() == pytest.approx(offset_max, rel=1e-3)
    # The offset peak is down (+y, +n_v) and to the right (+x, +n_h) of the centre peak.
    assert h > 300 and v > 300


@pytest.mark.parametrize("theta_i", [20.0, 60.0])
@pytest.mark.parametrize("grating_factor, expected", [(True, 26), (False, None)])
def test_figure_33_diffraction_maxima_along_centre_column(theta_i, grating_factor, expected):
    """26 maxima between the centre and the top edge (14 / 26 without the 2 cos(theta_i) factor)."""
    if expected is None:
        expected = {20.0: 14, 60.0: 26}[theta_i]
    bars = bj.Diffraction(rho=300.0, a=8e-4, b=1e-5, c=4e-5, grating_factor=grating_factor)
    col = np.asarray(bj.render(bars, bj.Conditions.from_degrees(theta_i), DET, roi=(0, 0, -1235, 0)))[:, 0]
    assert col[-1] == pytest.approx(300.0, rel=1e-6)  # value at the centre pixel
    inner = col[1:-1]
    n_max = int(np.sum((inner > col[:-2]) & (inner > col[2:])))
    assert n_max == expected


@pytest.mark.parametrize("theta_i, phi_ref", [(20.0, 0.0), (60.0, 0.0), (40.0, 45.0), (40.0, 90.0)])
def test_float32_matches_float64_where_it_matters(theta_i, phi_ref):
    model = bj.solar_cell()
    frame = bj.Conditions.from_degrees(theta_i, phi_ref)
    with jax.numpy_dtype_promotion("strict"):  # no silent float64 inside the float32 program
        f32 = bj.render(model, frame, DET, step=4, precision="float32")
    assert f32.dtype == jnp.float32
    f32 = np.asarray(f32, dtype=np.float64)
    f64 = np.asarray(bj.render(model, frame, DET, step=4, precision="float64"))
    assert f32.dtype == np.float64 and f64.max() > 1e4
    keep = f64 > 1e-3 * f64.max()
    rel = np.abs(f32[keep] - f64[keep]) / f64[keep]
    assert rel.max() < 1e-3, rel.max()


@pytest.mark.parametrize("theta_i", [20.0, 60.0])
def test_jax_frame_matches_numpy_oracle(theta_i):
    """Independent NumPy float64 implementation (brdfjax.reference) on a decimated frame."""
    step = 16
    got = np.asarray(bj.render(bj.solar_cell(), bj.Conditions.from_degrees(theta_i), DET, step=step, precision="float64"))
    want = ref.solar_cell_frame(np.deg2rad(theta_i), step=step)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * want.max())


def test_chunking_does_not_change_the_frame():
    model, frame = bj.solar_cell(), bj.Conditions.from_degrees(20)
    a = np.asarray(bj.render(model, frame, DET, step=8, precision="float64", chunk_pixels=10_000))
    b = np.asarray(bj.render(model, frame, DET, step=8, precision="float64", chunk_pixels=1 << 22))
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=0)  # only compiled-code rounding differs


# --- gradients -----------------------------------------------------------------------


def _loss_fn(pixels):
    nh = jnp.asarray([p[0] for p in pixels], dtype=jnp.float64)
    nv = jnp.asarray([p[1] for p in pixels], dtype=jnp.float64)

    def loss(model, frame, det):
        f = bj.evaluate_pixels(model, frame, det, nh, nv)
        return jnp.sum(jnp.log(f + 1.0))

    return loss


def _f64(x):
    # A strongly typed float64 scalar (a weakly typed one would retrace the jitted loss).
    return jnp.asarray(np.float64(x))


def _leaves_with_names(tree, prefix):
    out = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        if eqx.is_array(leaf):
            out.append((prefix + jax.tree_util.keystr(path), path))
    return out


def _set(tree, path, value):
    return eqx.tree_at(lambda t: _get(t, path), tree, value)


def _get(tree, path):
    for k in path:
        if isinstance(k, jax.tree_util.GetAttrKey):
            tree = getattr(tree, k.name)
        elif isinstance(k, jax.tree_util.DictKey):
            tree = tree[k.key]
        else:
            tree = tree[k.idx]
    return tree


CASES = {
    # the specular pixel, a pixel on the offset peak's flank and a diffraction pixel
    "theta_i=20": (bj.Conditions.from_degrees(20.0, 0.0), DET, [(0, 0), (2, -1), (731, 690), (0, -40)]),
    # normal incidence with the arm at 0: atan2 and sqrt at the origin
    "theta_c=0": (bj.Conditions(0.0, 0.0), DET.at(0.0), [(0, 0), (1, 0), (0, 3)]),
    "phi_ref=0 misaligned": (bj.Conditions.from_degrees(35.0, 0.0), bj.Detector.seed_misaligned_example(), [(-3, -5), (0, 0)]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_gradients_are_finite_and_match_finite_differences(case):
    frame, det, pixels = CASES[case]
    model = bj.solar_cell(m1=3e-4, m2=3e-4, c=8e-5)
    det = det if det.theta_c is not None else det.at(jnp.asarray(frame.theta_i))
    loss = _loss_fn(pixels)
    args = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if eqx.is_array(x) else x, (model, frame, det))
    grads = eqx.filter_jit(eqx.filter_grad(lambda a: loss(*a)))(args)
    f = eqx.filter_jit(lambda a: loss(*a))
    names = _leaves_with_names(args, "")
    assert len(names) >= 25
    for name, path in names:
        g = float(_get(grads, path))
        assert np.isfinite(g), name
        x0 = float(_get(args, path))
        at = lambda x, path=path: float(f(_set(args, path, _f64(x))))  # noqa: E731
        # Step that changes the loss by ~1e-7 of itself (roundoff ~1e-9 relative), capped well
        # below each parameter's scale of variation; fourth-order stencil so truncation is negligible.
        f0 = abs(at(x0))
        h = min(1e-7 * f0 / abs(g), 1e-3 * max(abs(x0), 1e-2)) if g != 0 else 1e-7 * max(abs(x0), 1e-2)
        if x0 == 0.0 and ("theta_i" in name or "theta_c" in name):
            # one-sided (second order) at the domain edge theta = 0
            fd = (-3 * at(x0) + 4 * at(x0 + h) - at(x0 + 2 * h)) / (2 * h)
        else:
            fd = (-at(x0 + 2 * h) + 8 * at(x0 + h) - 8 * at(x0 - h) + at(x0 - 2 * h)) / (12 * h)
        assert g == pytest.approx(fd, rel=1e-4, abs=1e-6 * max(1.0, abs(fd))), name


# --- bad input -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"theta_i": -0.1}, "theta_i"),
        ({"theta_i": np.pi / 2}, "0 <= theta_i < 90 deg"),
        ({"theta_i": 0.3, "wavelength": 0.0}, "positive wavelength"),
        ({"theta_i": 0.3, "wavelength": -6e-7}, "wavelength"),
        ({"theta_i": float("nan")}, "theta_i"),
    ],
)
def test_bad_frame_raises(kwargs, message):
    with pytest.raises(ValueError, match=message):
        bj.Conditions(**kwargs)


def test_bad_precision_raises():
    with pytest.raises(ValueError, match="precision must be 'float32' or 'float64'"):
        bj.render(bj.Lambertian(0.1), bj.Conditions(0.1), DET, step=64, precision="float16")


def test_float64_without_x64_is_refused():
    """brdfjax never flips jax_enable_x64; asking for float64 without it is an error that says what to do."""
    import subprocess
    import sys

    code = (
        "import brdfjax as bj\n"
        "try:\n"
        "    bj.render(bj.Lambertian(0.1), bj.Conditions(0.1), bj.Detector.seed(), step=64, precision='float64')\n"
        "except ValueError as e:\n"
        "    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "jax.config.update('jax_enable_x64', True)" in out.stdout, out.stdout + out.stderr
