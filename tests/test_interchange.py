"""The sinecal-csv interchange format: import of runs recorded on other DAQs, export, round trips,
and every malformed input refused with file, line and reason, leaving nothing behind."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from station.errors import RecordingFormatError, StationError
from station.interchange import HEADER, export_run, import_run
from station.recording import ChannelSpec, RecordingWriter, RunMetadata, read_recording

G = 9.80665
RADIUS = 0.002
TOP_MASS = 26.167
END_MASS = 0.12
SENS = -0.002  # V/N of the recorded signal: this DAQ's conditioner inverts


@dataclass
class Run:
    """A run folder written by ``make_run`` and the samples it holds."""

    folder: Path
    doc: dict[str, Any]
    fs: float
    disp: list[np.ndarray] = field(default_factory=list)
    force: list[np.ndarray] = field(default_factory=list)

    @property
    def yaml_path(self) -> Path:
        return self.folder / "RUN.yaml"

    def csv(self, i: int) -> Path:
        return self.folder / self.doc["steps"][i]["file"]

    def write_doc(self) -> None:
        self.yaml_path.write_text(yaml.safe_dump(self.doc, sort_keys=False), encoding="utf-8")


def _rows(t: np.ndarray, d: np.ndarray, f: np.ndarray) -> str:
    return "".join(f"{a!r},{b!r},{c!r}\n" for a, b, c in zip(t.tolist(), d.tolist(), f.tolist(), strict=True))


def make_run(folder: Path, *, fs: float = 2000.0, steps: tuple[tuple[float, int], ...] = ((5.0, 400), (20.0, 300)),
             t0: float = 0.0, end_mass: float | None = END_MASS) -> Run:
    """A valid run: the crank's sine and a force signal with the static preload, inverted polarity."""
    folder.mkdir(parents=True, exist_ok=True)
    M = TOP_MASS + (end_mass or 0.0)
    entries = []
    run = Run(folder, {}, fs)
    k0 = round(t0 * fs)
    for i, (freq, n) in enumerate(steps):
        k = np.arange(k0, k0 + n)
        t = k / fs
        w = 2 * math.pi * freq
        d = RADIUS * np.sin(w * t)
        f = SENS * M * (G + RADIUS * w * w * np.sin(w * t)) + 0.013
        name = f"step{i:02d}.csv"
        (folder / name).write_text(HEADER + "\n" + _rows(t, d, f), encoding="utf-8")
        entries.append({"file": name, "crank_frequency_hz": freq})
        run.disp.append(d)
        run.force.append(f)
        k0 += n + 1000
    run.doc = {"format": "sinecal-csv", "format_version": 1, "sample_rate_hz": fs, "crank_radius_m": RADIUS,
               "top_mass_kg": TOP_MASS,
               **({"end_mass_kg": end_mass} if end_mass is not None else {}),
               "transducer": {"id": "EXT-42", "capacity_N": 5000.0, "sensitivity_V_per_N": SENS},
               "steps": entries}
    run.write_doc()
    return run


@pytest.fixture
def run(tmp_path: Path) -> Run:
    return make_run(tmp_path / "elsewhere")


@pytest.fixture
def out(tmp_path: Path) -> Path:
    """An output folder that already holds a recording (which must stay as it is)."""
    d = tmp_path / "recordings"
    d.mkdir()
    (d / "earlier.h5").write_bytes(b"an earlier recording")
    return d


def _listing(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()} if folder.exists() else {}


# -- import --------------------------------------------------------------------------------------

def test_import_gives_a_complete_recording_of_the_same_samples(run: Run, out: Path) -> None:
    path = import_run(run.yaml_path, out)
    assert path.parent == out and path.suffix == ".h5"
    assert sorted(p.name for p in out.iterdir()) == sorted(["earlier.h5", path.name])
    assert (out / "earlier.h5").read_bytes() == b"an earlier recording"
    rec = read_recording(path)
    assert rec.complete and rec.exit_status == "completed"
    assert rec.source == "import"
    assert rec.transducer_id == "EXT-42" and rec.run_id.split("-")[1:3] == ["EXT", "42"]
    assert rec.sample_rate_hz == 2000.0
    assert (rec.load_mass_kg, rec.end_mass_kg, rec.capacity_N) == (TOP_MASS, END_MASS, 5000.0)
    assert rec.sensitivity_V_per_N == SENS  # polarity kept
    assert rec.config == run.doc  # RUN.yaml is the config snapshot
    np.testing.assert_array_equal(rec.displacement_m, np.concatenate(run.disp))
    np.testing.assert_array_equal(rec.force_V, np.concatenate(run.force))
    assert [(s.crank_frequency_hz, s.crank_radius_m, s.start_sample, s.end_sample) for s in rec.steps] == [
        (5.0, RADIUS, 0, 400), (20.0, RADIUS, 400, 700)]
    for s, d, f in zip(rec.steps, run.disp, run.force, strict=True):
        sd, sf = rec.step_signals(s)
        np.testing.assert_array_equal(sd, d)
        np.testing.assert_array_equal(sf, f)
    docs = rec.documents
    assert [d["kind"] for d in docs] == ["start", "step", "step", "stop"]
    assert docs[0]["plan"]["kind"] == "import" and docs[0]["plan"]["format"] == "sinecal-csv"
    assert [d["file"] for d in docs[1:3]] == ["step00.csv", "step01.csv"]
    assert docs[1]["t0_s"] == 0.0 and docs[2]["t0_s"] == pytest.approx(1400 / 2000.0)


def test_import_keeps_the_offset_of_the_force_signal(run: Run, out: Path) -> None:
    rec = read_recording(import_run(run.yaml_path, out))
    # the static preload (weight x sensitivity) stays in the signal, with the DAQ's polarity
    assert np.mean(rec.step_signals(rec.steps[0])[1]) == pytest.approx(SENS * (TOP_MASS + END_MASS) * G + 0.013,
                                                                       rel=1e-3)


def test_end_mass_is_optional(tmp_path: Path, out: Path) -> None:
    run = make_run(tmp_path / "r", end_mass=None)
    rec = read_recording(import_run(run.yaml_path, out))
    assert rec.end_mass_kg is None


def test_import_creates_the_output_folder(run: Run, tmp_path: Path) -> None:
    path = import_run(run.yaml_path, tmp_path / "new" / "dir")
    assert path.parent == tmp_path / "new" / "dir"


def test_step_time_base_may_start_anywhere(tmp_path: Path, out: Path) -> None:
    run = make_run(tmp_path / "r", t0=12.5)
    rec = read_recording(import_run(run.yaml_path, out))
    assert rec.documents[1]["t0_s"] == 12.5
    np.testing.assert_array_equal(rec.displacement_m[:400], run.disp[0])


def test_tolerated_layout_variations(run: Run, out: Path) -> None:
    """CRLF line ends, blank lines, blanks around cells and in the header are accepted."""
    text = run.csv(0).read_text(encoding="utf-8")
    lines = text.splitlines()
    lines[0] = "t_s, displacement_m, force_V"
    lines[3] = " " + lines[3].replace(",", " , ")
    lines.insert(5, "")
    run.csv(0).write_bytes(("\r\n".join(lines) + "\r\n\r\n").encode())
    rec = read_recording(import_run(run.yaml_path, out))
    np.testing.assert_array_equal(rec.force_V[:400], run.force[0])


def test_sample_rate_tolerance(tmp_path: Path, out: Path) -> None:
    """Time steps may deviate from 1/fs by less than 0.1 %: a DAQ clock 0.05 % fast is accepted."""
    run = make_run(tmp_path / "ok", steps=((5.0, 50),))
    run.doc["sample_rate_hz"] = 2000.0 * 1.0005
    run.write_doc()
    import_run(run.yaml_path, out)
    run.doc["sample_rate_hz"] = 2000.0 * 1.002
    run.write_doc()
    with pytest.raises(RecordingFormatError, match="sample interval"):
        import_run(run.yaml_path, out)


# -- malformed input ------------------------------------------------------------------------------

def _edit_csv(i: int, fn: Callable[[list[str]], list[str] | str]) -> Callable[[Run], Path]:
    def apply(run: Run) -> Path:
        p = run.csv(i)
        lines = p.read_text(encoding="utf-8").splitlines()
        res = fn(lines)
        p.write_text(res if isinstance(res, str) else "\n".join(res) + "\n", encoding="utf-8")
        return p

    return apply


def _set_line(n: int, text: str) -> Callable[[list[str]], list[str]]:
    def fn(lines: list[str]) -> list[str]:
        lines[n - 1] = text
        return lines

    return fn


def _retime(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[list[str]], list[str]]:
    def apply(lines: list[str]) -> list[str]:
        rows = [ln.split(",") for ln in lines[1:]]
        t = fn(np.array([float(r[0]) for r in rows]))
        return [lines[0]] + [f"{ti!r},{r[1]},{r[2]}" for ti, r in zip(t.tolist(), rows, strict=True)]

    return apply


def _nudge(k: int, dt: float) -> Callable[[np.ndarray], np.ndarray]:
    def fn(t: np.ndarray) -> np.ndarray:
        t = t.copy()
        t[k:] += dt
        return t

    return fn


def _drop_column(lines: list[str]) -> list[str]:
    return ["t_s,displacement_m"] + [ln.rsplit(",", 1)[0] for ln in lines[1:]]


CSV_CASES: dict[str, tuple[Callable[[Run], Path], str]] = {
    "missing column": (_edit_csv(1, _drop_column),
                       "line 1: header 't_s,displacement_m,force_V' expected, got 't_s,displacement_m'"),
    "columns swapped": (_edit_csv(0, _set_line(1, "t_s,force_V,displacement_m")),
                        "line 1: header 't_s,displacement_m,force_V' expected"),
    "no header": (_edit_csv(0, lambda lines: lines[1:]), "line 1: header 't_s,displacement_m,force_V' expected"),
    "non-numeric cell": (_edit_csv(1, _set_line(57, "0.5,0.001,abc")),
                         "line 57: column force_V: a number expected, got 'abc'"),
    "non-numeric time": (_edit_csv(0, _set_line(3, "1 ms,0.001,0.5")), "line 3: column t_s: a number expected"),
    "empty cell": (_edit_csv(0, _set_line(10, "0.0045,,0.5")),
                   "line 10: column displacement_m: a number expected, got ''"),
    "nan cell": (_edit_csv(0, _set_line(4, "0.001,nan,0.5")),
                 "line 4: column displacement_m: a finite number expected, got 'nan'"),
    "inf cell": (_edit_csv(0, _set_line(4, "0.001,0.0,-inf")),
                 "line 4: column force_V: a finite number expected, got '-inf'"),
    "comment in a cell": (_edit_csv(0, _set_line(6, "0.002,0.0,0.5 # spike")),
                          "line 6: column force_V: a number expected, got '0.5 # spike'"),
    "commented-out row": (_edit_csv(0, _set_line(6, "#0.002,0.0,0.5")), "line 6: column t_s: a number expected"),
    "unequal lengths (short row)": (_edit_csv(1, lambda lines: [*lines[:-1], lines[-1].rsplit(",", 1)[0]]),
                                    "line 301: 3 cells expected, got 2"),
    "unequal lengths (long row)": (_edit_csv(0, _set_line(20, "0.009,0.0,0.5,0.7")),
                                   "line 20: 3 cells expected, got 4"),
    "semicolons": (_edit_csv(0, lambda lines: [ln.replace(",", ";") for ln in lines]),
                   "line 1: header 't_s,displacement_m,force_V' expected, got 't_s;displacement_m;force_V'"),
    "non-uniform time (gap)": (_edit_csv(1, _retime(_nudge(150, 0.0004))),
                               "line 152: non-uniform time: t_s steps by 0.0009"),
    "non-uniform time (repeated row)": (_edit_csv(0, lambda lines: [*lines[:100], lines[99], *lines[100:]]),
                                        "line 101: non-uniform time: t_s steps by 0 s"),
    "non-uniform time (backwards)": (_edit_csv(0, _retime(_nudge(200, -0.001))),
                                     "line 202: non-uniform time: t_s steps by -0.0005 s"),
    "wrong rate": (_edit_csv(1, _retime(lambda t: t * 2)),
                   "sample interval 0.001 s (1000 Hz) found, RUN.yaml says sample_rate_hz 2000 (interval 0.0005 s)"),
    "line numbers count blank lines": (
        _edit_csv(0, lambda lines: [*lines[:3], "", "", *lines[3:8], "0.0035,x,1", *lines[8:]]),
        "line 11: column displacement_m: a number expected, got 'x'"),
    "one sample": (_edit_csv(0, lambda lines: lines[:2]), "at least 2 samples expected, got 1"),
    "empty file": (_edit_csv(0, lambda lines: ""), "line 1: header 't_s,displacement_m,force_V' expected, "
                                                   "got 'an empty file'"),
}


@pytest.mark.parametrize("case", list(CSV_CASES))
def test_malformed_step_file_is_refused_with_file_line_and_reason(run: Run, out: Path, case: str) -> None:
    damage, expected = CSV_CASES[case]
    bad_file = damage(run)
    before = _listing(out)
    with pytest.raises(RecordingFormatError) as exc:
        import_run(run.yaml_path, out)
    msg = str(exc.value)
    assert msg.startswith(str(bad_file.resolve())), msg
    assert expected in msg, msg
    assert _listing(out) == before


def _doc_edit(fn: Callable[[dict[str, Any]], None]) -> Callable[[Run], None]:
    def apply(run: Run) -> None:
        fn(run.doc)
        run.write_doc()

    return apply


def _raw_yaml(text: str) -> Callable[[Run], None]:
    def apply(run: Run) -> None:
        run.yaml_path.write_text(text, encoding="utf-8")

    return apply


def _nan_sensitivity(run: Run) -> None:
    run.doc["transducer"]["sensitivity_V_per_N"] = "NAN"
    run.yaml_path.write_text(yaml.safe_dump(run.doc).replace("'NAN'", ".nan"), encoding="utf-8")


RUN_CASES: dict[str, tuple[Callable[[Run], None], str]] = {
    "wrong format": (_doc_edit(lambda d: d.update(format="other-csv")),
                     "format 'sinecal-csv' version 1 or 2 expected, got 'other-csv' version 1"),
    "wrong version": (_doc_edit(lambda d: d.update(format_version=3)),
                      "format 'sinecal-csv' version 1 or 2 expected, got 'sinecal-csv' version 3"),
    "no format": (_doc_edit(lambda d: d.pop("format")), "format 'sinecal-csv' version 1 or 2 expected, got None"),
    "unknown key": (_doc_edit(lambda d: d.update(gain=1000)), "gain: Extra inputs are not permitted (received 1000)"),
    "unknown step key": (_doc_edit(lambda d: d["steps"][0].update(radius=0.01)),
                         "steps.0.radius: Extra inputs are not permitted"),
    "step radius in v1": (_doc_edit(lambda d: d["steps"][0].update(crank_radius_m=0.01)),
                          "steps.0.crank_radius_m: not part of version 1 (one crank radius per run); write "
                          "format_version: 2"),
    "rig limits in v1": (_doc_edit(lambda d: d.update(rig={"crank_frequency_hz": {"min": 1, "max": 100},
                                                           "crank_radius_m": {"min": 1e-4, "max": 0.05}})),
                         "rig: not part of version 1"),
    "no radius in v1": (_doc_edit(lambda d: d.pop("crank_radius_m")), "crank_radius_m: Field required"),
    "v2 step without radius": (_doc_edit(lambda d: (d.pop("crank_radius_m"), d.update(format_version=2),
                                                     d["steps"][0].update(crank_radius_m=0.01))),
                               "steps.1.crank_radius_m: no crank radius for this step"),
    "missing rate": (_doc_edit(lambda d: d.pop("sample_rate_hz")), "sample_rate_hz: Field required"),
    "missing transducer id": (_doc_edit(lambda d: d["transducer"].pop("id")), "transducer.id: Field required"),
    "negative rate": (_doc_edit(lambda d: d.update(sample_rate_hz=-2000)),
                      "sample_rate_hz: Input should be greater than 0 (received -2000)"),
    "zero radius": (_doc_edit(lambda d: d.update(crank_radius_m=0)),
                    "crank_radius_m: Input should be greater than 0 (received 0)"),
    "heavy end mass": (_doc_edit(lambda d: d.update(end_mass_kg=500)),
                       "end_mass_kg: Input should be less than or equal to 100 (received 500)"),
    "text frequency": (_doc_edit(lambda d: d["steps"][1].update(crank_frequency_hz="fast")),
                       "steps.1.crank_frequency_hz: Input should be a valid number"),
    "zero sensitivity": (_doc_edit(lambda d: d["transducer"].update(sensitivity_V_per_N=0)),
                         "transducer.sensitivity_V_per_N must not be 0"),
    "nan sensitivity": (_nan_sensitivity, "transducer.sensitivity_V_per_N: Input should be a finite number"),
    "bad transducer id": (_doc_edit(lambda d: d["transducer"].update(id="EXT 42/1")),
                          "transducer.id: String should match pattern"),
    "no steps": (_doc_edit(lambda d: d.update(steps=[])), "steps: List should have at least 1 item"),
    "step file outside": (_doc_edit(lambda d: d["steps"][1].update(file="../step01.csv")),
                          "step file '../step01.csv' must lie beside RUN.yaml"),
    "invalid YAML": (_raw_yaml("format: sinecal-csv\nsteps: [\n"), "not valid YAML"),
    "not a mapping": (_raw_yaml("- format: sinecal-csv\n"), "a mapping was expected, got list"),
}


@pytest.mark.parametrize("case", list(RUN_CASES))
def test_malformed_run_file_is_refused_with_key_and_reason(run: Run, out: Path, case: str) -> None:
    damage, expected = RUN_CASES[case]
    damage(run)
    before = _listing(out)
    with pytest.raises(RecordingFormatError) as exc:
        import_run(run.yaml_path, out)
    msg = str(exc.value)
    assert msg.startswith(f"{run.yaml_path}: "), msg
    assert expected in msg, msg
    assert _listing(out) == before


def test_missing_step_file(run: Run, out: Path) -> None:
    run.csv(1).unlink()
    with pytest.raises(RecordingFormatError) as exc:
        import_run(run.yaml_path, out)
    assert str(exc.value) == f"{run.csv(1).resolve()}: cannot read: No such file or directory"
    assert _listing(out) == {"earlier.h5": b"an earlier recording"}


def test_missing_run_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingFormatError, match=r"RUN\.yaml: cannot read"):
        import_run(tmp_path / "RUN.yaml", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_refused_import_does_not_create_the_output_folder(run: Run, tmp_path: Path) -> None:
    CSV_CASES["non-numeric cell"][0](run)
    with pytest.raises(RecordingFormatError):
        import_run(run.yaml_path, tmp_path / "fresh")
    assert not (tmp_path / "fresh").exists()


def test_failure_while_writing_leaves_nothing_behind(run: Run, out: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = RecordingWriter.add_step
    calls = {"n": 0}

    def add_step(self: RecordingWriter, **kw: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(28, "No space left on device")
        real(self, **kw)

    monkeypatch.setattr(RecordingWriter, "add_step", add_step)
    before = _listing(out)
    with pytest.raises(OSError, match="No space left"):
        import_run(run.yaml_path, out)
    assert calls["n"] == 2
    assert _listing(out) == before


# -- export and round trips ------------------------------------------------------------------------

def test_export_writes_the_interchange_format(sim_recording_one_radius: Path, tmp_path: Path) -> None:
    rec = read_recording(sim_recording_one_radius)
    run_yaml = export_run(sim_recording_one_radius, tmp_path)
    assert run_yaml == tmp_path / rec.run_id / "RUN.yaml"
    assert sorted(p.name for p in tmp_path.iterdir()) == [rec.run_id]
    doc = yaml.safe_load(run_yaml.read_text(encoding="utf-8"))
    rig = rec.config["rig"]
    assert doc == {"format": "sinecal-csv", "format_version": 2, "sample_rate_hz": rec.sample_rate_hz,
                   "top_mass_kg": rec.load_mass_kg, "end_mass_kg": rec.end_mass_kg,
                   "rig": {"crank_frequency_hz": rig["crank_frequency_hz"], "crank_radius_m": rig["crank_radius_m"],
                           "peak_force_fraction": rig["peak_force_fraction"]},
                   "transducer": {"id": "TX5K-0001", "capacity_N": 5000.0,
                                  "sensitivity_V_per_N": rec.sensitivity_V_per_N},
                   "steps": [{"file": f"step{i:02d}.csv", "crank_frequency_hz": s.crank_frequency_hz,
                              "crank_radius_m": 0.0004} for i, s in enumerate(rec.steps)]}
    assert sorted(p.name for p in run_yaml.parent.iterdir()) == ["RUN.yaml", "step00.csv", "step01.csv",
                                                                 "step02.csv"]
    for s in rec.steps:
        lines = (run_yaml.parent / f"step{s.index:02d}.csv").read_text(encoding="utf-8").splitlines()
        assert lines[0] == "t_s,displacement_m,force_V"
        assert len(lines) == 1 + s.end_sample - s.start_sample
        data = np.array([[float(c) for c in ln.split(",")] for ln in lines[1:]])
        np.testing.assert_array_equal(data[:, 0], np.arange(s.start_sample, s.end_sample) / rec.sample_rate_hz)
        d, f = rec.step_signals(s)
        np.testing.assert_array_equal(data[:, 1], d)
        np.testing.assert_array_equal(data[:, 2], f)


def test_round_trip_simulate_export_import(sim_recording_one_radius: Path, tmp_path: Path) -> None:
    original = read_recording(sim_recording_one_radius)
    imported = read_recording(import_run(export_run(sim_recording_one_radius, tmp_path / "x"), tmp_path / "r"))
    assert imported.run_id != original.run_id and imported.source == "import"
    for attr in ("transducer_id", "sample_rate_hz", "load_mass_kg", "end_mass_kg", "sensitivity_V_per_N",
                 "capacity_N"):
        assert getattr(imported, attr) == getattr(original, attr), attr
    assert len(imported.steps) == len(original.steps) == 3
    for a, b in zip(original.steps, imported.steps, strict=True):
        assert (b.crank_frequency_hz, b.crank_radius_m) == (a.crank_frequency_hz, a.crank_radius_m)
        assert b.end_sample - b.start_sample == a.end_sample - a.start_sample
        for x, y in zip(original.step_signals(a), imported.step_signals(b), strict=True):
            np.testing.assert_array_equal(y, x)  # the same samples, bit for bit
    assert imported.displacement_m.size == sum(s.end_sample - s.start_sample for s in original.steps)


def test_round_trip_import_export(run: Run, out: Path, tmp_path: Path) -> None:
    rec = read_recording(import_run(run.yaml_path, out))
    run_yaml = export_run(rec.path, tmp_path / "back")
    doc = yaml.safe_load(run_yaml.read_text(encoding="utf-8"))
    # v2 now: the run's radius on every step
    assert doc["format_version"] == 2 and "crank_radius_m" not in doc
    assert ({k: v for k, v in doc.items() if k not in ("steps", "format_version")}
            == {k: v for k, v in run.doc.items() if k not in ("steps", "format_version", "crank_radius_m")})
    assert [(s["crank_frequency_hz"], s["crank_radius_m"]) for s in doc["steps"]] == [(5.0, RADIUS), (20.0, RADIUS)]
    again = read_recording(import_run(run_yaml, out))
    np.testing.assert_array_equal(again.displacement_m, rec.displacement_m)
    np.testing.assert_array_equal(again.force_V, rec.force_V)


def test_export_without_end_mass_omits_it(tmp_path: Path, out: Path) -> None:
    run = make_run(tmp_path / "r", end_mass=None)
    doc = yaml.safe_load(export_run(import_run(run.yaml_path, out), tmp_path / "e").read_text(encoding="utf-8"))
    assert "end_mass_kg" not in doc


def test_a_run_with_a_radius_per_step_exports_and_imports(sim_recording: Path, tmp_path: Path) -> None:
    """The station's default plan changes the radius between steps: v2 carries each step's radius, and
    the round trip keeps them (and the samples, bit for bit)."""
    original = read_recording(sim_recording)
    run_yaml = export_run(sim_recording, tmp_path / "x")
    doc = yaml.safe_load(run_yaml.read_text(encoding="utf-8"))
    assert doc["format_version"] == 2
    assert sorted({s["crank_radius_m"] for s in doc["steps"]}) == [0.00015, 0.001, 0.01]
    imported = read_recording(import_run(run_yaml, tmp_path / "r"))
    assert [(s.crank_frequency_hz, s.crank_radius_m) for s in imported.steps] == \
        [(s.crank_frequency_hz, s.crank_radius_m) for s in original.steps]
    for a, b in zip(original.steps, imported.steps, strict=True):
        for x, y in zip(original.step_signals(a), imported.step_signals(b), strict=True):
            np.testing.assert_array_equal(y, x)


def test_v2_step_radius_overrides_the_runs(run: Run, out: Path) -> None:
    """v2: the run's crank_radius_m is the default of steps that give none."""
    run.doc.update(format_version=2)
    run.doc["steps"][1]["crank_radius_m"] = 0.002
    run.yaml_path.write_text(yaml.safe_dump(run.doc), encoding="utf-8")
    rec = read_recording(import_run(run.yaml_path, out))
    assert [s.crank_radius_m for s in rec.steps] == [RADIUS, 0.002]


def test_export_never_overwrites(sim_recording_one_radius: Path, tmp_path: Path) -> None:
    run_yaml = export_run(sim_recording_one_radius, tmp_path)
    before = {p.name: p.read_bytes() for p in run_yaml.parent.iterdir()}
    with pytest.raises(StationError, match="exists already; not overwriting it"):
        export_run(sim_recording_one_radius, tmp_path)
    assert {p.name: p.read_bytes() for p in run_yaml.parent.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [run_yaml.parent.name]


def test_export_refuses_a_recording_without_steps(tmp_path: Path) -> None:
    meta = RunMetadata(run_id="no-steps", transducer_id="T", source="calibrate", sample_rate_hz=1000.0,
                       load_mass_kg=26.0, end_mass_kg=None, sensitivity_V_per_N=0.002, capacity_N=5000.0,
                       config_yaml="")
    w = RecordingWriter(tmp_path, meta, (ChannelSpec("displacement", "f8", "m", "m", scale=1.0),
                                         ChannelSpec("force", "f8", "V", "V", scale=1.0)))
    w.append(np.zeros(100), np.zeros(100))
    path = w.finish("aborted")
    with pytest.raises(StationError, match="no steps to export"):
        export_run(path, tmp_path / "e")
    assert not (tmp_path / "e").exists()
