"""Device layer: interfaces, the simulated bench, capture plans, interlock, alignment, resume, live view, lab adapters.

Everything runs on small simulated cameras (the seed camera binned 8 x 8 and cut to a few thousand
pixels, every instrument effect on); the pylablib adapters run against pylablib's own classes with
their transport replaced (an emulated APT controller and SCPI power meter behind custom pylablib comm
backends, the TSI SDK library replaced for the camera).
"""

from __future__ import annotations

import math
import os
import signal
import struct
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
from helpers import write_config

import brdfjax as bj
from brdfjax.devices import Bench, SimulatedBench, check_bench, interfaces as itf
from brdfjax.devices.alignment import run_alignment, solve_alignment, spot_pixel
from brdfjax.devices.capture import CaptureError, load_capture_config, run_capture
from brdfjax.devices.liveview import LiveView
from brdfjax.devices.plans import Interlock, InterlockError, select_stack
from brdfjax.instrument.synthetic import InstrumentConfig
from brdfjax.io.raw import read_manifest, read_raw_exr

ROOT = Path(__file__).resolve().parents[2]

SMALL = """
seed = 7
[instrument]
kind = "simulated"
bin = 8
shape = [48, 64]
roll_deg = 0.0
camera_seed = 3
{instrument_extra}
[model]
preset = "solar_cell"
[exposure]
exposures_ms = [1, 10, 100, 1000]
n_frames = 32
[beam]
nd = "{beam_nd}"
[[measurements]]
name = "ti20"
theta_i_deg = 20.0
[[measurements]]
name = "ti40"
theta_i_deg = 40.0
[[measurements]]
name = "ti60"
theta_i_deg = 60.0
[capture]
live = "off"
retries = 2
[calibration.nd_tolerances]
"3.0" = 0.15
"""


def _config(tmp_path: Path, name: str = "cap.toml", *, beam_nd: str = "auto", instrument_extra: str = "") -> Path:
    return write_config(tmp_path, SMALL, name, beam_nd=beam_nd, instrument_extra=instrument_extra)


def _sim(shape=(48, 64), **det_kw) -> SimulatedBench:
    det = bj.Detector.seed(shape=shape, pixel_pitch=44e-6, pixel_pitch_v=44e-6, **det_kw)
    return SimulatedBench(bj.solar_cell(), det, InstrumentConfig(camera_seed=3).coarse(8), seed=5)


# --- interfaces -----------------------------------------------------------------------------------


def test_simulated_bench_satisfies_every_interface():
    bench = _sim().bench()
    assert check_bench(bench) == []
    for slot, proto in itf.SLOTS.items():
        assert isinstance(getattr(bench, slot), proto), slot
    frame = bench.camera.read_frame()
    assert frame.counts.shape == (48, 64) and frame.counts.dtype == np.float32
    assert frame.full_scale == 16383.0 and frame.black_level == pytest.approx(29.2736)
    # a device that lacks a method is named with what it misses
    broken = Bench(**{**bench.__dict__, "arm": object()})
    problems = check_bench(broken)
    assert len(problems) == 1 and problems[0].startswith("arm: object is not a RotationStage (missing: get_position, move_to)")


def test_od_rule_matches_synthesize_rule():
    from brdfjax.instrument.nd import ND_STACKS, choose_nd_filters

    sim = _sim()
    ins = sim.instrument
    brdf = ins.render_brdf(bj.solar_cell(), bj.Conditions.from_degrees(20))
    frame = bj.Conditions.from_degrees(20)
    expected = choose_nd_filters(lambda s: ins.sample_flux(brdf, frame, s), ins)
    peak = float(np.max(ins.sample_flux(brdf, frame, "")))
    cfg = ins.config
    got = select_stack(peak, t_min=cfg.exposures_s[0], black_level=cfg.black_level.counts,
                       full_scale=cfg.full_scale, stacks=ND_STACKS)
    assert got == expected == "3.0"


# --- capture -> reduce ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cap")
    cfg = load_capture_config(_config(tmp))
    live = LiveView(tmp / "live", mode="png", min_interval_s=1e9)  # redraw on the last exposure of each measurement
    t0 = time.perf_counter()
    manifest = run_capture(cfg, tmp / "set", live=live)
    return tmp, manifest, live, time.perf_counter() - t0


def test_capture_writes_the_raw_format_that_reduce_reads(captured):
    from brdfjax.cli import main

    tmp, manifest, _, seconds = captured
    m = read_manifest(manifest)
    assert [s.name for s in m.samples] == ["ti20", "ti40", "ti60"]
    beam = read_raw_exr(m.beam.file)
    assert beam.attrs.kind == "beam" and beam.attrs.nd_filters == "4.0+1.0+0.2"  # the seed's beam stack
    assert [e.exposure_s for e in beam.exposures] == [1e-3, 1e-2, 1e-1, 1.0]
    s20 = read_raw_exr(m.samples[0].file)
    assert s20.attrs.kind == "sample" and s20.attrs.theta_c == pytest.approx(math.radians(20))
    assert s20.attrs.nd_filters == "3.0"  # the seed's rule, as brdfjax synthesize picks it
    state = tomllib.loads(manifest.read_text())["capture"]
    assert state["status"] == "complete" and state["done"] == ["beam", "ti20", "ti40", "ti60"]
    assert state["interlock_safe_nd"] == "4.0+1.0+0.2"
    assert not (manifest.parent / ".parts").exists()
    # brdfjax reduce runs on it unchanged
    assert main(["reduce", str(manifest), "--out", str(tmp / "reduced"), "--no-figures"]) == 0
    from brdfjax.instrument.reduce import read_reduced_frame

    red = read_reduced_frame(tmp / "reduced" / "ti20.exr")
    mask = np.asarray(red.extra["mask"]) > 0
    assert mask.sum() > 50
    # the reduced peak agrees with the model convolved with the beam footprint
    sim = _sim()
    truth = sim.instrument.expected_brdf(sim.instrument.render_brdf(bj.solar_cell(), bj.Conditions.from_degrees(20)))
    r, c = np.unravel_index(np.argmax(np.where(mask, red.brdf, -np.inf)), red.brdf.shape)
    assert red.brdf[r, c] == pytest.approx(truth[r, c], rel=0.1)
    print(f"capture of beam + 3 samples (48 x 64 px): {seconds:.1f} s")


def test_live_view_renders_headless_and_updates(captured, tmp_path):
    _, _, live, _ = captured
    assert live.mode == "png" and live.png.is_file() and live.page.is_file()
    assert live.updates == 5  # the first frame, then beam + 3 samples each redrawn at its last exposure
    assert "live.png" in live.page.read_text()
    # a fresh view: two updates rewrite the PNG with different content
    sim = _sim()
    bench = sim.bench()
    from brdfjax.devices.plans import Measurement

    m = Measurement("ti20", "sample", theta_i=math.radians(20), theta_c=math.radians(20), exposures_s=(1e-3, 1e-2))
    view = LiveView(tmp_path / "lv", mode="png", min_interval_s=0.0)
    sim.sample_theta.move_to(m.theta_i), sim.arm.move_to(m.theta_c), sim.filter_changer.set_filters("3.0")
    sim.beam_block.open()
    shots = []
    for t in m.exposures_s:
        sim.camera.set_exposure(t)
        f = sim.camera.read_frame()
        from brdfjax.io.raw import Exposure

        assert view.update_exposure(m, "3.0", Exposure(t, f.n_frames, f.counts), f.black_level, f.full_scale,
                                    6.6e13, {}, bench)
        shots.append((view.png.stat().st_mtime_ns, view.png.read_bytes()))
    assert shots[0][1] != shots[1][1] and shots[1][0] >= shots[0][0]
    assert shots[1][1][:8] == b"\x89PNG\r\n\x1a\n"
    # window mode (here on the non-interactive Agg backend): the same PNG, shown in a pyplot figure
    import warnings

    win = LiveView(tmp_path / "win", mode="window", min_interval_s=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "FigureCanvasAgg is non-interactive"
        assert win.update_exposure(m, "3.0", Exposure(t, f.n_frames, f.counts), f.black_level, f.full_scale,
                                   6.6e13, {}, bench)
    assert win._fig is not None and win.png.is_file()
    win.close()
    assert win._fig is None


# --- interlock ------------------------------------------------------------------------------------


def test_interlock_refuses_an_unsafe_beam_od(tmp_path):
    cfg = load_capture_config(_config(tmp_path, beam_nd="1.0"))
    with pytest.raises(InterlockError) as e:
        run_capture(cfg, tmp_path / "set")
    msg = str(e.value)
    assert msg.startswith("interlock: refusing the beam measurement through ND '1.0' (OD 1): it would expose the array "
                          "to the focused beam below the smallest safe OD 5.2 ('4.0+1.0+0.2'; brightest pixel")
    assert "override_interlock = true or --override-interlock" in msg
    assert not (tmp_path / "set" / "beam.exr").exists()
    # the CLI: a refusal, exit 2 (brdfjax.runtime.errors), and the same message
    from brdfjax.cli import main

    assert main(["capture", str(_config(tmp_path, "c2.toml", beam_nd="3.0")), "--out", str(tmp_path / "s2"),
                 "--no-progress"]) == 2


def test_interlock_unit_rules():
    lk = Interlock()
    with pytest.raises(InterlockError, match="safe OD for the focused beam is not known yet"):
        lk.check("4.0", "the alignment")
    lk.establish("4.0+1.0+0.2", "evidence")
    lk.check("4.0+1.0+0.3", "x")  # denser: fine
    with pytest.raises(InterlockError, match=r"through ND '4.0\+1.0' \(OD 5\)"):
        lk.check("4.0+1.0", "the alignment")
    notes = []
    over = Interlock(override=True, log=notes.append)
    over.establish("4.0+1.0+0.2", "e")
    over.check("1.0", "the beam measurement")
    assert over.overridden and notes[0].startswith("OVERRIDDEN interlock: refusing the beam measurement")


# --- alignment ------------------------------------------------------------------------------------


def test_alignment_measures_injected_roll_yaw_pitch():
    true = dict(roll=math.radians(0.35), yaw=math.radians(-0.21), pitch=math.radians(0.14))
    sim = _sim(shape=(100, 160), m_h=1.5, m_v=-2.0, **true)
    bench = sim.bench()
    lk = Interlock()
    lk.establish("4.0+1.0+0.2", "test")
    res = run_alignment(bench, nd_filters="4.0+1.0+0.2", slew=math.radians(0.5), translation=0.0254,
                        w_px=25 / 8, exposure_s=1e-3, n_frames=32, check_safe=lambda s: lk.check(s, "alignment"),
                        seed_noise=lambda k: sim.seed_noise(99, k))
    errors = {k: math.degrees(getattr(res, k) - v) for k, v in true.items()}
    print("alignment errors (deg):", errors, "seed formulas:", res.degrees())
    for k, e in errors.items():
        assert abs(e) < 0.02, (k, e)
    # the seed's formulas agree to first order
    assert abs(math.degrees(res.seed_roll - true["roll"])) < 0.02
    assert abs(math.degrees(res.seed_yaw - true["yaw"])) < 0.02
    assert abs(math.degrees(res.seed_pitch - true["pitch"])) < 0.02
    assert res.m_h == pytest.approx(1.5, abs=0.1) and res.m_v == pytest.approx(-2.0, abs=0.1)
    assert sim.theta_c == 0.0 and sim.axial == 0.0 and not sim.shutter_open
    # the alignment refuses an unsafe stack through the interlock
    with pytest.raises(InterlockError):
        run_alignment(bench, nd_filters="1.0", slew=0.01, translation=0.0254, w_px=3, exposure_s=1e-3, n_frames=1,
                      check_safe=lambda s: lk.check(s, "the alignment"))


def test_spot_geometry_matches_the_pixel_mapping_and_the_seed_example():
    det = bj.Detector.seed(roll=math.radians(0.3), yaw=math.radians(0.2), pitch=math.radians(-0.1), m_h=2.0, m_v=-3.0)
    for tc in (0.0, 0.01):
        h, v = spot_pixel(theta_c=tc, roll=float(det.roll), yaw=float(det.yaw), pitch=float(det.pitch), m_h=2.0,
                          m_v=-3.0, pixel_pitch=(5.5e-6, 5.5e-6), distance=0.325)
        ph, pv = (float(x) for x in det.pixel_of(0.0, 0.0, theta_c=tc))
        assert h == pytest.approx(ph, abs=2e-3) and v == pytest.approx(pv, abs=2e-3)
    # seed §3.4: a 1.5 deg slew moves the spot 1545 px; 46 px over 4618.2 px/inch is 0.57 deg of yaw
    h, _ = spot_pixel(theta_c=math.radians(1.5), pixel_pitch=(5.5e-6, 5.5e-6), distance=0.325)
    assert abs(h) == pytest.approx(1547, abs=3)
    spots = [(0.0, 0.0, 0.0, 0.0), (-0.1, 0.0, 100.0, 0.0), (0.1, 0.0, -100.0, 0.0), (0.0, 0.0254, 46.0, -12.0)]
    res = solve_alignment(spots, pixel_pitch=(0.0254 / 4618.2, 0.0254 / 4618.2), distance=0.325, slew=0.1,
                          translation=0.0254)
    assert math.degrees(res.seed_yaw) == pytest.approx(0.5707, abs=1e-3)
    assert math.degrees(res.seed_pitch) == pytest.approx(0.1489, abs=1e-3)


# --- device errors --------------------------------------------------------------------------------


def test_retryable_camera_error_is_retried_and_a_stage_fault_stops_with_a_message(tmp_path):
    cfg = load_capture_config(_config(tmp_path))
    from brdfjax.devices.capture import build_bench

    bench, sim = build_bench(cfg)
    sim.faults = {"read_frame": {3, 4}}  # two timeouts in a row: retried (retries = 2)
    run_capture(cfg, tmp_path / "ok", bench=bench, sim=sim)
    assert read_manifest(tmp_path / "ok" / "manifest.toml").samples[-1].name == "ti60"

    bench, sim = build_bench(cfg)
    sim.faults = {"move_theta_c": {3}}  # the arm faults on its way to the second sample
    with pytest.raises(CaptureError) as e:
        run_capture(cfg, tmp_path / "stop", bench=bench, sim=sim)
    msg = str(e.value)
    assert "capture stopped during 'ti40' (detector arm: move): simulated move_theta_c failure (call 3)" in msg
    assert "the beam is blocked" in msg and "Check the detector arm" in msg and "--resume" in msg
    assert "theta_i 40.0000 deg" in msg and "theta_c 20.0000 deg" in msg  # left where it was
    state = tomllib.loads((tmp_path / "stop" / "manifest.toml").read_text())["capture"]
    assert state["done"] == ["beam", "ti20"] and state["status"] == "in progress"
    # after the fix: --resume finishes the plan without repeating the finished measurements
    bench, sim = build_bench(cfg)
    run_capture(cfg, tmp_path / "stop", bench=bench, sim=sim, resume=True)
    state = tomllib.loads((tmp_path / "stop" / "manifest.toml").read_text())["capture"]
    assert state["done"] == ["beam", "ti20", "ti40", "ti60"] and state["status"] == "complete"
    assert sim.calls["move_theta_c"] == 2  # only ti40 and ti60 were measured again


# --- resume ---------------------------------------------------------------------------------------


def test_killed_capture_resumes_bit_identical(tmp_path):
    slow_cfg = _config(tmp_path, "slow.toml", instrument_extra="frame_delay_s = 0.15")
    out = tmp_path / "killed"
    env = {**os.environ, "MPLBACKEND": "Agg", "JAX_PLATFORMS": "cpu"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "brdfjax", "capture", str(slow_cfg), "--out", str(out), "--no-progress"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    manifest = out / "manifest.toml"
    deadline = time.time() + 240
    done: list = []
    while time.time() < deadline and proc.poll() is None:
        if manifest.exists():
            done = tomllib.loads(manifest.read_text())["capture"]["done"]
            if len(done) >= 2:  # beam and ti20 finished: kill it in the middle of ti40
                time.sleep(0.6)
                proc.send_signal(signal.SIGKILL)
                break
        time.sleep(0.05)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    state = tomllib.loads(manifest.read_text())["capture"]
    assert state["status"] == "in progress" and 2 <= len(state["done"]) < 4
    # without --resume the folder is refused
    with pytest.raises(FileExistsError, match="pass --resume"):
        run_capture(load_capture_config(slow_cfg), out)
    resumed = run_capture(load_capture_config(slow_cfg), out, resume=True)
    # reference: the same seed, uninterrupted (no acquisition delay: the delay does not change the data)
    ref = run_capture(load_capture_config(_config(tmp_path, "ref.toml")), tmp_path / "ref")
    m_res, m_ref = read_manifest(resumed), read_manifest(ref)
    assert [s.name for s in m_res.samples] == ["ti20", "ti40", "ti60"]  # each exactly once
    assert [s.name for s in m_ref.samples] == [s.name for s in m_res.samples]
    assert tomllib.loads(resumed.read_text())["capture"]["done"] == ["beam", "ti20", "ti40", "ti60"]
    files = sorted(p.name for p in out.glob("*.exr"))
    assert files == sorted(p.name for p in (tmp_path / "ref").glob("*.exr")) and len(files) == 8
    for name in files:
        a, b = read_raw_exr(out / name), read_raw_exr(tmp_path / "ref" / name)
        for ea, eb in zip(a.exposures, b.exposures, strict=True):
            assert np.array_equal(ea.counts, eb.counts), name
        assert a.attrs == b.attrs, name
        assert (out / name).read_bytes() == (tmp_path / "ref" / name).read_bytes(), name
    assert not (out / ".parts").exists()


# --- config errors --------------------------------------------------------------------------------


def test_config_errors_name_the_key(tmp_path):
    from brdfjax.config import ConfigError

    p = tmp_path / "bad.toml"
    p.write_text('[instrument]\nkind = "simulated"\nbinn = 8\n[model]\npreset = "solar_cell"\n'
                 '[[measurements]]\ntheta_i_deg = 95.0\n')
    with pytest.raises(ConfigError) as e:
        load_capture_config(p)
    text = str(e.value)
    assert f"{p}: instrument.binn: unknown key" in text
    assert f"{p}: measurements[0].theta_i_deg: Input should be less than 89 (got 95.0)" in text
    p.write_text('[model]\npreset = "solar_cell"\n[beam]\nnd = "4.0+x"\n[[measurements]]\ntheta_i_deg = 20.0\n')
    with pytest.raises(ConfigError, match=r"beam.nd: .*expected \"auto\" or a stack"):
        load_capture_config(p)


def test_shipped_config_loads():
    cfg = load_capture_config(ROOT / "configs" / "capture_simulated.toml")
    assert [m.theta_i_deg for m in cfg.measurements] == [20.0, 40.0, 60.0]
    assert cfg.alignment.enabled and cfg.instrument.kind == "simulated"


# --- pylablib adapters with their transport replaced ---------------------------------------------

pylablib = pytest.importorskip("pylablib")
from pylablib.core.devio.comm_backend import IDeviceCommBackend  # noqa: E402


class FakeAPT(IDeviceCommBackend):
    """An emulated Kinesis KDC101 controller behind a pylablib comm backend: answers the APT protocol bytes."""

    _backend = "fake_apt"
    instances: list = []

    def __init__(self, conn, timeout=None, term_write=None, term_read=None, datatype="auto", reraise_error=None):
        super().__init__({"port": str(conn)}, timeout=timeout, term_write=term_write, term_read=term_read,
                         datatype=datatype, reraise_error=reraise_error)
        self.buf = b""
        self.pos = 0  # steps
        self.target = 0
        self.moving = 0
        self.fail_next_reads = 0
        self.status_extra = 0
        self.sent: list[int] = []
        FakeAPT.instances.append(self)

    def _reply(self, mid: int, data: bytes | None = None, p1: int = 0, p2: int = 0):
        if data is None:
            self.buf += struct.pack("<HBBBB", mid, p1, p2, 0x01, 0x50)
        else:
            self.buf += struct.pack("<HHBB", mid, len(data), 0x01 | 0x80, 0x50) + data

    def write(self, data, flush=True, read_echo=False, read_echo_delay=0, read_echo_lines=1):
        data = bytes(data)
        while data:
            mid, = struct.unpack("<H", data[:2])
            dest = data[4]
            if dest & 0x80:
                n, = struct.unpack("<H", data[2:4])
                payload, data = data[6:6 + n], data[6 + n:]
            else:
                payload, data = data[2:4], data[6:]
            self.sent.append(mid)
            if self.fail_next_reads:
                continue  # the controller does not answer (the read times out)
            if mid == 0x0005:
                info = bytearray(84)
                info[0:4] = struct.pack("<I", 27000001)
                info[4:12] = b"KDC101\x00\x00"
                info[12:14] = struct.pack("<H", 16)
                info[14:17] = bytes([3, 2, 1])
                info[78:84] = struct.pack("<HHH", 1, 0, 1)
                self._reply(0x0006, bytes(info))
            elif mid == 0x0429:
                if self.moving:
                    self.moving -= 1
                    if not self.moving:
                        self.pos = self.target
                status = (1 << 10) | (1 << 31) | self.status_extra | ((1 << 5) if self.moving else 0)
                self._reply(0x042A, struct.pack("<HI", 1, status))
            elif mid == 0x0411:
                self._reply(0x0412, struct.pack("<Hi", 1, self.pos))
            elif mid == 0x0453:
                _, self.target = struct.unpack("<Hi", payload[:6])
                self.moving = 2

    def read(self, size=None):
        if self.fail_next_reads:
            self.fail_next_reads -= 1
            raise self.Error("read timeout (emulated)")
        if size is None:
            out, self.buf = self.buf, b""
            return out
        if len(self.buf) < size:
            raise self.Error("read timeout (emulated)")
        out, self.buf = self.buf[:size], self.buf[size:]
        return out

    def readline(self, remove_term=True, timeout=None, skip_empty=True):
        raise self.Error("APT has no lines")


class FakePM(IDeviceCommBackend):
    """An emulated Thorlabs PM160 behind a pylablib comm backend: answers SCPI lines."""

    _backend = "fake_scpi"

    def __init__(self, conn, timeout=None, term_write=None, term_read=None, datatype="auto", reraise_error=None):
        super().__init__(conn, timeout=timeout, term_write=term_write, term_read=term_read, datatype=datatype,
                         reraise_error=reraise_error)
        self.lines: list[bytes] = []
        self.esr = 0
        self.wavelength_nm = 635.0
        self.power_w = 1.234e-3
        self.mode = "POW"

    def write(self, data, flush=True, read_echo=False, read_echo_delay=0, read_echo_lines=1):
        for cmd in (data.decode() if isinstance(data, bytes) else str(data)).strip().split(";"):
            cmd = cmd.strip()
            up = cmd.upper()
            if up == "*CLS":
                self.esr = 0
            elif up == "*ESR?":
                self.lines.append(str(self.esr).encode())
                self.esr = 0
            elif up == "*IDN?":
                self.lines.append(b"Thorlabs,PM160,P1000001,1.5.0")
            elif up in ("INIT", ""):
                pass
            elif up == ":SENSE:POW:RANGE?" or up == ":SENS:POW:RANG?":
                self.lines.append(b"2.0E-2")
            elif up.startswith(":SENSE:") and up.endswith(":RANGE?"):
                self.esr |= 0x20
            elif up.startswith(":CONF:"):
                self.mode = up.split(":")[2]
            elif up == ":CONF?":
                self.lines.append(self.mode.encode())
            elif up == ":READ?":
                self.lines.append(repr(self.power_w).encode())
            elif up.startswith(":SENS:CORR:WAV?"):
                self.lines.append(repr(self.wavelength_nm).encode())
            elif up.startswith(":SENS:CORR:WAV "):
                self.wavelength_nm = float(cmd.split()[1])
            else:
                self.esr |= 0x20

    def readline(self, remove_term=True, timeout=None, skip_empty=True):
        if not self.lines:
            raise self.Error("read timeout (emulated)")
        return self.lines.pop(0)

    def read(self, size=None):
        if size is None:
            out = b"\n".join(self.lines)
            self.lines = []
            return out
        raise self.Error("read timeout (emulated)")


def test_kinesis_adapter_drives_pylablib_kinesis_motor_over_emulated_apt():
    import warnings

    from pylablib.devices import Thorlabs

    from brdfjax.devices.lab import KinesisRotation, KinesisTranslation

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "could not cycle RTS" with a non-serial backend
        motor = Thorlabs.KinesisMotor((FakeAPT, "27000001"), scale="PRM1-Z8")
    fake = FakeAPT.instances[-1]
    assert motor.get_scale_units() == "deg"
    stage = KinesisRotation(motor, label="detector arm")
    assert isinstance(stage, itf.RotationStage)
    stage.move_to(math.radians(20.0))
    assert fake.pos == int(20.0 * 1919.6418578623391)  # PRM1-Z8: 1919.64 steps per degree; pylablib truncates
    assert 0x0453 in fake.sent and fake.sent.count(0x0429) >= 3  # move, then status polled until it stopped
    assert math.degrees(stage.get_position()) == pytest.approx(20.0, abs=1e-3)
    # a controller that stops answering: a retryable DeviceError (the capture retries absolute moves)
    fake.fail_next_reads = 1
    with pytest.raises(itf.DeviceError) as e:
        stage.get_position()
    assert e.value.retryable and "detector arm: position" in str(e.value)
    fake.fail_next_reads = 0
    fake.buf = b""
    # a limit switch after the move: not retryable, names the fault
    fake.status_extra = 1 << 1
    with pytest.raises(itf.DeviceError, match=r"motion to .* ended with \['hw_fw_lim'\]") as e:
        stage.move_to(math.radians(30.0))
    assert not e.value.retryable
    # a rotation stage is refused as a translation (units)
    with pytest.raises(itf.DeviceError, match="position units are 'deg', expected 'm'"):
        KinesisTranslation(motor)


def test_power_meter_adapter_drives_pylablib_pm160_over_emulated_scpi():
    from pylablib.devices import Thorlabs

    from brdfjax.devices.lab import PowerMeterAdapter

    pm = Thorlabs.PM160((FakePM, "USB0::0x1313::0x8078::P1000001::INSTR"))
    meter = PowerMeterAdapter(pm)
    assert isinstance(meter, itf.PowerMeter)
    assert meter.read_power() == pytest.approx(1.234e-3)
    meter.set_wavelength(632.8e-9)
    assert pm.get_wavelength() == pytest.approx(632.8e-9)


def test_camera_adapter_maps_pylablib_tlcamera_with_the_sdk_replaced(monkeypatch):
    from pylablib.devices.Thorlabs import TLCamera as tlmod

    from brdfjax.devices.lab import TLCameraAdapter

    class FakeSDK:
        exposure_us = 1000
        black = 10

        def __getattr__(self, name):
            raise AttributeError(name)

        def tl_camera_set_exposure_time(self, h, us):
            self.exposure_us = us

        def tl_camera_get_exposure_time(self, h):
            return self.exposure_us

        def tl_camera_get_frame_time(self, h):
            return 50000

        def tl_camera_get_black_level(self, h):
            return self.black

        def tl_camera_get_black_level_range(self, h):
            return (0, 100)

        def tl_camera_set_black_level(self, h, level):
            self.black = level

        def tl_camera_get_roi_range(self, h):
            return (0, 0, 0, 0, 3295, 2471, 3295, 2471)

        def tl_camera_get_camera_sensor_type(self, h):
            return 0

        def tl_camera_get_bit_depth(self, h):
            return 14

    sdk = FakeSDK()
    monkeypatch.setattr(tlmod, "lib", sdk)
    monkeypatch.setattr(tlmod.ThorlabsTLCamera, "open", lambda self: setattr(self, "handle", 1))
    cam = tlmod.ThorlabsTLCamera("12345")
    rng = np.random.default_rng(0)
    grabbed = []

    def grab(n, frame_timeout=5.0, **kw):
        grabbed.append(n)
        return [(100 + 10 * rng.standard_normal((4, 6))).astype(np.uint16) for _ in range(n)]

    monkeypatch.setattr(cam, "grab", grab)
    adapter = TLCameraAdapter(cam)
    assert isinstance(adapter, itf.Camera)
    assert adapter.shape == (2472, 3296) and adapter.full_scale == 16383.0
    assert adapter.set_exposure(0.1) == pytest.approx(0.1) and sdk.exposure_us == 100000
    assert adapter.set_black_level(250) == 100  # pylablib truncates to the SDK's range
    adapter.set_frame_averaging(8)
    f = adapter.read_frame()
    assert grabbed == [8] and f.n_frames == 8 and f.counts.dtype == np.float32 and f.counts.shape == (4, 6)
    assert f.exposure_s == pytest.approx(0.1) and f.black_level == 100 and f.counts_std is not None
    assert 90 < float(f.counts.mean()) < 110
    cam.handle = None  # nothing to close
