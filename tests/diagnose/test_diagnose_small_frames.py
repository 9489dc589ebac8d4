"""Effect signatures on small frames: the smoothed residual map keeps the frame's shape when the smoothing
kernel is longer than a side (measured: an 8 x 11 frame at step 16 became 9 x 11, and the offset-peak
candidate could not be set up on two-effect evaluation trials: "operands could not be broadcast together")."""

from __future__ import annotations

import numpy as np

from brdfjax.diagnose.effects.base import smooth_z


def test_smooth_z_keeps_the_shape_of_a_frame_smaller_than_its_kernel():
    r = np.random.default_rng(1).standard_normal((8, 11))
    r[2, 3] = np.nan
    z = smooth_z(r, 1.2)  # kernel of 9 samples, longer than the 8 rows
    assert z.shape == (8, 11)
    assert np.isnan(z).sum() < z.size and np.isfinite(z[4, 5])


def test_smooth_z_is_the_centred_convolution_on_larger_frames():
    r = np.random.default_rng(2).standard_normal((20, 25))
    z = smooth_z(r, 1.2)
    x = np.arange(-4, 5)
    k = np.exp(-0.5 * (x / 1.2) ** 2)
    num = np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), 0, r)
    num = np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), 1, num)
    den = np.sqrt(np.sum(k * k) ** 2)
    np.testing.assert_allclose(z[6:-6, 6:-6], (num / den)[6:-6, 6:-6], rtol=1e-12)
