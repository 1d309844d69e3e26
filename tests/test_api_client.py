"""The published API is what a generated client needs: a client generated off the shelf
(``openapi-python-client``) from the daemon's OpenAPI document, with no hand-written code, starts a
run, follows it to its results and downloads a plot and the recording; the closed sets of values are
enumerations in the document, the budgets, assumptions and checks typed objects.

The app runs in-process (the simulated rig on a virtual clock, one identification worker); the
client talks to it through httpx's ASGI transport, as it would over a socket."""

from __future__ import annotations

import asyncio
import importlib
import io
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, get_args

import h5py
import httpx
import pytest

from station.api import create_app
from station.api.schemas import MethodName, ModelName
from station.config import parse_config
from station.ident.names import METHODS, MODELS
from station.run.procedure import StepState
from station.service.settings import build_settings
from station.vocabulary import Flag, Severity
from tests.station_support import TOKEN, daemon_config, running_app


def openapi(tmp: Path) -> dict[str, Any]:
    app = create_app(build_settings(parse_config(daemon_config(tmp / "recordings")), sim=True,
                                    env={"STATION_TOKEN": TOKEN}))
    return app.openapi()


@pytest.fixture(scope="module")
def spec(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The daemon's OpenAPI document, made once for the module (about a second of CPU; read only)."""
    return openapi(tmp_path_factory.mktemp("openapi"))


@pytest.mark.slow
def test_closed_sets_are_enumerations_and_results_are_typed(spec: dict[str, Any]) -> None:
    schemas = spec["components"]["schemas"]

    def enum(schema: str, field: str) -> list[Any]:
        prop = schemas[schema]["properties"][field]
        options = [schemas[o["$ref"].rsplit("/", 1)[-1]] if "$ref" in o else o for o in prop.get("anyOf", [prop])]
        return next(o["enum"] for o in options if "enum" in o)
    assert enum("RunStatus", "step_state") == list(get_args(StepState))
    assert enum("RunStatus", "state") == ["queued", "running", "identifying", "completed", "aborted", "failed",
                                          "interrupted"]
    assert enum("ParameterOut", "flag") == ["", "poorly_determined", "conditional"]
    assert enum("CheckOut", "severity") == ["info", "warning", "refused"]
    assert enum("RunResults", "method") == list(METHODS) == [m.value for m in MethodName]
    assert enum("RunResults", "model") == list(MODELS) == [m.value for m in ModelName]
    # the domain's enumerations themselves, one schema each
    assert schemas["Severity"]["enum"] == [s.value for s in Severity] and schemas["Flag"]["enum"] == list(Flag)
    assert enum("CampaignOut", "status") == ["separated", "conditional", "refused"]
    assert enum("EStopState", "source") == ["page", "api", "controller", "drive", "link"]
    results = schemas["RunResults"]["properties"]
    assert results["budget"]["additionalProperties"]["$ref"].endswith("/BudgetOut")
    assert results["assumptions"]["$ref"].endswith("/AssumptionsOut")
    assert results["checks"]["items"]["$ref"].endswith("/CheckOut")
    assert results["determined"]["additionalProperties"]["$ref"].endswith("/DeterminedOut")
    assert schemas["CampaignOut"]["properties"]["assumptions"]["$ref"].endswith("/CampaignAssumptionsOut")
    paths = spec["paths"]
    binary = {"type": "string", "format": "binary"}
    octet = {"application/octet-stream": {"schema": binary}}  # first: generic clients read bytes
    assert paths["/runs/{run_id}/plots/{name}.png"]["get"]["responses"]["200"]["content"] == {
        **octet, "image/png": {"schema": binary}}
    assert paths["/runs/{run_id}/recording"]["get"]["responses"]["200"]["content"] == {
        **octet, "application/x-hdf5": {"schema": binary}}
    assert paths["/runs/{run_id}/report.pdf"]["get"]["responses"]["200"]["content"] == {
        **octet, "application/pdf": {"schema": binary}}
    assert next(iter(paths["/runs/{run_id}/export/{name}"]["get"]["responses"]["200"]["content"])) == \
        "application/octet-stream"
    assert paths["/runs/{run_id}/certificate.{ext}"]["get"]["responses"]["200"]["content"]["application/pdf"] == {
        "schema": binary}
    assert paths["/runs"]["post"]["operationId"] == "start_run"  # readable names in generated clients


@pytest.mark.slow  # the generator, then a run identified in a worker process
def test_a_generated_client_drives_a_run(spec: dict[str, Any], tmp_path: Path) -> None:
    spec_path = tmp_path / "openapi.json"
    spec_path.write_text(json.dumps(spec))
    out = tmp_path / "gen" / "sinecal_client"  # off the shelf: no configuration, no override
    r = subprocess.run([sys.executable, "-m", "openapi_python_client", "generate", "--path", str(spec_path),
                        "--output-path", str(out), "--meta", "none"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "WARNING" not in r.stdout + r.stderr, r.stdout + r.stderr
    sys.path.insert(0, str(out.parent))
    try:
        client_pkg = importlib.import_module("sinecal_client")
        runs = importlib.import_module("sinecal_client.api.runs")
        models = importlib.import_module("sinecal_client.models")
        for name in ("start_run", "get_run", "run_results", "run_plot", "run_recording", "run_export"):
            importlib.import_module(f"sinecal_client.api.runs.{name}")
        # every file download is read as bytes (File), the certificate's PDF too, not text
        for module in ("runs.run_plot", "runs.run_recording", "runs.run_report_pdf", "runs.run_export",
                       "certificates.run_certificate", "certificates.issued_certificate"):
            source = (out / "api" / (module.replace(".", "/") + ".py")).read_text()
            assert "File(payload=BytesIO(response.content))" in source, module
        asyncio.run(_drive(tmp_path / "recordings", client_pkg, runs, models))
    finally:
        sys.path.remove(str(out.parent))
        for m in [m for m in sys.modules if m == "sinecal_client" or m.startswith("sinecal_client.")]:
            del sys.modules[m]


async def _drive(rec: Path, pkg: Any, runs: Any, models: Any) -> None:
    # the rig at 5x real time: its run of a few virtual seconds still takes about a second, and while
    # the identification worker works the idle rig's DAQ streams a quarter of what it would at 20x
    async with running_app(rec, workers=1, max_speedup=5.0) as app:
        transport = httpx.ASGITransport(app=app, client=("127.0.0.1", 40000))
        client = pkg.AuthenticatedClient(base_url="http://127.0.0.1", token=TOKEN, raise_on_unexpected_status=True,
                                         httpx_args={"transport": transport})
        async with client:
            body = models.RunRequest(transducer_id="TX5K-0001", top_mass_kg=25.717, steps=[
                models.StepSpec(crank_frequency_hz=f, crank_radius_m=0.001) for f in (10.0, 20.0)])
            accepted = await runs.start_run.asyncio(client=client, body=body)
            assert isinstance(accepted, models.RunAccepted), accepted
            rid = accepted.id
            for _ in range(1200):  # the rig on a virtual clock, then the identification worker
                status = await runs.get_run.asyncio(rid, client=client)
                assert isinstance(status, models.RunStatus)
                if status.state.value in ("completed", "aborted", "failed", "interrupted"):
                    break
                await asyncio.sleep(0.05)
            assert status.state.value == "completed", status
            assert status.step_state.value == "done" and status.lost_samples == 0
            res = await runs.run_results.asyncio(rid, client=client)
            assert isinstance(res, models.RunResults), res
            assert res.method.value == "fd" and res.model.value == "sdof"
            k_f = next(p for p in res.parameters if p.name == "k_f")
            assert k_f.identifiable and k_f.unit == "N/m" and k_f.flag.value in ("", "conditional")
            assert abs(k_f.value - 2.91e7) < 4 * k_f.std + 0.02 * 2.91e7  # the simulated truth
            budget = res.budget.additional_properties["k_f"]
            assert isinstance(budget, models.BudgetOut) and budget.unit == "N/m"
            assert budget.combined == pytest.approx(k_f.std, rel=1e-9)
            assert isinstance(res.assumptions, models.AssumptionsOut)
            assert res.assumptions.end_mass_kg.value == pytest.approx(0.12)
            assert all(isinstance(c, models.CheckOut) and c.severity.value in ("info", "warning", "refused")
                       for c in res.checks)
            png = await runs.run_plot.asyncio(rid, "bode", client=client)
            assert png.payload.read()[:8] == b"\x89PNG\r\n\x1a\n"
            h5 = await runs.run_recording.asyncio(rid, client=client)
            assert not isinstance(h5, models.Problem), h5.detail
            with h5py.File(io.BytesIO(h5.payload.read()), "r") as f:
                assert f.attrs["run_id"] == rid and f.attrs["exit_status"] == "completed"
            xlsx = await runs.run_export.asyncio(rid, models.RunExportName("results.xlsx"), client=client)
            assert xlsx.payload.read()[:2] == b"PK"  # a workbook is a zip
