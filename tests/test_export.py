"""The results as tables for a spreadsheet: parameters with their uncertainties and S_dyn(f) as CSV
and as an Excel workbook, from the command line and the API; they open in openpyxl and pandas, with
the units in the headers, and state what the stored identification states."""

from __future__ import annotations

import asyncio
import io
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import pytest

from station.cli import main
from tests.station_support import CAPPED_SPEEDUP, Seed, asgi_client, daemon_config, running_app, seed_runs

if TYPE_CHECKING:  # pandas and openpyxl (1.5 s of import) are loaded by the tests that read tables
    import pandas as pd

pytestmark = pytest.mark.slow  # a simulated, identified run and its report data (~15 s)

Seeded = tuple[dict[str, Any], Path, str, dict[str, Any], dict[str, httpx.Response]]


@pytest.fixture(scope="module")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> Seeded:
    """A completed run's configuration, recording, id, the API's results of it and the API's answers
    to its exports (the three tables, an unknown one, the archive), from one start of the app."""
    tmp = tmp_path_factory.mktemp("export")
    cfg = daemon_config(tmp / "recordings")
    [rid] = seed_runs(cfg, [Seed(freqs=(10.0, 20.0, 40.0))])

    async def go() -> tuple[dict[str, Any], dict[str, httpx.Response]]:
        async with (running_app(tmp / "recordings", config=cfg, max_speedup=CAPPED_SPEEDUP) as app,
                    asgi_client(app) as c):
            r = await c.get(f"/runs/{rid}/results")
            assert r.status_code == 200, r.text
            out = {n: await c.get(f"/runs/{rid}/export/{n}") for n in ("parameters.csv", "sdyn.csv", "results.xlsx")}
            out["bad"] = await c.get(f"/runs/{rid}/export/results.ods")
            out["zip"] = await c.get(f"/runs/{rid}/archive.zip")
            return dict(r.json()), out
    results, exports = asyncio.run(go())
    return cfg, tmp / "recordings" / f"{rid}.h5", rid, results, exports


def _check_tables(params: pd.DataFrame, sdyn: pd.DataFrame, cfg: dict[str, Any], results: dict[str, Any]) -> None:
    assert list(sdyn.columns)[:4] == ["step", "f (Hz)", "|S_dyn| (V/N)", "u(|S_dyn|) (V/N)"]
    assert "phase of S_dyn (°)" in sdyn.columns and "U(|S_dyn|), k = 2 (V/N)" in sdyn.columns
    assert list(sdyn["step"]) == [1, 2, 3] and list(sdyn["f (Hz)"]) == pytest.approx([10.0, 20.0, 40.0], rel=1e-3)
    # far below the resonance S_dyn is the simulated chain's sensitivity (the truth of the physics)
    chain = cfg["transducer"]["sensitivity_V_per_N"] * cfg["conditioner"]["gain"]
    assert sdyn["|S_dyn| (V/N)"].iloc[0] == pytest.approx(chain, rel=0.02)
    assert list(sdyn["U(|S_dyn|), k = 2 (V/N)"]) == pytest.approx(list(2 * sdyn["u(|S_dyn|) (V/N)"]), rel=1e-12)
    assert list(params.columns)[:5] == ["parameter", "quantity", "value", "standard uncertainty u (k = 1)", "unit"]
    rows = params.set_index("parameter")
    # what the stored identification says, value and uncertainty, as the API's results state it
    for p in results["parameters"]:
        name = p["name"]
        if p["value"] is not None:
            assert rows.loc[name, "value"] == pytest.approx(p["value"], rel=1e-12), name
            assert rows.loc[name, "standard uncertainty u (k = 1)"] == pytest.approx(p["std"], rel=1e-12), name
            assert rows.loc[name, "unit"] == p["unit"]
    assert rows.loc["k_f", "unit"] == "N/m" and rows.loc["S", "unit"] == "V/N"


def test_the_command_line_writes_csv_and_a_workbook(seeded: Seeded, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    cfg, recording, _, results, _ = seeded
    assert main(["export", str(recording), "--results", "--out", str(tmp_path)]) == 0
    written = [Path(line) for line in capsys.readouterr().out.split()]
    assert sorted(p.name for p in written) == sorted(f"{recording.stem}.{n}" for n in
                                                     ("parameters.csv", "sdyn.csv", "results.xlsx"))
    by = {p.name.removeprefix(recording.stem + "."): p for p in written}
    import openpyxl
    import pandas as pd

    params = pd.read_csv(by["parameters.csv"], encoding="utf-8-sig")
    sdyn = pd.read_csv(by["sdyn.csv"], encoding="utf-8-sig")
    _check_tables(params, sdyn, cfg, results)
    wb = openpyxl.load_workbook(by["results.xlsx"])
    assert wb.sheetnames == ["parameters", "S_dyn", "about"]
    assert [c.value for c in wb["S_dyn"][1]][:3] == ["step", "f (Hz)", "|S_dyn| (V/N)"]
    about = dict(wb["about"].iter_rows(min_row=2, values_only=True))
    assert about["recording"] == recording.name and "S_dyn(f) = -H(f)/M" in about["S_dyn"]
    x = pd.read_excel(by["results.xlsx"], sheet_name=None)
    _check_tables(x["parameters"], x["S_dyn"], cfg, results)


def test_the_api_serves_the_exports_and_refuses_an_unknown_one(seeded: Seeded) -> None:
    cfg, recording, _, results, r = seeded
    assert r["parameters.csv"].headers["content-type"].startswith("text/csv")
    assert r["results.xlsx"].headers["content-type"].endswith("spreadsheetml.sheet")
    assert f'filename="{recording.stem}.results.xlsx"' in r["results.xlsx"].headers["content-disposition"]
    import pandas as pd

    params = pd.read_csv(io.BytesIO(r["parameters.csv"].content), encoding="utf-8-sig")
    sdyn = pd.read_csv(io.BytesIO(r["sdyn.csv"].content), encoding="utf-8-sig")
    _check_tables(params, sdyn, cfg, results)
    x = pd.read_excel(io.BytesIO(r["results.xlsx"].content), sheet_name=None)
    _check_tables(x["parameters"], x["S_dyn"], cfg, results)
    assert r["bad"].status_code == 422 and r["bad"].headers["content-type"] == "application/problem+json"
    import zipfile

    assert r["zip"].status_code == 200 and r["zip"].headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(r["zip"].content)) as z:
        files = json.loads(z.read("MANIFEST.json"))["files"]
        assert z.read(recording.name) == recording.read_bytes() and recording.name in files
        assert any(n.startswith(f"{recording.stem}.results/") for n in files)
