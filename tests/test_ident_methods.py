"""Several identifications per run (``identification.methods``): the expert estimator first, the
paper's PSO+ (Eq. 11) beside it; a secondary method's refusal never fails the run.

Truth: the simulator's configuration (k_f 2.91e7 N/m, b_f 17136 N*s/m, S 2e-3 V/N); recordings are
synthesised by ``station.simulate`` (Eq. 3 integrated), not by the estimators under test."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from typing import Any

import httpx
import pytest

from station.config import IdentificationConfig, MethodChoice, parse_config
from station.errors import ConfigError
from station.ident.result import Estimate, FitSummary, IdentificationResult
from station.recording import read_recording, read_result
from station.run.methods import STATUSES, agreement, identify_all, read_outcomes
from station.run.request import RunRequest, plan_run
from tests.conftest import station_dict
from tests.ident_support import sim
from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, app_in_process, run_body, wait_state

K, B, S = 2.91e7, 17136.0, 2e-3


# ---------------------------------------------------------------------------------------- the list
def test_default_is_fd_first_and_pso_plus_on_eq11_beside_it() -> None:
    methods = IdentificationConfig().methods
    assert [(m.method, m.model_key) for m in methods] == [("fd", "auto"), ("pso+", "h2")]
    shipped = parse_config(station_dict()).identification.methods
    assert [(m.method, m.model_key) for m in shipped] == [("fd", "auto"), ("pso+", "h2")]


@pytest.mark.parametrize("methods, words", [
    ([{"method": "rls", "model": "h1"}], "defined for the models h2"),
    ([{"method": "fd", "model": "h2"}], "defined for the models auto, sdof, coupled"),
    ([{"method": "fd"}, {"method": "pso+", "model": "h2"}, {"method": "pso+"}], "listed twice"),
    ([{"method": "fd", "model": "auto"}, {"method": "fd", "model": "sdof"}], "either auto or explicit"),
    ([], "at least 1"),
    ([{"method": "lsq"}], "fd"),
])
def test_a_bad_method_list_is_refused_with_its_reason(methods: list[dict[str, Any]], words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        parse_config(station_dict(identification={"methods": methods}))
    with pytest.raises(ValueError, match=words):
        RunRequest.model_validate({**run_body(), "methods": methods})


def test_a_request_names_its_own_methods_and_the_recording_keeps_them() -> None:
    cfg = parse_config(station_dict())
    req = RunRequest.model_validate({**run_body(), "methods": [{"method": "pso", "model": "h2", "seed": 7},
                                                              {"method": "fd"}]})
    plan = plan_run(cfg, req)
    assert plan.config.identification.methods == [MethodChoice(method="pso", model="h2", seed=7),
                                                  MethodChoice(method="fd")]
    assert plan.config.identification.swarm == cfg.identification.swarm  # the rest as configured
    assert plan_run(cfg, RunRequest.model_validate(run_body())).config.identification.methods == \
        cfg.identification.methods


@pytest.mark.slow
def test_the_api_refuses_a_bad_list_at_its_field_and_runs_a_good_one(tmp_path: Path) -> None:
    async def go() -> tuple[httpx.Response, dict[str, Any]]:
        async with app_in_process(tmp_path) as (_, c):  # no worker: the run stops at identifying
            bad = await c.post("/runs", json={**run_body(), "methods": [{"method": "rls", "model": "h1"}]})
            body = {**run_body((10.0,), record_s=0.2), "methods": [{"method": "pso", "seed": 3}]}
            good = await c.post("/runs", json=body)
            assert good.status_code == 202, good.text
            return bad, await wait_state(c, good.json()["id"], ("identifying",))
    bad, st = asyncio.run(go())
    assert bad.status_code == 422
    [err] = bad.json()["errors"]
    assert err["loc"][:3] == ["body", "methods", 0] and "defined for the models h2" in err["msg"]
    rec = read_recording(tmp_path / st["recording"])  # the request's list is in the recording's configuration
    assert rec.config["identification"]["methods"] == [{"method": "pso", "seed": 3}]


def test_method_status_literal_matches_the_outcomes() -> None:
    from typing import get_args

    from station.api.schemas import MethodStatus, ModelChoiceName
    from station.config import ModelChoice

    assert get_args(MethodStatus) == STATUSES
    assert get_args(ModelChoiceName) == get_args(ModelChoice)


def test_every_list_of_methods_reads_the_one_registry() -> None:
    from station.config import MethodChoice
    from station.ident.names import METHOD_DESCRIPTIONS, METHOD_PREFERENCE, METHODS, SWARM_METHODS
    from station.vocabulary import METHOD_REGISTRY, MODELS_OF_METHOD, Method

    # the configuration's (and the request's) method choice is the vocabulary's enumeration
    assert MethodChoice.model_fields["method"].annotation is Method
    assert sorted(METHOD_PREFERENCE) == sorted(METHODS) == sorted(MODELS_OF_METHOD) == sorted(METHOD_DESCRIPTIONS)
    assert len(METHOD_REGISTRY) == len(METHODS) and set(SWARM_METHODS) == {"pso", "pso+"}
    with pytest.raises(ValueError, match="defined for the models h2"):
        MethodChoice.model_validate({"method": "rls", "model": "h1"})


# ---------------------------------------------------------------------------------------- agreement
def _result(method: str, **params: tuple[float | None, float | None, str]) -> IdentificationResult:
    ps = {n: Estimate(v, s, "N/m", v is not None, why) for n, (v, s, why) in params.items()}
    return IdentificationResult(method, "sdof", ps, FitSummary(0.0, (0.0,), math.nan, 1))


def test_agreement_is_the_difference_in_combined_standard_uncertainties() -> None:
    fd = _result("fd", k_f=(100.0, 3.0, ""), b_f=(5.0, 1.0, ""), S=(1.0, 0.1, ""))
    pso = _result("pso+", k_f=(108.0, 4.0, ""), b_f=(None, None, "not stable against the swarm seed"),
                  S=(1.0, 0.0, ""))
    a = agreement(fd, pso)
    assert a["k_f"]["difference"] == pytest.approx(8.0) and a["k_f"]["combined_std"] == pytest.approx(5.0)
    assert a["k_f"]["z"] == pytest.approx(1.6) and a["k_f"]["reason"] == ""
    assert a["b_f"]["z"] is None and a["b_f"]["reason"] == "pso+ withholds it: not stable against the swarm seed"
    assert a["S"]["z"] == pytest.approx(0.0)
    assert agreement(pso, fd)["b_f"]["reason"].startswith("pso+ withholds it")


# ---------------------------------------------------------------------------------------- one recording
@pytest.mark.slow
def test_a_refusing_secondary_method_leaves_the_primary_result(tmp_path: Path) -> None:
    """1 s records: too short for the paper's protocol (200 + 400 points at 500 Hz), so PSO+ refuses."""
    path = sim(tmp_path, ((10.0, 1e-3), (30.0, 1e-3)), record_s=0.6)
    res = identify_all(path, read_recording(path))
    assert res.method == "fd" and res.parameter("k_f").identifiable
    fd, pso = read_outcomes(path)
    assert (fd.method, fd.primary, fd.status, fd.result_name) == ("fd", True, "done", res.result_name)
    assert fd.compute_s is not None and fd.compute_s > 0 and fd.cpu_s is not None
    assert (pso.method, pso.model, pso.primary, pso.status) == ("pso+", "h2", False, "refused")
    assert "the protocol needs 600" in pso.reason and pso.result_name is None and pso.seed == 0
    assert read_result(path, "identify_pso+_h2") is None
    # the report shows both side by side: fd's values as the primary, PSO+ with its reason
    from station.report.data import load_run
    from station.report.html import methods_section

    html = methods_section(load_run(path))
    assert "Methods side by side" in html and "★ fd (auto → sdof)" in html
    assert f'data-key="method.fd/auto.k_f" data-value="{res.parameter("k_f").value!r}"' in html
    assert 'data-key="method.pso+/h2">' in html and "the protocol needs 600" in html


def test_a_failing_secondary_method_is_its_outcome_not_the_runs(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """An estimator that raises (a bug, not a refusal) beside fd: fd's result stands, the failure is
    named; the same exception in the primary is raised (the run fails)."""
    import station.ident.identify as ident_mod

    real = ident_mod.identify_recording

    def flaky(rec: Any, method: str | None = None, *a: Any, **kw: Any) -> IdentificationResult:
        if method == "pso+":
            raise FloatingPointError("overflow in the swarm")
        return real(rec, method, *a, **kw)
    monkeypatch.setattr(ident_mod, "identify_recording", flaky)
    path = sim(tmp_path, ((10.0, 1e-3), (30.0, 1e-3)), record_s=0.6)
    assert identify_all(path, read_recording(path)).method == "fd"
    fd, pso = read_outcomes(path)
    assert fd.status == "done" and (pso.status, pso.reason) == ("failed", "FloatingPointError: overflow in the swarm")
    edit = {"methods": [{"method": "pso+"}, {"method": "fd"}]}
    path2 = sim(tmp_path / "b", ((10.0, 1e-3),), record_s=0.3, edit=lambda d: d["identification"].update(edit))
    with pytest.raises(FloatingPointError):
        identify_all(path2, read_recording(path2))


# ---------------------------------------------------------------------------------------- the daemon
async def _events(c: httpx.AsyncClient, rid: str) -> list[tuple[str, dict[str, Any]]]:
    out: list[tuple[str, dict[str, Any]]] = []
    async with c.stream("GET", f"/runs/{rid}/events") as r:
        name = ""
        async for line in r.aiter_lines():
            if line.startswith("event:"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                out.append((name, json.loads(line.split(":", 1)[1])))
                if name == "end":
                    return out
    return out


@pytest.mark.slow
def test_the_daemon_runs_each_listed_method_and_shows_them_side_by_side(tmp_path: Path) -> None:
    """One run asks for fd, PSO+ (Eq. 11) and RLS with records long enough for the paper's protocol
    (the default list on short records, PSO+ refusing: tests/test_api.py's live run)."""
    methods = [{"method": "fd"}, {"method": "pso+", "model": "h2", "seed": 5}, {"method": "rls"}]

    async def go() -> tuple[list, dict]:
        # capped (the run at 20x real time, idle at 4x): the idle rig would otherwise stream flat out on
        # a core for as long as the worker process starts and identifies
        async with app_in_process(tmp_path, workers=1, max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (_, c):
            body = {**run_body((10.0, 100.0), radius=1.5e-4, record_s=1.4), "methods": methods}
            rid = (await c.post("/runs", json=body)).json()["id"]
            events = await asyncio.wait_for(_events(c, rid), 120)
            res = (await c.get(f"/runs/{rid}/results")).json()
            return events, res
    events, res = asyncio.run(go())

    results = [d for n, d in events if n == "result"]
    assert [(d["method"], d["status"]) for d in results] == [("fd", "done"), ("pso+", "done"), ("rls", "done")]
    assert results[0]["primary"] and not results[1]["primary"]
    assert events[-1][0] == "end" and events[-1][1]["state"] == "completed"
    # the primary's result event comes with the run completed, before the others are done
    first = next(i for i, (n, _) in enumerate(events) if n == "result")
    assert events[first - 1][1]["state"] == "completed"
    assert [m["status"] for m in events[first - 1][1]["methods"]][1:] in (["pending", "pending"],
                                                                            ["running", "pending"])

    assert res["method"] == "fd"
    by = {m["method"]: m for m in res["methods"]}
    assert [m["method"] for m in res["methods"]] == ["fd", "pso+", "rls"]
    assert by["pso+"]["seed"] == 5 and by["pso+"]["result_model"] == "h2" and by["pso+"]["compute_s"] > 0
    fd_k = {p["name"]: p for p in by["fd"]["parameters"]}["k_f"]
    assert abs(fd_k["value"] - K) < 4 * fd_k["std"] + 0.02 * K  # the simulated truth
    for m in ("pso+", "rls"):
        assert isinstance(by[m]["checks"], list) and by[m]["identifiability"]["names"] == ["S", "k_f", "b_f"]
        assert set(by[m]["agreement"]) == {"S", "k_f", "b_f"}
        for name, a in by[m]["agreement"].items():  # a z, or why not: which method withholds it
            withheld = [x for x in ("fd", m) if not {p["name"]: p for p in by[x]["parameters"]}[name]["identifiable"]]
            if withheld:
                assert a["z"] is None and a["reason"].startswith(f"{withheld[0]} withholds it: ")
            else:
                assert a["reason"] == "" and a["z"] == pytest.approx(a["difference"] / a["combined_std"])
    rls_s = by["rls"]["agreement"]["S"]  # RLS determines S on one step: it agrees with fd's
    assert rls_s["z"] is not None and abs(rls_s["z"]) < 4
    assert by["fd"]["agreement"] == {}

