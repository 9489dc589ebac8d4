"""OpenEXR frame files: exact round trip, doubles in the header, atomic writes, damaged files."""

from __future__ import annotations

import os

import numpy as np
import OpenEXR
import pytest

import brdfjax.io.exr as exr
from brdfjax.io import ExrError, read_frame_exr, write_frame_exr

SHAPE = (7, 5)


def attrs(**kw):
    base = {
        "theta_i": np.deg2rad(20.0),
        "theta_c": np.deg2rad(20.0),
        "phi_ref": 0.1,  # not representable in float32: must come back exactly
        "wavelength": 632.8e-9,
        "R": 0.325,
        "pixel_pitch": 5.5e-6,
        "pixel_pitch_v": 5.5e-6,
        "step": 16,
        "roi": (-160, 160, -96, 96),
        "model": "preset solar_cell",
        "brdfjax_version": "0.1.0",
    }
    base.update(kw)
    return base


def channels(seed=0):
    rng = np.random.default_rng(seed)
    return [rng.random(SHAPE) * s for s in (1e4, 1.0, 6.0, 3e-10)]


@pytest.fixture
def frame_file(tmp_path):
    path = tmp_path / "f.exr"
    write_frame_exr(path, *channels(), attrs())
    return path


def test_round_trip_exact(frame_file):
    data = read_frame_exr(frame_file)
    for name, arr in zip(("brdf", "theta_s", "phi_s", "omega"), channels(), strict=True):
        got = getattr(data, name)
        assert got.dtype == np.float32 and got.shape == SHAPE
        np.testing.assert_array_equal(got, arr.astype(np.float32))
    a = data.attrs
    for key, value in attrs().items():
        if key in exr.DOUBLE_ATTRS:
            assert type(a[key]) is float and a[key] == value, key  # exact doubles
    assert a["phi_ref"] == 0.1
    assert a["step"] == 16 and type(a["step"]) is int
    assert a["roi"] == (-160, 160, -96, 96)
    assert a["model"] == "preset solar_cell" and a["brdfjax_version"] == "0.1.0"
    assert "brdf: sr^-1" in a["channel_units"]


def test_header_stores_doubles_and_zip(frame_file):
    h = OpenEXR.File(str(frame_file), header_only=True).header()
    assert h["compression"] == OpenEXR.ZIP_COMPRESSION
    for key in ("theta_i", "theta_c", "phi_ref", "wavelength", "R", "pixel_pitch"):
        assert isinstance(h[key], np.ndarray) and h[key].dtype == np.float64 and h[key].shape == (1,), key
    assert sorted(c.name for c in h["channels"]) == sorted(exr.CHANNELS)


def test_write_rejects_bad_input(tmp_path):
    a = np.zeros(SHAPE)
    with pytest.raises(ExrError, match=r"f\.exr: missing attribute\(s\) \['R'\]"):
        write_frame_exr(tmp_path / "f.exr", a, a, a, a, {k: v for k, v in attrs().items() if k != "R"})
    with pytest.raises(ExrError, match=r"channel 'omega' has shape \(3, 3\)"):
        write_frame_exr(tmp_path / "f.exr", a, a, a, np.zeros((3, 3)), attrs())
    with pytest.raises(ExrError, match="2-D"):
        write_frame_exr(tmp_path / "f.exr", np.zeros(5), a, a, a, attrs())
    with pytest.raises(ExrError, match="'theta_i' must be one finite number"):
        write_frame_exr(tmp_path / "f.exr", a, a, a, a, attrs(theta_i=float("nan")))
    assert os.listdir(tmp_path) == []


def test_atomic_write_leaves_no_temp_files(tmp_path):
    path = tmp_path / "f.exr"
    write_frame_exr(path, *channels(0), attrs())
    write_frame_exr(path, *channels(1), attrs(step=4))  # overwrite in place
    assert os.listdir(tmp_path) == ["f.exr"]
    assert read_frame_exr(path).attrs["step"] == 4


def test_failed_write_keeps_old_file_and_cleans_up(tmp_path, monkeypatch):
    path = tmp_path / "f.exr"
    write_frame_exr(path, *channels(0), attrs())
    before = path.read_bytes()

    class Boom:
        ZIP_COMPRESSION = OpenEXR.ZIP_COMPRESSION
        scanlineimage = OpenEXR.scanlineimage

        class File:
            def __init__(self, header, chans):
                pass

            def write(self, p):
                with open(p, "wb") as fh:  # a partial file, then a crash
                    fh.write(b"v/1\x01partial")
                raise RuntimeError("disk on fire")

    monkeypatch.setattr(exr, "_openexr", lambda: Boom)
    with pytest.raises(ExrError, match=r"f\.exr: could not write the OpenEXR file: disk on fire"):
        write_frame_exr(path, *channels(1), attrs())
    assert os.listdir(tmp_path) == ["f.exr"]
    assert path.read_bytes() == before


@pytest.mark.parametrize("keep", [0.5, 0.9, 0.999])
def test_truncated_file_is_an_error_naming_it(frame_file, tmp_path, keep):
    data = frame_file.read_bytes()
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ExrError, match=r"cut\.exr: .*(damaged or truncated|not a readable OpenEXR)"):
        read_frame_exr(cut)


def test_corrupt_pixels_are_an_error(frame_file, tmp_path):
    data = bytearray(frame_file.read_bytes())
    n = len(data)
    data[n - 200 : n - 100] = bytes(100)  # zero part of the last compressed chunk
    bad = tmp_path / "bad.exr"
    bad.write_bytes(bytes(data))
    with pytest.raises(ExrError, match=r"bad\.exr: .*(damaged or truncated|does not match its checksum)"):
        read_frame_exr(bad)


def test_checksum_catches_silent_damage(frame_file, tmp_path):
    # Random floats do not compress, so OpenEXR stores these chunks raw: flipping
    # pixel bytes decodes without complaint, and only the checksum notices.
    data = bytearray(frame_file.read_bytes())
    data[-40] ^= 0xFF
    bad = tmp_path / "flip.exr"
    bad.write_bytes(bytes(data))
    with pytest.raises(ExrError, match=r"flip\.exr: the pixel data does not match its checksum"):
        read_frame_exr(bad)


def test_not_an_exr_file(tmp_path):
    p = tmp_path / "junk.exr"
    p.write_bytes(b"this is not an image")
    with pytest.raises(ExrError, match=r"junk\.exr: not a readable OpenEXR file"):
        read_frame_exr(p)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"gone\.exr"):
        read_frame_exr(tmp_path / "gone.exr")


def test_missing_channel_and_attribute_named(tmp_path):
    p = tmp_path / "other.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "theta_i": np.array([0.3])}
    OpenEXR.File(header, {"brdf": np.zeros(SHAPE, np.float32)}).write(str(p))
    with pytest.raises(ExrError, match=r"other\.exr: missing channel\(s\) \['theta_s', 'phi_s', 'omega'\]"):
        read_frame_exr(p)
    chans = dict(zip(exr.CHANNELS, (np.zeros(SHAPE, np.float32),) * 4, strict=True))
    OpenEXR.File(header, chans).write(str(p))
    with pytest.raises(ExrError, match=r"other\.exr: missing attribute\(s\) \['theta_c', 'phi_ref'"):
        read_frame_exr(p)


def test_extra_channels_round_trip_and_checksum(tmp_path):
    from brdfjax.io.exr import ExrError, read_frame_exr, write_frame_exr

    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    attrs = {"theta_i": 0.3, "theta_c": 0.3, "phi_ref": 0.0, "wavelength": 6.328e-7, "R": 0.325,
             "pixel_pitch": 5.5e-6, "step": 1, "roi": (0, 3, 0, 2), "model": "test", "brdfjax_version": "0"}
    p = write_frame_exr(tmp_path / "f.exr", a, a, a, a, attrs, extra_channels={"sigma_rel": a / 10, "mask": a > 3})
    fd = read_frame_exr(p)
    assert set(fd.extra) == {"sigma_rel", "mask"}
    np.testing.assert_array_equal(fd.extra["sigma_rel"], a / 10)
    np.testing.assert_array_equal(fd.extra["mask"], (a > 3).astype(np.float32))
    with pytest.raises(ExrError, match="clash with the frame channels"):
        write_frame_exr(tmp_path / "g.exr", a, a, a, a, attrs, extra_channels={"brdf": a})
    with pytest.raises(ExrError, match="channel 'mask' has shape"):
        write_frame_exr(tmp_path / "h.exr", a, a, a, a, attrs, extra_channels={"mask": a[:2]})


def test_threaded_writes_are_the_same_bytes(tmp_path):
    """brdfjax turns on OpenEXR's thread pool (none by default); the file is byte for byte the one-thread file."""
    assert OpenEXR.global_thread_count() >= 1
    chans = [np.tile(c, (40, 60)) for c in channels(3)]  # 280 x 300: several line blocks per channel
    kept = OpenEXR.global_thread_count()
    try:
        paths = []
        for n in (0, kept):
            OpenEXR.set_global_thread_count(n)
            paths.append(write_frame_exr(tmp_path / f"t{n}.exr", *chans, attrs()))
    finally:
        OpenEXR.set_global_thread_count(kept)
    assert paths[0].read_bytes() == paths[1].read_bytes()
