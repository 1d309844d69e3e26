"""Results beside a closed recording: the sidecar folder, atomic writes, old in-file results, a kill
or a full disk while results are written."""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from station.errors import StationError
from station.recording import RecordingWriter, read_recording, read_result, read_stored, write_result
from station.recording.stored import ResultWriteError, read_processed, result_path, sidecar_dir, stale_temporaries
from tests.disk_support import mounted_tmpfs
from tests.recording_support import FLOAT_CHANNELS, killed_in_place_write, run_metadata, small_recording


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture
def rec(tmp_path: Path) -> Path:
    return small_recording(tmp_path)


def test_results_live_beside_the_recording_which_is_never_opened_for_writing(rec: Path) -> None:
    before, mtime = _digest(rec), rec.stat().st_mtime_ns
    assert read_result(rec, "fit") is None and read_stored(rec) == {}
    where = write_result(rec, "fit", {"k_f": 2.9e7, "ok": True}, {"residual": np.arange(4.0)})
    assert where == sidecar_dir(rec) / "results.fit.h5" == result_path(rec, "fit")
    assert sidecar_dir(rec).name == rec.name[: -len(".h5")] + ".results"
    write_result(rec, "frf-step+1", {"n": np.int64(3)}, {"H": np.array([1 + 2j, 3 - 1j])}, group="processed")
    s = read_stored(rec)["fit"]
    assert s.doc == {"k_f": 2.9e7, "ok": True} and list(s.arrays) == ["residual"] and s.source == str(where)
    np.testing.assert_array_equal(s.arrays["residual"], np.arange(4.0))
    write_result(rec, "fit", {"k_f": 3.0e7})  # replaced as a whole, arrays included
    assert read_stored(rec)["fit"].arrays == {} and read_result(rec, "fit") == {"k_f": 3.0e7}
    p = read_stored(rec, "processed")["frf-step+1"]
    assert p.doc == {"n": 3} and p.arrays["H"].tolist() == [1 + 2j, 3 - 1j]
    with h5py.File(where, "r") as f:  # readable with plain h5py, and says what it is
        assert f.attrs["format"] == "sinecal-result" and f.attrs["recording"] == rec.name
        assert json.loads(f.attrs["json"]) == {"k_f": 3.0e7}
    assert _digest(rec) == before and rec.stat().st_mtime_ns == mtime
    assert sorted(q.name for q in sidecar_dir(rec).iterdir()) == ["processed.frf-step+1.h5", "results.fit.h5"]


def test_old_recordings_with_results_inside_still_read_and_the_sidecar_wins(rec: Path) -> None:
    with h5py.File(rec, "r+") as f:  # what the station wrote before results moved beside the recording
        g = f.require_group("results").create_group("identify_fd_sdof")
        g.attrs.update({"json": json.dumps({"k_f": 1.0}), "written": "2025-01-01T00:00:00.000+00:00"})
        p = f.require_group("processed").create_group("steps")
        p.attrs.update({"json": json.dumps({"steps": []}), "written": "2025-01-01T00:00:00.000+00:00"})
        p.create_dataset("H", data=np.array([1j]))
        f.require_group("results").create_group("empty")  # a group without a document is not a result
    before = _digest(rec)
    old = read_stored(rec)
    assert set(old) == {"identify_fd_sdof"} and old["identify_fd_sdof"].source.endswith(":/results/identify_fd_sdof")
    assert read_processed(rec) is not None and read_processed(rec).arrays["H"].tolist() == [1j]  # type: ignore[union-attr]
    write_result(rec, "identify_fd_sdof", {"k_f": 2.0})
    assert read_result(rec, "identify_fd_sdof") == {"k_f": 2.0}
    assert read_stored(rec)["identify_fd_sdof"].doc == {"k_f": 2.0}
    assert _digest(rec) == before  # the old in-file result is read, never rewritten


@pytest.mark.parametrize("group", ["raw", "steps", "config", "/", ""])
def test_results_only_in_the_result_groups(rec: Path, group: str) -> None:
    with pytest.raises(ValueError, match="results go into one of the groups"):
        write_result(rec, "displacement", {"x": 1}, group=group)


@pytest.mark.parametrize("name", ["", "a/b", "../x", "x y", "a.b"])
def test_result_names_are_plain(rec: Path, name: str) -> None:
    with pytest.raises(ValueError, match="result name must be alphanumeric"):
        write_result(rec, name, {})
    assert not sidecar_dir(rec).exists()


def test_an_identical_result_asked_to_be_kept_is_not_written_again(rec: Path) -> None:
    doc = {"gap_V": 1.5e-4, "effects": ["mains"]}
    q = write_result(rec, "discrepancy", doc, keep_identical=True)
    before = q.stat().st_mtime_ns, os.stat(q).st_ino
    time.sleep(0.01)  # a rewrite would show in the modification time (ns) and the inode (a new file renamed)
    assert write_result(rec, "discrepancy", dict(doc), keep_identical=True) == q
    assert (q.stat().st_mtime_ns, os.stat(q).st_ino) == before
    # a different document, or one written without the option, replaces it
    write_result(rec, "discrepancy", {**doc, "gap_V": 1.6e-4}, keep_identical=True)
    assert os.stat(q).st_ino != before[1] and read_result(rec, "discrepancy") == {**doc, "gap_V": 1.6e-4}
    ino = os.stat(q).st_ino
    write_result(rec, "discrepancy", {**doc, "gap_V": 1.6e-4})
    assert os.stat(q).st_ino != ino
    # a result with arrays is always written again (the arrays are not compared)
    a = write_result(rec, "fit", doc, {"x": np.arange(3.0)}, keep_identical=True)
    ino = os.stat(a).st_ino
    write_result(rec, "fit", doc, {"x": np.arange(3.0)}, keep_identical=True)
    assert os.stat(a).st_ino != ino


def test_results_only_for_complete_recordings(tmp_path: Path) -> None:
    w = RecordingWriter(tmp_path, run_metadata(), FLOAT_CHANNELS)
    w.abandon()
    with pytest.raises(StationError, match="only for complete recordings"):
        write_result(w.partial_path, "fit", {})
    with pytest.raises(StationError, match="no such recording"):
        write_result(tmp_path / "nothing.h5", "fit", {})


def test_a_failed_write_leaves_the_earlier_result_and_no_temporary(rec: Path) -> None:
    write_result(rec, "fit", {"v": 1})
    with pytest.raises(TypeError):
        write_result(rec, "fit", {"v": object()})  # not JSON: refused before anything is written
    with pytest.raises(TypeError):
        write_result(rec, "fit", {"v": 2}, {"bad": np.array([object()])})  # fails inside the HDF5 write
    assert read_result(rec, "fit") == {"v": 1}
    assert [q.name for q in sidecar_dir(rec).iterdir()] == ["results.fit.h5"]


# -- a kill at any instant ---------------------------------------------------------------------------

def _writer_loop(rec: Path, seed: int) -> None:
    """In a forked child: write results until killed (each one's payload checks its own arrays)."""
    rng = np.random.default_rng(seed)
    i = 0
    while True:
        a = rng.standard_normal(int(rng.integers(10, 40_000)))
        for name, group in (("identify_fd_sdof", "results"), ("steps", "processed"), ("discrepancy", "results")):
            write_result(rec, name, {"i": i, "n": a.size, "sum": float(a.sum())}, {"a": a}, group=group)
        i += 1


def _consistent(rec: Path) -> dict[str, Any]:
    out = {}
    for group in ("results", "processed"):
        for name, s in read_stored(rec, group).items():
            a = s.arrays["a"]
            assert a.size == s.doc["n"] and float(a.sum()) == s.doc["sum"], (group, name)
            out[f"{group}/{name}"] = s.doc["i"]
    return out


@pytest.mark.slow
def test_thirty_kills_while_results_are_written_leave_everything_readable(rec: Path) -> None:
    """SIGKILL of a process writing results at 30 random instants: the recording is untouched and
    every result reads whole (the last complete one of each name); no kill corrupts anything."""
    digest, rng = _digest(rec), random.Random(7)
    a = np.arange(5.0)
    for name, group in (("identify_fd_sdof", "results"), ("steps", "processed"), ("discrepancy", "results")):
        write_result(rec, name, {"i": -1, "n": a.size, "sum": float(a.sum())}, {"a": a}, group=group)
    names = set(_consistent(rec))
    for k in range(30):
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child is killed
            try:
                _writer_loop(rec, k)
            finally:
                os._exit(1)
        time.sleep(rng.uniform(0.002, 0.05))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        assert _digest(rec) == digest
        assert read_recording(rec).complete
        assert set(_consistent(rec)) == names  # each result whole: the last complete one of its name
    leftovers = stale_temporaries(rec.parent)  # what a kill mid-write leaves: never read as a result
    assert leftovers and all(q.name.startswith(".") for q in leftovers)  # some kills did land mid-write


# -- a full disk ------------------------------------------------------------------------------------

def test_a_full_disk_while_results_are_written_loses_nothing(tmp_path: Path) -> None:
    with mounted_tmpfs(tmp_path, 2) as disk:
        rec = small_recording(disk)
        digest = _digest(rec)
        write_result(rec, "identify_fd_sdof", {"k_f": 2.9e7}, {"a": np.arange(100.0)})
        filler = disk / "filler"
        with open(filler, "wb") as f:  # fill the file system to the last block
            try:
                while True:
                    f.write(b"\0" * 65536)
                    f.flush()
            except OSError:
                pass
        for name in ("identify_fd_sdof", "discrepancy"):
            with pytest.raises(ResultWriteError, match="not written") as exc:
                write_result(rec, name, {"k_f": 3.0e7}, {"a": np.arange(200_000.0)})
            assert "recording and any earlier result are unchanged" in str(exc.value)
        assert _digest(rec) == digest and read_recording(rec).complete
        s = read_stored(rec)
        assert set(s) == {"identify_fd_sdof"} and s["identify_fd_sdof"].doc == {"k_f": 2.9e7}
        assert [q.name for q in sidecar_dir(rec).iterdir()] == ["results.identify_fd_sdof.h5"]
        filler.unlink()
        write_result(rec, "discrepancy", {"ok": True})
        assert read_result(rec, "discrepancy") == {"ok": True}


# -- recordings damaged by the old in-place writes -------------------------------------------------

def test_a_recording_left_flagged_by_a_killed_in_place_write_is_repaired_at_start(tmp_path: Path) -> None:
    from station.recording.repair import check_folder

    rec = small_recording(tmp_path)
    good = read_recording(rec)
    killed_in_place_write(rec)
    with pytest.raises(OSError, match="already open for write"):
        h5py.File(rec, "r")
    (tmp_path / "garbage.h5").write_bytes(b"not an HDF5 file" * 100)
    cut = tmp_path / "cut.h5"  # flagged and cut short: clearing the flag does not make it readable
    cut.write_bytes(rec.read_bytes()[:3000])
    cut_bytes = cut.read_bytes()
    write_result(rec, "steps", {"n": 1}, group="processed")
    tmp = next(iter(sidecar_dir(rec).iterdir())).with_name(".results.fit.h5.tmp-1-abcdef")
    tmp.write_bytes(b"cut off")
    out = check_folder(tmp_path)
    assert out.repaired == (rec.name,) and [n for n, _ in out.unreadable] == ["cut.h5", "garbage.h5"]
    assert cut.read_bytes() == cut_bytes  # its superblock put back as it was: left for a person to look at
    assert out.temporaries_removed == (f"{sidecar_dir(rec).name}/{tmp.name}",) and not tmp.exists()
    with h5py.File(rec, "r") as f:  # opens normally again
        assert "identify_fd_sdof" in f["results"]
    again = read_recording(rec)
    assert again.complete and again.exit_status == "completed" and again.steps == good.steps
    np.testing.assert_array_equal(again.force_V, good.force_V)
    np.testing.assert_array_equal(again.displacement_m, good.displacement_m)
    assert read_result(rec, "identify_fd_sdof") == {"k_f": 1.0} and read_result(rec, "steps", group="processed")
    assert (tmp_path / "garbage.h5").read_bytes()[:6] == b"not an"  # named, never deleted
    assert check_folder(tmp_path).repaired == ()  # nothing left to repair


# -- one result type, stored and read back unchanged ------------------------------------------------

@pytest.mark.parametrize("method", ["fd", "oe"])
def test_an_identification_round_trips_through_the_sidecar_with_its_covariance(sim_recording: Path, tmp_path: Path,
                                                                               method: str) -> None:
    from station.ident.identify import identify_recording, store_result
    from station.ident.result import IdentificationResult

    rec = tmp_path / sim_recording.name
    rec.write_bytes(sim_recording.read_bytes())
    res = identify_recording(read_recording(rec), method)
    cov = res.covariance
    assert cov is not None and cov.names == tuple(n for n, p in res.parameters.items() if p.value is not None)
    assert cov.units == tuple(res.parameters[n].unit for n in cov.names)
    for n in cov.names:  # the diagonal is the stated standard uncertainty squared
        assert cov.std(n) == pytest.approx(res.parameters[n].std, rel=1e-12)
    c = cov.array
    assert np.allclose(c, c.T) and np.all(np.linalg.eigvalsh(c) > -1e-12 * np.abs(c).max())
    assert abs(c[0, 1]) > 0  # S and k_f are correlated: the matrix is more than the stds
    store_result(rec, res)
    back = IdentificationResult.from_dict(read_result(rec, res.result_name) or {})
    if method == "oe":  # OE has no chi^2/dof (NaN, stored as null): compare it apart
        assert np.isnan(back.fit.chi2_per_dof) and np.isnan(res.fit.chi2_per_dof)
        back = replace(back, fit=res.fit)
    assert back == res
    assert back.covariance is not None and np.array_equal(back.covariance.array, c)
