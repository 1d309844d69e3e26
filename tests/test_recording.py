"""HDF5 recordings: the layout the writer produces, reading (complete, abandoned, cut off by a kill -9),
recovery of partial files, results, and the offline simulation written as a recording."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

import station
from station.config import StationConfig, parse_config
from station.errors import ConfigError, LimitError, RecordingFormatError, StationError
from station.recording import (
    ChannelSpec,
    RecordingWriter,
    new_run_id,
    read_recording,
    recover_partial,
)
from station.simulate import simulate_run
from tests.recording_support import FLOAT_CHANNELS, FS, run_metadata

COUNT_CHANNELS = (
    ChannelSpec("displacement", "i2", "count", "m", scale=6.103515625e-07, volts_per_count=3.0517578125e-4),
    ChannelSpec("force", "i2", "count", "V", scale=3.0517578125e-4, offset=-0.25,
                volts_per_count=3.0517578125e-4),
)


def _counts(n0: int, n: int, mod: int = 30_000) -> np.ndarray:
    return ((np.arange(n0, n0 + n) % mod) - mod // 2).astype(np.int16)


def _docs(path: Path) -> list[dict[str, Any]]:
    with h5py.File(path, "r") as f:
        return [json.loads(line) for line in bytes(f["documents"][...]).decode().splitlines()]


def _iso(text: str) -> datetime:
    t = datetime.fromisoformat(text)
    assert t.tzinfo is not None, f"{text!r} has no time zone"
    return t


# -- the layout, read with plain h5py --------------------------------------------------------------

@pytest.fixture
def written(tmp_path: Path) -> tuple[Path, int]:
    """A completed recording with 3 blocks of ADC codes, 2 steps, a lost-sample report and an event."""
    w = RecordingWriter(tmp_path, run_metadata(), COUNT_CHANNELS, plan={"kind": "test", "steps": [1, 2]},
                        chunk_samples=1000)
    assert w.partial_path.exists() and not w.final_path.exists()
    n = 0
    for size in (2500, 1000, 3500):
        w.append(_counts(n, size), -_counts(n, size))
        n += size
    w.add_step(crank_frequency_hz=4.0, crank_radius_m=0.01, start_sample=1000, end_sample=3000)
    w.add_lost(4000, 25)
    w.add_step(crank_frequency_hz=12.5, crank_radius_m=0.004, start_sample=3500, end_sample=6000,
               lost_in_window=25, extra={"note": "gap"})
    w.document("event", {"warning": "test event", "value": np.float64(1.5)})
    path = w.finish("completed")
    return path, n


def test_finish_moves_the_partial_file_into_place(written: tuple[Path, int], tmp_path: Path) -> None:
    path, _ = written
    assert path == tmp_path / "20250101T000000-TX-1-abcdef.h5"
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_root_attributes(written: tuple[Path, int]) -> None:
    path, _ = written
    with h5py.File(path, "r") as f:
        a = dict(f.attrs)
    assert a["format"] == "sinecal-recording"
    assert a["format_version"] == 1
    assert a["run_id"] == "20250101T000000-TX-1-abcdef"
    assert a["transducer_id"] == "TX-1"
    assert a["source"] == "calibrate"
    assert a["sample_rate_hz"] == FS
    assert a["load_mass_kg"] == 26.167
    assert a["end_mass_kg"] == 0.12
    assert a["sensitivity_V_per_N"] == 0.002
    assert a["capacity_N"] == 5000.0
    assert a["software_version"] == station.__version__
    assert a["exit_status"] == "completed"
    assert a["reason"] == ""
    assert _iso(a["start_time"]) <= _iso(a["end_time"])


def test_config_snapshot_is_stored_verbatim(written: tuple[Path, int]) -> None:
    path, _ = written
    with h5py.File(path, "r") as f:
        d = f["config/yaml"]
        assert d.dtype == np.uint8 and d.ndim == 1
        assert bytes(d[...]).decode("utf-8") == "transducer:\n  id: TX-1  # µ-test\n"
        assert f["config"].attrs["encoding"] == "utf-8 YAML"


def test_raw_channels_with_units_and_scaling(written: tuple[Path, int]) -> None:
    path, n = written
    with h5py.File(path, "r") as f:
        assert f["raw"].attrs["sample_rate_hz"] == FS
        assert f["raw"].attrs["units_of_time"] == "s"
        assert sorted(f["raw"]) == ["displacement", "force"]
        for name, spec, sign in (("displacement", COUNT_CHANNELS[0], 1), ("force", COUNT_CHANNELS[1], -1)):
            d = f["raw"][name]
            assert d.dtype == np.int16
            assert d.shape == (n,) and d.maxshape == (None,) and d.chunks == (1000,)
            assert dict(d.attrs) == {"stored_unit": "count", "physical_unit": spec.physical_unit,
                                     "scale": spec.scale, "offset": spec.offset,
                                     "volts_per_count": spec.volts_per_count}
            np.testing.assert_array_equal(d[...], sign * _counts(0, n))


def test_step_table(written: tuple[Path, int]) -> None:
    path, _ = written
    expected = {"crank_frequency_hz": ([4.0, 12.5], np.float64, "Hz"),
                "crank_radius_m": ([0.01, 0.004], np.float64, "m"),
                "start_sample": ([1000, 3500], np.int64, "sample"),
                "end_sample": ([3000, 6000], np.int64, "sample"),
                "lost_in_window": ([0, 25], np.int64, "sample")}
    with h5py.File(path, "r") as f:
        assert sorted(f["steps"]) == sorted(expected)
        for name, (values, dtype, unit) in expected.items():
            d = f["steps"][name]
            assert d.dtype == dtype and d.shape == (2,) and d.maxshape == (None,)
            assert d.attrs["unit"] == unit
            assert d[...].tolist() == values


def test_lost_samples_and_empty_result_groups(written: tuple[Path, int]) -> None:
    path, _ = written
    with h5py.File(path, "r") as f:
        lost = f["lost_samples"]
        assert lost.dtype == np.int64 and lost.shape == (1, 2) and lost.maxshape == (None, 2)
        assert lost[...].tolist() == [[4000, 25]]
        assert lost.attrs["columns"] == "first_sample, count"
        assert isinstance(f["processed"], h5py.Group) and len(f["processed"]) == 0
        assert isinstance(f["results"], h5py.Group) and len(f["results"]) == 0


def test_run_documents(written: tuple[Path, int]) -> None:
    path, n = written
    with h5py.File(path, "r") as f:
        assert f["documents"].dtype == np.uint8
        start_time, end_time = f.attrs["start_time"], f.attrs["end_time"]
    docs = _docs(path)
    assert [d["kind"] for d in docs] == ["start", "step", "step", "event", "stop"]
    start, step0, step1, event, stop = docs
    assert start["run_id"] == "20250101T000000-TX-1-abcdef"
    assert start["time"] == start_time
    assert start["plan"] == {"kind": "test", "steps": [1, 2]}
    assert start["software_version"] == station.__version__
    assert start["metadata"]["transducer_id"] == "TX-1"
    assert start["metadata"]["end_mass_kg"] == 0.12
    assert "config_yaml" not in start["metadata"]
    assert step0["index"] == 0 and step1["index"] == 1
    assert step0["crank_frequency_hz"] == 4.0 and step0["start_sample"] == 1000 and step0["end_sample"] == 3000
    assert step1["lost_in_window"] == 25 and step1["note"] == "gap"
    assert step1["units"]["crank_radius_m"] == "m"
    assert event["warning"] == "test event" and event["value"] == 1.5
    assert stop == {"kind": "stop", "time": end_time, "exit_status": "completed", "reason": "",
                    "samples": n}


# -- reading --------------------------------------------------------------------------------------

def test_read_recording_in_physical_units(written: tuple[Path, int]) -> None:
    path, n = written
    rec = read_recording(path)
    assert rec.complete is True
    assert rec.exit_status == "completed"
    assert rec.run_id == "20250101T000000-TX-1-abcdef" and rec.transducer_id == "TX-1"
    assert rec.source == "calibrate" and rec.sample_rate_hz == FS
    assert (rec.load_mass_kg, rec.end_mass_kg, rec.sensitivity_V_per_N, rec.capacity_N) == (
        26.167, 0.12, 0.002, 5000.0)
    assert rec.software_version == station.__version__
    assert rec.config == {"transducer": {"id": "TX-1"}}
    np.testing.assert_array_equal(rec.displacement_m, _counts(0, n) * COUNT_CHANNELS[0].scale)
    np.testing.assert_array_equal(rec.force_V, -_counts(0, n) * COUNT_CHANNELS[1].scale - 0.25)
    assert rec.lost_samples.tolist() == [[4000, 25]]
    assert [(s.index, s.crank_frequency_hz, s.start_sample, s.end_sample, s.usable) for s in rec.steps] == [
        (0, 4.0, 1000, 3000, True), (1, 12.5, 3500, 6000, False)]
    d, fv = rec.step_signals(rec.steps[0])
    np.testing.assert_array_equal(d, rec.displacement_m[1000:3000])
    np.testing.assert_array_equal(fv, rec.force_V[1000:3000])
    assert [doc["kind"] for doc in rec.documents] == ["start", "step", "step", "event", "stop"]


def test_unknown_end_mass_is_stored_as_nan(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path, run_metadata(end_mass_kg=None), FLOAT_CHANNELS)
    w.append(np.zeros(10), np.ones(10))
    path = w.finish("completed")
    with h5py.File(path, "r") as f:
        assert np.isnan(f.attrs["end_mass_kg"])
    assert read_recording(path).end_mass_kg is None


def test_new_run_ids_are_unique_and_sortable() -> None:
    ids = [new_run_id("TX-1") for _ in range(50)]
    assert len(set(ids)) == 50
    stamp, tid, suffix = ids[0][:15], ids[0][16:20], ids[0][21:]
    assert datetime.strptime(stamp, "%Y%m%dT%H%M%S") and tid == "TX-1" and len(suffix) == 6


@pytest.mark.parametrize("status", ["aborted", "failed", "interrupted"])
def test_other_exit_statuses_and_reason(tmp_path: Path, status: str) -> None:
    w = RecordingWriter(tmp_path, run_metadata(), FLOAT_CHANNELS)
    w.append(np.arange(5.0), np.arange(5.0))
    path = w.finish(status, reason="operator pressed stop")
    rec = read_recording(path)
    assert rec.complete is True
    assert (rec.exit_status, rec.reason) == (status, "operator pressed stop")
    assert rec.documents[-1]["exit_status"] == status


def test_unknown_exit_status_is_refused_and_the_run_can_still_finish(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path, run_metadata(), FLOAT_CHANNELS)
    w.append(np.arange(5.0), np.arange(5.0))
    with pytest.raises(ValueError, match="exit status must be one of"):
        w.finish("done")
    assert w.partial_path.exists()
    assert read_recording(w.finish("completed")).exit_status == "completed"


def test_unequal_blocks_are_refused(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path, run_metadata(), FLOAT_CHANNELS)
    w.append(np.arange(4.0), np.arange(4.0))
    with pytest.raises(ValueError, match="equal 1-D blocks"):
        w.append(np.arange(5.0), np.arange(4.0))
    with pytest.raises(ValueError, match="equal 1-D blocks"):
        w.append(np.zeros((2, 2)), np.zeros((2, 2)))
    assert w.samples_written == 4
    assert read_recording(w.finish("completed")).displacement_m.size == 4


# -- nothing recorded is overwritten ---------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".h5", ".h5.partial"])
def test_existing_recording_is_never_overwritten(tmp_path: Path, suffix: str) -> None:
    run_id = "20250101T000000-TX-1-abcdef"
    existing = tmp_path / f"{run_id}{suffix}"
    existing.write_bytes(b"an earlier run")
    with pytest.raises(StationError, match="refusing to overwrite existing recording"):
        RecordingWriter(tmp_path, run_metadata(run_id), FLOAT_CHANNELS)
    assert existing.read_bytes() == b"an earlier run"
    assert [p.name for p in tmp_path.iterdir()] == [existing.name]


def test_writer_creates_the_output_folder(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path / "a" / "b", run_metadata(), FLOAT_CHANNELS)
    assert w.partial_path.parent == tmp_path / "a" / "b"
    w.abandon()


# -- abandoned and truncated files -----------------------------------------------------------------

def test_abandoned_run_reads_as_interrupted_and_recovers(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path, run_metadata(), COUNT_CHANNELS)
    w.append(_counts(0, 3000), _counts(0, 3000))
    w.add_step(crank_frequency_hz=4.0, crank_radius_m=0.01, start_sample=0, end_sample=3000)
    w.abandon()
    w.abandon()  # idempotent
    assert not w.final_path.exists()
    rec = read_recording(w.partial_path)
    assert rec.complete is False
    assert rec.exit_status == "interrupted"
    assert rec.displacement_m.size == 3000 and len(rec.steps) == 1
    assert "stop" not in [d["kind"] for d in rec.documents]

    dst = recover_partial(w.partial_path)
    assert dst == w.final_path and not w.partial_path.exists()
    rec2 = read_recording(dst)
    assert rec2.complete is True
    assert rec2.exit_status == "interrupted"
    assert "recovered" in rec2.reason
    np.testing.assert_array_equal(rec2.displacement_m, rec.displacement_m)
    np.testing.assert_array_equal(rec2.force_V, rec.force_V)
    assert rec2.steps == rec.steps
    assert _iso(rec2.end_time) >= _iso(rec2.start_time)
    assert sorted(p.name for p in tmp_path.iterdir()) == [dst.name]


def test_crash_between_stop_record_and_rename(tmp_path: Path, written: tuple[Path, int]) -> None:
    """finish() writes the exit status, then renames; a *.partial is incomplete whatever it says."""
    path, n = written
    partial = path.with_name(path.name + ".partial")
    path.rename(partial)
    rec = read_recording(partial)
    assert rec.complete is False
    assert rec.exit_status == "interrupted"
    dst = recover_partial(partial)
    assert dst == path
    rec2 = read_recording(dst)
    assert rec2.complete is True and rec2.exit_status == "interrupted"
    assert rec2.displacement_m.size == n and len(rec2.steps) == 2


def test_channel_cut_short_and_step_beyond_the_data(tmp_path: Path) -> None:
    """A crash can leave one channel a block shorter and a step whose window was never flushed."""
    w = RecordingWriter(tmp_path, run_metadata(), FLOAT_CHANNELS)
    w.append(np.arange(1000.0), -np.arange(1000.0))
    w.add_step(crank_frequency_hz=5.0, crank_radius_m=0.01, start_sample=0, end_sample=800)
    w.add_step(crank_frequency_hz=6.0, crank_radius_m=0.01, start_sample=800, end_sample=1000)
    w.abandon()
    with h5py.File(w.partial_path, "r+") as f:
        f["raw/force"].resize((900,))
    rec = read_recording(w.partial_path)
    assert rec.displacement_m.size == rec.force_V.size == 900
    assert [s.end_sample for s in rec.steps] == [800]
    dst = recover_partial(w.partial_path)
    with h5py.File(dst, "r") as f:
        assert f["raw/displacement"].shape == f["raw/force"].shape == (900,)
    np.testing.assert_array_equal(read_recording(dst).force_V, -np.arange(900.0))


def test_document_cut_in_the_middle_is_dropped(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path, run_metadata(), FLOAT_CHANNELS)
    w.add_step(crank_frequency_hz=5.0, crank_radius_m=0.01, start_sample=0, end_sample=0)
    w.document("event", {"message": "x" * 100})
    w.abandon()
    with h5py.File(w.partial_path, "r+") as f:
        f["documents"].resize((f["documents"].shape[0] - 40,))
    assert [d["kind"] for d in read_recording(w.partial_path).documents] == ["start", "step"]


def test_recover_refuses_other_files_and_never_overwrites(tmp_path: Path, written: tuple[Path, int]) -> None:
    path, _ = written
    with pytest.raises(StationError, match=r"only \*\.h5\.partial files are recovered"):
        recover_partial(path)
    w = RecordingWriter(tmp_path / "other", run_metadata(), FLOAT_CHANNELS)
    w.append(np.arange(3.0), np.arange(3.0))
    w.abandon()
    shutil.copy(path, w.final_path)  # a complete file of the same name exists already
    before = w.final_path.read_bytes()
    with pytest.raises(StationError, match="exists already; not overwriting it"):
        recover_partial(w.partial_path)
    assert w.final_path.read_bytes() == before
    assert w.partial_path.exists()


# -- bad files ------------------------------------------------------------------------------------

def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingFormatError, match="no such recording"):
        read_recording(tmp_path / "nope.h5")


def test_not_hdf5(tmp_path: Path) -> None:
    p = tmp_path / "text.h5"
    p.write_text("hello", encoding="utf-8")
    with pytest.raises(RecordingFormatError, match="not a readable HDF5 recording") as exc:
        read_recording(p)
    assert str(p) in str(exc.value)


def test_foreign_hdf5(tmp_path: Path) -> None:
    p = tmp_path / "foreign.h5"
    with h5py.File(p, "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(RecordingFormatError, match="format 'sinecal-recording' expected, got 'something-else'"):
        read_recording(p)


@pytest.mark.parametrize(("damage", "message"), [
    (lambda f: f.__delitem__("raw/force"), "dataset /raw/force expected, not found"),
    (lambda f: f["raw/displacement"].attrs.__delitem__("scale"), "/raw/displacement lacks its 'scale' attribute"),
    (lambda f: f.attrs.__delitem__("run_id"), "attribute 'run_id' expected in the root group"),
])
def test_damaged_recording_names_what_is_missing(written: tuple[Path, int], damage: Any, message: str) -> None:
    path, _ = written
    with h5py.File(path, "r+") as f:
        damage(f)
    with pytest.raises(RecordingFormatError, match=message) as exc:
        read_recording(path)
    assert str(path) in str(exc.value)


# -- kill -9 of a writing process ------------------------------------------------------------------

KILL_WRITER = r"""
import sys, time
import numpy as np
from station.recording import ChannelSpec, RecordingWriter, RunMetadata

out, fs, block = sys.argv[1], 20000.0, 200          # 10 ms blocks at (at most) 20 kHz
meta = RunMetadata(run_id="killed", transducer_id="TX-KILL", source="calibrate", sample_rate_hz=fs,
                   load_mass_kg=26.0, end_mass_kg=0.12, sensitivity_V_per_N=0.002, capacity_N=5000.0,
                   config_yaml="kill: test\n")
channels = (ChannelSpec("displacement", "i2", "count", "m", scale=1e-6),
            ChannelSpec("force", "f8", "V", "V", scale=1.0))
w = RecordingWriter(out, meta, channels)             # the default flush interval
k = 0
while True:
    idx = np.arange(k, k + block)
    w.append((idx % 30000).astype(np.int16), idx * 1e-3)
    k += block
    if k == 10000:                                   # one step early on; no documents after it
        w.add_step(crank_frequency_hz=4.0, crank_radius_m=0.01, start_sample=2000, end_sample=10000)
    print(k, flush=True)
    time.sleep(block / fs)                           # never faster than fs, even after a stall
"""


def _expected_disp(n: int) -> np.ndarray:
    return (np.arange(n) % 30000).astype(np.int16) * 1e-6


@pytest.mark.slow
@pytest.mark.waits  # a writer process killed mid-run: about 4 s of wall time, 0.6 s of CPU
def test_kill_9_leaves_a_readable_interrupted_file(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", KILL_WRITER, str(tmp_path)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    partial = tmp_path / "killed.h5.partial"
    live: int | None = None
    reported = 0
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            reported = int(line)
            if live is None and reported >= 30_000:
                # SWMR: another process reads the file while it is being written
                rec = read_recording(partial)
                assert rec.complete is False and rec.exit_status == "interrupted"
                live = rec.displacement_m.size
                assert reported - FS * 1.0 <= live <= reported + FS * 0.5
                np.testing.assert_array_equal(rec.displacement_m, _expected_disp(live))
            if reported >= 46_100:  # 2.3 s in, long after the last document was written
                os.kill(proc.pid, signal.SIGKILL)
                break
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        stderr = proc.stderr.read() if proc.stderr else ""
    assert proc.returncode == -signal.SIGKILL, stderr
    assert live is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["killed.h5.partial"]

    # the documented plain-h5py recipe opens it
    with h5py.File(partial, "r", swmr=True) as f:
        assert f.attrs["exit_status"] == "running"
        assert f["raw/displacement"].shape[0] > 0

    rec = read_recording(partial)
    n = rec.displacement_m.size
    assert rec.complete is False
    assert rec.exit_status == "interrupted"
    assert "cut off" in rec.reason
    # at most one second lost, nothing invented
    assert reported - FS * 1.0 <= n <= reported + FS * 0.5, (n, reported)
    assert n >= live
    np.testing.assert_array_equal(rec.displacement_m, _expected_disp(n))
    np.testing.assert_array_equal(rec.force_V, np.arange(n) * 1e-3)
    assert [(s.start_sample, s.end_sample) for s in rec.steps] == [(2000, 10000)]
    assert [d["kind"] for d in rec.documents] == ["start", "step"]

    dst = recover_partial(partial)
    assert dst == tmp_path / "killed.h5" and not partial.exists()
    rec2 = read_recording(dst)
    assert rec2.complete is True
    assert rec2.exit_status == "interrupted"
    np.testing.assert_array_equal(rec2.displacement_m, rec.displacement_m)
    np.testing.assert_array_equal(rec2.force_V, rec.force_V)
    assert rec2.steps == rec.steps
    with h5py.File(dst, "r") as f:  # a recovered file opens without SWMR
        assert f.attrs["exit_status"] == "interrupted"


# -- the offline simulation as a recording ---------------------------------------------------------

def test_simulated_recording_metadata(sim_recording: Path, fast_config: StationConfig) -> None:
    rec = read_recording(sim_recording)
    cfg = fast_config
    assert sim_recording.suffix == ".h5" and rec.complete and rec.exit_status == "completed"
    assert rec.source == "simulate"
    assert rec.transducer_id == cfg.transducer.id == "TX5K-0001"
    assert rec.run_id == sim_recording.stem and rec.run_id.split("-")[1:3] == ["TX5K", "0001"]
    assert rec.sample_rate_hz == cfg.daq.sample_rate_hz
    assert rec.load_mass_kg == pytest.approx(25.717 + 0.45)
    assert rec.end_mass_kg == 0.12
    assert rec.sensitivity_V_per_N == pytest.approx(2.0e-6 * 1000.0)  # transducer x conditioner
    assert rec.capacity_N == 5000.0
    assert parse_config(rec.config, "snapshot") == cfg
    start = rec.documents[0]
    assert start["kind"] == "start" and start["plan"]["seed"] == 1
    assert start["plan"]["steps"] == [s.model_dump(exclude_none=True) for s in cfg.plan.steps]
    assert [d["kind"] for d in rec.documents] == ["start", "step", "step", "step", "stop"]


def test_simulated_recording_stores_adc_codes(sim_recording: Path, fast_config: StationConfig) -> None:
    lsb = 2 * 10.0 / 2**16
    with h5py.File(sim_recording, "r") as f:
        d, fc = f["raw/displacement"], f["raw/force"]
        assert d.dtype == fc.dtype == np.int16
        assert d.attrs["stored_unit"] == "count" and d.attrs["physical_unit"] == "m"
        assert fc.attrs["stored_unit"] == "count" and fc.attrs["physical_unit"] == "V"
        assert d.attrs["volts_per_count"] == fc.attrs["volts_per_count"] == lsb
        assert d.attrs["scale"] == pytest.approx(lsb / fast_config.displacement_sensor.gain_V_per_m)
        assert fc.attrs["scale"] == lsb


def test_simulated_steps_follow_the_plan(sim_recording: Path, fast_config: StationConfig) -> None:
    rec = read_recording(sim_recording)
    fs = rec.sample_rate_hz
    plan = fast_config.plan
    assert [(s.crank_frequency_hz, s.crank_radius_m) for s in rec.steps] == [
        (s.crank_frequency_hz, s.crank_radius_m) for s in plan.steps]
    ends = [0]
    for s in rec.steps:
        assert s.end_sample - s.start_sample == round(plan.record_s * fs)
        # settle time lies before every record window, and windows do not overlap
        assert s.start_sample - ends[-1] >= round(plan.settle_s * fs)
        assert s.usable
        ends.append(s.end_sample)
    assert ends[-1] < rec.displacement_m.size  # the crank ramps down after the last step


def test_simulated_signals_carry_the_physics(sim_recording: Path) -> None:
    """Displacement is the crank's sine at the step frequency; force_V carries the static preload."""
    rec = read_recording(sim_recording)
    g, M, S = 9.80665, rec.load_mass_kg + 0.12, rec.sensitivity_V_per_N
    # standstill pre-roll: the transducer carries the load's weight (negative with this sign convention)
    assert np.mean(rec.force_V[:2000]) == pytest.approx(-S * M * g, rel=0.01)
    assert np.std(rec.displacement_m[:2000]) < 2e-6
    for s in rec.steps:
        d, fv = rec.step_signals(s)
        t = np.arange(d.size) / rec.sample_rate_hz
        w = 2 * np.pi * s.crank_frequency_hz
        basis = np.column_stack([np.sin(w * t), np.cos(w * t), np.ones_like(t)])
        coef_d = np.linalg.lstsq(basis, d, rcond=None)[0]
        assert np.hypot(coef_d[0], coef_d[1]) == pytest.approx(s.crank_radius_m, rel=0.01)
        assert np.std(d - basis @ coef_d) < 0.02 * s.crank_radius_m
        coef_f = np.linalg.lstsq(basis, fv, rcond=None)[0]
        assert coef_f[2] == pytest.approx(-S * M * g, rel=0.02)
        if s.crank_frequency_hz < 10:  # far below resonance: F = M r w^2, in phase with displacement
            assert np.hypot(coef_f[0], coef_f[1]) == pytest.approx(S * M * s.crank_radius_m * w * w, rel=0.02)
            assert np.dot(coef_f[:2], coef_d[:2]) > 0


def test_simulation_is_reproducible_by_seed(tmp_path: Path, sim_recording: Path,
                                            fast_config: StationConfig) -> None:
    again = read_recording(simulate_run(fast_config, tmp_path / "a"))  # the config's seed, 1
    other = read_recording(simulate_run(fast_config, tmp_path / "b", seed=2))
    ref = read_recording(sim_recording)
    assert again.run_id != ref.run_id
    np.testing.assert_array_equal(again.displacement_m, ref.displacement_m)
    np.testing.assert_array_equal(again.force_V, ref.force_V)
    assert other.force_V.size == ref.force_V.size
    assert not np.array_equal(other.force_V, ref.force_V)
    assert other.documents[0]["plan"]["seed"] == 2


def test_simulation_beyond_the_limits_writes_nothing(tmp_path: Path, fast_config_dict: dict[str, Any]) -> None:
    fast_config_dict["plan"]["steps"][1]["crank_radius_m"] = 0.01  # 30 Hz x 10 mm: ~9 kN > 4 kN
    out = tmp_path / "out"
    with pytest.raises(LimitError, match=r"step 2 \(30 Hz, 0.01 m\): peak force"):
        simulate_run(parse_config(fast_config_dict), out)
    assert not out.exists() or not any(out.iterdir())


def test_simulation_without_end_mass_writes_nothing(tmp_path: Path, fast_config_dict: dict[str, Any]) -> None:
    del fast_config_dict["transducer"]["end_mass_kg"]
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match="end mass"):
        simulate_run(parse_config(fast_config_dict), out)
    assert not out.exists() or not any(out.iterdir())


def test_failed_simulation_is_kept_as_failed(tmp_path: Path, fast_config: StationConfig,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """A run that breaks off is not deleted: what was recorded stays, marked failed."""
    from drivers.rig.synth import RigSynth

    calls = {"n": 0}
    real_advance = RigSynth.advance

    def advance(self: RigSynth, n: int, f_end_hz: float) -> Any:
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("synthetic failure")
        return real_advance(self, n, f_end_hz)

    monkeypatch.setattr(RigSynth, "advance", advance)
    with pytest.raises(RuntimeError, match="synthetic failure"):
        simulate_run(fast_config, tmp_path)
    files = list(tmp_path.iterdir())
    assert len(files) == 1 and files[0].suffix == ".h5"
    rec = read_recording(files[0])
    assert rec.complete is True and rec.exit_status == "failed"
    assert "synthetic failure" in rec.reason
    assert rec.displacement_m.size > 0


def test_time_stamps_are_iso_8601(sim_recording: Path) -> None:
    rec = read_recording(sim_recording)
    start, end = _iso(rec.start_time), _iso(rec.end_time)
    assert start <= end
    assert abs((datetime.now(start.tzinfo) - start).total_seconds()) < 3600
    assert rec.documents[0]["time"] == rec.start_time
    assert rec.documents[-1]["time"] == rec.end_time
