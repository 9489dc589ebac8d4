"""Raw exposure-stack format (brdfjax.io.raw): round trip, every validation error, manifests."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from brdfjax.io.raw import (
    FILE_ATTRS,
    Calibration,
    Exposure,
    ManifestError,
    RawAttrs,
    RawFormatError,
    read_manifest,
    read_raw_exr,
    read_raw_header,
    write_manifest,
    write_raw_exr,
)

EXAMPLE = Path(__file__).resolve().parents[1] / "data" / "example_set"
SHAPE = (12, 16)


def _attrs(**kw) -> RawAttrs:
    base = dict(
        kind="sample",
        optical_density=3.0,
        nd_filters="3.0",
        theta_i=0.1,  # 0.1 is not a float32: checks that angles are stored as doubles
        theta_c=0.1,
        phi_ref=0.3,
        wavelength=632.8e-9,
        R=0.325,
        pixel_pitch=5.5e-6,
        black_level=29.2736,
        full_scale=16383.0,
        roll=1e-3,
        yaw=-2e-3,
        pitch=3e-4,
        m_h=3.0,
        m_v=-5.0,
        sample="test sample",
    )
    base.update(kw)
    return RawAttrs(**base)


def _exposures(times=(1e-3, 1e-2, 1e-1, 1.0), with_std=True, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for t in times:
        counts = rng.normal(100 * t + 30, 3, SHAPE).astype(np.float32)
        std = np.full(SHAPE, 2.5, np.float32) if with_std else None
        out.append(Exposure(t, 32, counts, std))
    return out


def _write_parts(path: Path, parts: list[tuple[dict, dict]]) -> Path:
    """Write a multi-part file directly with OpenEXR (for files the brdfjax writer refuses to make)."""
    exr = []
    for i, (header, channels) in enumerate(parts):
        h = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **header}
        exr.append(OpenEXR.Part(h, channels, f"exposure_{i}"))
    OpenEXR.File(exr).write(str(path))
    return path


def _file_header(attrs: RawAttrs, drop=()) -> dict:
    h = {}
    for k, (typ, _) in FILE_ATTRS.items():
        if k in drop:
            continue
        v = getattr(attrs, k)
        h[k] = np.array([v], np.float64) if typ is float else v
    return h


def _part_header(t, n=32):
    return {"exposure_s": np.array([t], np.float64), "n_frames": n}


# --- round trip --------------------------------------------------------------------------------


def test_round_trip_exact(tmp_path):
    attrs = _attrs(pixel_pitch_v=5.6e-6, software="pytest", extra={"operator": "me", "temperature_c": 21.5})
    exps = _exposures()
    exps[1] = dataclasses.replace(exps[1], counts_std=None)  # counts_std is optional per part
    path = write_raw_exr(tmp_path / "m.exr", attrs, exps)
    st = read_raw_exr(path)
    assert st.path == path
    assert st.shape == SHAPE
    assert st.attrs == attrs  # every double exactly (0.1 stays 0.1), strings, extras
    assert st.attrs.theta_i == 0.1
    for a, b in zip(exps, st.exposures):
        assert (a.exposure_s, a.n_frames) == (b.exposure_s, b.n_frames)
        np.testing.assert_array_equal(a.counts, b.counts)
        if a.counts_std is None:
            assert b.counts_std is None
        else:
            np.testing.assert_array_equal(a.counts_std, b.counts_std)
    h_attrs, shape, meta = read_raw_header(path)
    assert h_attrs == attrs and shape == SHAPE and meta == [(e.exposure_s, 32) for e in exps]
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was renamed into place


def test_attrs_build_detector_and_frame():
    attrs = _attrs()
    det = attrs.detector((48, 64))
    assert det.shape == (48, 64)
    assert float(det.theta_c) == 0.1 and float(det.m_h) == 3.0 and float(det.pixel_pitch_v) == 5.5e-6
    frame = attrs.frame()
    assert float(frame.theta_i) == 0.1 and float(frame.phi_ref) == 0.3
    assert attrs.filters == (3.0,)


def test_example_set_is_valid():
    m = read_manifest(EXAMPLE / "manifest.toml")
    assert m.samples[0].name == "solar_cell_20deg"
    assert m.calibration.nd_tolerances == {3.0: 0.15}
    kinds = {}
    for p in m.files():
        st = read_raw_exr(p)
        kinds[p.name] = st.attrs.kind
        assert st.shape == (48, 64)
        assert st.exposure_times.tolist() == [1e-3, 1e-2, 1e-1, 1.0]
        assert all(e.counts.max() <= st.attrs.full_scale for e in st.exposures)
    assert kinds == {
        "beam.exr": "beam",
        "beam_background.exr": "background",
        "solar_cell_20deg.exr": "sample",
        "solar_cell_20deg_background.exr": "background",
    }
    total = sum(p.stat().st_size for p in EXAMPLE.iterdir())
    assert total < 1_000_000  # small enough for git


# --- validation on read: each error names the file and the problem -----------------------------


def _good_parts(attrs=None, times=(1e-3, 1e-2)):
    attrs = attrs or _attrs()
    return [(_file_header(attrs) | _part_header(t), {"counts": np.ones(SHAPE, np.float32)}) for t in times]


def _expect(path, *fragments):
    with pytest.raises(RawFormatError) as e:
        read_raw_exr(path)
    msg = str(e.value)
    assert str(path) in msg
    for f in fragments:
        assert f in msg, msg
    return msg


def test_missing_file_attribute(tmp_path):
    parts = _good_parts()
    for h, _ in parts:
        del h["R"], h["kind"]
    _expect(_write_parts(tmp_path / "a.exr", parts), "missing attribute(s)", "'kind'", "'R'")


def test_missing_part_attribute(tmp_path):
    parts = _good_parts()
    del parts[1][0]["n_frames"]
    _expect(_write_parts(tmp_path / "a.exr", parts), "part 1", "missing attribute(s) ['n_frames']")


def test_part_without_counts(tmp_path):
    parts = _good_parts()
    parts[1] = (parts[1][0], {"signal": np.ones(SHAPE, np.float32)})
    _expect(_write_parts(tmp_path / "a.exr", parts), "part 1", "has no 'counts' channel", "signal")


def test_shapes_differ(tmp_path):
    parts = _good_parts()
    # Parts of a multi-part file share the display window; their data windows may differ.
    window = (np.array([0, 0], np.int32), np.array([SHAPE[1] - 1, SHAPE[0] - 1], np.int32))
    for h, _ in parts:
        h["displayWindow"] = window
    parts[1] = (parts[1][0], {"counts": np.ones((SHAPE[0] + 1, SHAPE[1]), np.float32)})
    _expect(_write_parts(tmp_path / "a.exr", parts), "part 1", "has shape (13, 16)", "part 0 has (12, 16)")


@pytest.mark.parametrize("times", [(1e-2, 1e-3), (1e-2, 1e-2)])
def test_exposures_not_increasing(tmp_path, times):
    _expect(_write_parts(tmp_path / "a.exr", _good_parts(times=times)), "not strictly increasing")


def test_nan_pixels(tmp_path):
    parts = _good_parts()
    c = np.ones(SHAPE, np.float32)
    c[3, 4] = np.nan
    c[5, 6] = np.inf
    parts[1] = (parts[1][0], {"counts": c})
    _expect(_write_parts(tmp_path / "a.exr", parts), "exposure_1", "2 NaN or infinite pixel(s)")


def test_bad_attribute_values(tmp_path):
    parts = _good_parts(_attrs(kind="flat"))
    _expect(_write_parts(tmp_path / "a.exr", parts), "'kind' is 'flat'", "sample, beam, background, dark")
    parts = _good_parts(_attrs(nd_filters="4.0+1.0"))
    _expect(_write_parts(tmp_path / "b.exr", parts), "'optical_density' = 3.0", "adds up to 5")
    parts = _good_parts()
    parts[0][0]["theta_i"] = 0.1  # a Python float is stored as a 32-bit float: accepted as a number
    parts[0][0]["wavelength"] = "632.8 nm"
    _expect(_write_parts(tmp_path / "c.exr", parts), "'wavelength' must be a finite number")


def test_file_attribute_differs_between_parts(tmp_path):
    parts = _good_parts()
    parts[1][0]["sample"] = "another sample"
    _expect(_write_parts(tmp_path / "a.exr", parts), "part 1", "'sample'", "differs from part 0")


def _valid_file(tmp_path, name="good.exr", big=False):
    exps = _exposures()
    if big:  # noisy pixels: ZIP cannot shrink them, so truncation hits pixel data, not the header
        rng = np.random.default_rng(1)
        exps = [dataclasses.replace(e, counts=rng.normal(0, 1, (64, 64)).astype(np.float32), counts_std=None)
                for e in exps]
    return write_raw_exr(tmp_path / name, _attrs(), exps)


@pytest.mark.parametrize("keep", [0.5, 0.9])
def test_truncated_file(tmp_path, keep, capfd):
    data = _valid_file(tmp_path, big=True).read_bytes()
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: int(len(data) * keep)])
    _expect(cut, "damaged or truncated")
    capfd.readouterr()  # OpenEXR prints its own warnings to stderr


def test_corrupt_pixels(tmp_path, capfd):
    path = _valid_file(tmp_path, big=True)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = bytes(b ^ 0x5A for b in data[mid : mid + 64])
    bad = tmp_path / "bad.exr"
    bad.write_bytes(bytes(data))
    msg = _expect(bad)
    assert "damaged" in msg
    capfd.readouterr()


def test_not_openexr_and_missing(tmp_path):
    p = tmp_path / "junk.exr"
    p.write_bytes(b"this is not an image" * 10)
    _expect(p, "not a readable OpenEXR file")
    with pytest.raises(FileNotFoundError, match="no such raw measurement file"):
        read_raw_exr(tmp_path / "nope.exr")


# --- validation on write: nothing is written ---------------------------------------------------


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda e: [e[1], e[0], *e[2:]], "not strictly increasing"),
        (lambda e: [dataclasses.replace(e[0], counts=np.full(SHAPE, np.nan, np.float32)), *e[1:]], "NaN"),
        (lambda e: [dataclasses.replace(e[0], counts=np.ones((3, 3), np.float32)), *e[1:]], "all parts must match"),
        (lambda e: [dataclasses.replace(e[0], n_frames=0), *e[1:]], "'n_frames' must be a positive integer"),
        (lambda e: [dataclasses.replace(e[0], exposure_s=-1.0), *e[1:]], "'exposure_s' must be a positive"),
        (lambda e: [], "no exposures"),
    ],
)
def test_writer_refuses(tmp_path, change, fragment):
    path = tmp_path / "w.exr"
    with pytest.raises(RawFormatError, match="cannot write raw measurement") as e:
        write_raw_exr(path, _attrs(), change(_exposures()))
    assert fragment in str(e.value) and str(path) in str(e.value)
    assert not path.exists() and not list(tmp_path.iterdir())


def test_writer_refuses_bad_attrs(tmp_path):
    with pytest.raises(RawFormatError, match="'theta_i' must be in"):
        write_raw_exr(tmp_path / "w.exr", _attrs(theta_i=2.0), _exposures())
    with pytest.raises(RawFormatError, match="is not an optical density"):
        write_raw_exr(tmp_path / "w.exr", _attrs(nd_filters="four"), _exposures())
    with pytest.raises(RawFormatError, match="clashes with a reserved"):
        write_raw_exr(tmp_path / "w.exr", _attrs(extra={"exposure_s": 1.0}), _exposures())
    assert not list(tmp_path.iterdir())


def test_rewrite_replaces_atomically(tmp_path, monkeypatch):
    path = _valid_file(tmp_path)
    before = path.read_bytes()

    def boom(self, filename):
        Path(filename).write_bytes(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(OpenEXR.File, "write", boom)
    with pytest.raises(KeyboardInterrupt):
        write_raw_exr(path, _attrs(sample="new"), _exposures(seed=5))
    assert path.read_bytes() == before  # the old file, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.exr"]  # no temporary left behind


# --- manifest ------------------------------------------------------------------------------------


def _manifest(tmp_path, text: str, files=("b.exr", "bb.exr", "s.exr", "sb.exr")) -> Path:
    for f in files:
        (tmp_path / f).write_bytes(b"")
    p = tmp_path / "manifest.toml"
    p.write_text(text)
    return p


GOOD = """
[beam]
file = "b.exr"
background = "bb.exr"

[[sample]]
name = "s1"
file = "s.exr"
background = "sb.exr"
"""


def test_manifest_paths_and_unknown_keys(tmp_path):
    p = _manifest(tmp_path, 'setup = "2026-11-21"\n' + GOOD + '\n[operator]\nname = "x"\n')
    m = read_manifest(tmp_path)  # the folder works too
    assert m.path == p.resolve()
    assert m.beam.file == (tmp_path / "b.exr").resolve()
    assert m.samples[0].background == (tmp_path / "sb.exr").resolve()
    assert m.extra == {"setup": "2026-11-21", "operator": {"name": "x"}}
    assert m.calibration == Calibration()


def test_manifest_write_read(tmp_path):
    for f in ("b.exr", "bb.exr", "s.exr", "sb.exr"):
        (tmp_path / f).write_bytes(b"")
    p = write_manifest(
        tmp_path / "manifest.toml", ("b.exr", "bb.exr"), [("s1", "s.exr", "sb.exr")],
        Calibration(scatter_nonlinearity=0.02, nd_tolerances={3.0: 0.15, 0.5: 0.02}),
    )
    m = read_manifest(p)
    assert [s.name for s in m.samples] == ["s1"]
    assert m.calibration == Calibration(0.02, {0.5: 0.02, 3.0: 0.15})
    curve = ((0.0, -0.0172), (0.5, 0.0), (1.0, 0.0172))
    p = write_manifest(
        tmp_path / "manifest.toml", ("b.exr", "bb.exr"), [("s1", "s.exr", "sb.exr")],
        Calibration(nd_tolerances={3.0: 0.15}, nonlinearity_curve=curve),
    )
    assert tomllib.loads(p.read_text())["calibration"]["nonlinearity_curve"] == [[0.0, -0.0172], [0.5, 0.0], [1.0, 0.0172]]
    assert read_manifest(p).calibration == Calibration(None, {3.0: 0.15}, curve)


@pytest.mark.parametrize(
    "text, fragment",
    [
        (GOOD.replace("[beam]", "[beams]"), "missing [beam] table"),
        (GOOD.replace('background = "bb.exr"', ""), "beam: missing key 'background'"),
        (GOOD.replace('file = "s.exr"', 'file = "missing.exr"'), "sample[0].file: no such file 'missing.exr'"),
        (GOOD.replace('name = "s1"', 'name = "a/b"'), "sample[0].name: must be a file-name-safe"),
        (GOOD + '[[sample]]\nname = "s1"\nfile = "s.exr"\nbackground = "sb.exr"\n', "duplicate sample name 's1'"),
        (GOOD.split("[[sample]]")[0], "missing [[sample]] tables"),
        (GOOD + "[calibration]\nscatter_nonlinearity = 2\n", "calibration.scatter_nonlinearity"),
        (GOOD + '[calibration.nd_tolerances]\n"three" = 0.1\n', "key 'three' is not a nominal OD"),
        (GOOD + "[calibration]\nnonlinearity_curve = 0.02\n", "calibration.nonlinearity_curve: must be a non-empty"),
        (GOOD + "[calibration]\nnonlinearity_curve = [[0.5, 0.01], [0.2, 0.0]]\n", "fractions must strictly increase"),
        (GOOD + "[calibration]\nnonlinearity_curve = [[1.5, 0.01]]\n", "outside [0, 1]"),
        (GOOD + "[calibration]\nnonlinearity_curve = [[0.5]]\n", "nonlinearity_curve[0]: must be a pair"),
        ("[beam\n", "not valid TOML"),
    ],
)
def test_manifest_errors(tmp_path, text, fragment):
    p = _manifest(tmp_path, text)
    with pytest.raises(ManifestError) as e:
        read_manifest(p)
    assert fragment in str(e.value) and str(p.resolve()) in str(e.value)
