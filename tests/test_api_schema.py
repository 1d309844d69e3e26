"""Schemathesis against the daemon's OpenAPI schema: generated requests for every operation (the
run-id parameter pinned to a real, completed run so results, plots, report and discrepancy are
reached; the run is seeded into the daemon's store before it starts) find no server error and no
response outside the documented statuses, content types and schemas.

Left out on purpose: `ignored_auth`/`missing_required_header` (reading is open on loopback by
design), `positive_data_acceptance` (a schema-valid run can still break the configured rig limits:
422 naming the field) and `allow_header_conformance` (Starlette's 405 for OPTIONS).

Cases (seed 1): the coverage phase's every boundary and invalid value of each operation's parameters and
body, two undefined methods per path, and 5 fuzzed examples per operation (10 found nothing more): 1600
requests (schemathesis 4.32.5), every operation with valid and invalid input, the same checks (1968 before
the cut).  Where they cost: one report PDF, one certificate PDF, one model-gap analysis and one report
render (each answer cached after the first); the rest are answers of a few milliseconds.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.station_support import TOKEN, Daemon, Seed

# Hypothesis's Unicode tables (its character categories, the UTF-8 codec's characters: about 2 s of CPU to
# build, the same for every run of one Python) kept in the checkout's ``.hypothesis/`` (ignored by git),
# not rebuilt in each run's new folder; only these tables are kept there (no example database)
UNICODE_TABLES = Path(__file__).resolve().parents[1] / ".hypothesis"

CHECKS = ("not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance,"
          "negative_data_rejection,response_headers_conformance")


@pytest.mark.slow
def test_schemathesis_finds_no_server_error(tmp_path: Path) -> None:
    with Daemon(tmp_path, seeds=[Seed()]) as d:
        [rid] = d.seeded
        assert d.c().get(f"/runs/{rid}").json()["state"] == "completed"
        cfg = tmp_path / "schemathesis.toml"
        # max_effects pinned: each value is a fresh model-gap analysis in the render worker, which
        # tests nothing new about the schema; its bounds are checked in tests/test_api.py.  Unique
        # inputs: the coverage phase otherwise sends an operation whose parameters are all pinned the
        # same request a dozen times (each a model-gap analysis or a render).  Undefined methods: two per
        # path (one the API uses elsewhere, one it never does), not eight: the 405 is the router's, one
        # answer for every path and method, and each of the other six added 50 requests
        cfg.write_text(f'generation.unique-inputs = true\n[phases.coverage]\nunexpected-methods = ["delete", "patch"]\n'
                       f'[parameters]\n"path.run_id" = "{rid}"\n"query.max_effects" = 2\n')
        r = subprocess.run(
            [sys.executable, "-m", "schemathesis.cli", "--config-file", str(cfg), "run", f"{d.url}/openapi.json",
             "--checks", CHECKS, "-H", f"Authorization: Bearer {TOKEN}", "--max-examples", "5",
             "--phases", "examples,coverage,fuzzing",
             "--request-timeout", "30", "--workers", "1", "--seed", "1", "--suppress-health-check", "all",
             # no example database: the run's folder is new each time, so nothing stored is ever replayed
             # (the cases are those of the seed alone); plain text: the output is read, not shown
             "--generation-database", "none", "--no-color"],
            capture_output=True, text=True, timeout=240, cwd=tmp_path,
            env={**os.environ, "HYPOTHESIS_STORAGE_DIRECTORY": str(UNICODE_TABLES)})
        out = r.stdout + r.stderr
        assert r.returncode == 0, out[-6000:]
        paths = d.c().get("/openapi.json").json()["paths"]
        operations = sum(len(ops) for ops in paths.values())
        assert "passed" in out and f"Tested: {operations}" in out, (operations, out[-3000:])
        print(next((ln.strip() for ln in out.splitlines() if " generated, " in ln), ""))  # the cases, for -s
        log = d.log()
        assert "Traceback" not in log and "Exception in ASGI application" not in log, log
        # the generated POST /stop latched the emergency stop; acknowledged, the station is healthy
        assert d.c().post("/stop/acknowledge", json={"operator": "schemathesis"}).status_code == 200
        assert d.c().get("/health").json()["status"] == "ok"
