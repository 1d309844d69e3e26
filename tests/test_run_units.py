"""Unit tests of the run layer's pieces: ring buffer, acquisition loop, limits, steady detection."""

from __future__ import annotations

import queue
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.daq.protocol import SampleBlock, SampleGap
from station.config import load_config
from station.errors import LimitError
from station.recording import ChannelSpec, RecordingWriter, RunMetadata, read_recording
from station.run.acquisition import Acquisition, AcquisitionError, RingBuffer
from station.run.request import RunRequest, StepSpec, default_request, plan_run
from station.run.steady import SteadyCriteria, is_steady

ROOT = Path(__file__).resolve().parent.parent
CFG = load_config(ROOT / "config" / "sim-5kN.yaml")


def test_ring_buffer_wraps_and_refuses_what_it_does_not_hold() -> None:
    rb = RingBuffer(10)
    rb.put(0, np.arange(7, dtype=np.int16), -np.arange(7, dtype=np.int16))
    rb.put(7, np.arange(7, 13, dtype=np.int16), -np.arange(7, 13, dtype=np.int16))
    d, f = rb.get(3, 13)
    assert d.tolist() == list(range(3, 13)) and f.tolist() == [-v for v in range(3, 13)]
    with pytest.raises(IndexError):
        rb.get(2, 5)  # overwritten
    with pytest.raises(IndexError):
        rb.get(10, 14)  # not yet acquired
    with pytest.raises(ValueError, match="expected sample 13"):
        rb.put(20, np.zeros(1, np.int16), np.zeros(1, np.int16))


def _Block(first: int, n: int) -> SampleBlock:
    """The driver's own event type (the acquisition matches on it)."""
    return SampleBlock(first, np.full(n, 7, dtype=np.int16), np.full(n, -7, dtype=np.int16))


def _Gap(first: int, count: int) -> SampleGap:
    return SampleGap(first, count, frames=1)


def _writer(tmp_path: Path, run_id: str = "unit") -> RecordingWriter:
    meta = RunMetadata(run_id=run_id, transducer_id="T", source="calibrate", sample_rate_hz=1000.0,
                       load_mass_kg=1.0, end_mass_kg=None, sensitivity_V_per_N=1e-3, capacity_N=100.0,
                       config_yaml="x: 1\n")
    ch = (ChannelSpec("displacement", "i2", "count", "m", 1e-6), ChannelSpec("force", "i2", "count", "V", 1e-3))
    return RecordingWriter(tmp_path, meta, ch)


def _feed(events: list[object]) -> tuple[queue.Queue[object], object]:
    q: queue.Queue[object] = queue.Queue()
    for e in events:
        q.put(e)

    def get(timeout: float) -> object | None:
        try:
            return q.get(timeout=timeout)
        except queue.Empty:
            return None
    return q, get


def test_acquisition_keeps_sample_positions_across_gaps(tmp_path: Path) -> None:
    events = [_Block(0, 100), _Gap(100, 30), _Block(130, 70), _Block(250, 50)]  # last: unreported gap
    _, get = _feed(events)
    w = _writer(tmp_path)
    acq = Acquisition(get, w, sample_rate_hz=1000.0, stall_limit_s=0.5)
    acq.start()
    acq.wait_for(300, 5.0)
    acq.stop()
    assert acq.lost == [(100, 30), (200, 50)]
    assert acq.lost_between(90, 140) == 30 and acq.lost_between(0, 100) == 0 and acq.lost_between(0, 300) == 80
    rec = read_recording(w.finish("completed"))
    assert rec.force_V.size == 300
    assert np.all(rec.force_V[100:130] == 0) and np.all(rec.force_V[130:200] == pytest.approx(-7e-3))
    assert rec.lost_samples.tolist() == [[100, 30], [200, 50]]


def test_acquisition_fails_on_a_stalled_stream(tmp_path: Path) -> None:
    _, get = _feed([_Block(0, 100)])
    acq = Acquisition(get, _writer(tmp_path), sample_rate_hz=1000.0, stall_limit_s=0.3)
    acq.start()
    with pytest.raises(AcquisitionError, match="stalled"):
        acq.wait_for(200, 3.0)
    acq.stop()


def test_acquisition_fails_on_a_crc_storm(tmp_path: Path) -> None:
    events: list[object] = []
    for k in range(20):  # every other 64-sample frame lost: 50 % + 1 frame
        events.append(_Block(k * 128, 64) if k % 3 == 0 else _Gap(k * 128, 64))
        events.append(_Gap(k * 128 + 64, 64))
    _, get = _feed(events)
    acq = Acquisition(get, _writer(tmp_path), sample_rate_hz=1000.0, stall_limit_s=5.0)
    acq.start()
    with pytest.raises(AcquisitionError, match="corrupted"):
        acq.wait_for(20 * 128, 3.0)
    acq.stop()


def test_disk_failure_stops_the_run_without_blocking_acquisition(tmp_path: Path) -> None:
    w = _writer(tmp_path)

    def broken(d: np.ndarray, f: np.ndarray) -> None:
        raise OSError(28, "No space left on device")
    w.append = broken  # type: ignore[method-assign]  # the disk, not the class, is under test here
    _, get = _feed([_Block(0, 100)])
    acq = Acquisition(get, w, sample_rate_hz=1000.0, stall_limit_s=5.0)
    acq.start()
    t0 = time.monotonic()
    while acq.disk_error is None and time.monotonic() - t0 < 3:
        time.sleep(0.01)
    with pytest.raises(AcquisitionError, match="No space left"):
        acq.check()
    acq.stop()
    w.abandon()


def test_unsafe_requests_are_refused_with_the_step_and_limit_named() -> None:
    ok = default_request(CFG)
    plan = plan_run(CFG, ok)
    assert len(plan.steps) == len(CFG.plan.steps)
    bad = ok.model_copy(update={"steps": [*ok.steps, StepSpec(crank_frequency_hz=90.0, crank_radius_m=0.01)]})
    with pytest.raises(LimitError, match=r"step 6 \(90 Hz, 0.01 m\): peak force .* exceeds the limit 4000 N"):
        plan_run(CFG, bad)
    with pytest.raises(LimitError, match=r"crank frequency 150 Hz is outside the rig's range \[1, 100\] Hz"):
        plan_run(CFG, ok.model_copy(update={"steps": [StepSpec(crank_frequency_hz=150, crank_radius_m=1e-4)]}))
    with pytest.raises(LimitError, match=r"radius 0\.2 m is outside"):
        plan_run(CFG, ok.model_copy(update={"steps": [StepSpec(crank_frequency_hz=2, crank_radius_m=0.2)]}))
    with pytest.raises(LimitError, match="not the one mounted"):
        plan_run(CFG, RunRequest(transducer_id="OTHER", top_mass_kg=25.7, steps=ok.steps))
    # a heavier top mass makes a step that was safe unsafe
    step = [StepSpec(crank_frequency_hz=60.0, crank_radius_m=0.0005)]
    plan_run(CFG, ok.model_copy(update={"steps": step}))
    with pytest.raises(LimitError, match="peak force"):
        plan_run(CFG, ok.model_copy(update={"steps": step, "top_mass_kg": 60.0}))


def test_default_request_picks_radii_within_the_limits() -> None:
    req = default_request(CFG, [3.0, 30.0, 100.0])
    plan = plan_run(CFG, req)  # must not raise
    assert [s.crank_frequency_hz for s in plan.steps] == [3.0, 30.0, 100.0]
    assert plan.steps[0].crank_radius_m > plan.steps[2].crank_radius_m


def test_steady_detection() -> None:
    fs, f = 20_000.0, 8.0
    t = np.arange(int(0.75 * fs)) / fs
    steady_d = 10_000 * np.sin(2 * np.pi * f * t)
    crit = SteadyCriteria()
    assert is_steady(steady_d, 0.5 * steady_d, f, fs, crit)
    growing = steady_d * (1 + 0.2 * t)  # amplitude still rising 20 %/s
    assert not is_steady(growing, 0.5 * steady_d, f, fs, crit)
    assert not is_steady(steady_d, 0.5 * growing, f, fs, crit)
    detuned = 10_000 * np.sin(2 * np.pi * 7.8 * t)  # not yet at the set-point
    assert not is_steady(detuned, detuned, f, fs, crit)
