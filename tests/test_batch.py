"""Nightly batch (station.batch, ``station batch``): the drift rule on synthetic histories, the
process pool and a Dask LocalCluster giving the identification's results, scope selection, and the
summary files end to end with a drift injected into the simulated transducer."""

from __future__ import annotations

import csv
import io
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from station.batch import BatchItem, drift_checks, run_batch, select_recordings, write_summaries
from station.batch.progress import ProgressBar
from station.cli import main
from station.config import parse_config
from station.errors import BadInputError
from station.ident.identify import identify_recording
from station.recording import read_recording, read_result
from station.simulate import simulate_run
from tests.conftest import fast_dict

TX, OTHER = "TX5K-0001", "TX12-0007"
N_STABLE = 6
FD_ONLY = {"methods": [{"method": "fd"}]}  # these runs list one method: one series (several: see below)


def _set_attrs(path: Path, **attrs: str) -> None:
    with h5py.File(path, "r+") as f:
        f.attrs.update(attrs)


def _day(i: int) -> str:
    return f"2025-03-{i + 1:02d}T09:00:00.000+00:00"


@pytest.fixture(scope="module")
def history(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A recordings folder: N_STABLE runs of TX on successive days, then one with k_f 0.2 % higher
    (about 40 standard uncertainties), one of another transducer, an aborted run and a partial file."""
    folder = tmp_path_factory.mktemp("recordings")
    d = fast_dict(identification=FD_ONLY)
    stable = []
    for i in range(N_STABLE):
        p = simulate_run(parse_config(d, "fast"), folder, seed=100 + i)
        _set_attrs(p, start_time=_day(i))
        stable.append(p)
    dd = fast_dict(identification=FD_ONLY)
    dd["simulation"]["truth"]["k_f"] *= 1.002
    drifted = simulate_run(parse_config(dd, "drift"), folder, seed=200)
    _set_attrs(drifted, start_time=_day(N_STABLE))
    do = fast_dict(identification=FD_ONLY)
    do["transducer"]["id"] = OTHER
    other = simulate_run(parse_config(do, "other"), folder, seed=300)
    _set_attrs(other, start_time=_day(2).replace("T09", "T08"))  # just before stable[2]
    aborted = simulate_run(parse_config(d, "fast"), folder, seed=400)
    _set_attrs(aborted, start_time=_day(3), exit_status="aborted", reason="operator stop")
    partial = folder / "20250310T090000-TX5K-0001-abcdef.h5.partial"
    shutil.copy(stable[0], partial)
    return {"folder": folder, "stable": stable, "drifted": drifted, "other": other, "aborted": aborted,
            "partial": partial}


# -- the drift rule -------------------------------------------------------------------------------

@pytest.mark.slow
def test_drift_rule_flags_an_injected_step_and_nothing_on_stable_histories() -> None:
    rng = np.random.default_rng(0)
    flags = judged = 0
    for _ in range(200):  # stable: values scatter by their stated uncertainty
        checks = drift_checks([(v, 1.0) for v in 100 + rng.normal(0, 1.0, 40)])
        flags += sum(c.flagged for c in checks)
        judged += sum(c.note == "" for c in checks)
    assert judged == 200 * 37
    assert flags / judged < 0.0027  # at most the two-sided 3-sigma false-alarm rate of a normal variable
    assert not any(c.flagged for c in drift_checks([(v, 1.0) for v in 100 + rng.normal(0, 1.0, 30)]))
    x = 100 + rng.normal(0, 1.0, 30)
    x[20:] += 8.0  # a step of 8 u from run 20 on
    checks = drift_checks([(v, 1.0) for v in x])
    assert [i for i, c in enumerate(checks) if c.flagged] == list(range(20, 30))  # flagged values stay out
    c = checks[20]
    assert c.n_history == 20 and c.history_mean == pytest.approx(np.mean(x[:20]))
    assert c.deviation == pytest.approx(x[20] - np.mean(x[:20]))
    assert [c.note for c in checks[:4]] == [f"history too short ({n} < 3)" for n in range(3)] + [""]


def test_drift_rule_uses_the_history_scatter_when_it_exceeds_the_uncertainty() -> None:
    hist = [(100 + s, 1.0) for s in (-5, 4, -3, 6, -4, 3, -6, 5)]  # scatter ~5, stated u 1
    s = float(np.std([h[0] for h in hist], ddof=1))
    assert not drift_checks([*hist, (100 + 2.5 * s, 1.0)])[-1].flagged  # within the scatter
    last = drift_checks([*hist, (100 + 4 * s, 1.0)])[-1]
    assert last.flagged and last.u_c == pytest.approx(np.sqrt(s**2 + s**2 / 8))
    assert drift_checks([*hist, (None, None)])[-1].note == "no value"


# -- executors -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def local_batch(history: dict, tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Path], list[BatchItem]]:
    """Four stable runs, a garbage file and the drifted run through the local pool (two processes),
    once for the module: (the paths, the items)."""
    bad = tmp_path_factory.mktemp("garbage") / "garbage.h5"
    bad.write_text("not an HDF5 file")
    paths = [*history["stable"][:4], bad, history["drifted"]]
    return paths, run_batch(paths, workers=2)


@pytest.mark.slow
@pytest.mark.xdist_group("local_batch")  # the two tests of the local pool's batch on one worker: it is run once
def test_run_batch_gives_the_identification_results_in_order(local_batch: tuple[list[Path], list[BatchItem]]) -> None:
    paths, items = local_batch
    bad = paths[4]
    assert [it.path for it in items] == paths
    assert [it.status for it in items] == ["ok", "ok", "ok", "ok", "failed", "ok"]
    assert "not a readable HDF5 recording" in items[4].error
    for it, p in zip(items, paths, strict=True):
        if p is bad:
            continue
        res = identify_recording(read_recording(p))
        assert it.parameters == {n: q.to_dict() for n, q in res.parameters.items()}
        assert (it.method, it.model, it.run_id) == (res.method, res.model, read_recording(p).run_id)
        # the structure the parameters rest on and identify's findings travel with the item
        assert it.structure == res.assumptions.structure.to_dict() and it.structure["coupling"]["assumed"] == "stiff"
        assert it.findings == [{"name": c.name, "severity": c.severity, "message": c.message}
                               for c in res.checks if c.severity != "info"]
        assert it.to_dict()["structure"] == it.structure
    assert run_batch([], workers=2) == []
    with pytest.raises(BadInputError):
        run_batch(paths[:1], workers=0)
    with pytest.raises(BadInputError, match="dask://HOST:PORT"):
        run_batch(paths[:1], executor="ray://x")


@pytest.mark.slow  # a worker process starts
def test_run_batch_stores_results_when_asked(history: dict, tmp_path: Path) -> None:
    p = tmp_path / history["stable"][0].name
    shutil.copy(history["stable"][0], p)
    [it] = run_batch([p], workers=1, store=True, chunksize=1)
    assert it.stored_as == f"{p.stem}.results/results.identify_{it.method}_{it.model}.h5"
    stored = read_result(p, f"identify_{it.method}_{it.model}")
    assert stored is not None and stored["parameters"] == it.parameters


@pytest.mark.slow
@pytest.mark.xdist_group("local_batch")
def test_dask_local_cluster_gives_the_local_pool_results(local_batch: tuple[list[Path], list[BatchItem]]) -> None:
    distributed = pytest.importorskip("distributed")
    ok = [(p, it) for p, it in zip(*local_batch, strict=True) if it.ok]  # the garbage file left out
    ok = [*ok[:2], ok[-1]]  # two stable runs and the drifted one: the order and the numbers
    paths, local = [p for p, _ in ok], [it for _, it in ok]
    # a worker process (about 2 s to start): the jobs are pickled to another process and sinecal is
    # imported there, as on a real cluster; the client reaches the scheduler over TCP
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = run_batch(paths, executor="dask://" + cluster.scheduler_address.removeprefix("tcp://"))
    assert [it.path for it in remote] == paths and all(it.ok for it in remote)
    for a, b in zip(remote, local, strict=True):
        assert a.run_id == b.run_id and (a.method, a.model) == (b.method, b.model)
        for name, pa in a.parameters.items():  # both single-threaded BLAS: the same numbers
            assert pa["value"] == pytest.approx(b.parameters[name]["value"], rel=1e-12)
            assert pa["std"] == pytest.approx(b.parameters[name]["std"], rel=1e-12)


# -- scope, summary, CLI ---------------------------------------------------------------------------

def test_scope_selection(history: dict) -> None:
    folder = history["folder"]
    paths, notes = select_recordings(folder)
    expected = [*history["stable"][:2], history["other"], *history["stable"][2:], history["drifted"]]
    assert paths == [p.resolve() for p in expected]  # by start time; aborted and partial left out
    assert any(history["partial"].name in n and "partial" in n for n in notes)
    assert any(history["aborted"].name in n and "'aborted'" in n for n in notes)
    tx_paths, _ = select_recordings(folder, transducer=OTHER)
    assert tx_paths == [history["other"].resolve()]
    from station.batch.scope import parse_when
    since, _ = select_recordings(folder, since=parse_when("2025-03-05"), transducer=TX)
    assert since == [p.resolve() for p in [*history["stable"][4:], history["drifted"]]]
    with pytest.raises(BadInputError, match="ISO 8601"):
        parse_when("yesterday")


@pytest.mark.slow
def test_station_batch_flags_the_injected_drift(history: dict, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "summary"
    args = ["batch", "--recordings", str(history["folder"]), "--summary-dir", str(out), "--no-progress", "--json"]
    assert main(args) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["recordings"] == N_STABLE + 2 and len(res["skipped"]) == 2
    drift_id = read_recording(history["drifted"]).run_id
    assert [(f["run_id"], f["parameter"]) for f in res["flagged"][TX]] == [(drift_id, "k_f")]
    assert res["flagged"][OTHER] == []
    rows = list(csv.DictReader(io.StringIO((out / f"{TX}.csv").read_text())))
    assert [r["run_id"] for r in rows][-1] == drift_id and len(rows) == N_STABLE + 1
    assert rows[-1]["k_f_drift"] == "DRIFT" and rows[-1]["S_drift"] == "" and rows[-1]["b_f_drift"] == ""
    assert all(r["k_f_drift"] != "DRIFT" for r in rows[:-1])
    assert float(rows[-1]["k_f_N_per_m"]) == pytest.approx(2.91e7 * 1.002, rel=2e-4)
    assert {"u_k_f_N_per_m", "S_V_per_N", "b_f_N_s_per_m"} <= set(rows[0])
    doc = json.loads((out / f"{TX}.json").read_text())
    assert doc["rule"]["k"] == 3.0 and doc["units"]["k_f"] == "N/m"
    # a later night re-identifies only the last run: the history comes from the summary file
    assert main([*args[:-1], "--since", _day(N_STABLE)[:10], "--transducer", TX]) == 0
    text = capsys.readouterr().out
    assert f"DRIFT k_f in run {drift_id}" in text
    assert len(json.loads((out / f"{TX}.json").read_text())["runs"]) == N_STABLE + 1


def test_summary_merges_by_run_id(tmp_path: Path) -> None:
    def item(i: int, k_f: float) -> BatchItem:
        return BatchItem(Path(f"r{i}.h5"), f"r{i}", TX, _day(i), "ok", "fd", "sdof",
                         {"k_f": {"value": k_f, "std": 1.0, "unit": "N/m", "identifiable": True}})
    write_summaries([item(i, 100.0 + 0.5 * (-1) ** i) for i in range(5)], tmp_path)
    doc = write_summaries([item(5, 120.0)], tmp_path)[TX]
    assert [r["run_id"] for r in doc["runs"]] == [f"r{i}" for i in range(6)]
    assert [f["run_id"] for f in doc["flagged"]] == ["r5"]
    # the control charts judge the newest run against the earlier ones
    assert {(o["chart"], o["run_id"]) for o in doc["out_of_control"]} == {("shewhart", "r5"), ("ewma", "r5")}
    assert doc["charts"]["fd"]["k_f"]["shewhart"]["reference"] == 5
    doc = write_summaries([item(5, 100.2)], tmp_path)[TX]  # re-identified: replaces its row
    assert len(doc["runs"]) == 6 and doc["flagged"] == [] and doc["out_of_control"] == []


def test_each_listed_method_is_its_own_drift_series(tmp_path: Path) -> None:
    """fd drifts on run r5, PSO+ does not move: only fd's r5 is flagged; a method that refused a run
    is a failed row of that method and leaves the other's series alone."""
    def item(i: int, method: str, k_f: float | None, error: str = "") -> BatchItem:
        p = {} if k_f is None else {"k_f": {"value": k_f, "std": 1.0, "unit": "N/m", "identifiable": True}}
        return BatchItem(Path(f"r{i}.h5"), f"r{i}", TX, _day(i), "failed" if error else "ok", method,
                         "sdof" if method == "fd" else "h2", p, error)
    items = [item(i, "fd", 100.0 + 0.5 * (-1) ** i) for i in range(5)]
    items += [item(i, "pso+", 200.0 + 0.5 * (-1) ** i) for i in range(5)]
    items += [item(5, "fd", 120.0), item(5, "pso+", 200.2), item(6, "pso+", None, "record too short")]
    doc = write_summaries(items, tmp_path)[TX]
    assert [(f["run_id"], f["method"]) for f in doc["flagged"]] == [("r5", "fd")]
    assert len(doc["runs"]) == 13
    pso5 = next(r for r in doc["runs"] if (r["run_id"], r["method"]) == ("r5", "pso+"))
    assert pso5["drift"]["k_f"]["n_history"] == 5 and not pso5["drift"]["k_f"]["flagged"]
    doc = write_summaries([item(5, "fd", 100.2)], tmp_path)[TX]  # fd re-identified: its row only
    assert len(doc["runs"]) == 13 and doc["flagged"] == []


@pytest.mark.slow
def test_a_recording_gives_one_item_per_listed_method(history: dict, tmp_path: Path) -> None:
    from station.batch.worker import identify_listed

    p = simulate_run(parse_config(fast_dict(), "listed"), tmp_path, seed=7)  # fd, then PSO+ (records too short)
    fd, pso = identify_listed(p)
    assert (fd.status, fd.method, fd.model) == ("ok", "fd", "sdof") and fd.parameters["k_f"]["identifiable"]
    assert (pso.status, pso.method, pso.model) == ("failed", "pso+", "h2") and "the protocol needs" in pso.error
    [only] = identify_listed(history["stable"][0])
    assert only.method == "fd" and only.ok


def test_progress_bar_lines_when_not_a_terminal() -> None:
    buf = io.StringIO()
    bar = ProgressBar(50, stream=buf)
    for _ in range(50):
        bar.update()
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 11 and lines[-1].startswith("[" + "#" * 30 + "] 50/50 recordings (100 %")


def test_pool_workers_run_single_threaded_blas() -> None:
    import os

    from station.batch.runner import open_executor

    before = os.environ.get("OPENBLAS_NUM_THREADS")
    with open_executor("local", 2) as ex:  # the fork server set this before importing numpy
        assert [f.result() for f in [ex.submit(os.getenv, "OPENBLAS_NUM_THREADS") for _ in range(4)]] == ["1"] * 4
    assert os.environ.get("OPENBLAS_NUM_THREADS") == before  # the parent's environment is not touched


def test_jobs_are_split_evenly_over_the_workers() -> None:
    from station.batch.runner import split_jobs

    paths = [Path(f"r{i}.h5") for i in range(50)]
    assert [len(c) for c in split_jobs(paths, 2)] == [1] * 50  # fewer than 32 per worker: one per job
    many = [Path(f"r{i}.h5") for i in range(75)]
    chunks = split_jobs(many, 2)  # size 75 // 32 = 2 -> 38 chunks of 1-2, shares even
    assert len(chunks) == 38 and sorted({len(c) for c in chunks}) == [1, 2]
    assert [p for c in chunks for p in c] == many  # every recording once, in order
    assert [len(c) for c in split_jobs(paths[:3], 2)] == [1, 1, 1]  # never an empty job
    assert [len(c) for c in split_jobs(paths, 2, chunksize=20)] == [20, 20, 10]
