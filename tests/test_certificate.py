"""Calibration certificates: the ISO/IEC 17025 content from a simulated run, the PDF read back (no
budget line cut), approval by a second person with the right role, numbering, immutability and
replacement."""

from __future__ import annotations

import io
import re
import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from station.certificate.content import certificate_content
from station.certificate.issue import CertificateError, draft, issue, list_issued, read_issued
from station.certificate.render import certificate_html
from station.ident.identify import identify_recording
from station.recording import read_recording, write_result
from tests.ident_support import sim


def _pdf(pdf: bytes) -> Any:
    """The PDF read back (pypdf, imported where a test reads one: 0.4 s of every worker's collection)."""
    from pypdf import PdfReader

    return PdfReader(io.BytesIO(pdf))


TECH, APPROVER = "T. Technician", "A. Approver"


@pytest.fixture(scope="module")
def stored(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated run (the shipped configuration: laboratory, customer, standards, users) with its
    identification stored beside it."""
    rec = sim(Path(tmp_path_factory.mktemp("cert")))
    res = identify_recording(read_recording(rec))
    write_result(rec, f"identify_{res.method}_{res.model}", res.to_dict())
    return rec


def _copy(rec: Path, tmp: Path) -> Path:
    dst = tmp / "recordings"
    dst.mkdir()
    shutil.copy2(rec, dst / rec.name)
    shutil.copytree(rec.with_name(rec.stem + ".results"), dst / (rec.stem + ".results"))
    return dst / rec.name


def _pdf_text(pdf: bytes) -> str:
    return "\n".join(p.extract_text() for p in _pdf(pdf).pages)


def _pdf_says(pdf: bytes, text: str) -> bool:
    """Whether a page of the PDF holds ``text`` (read back page by page, up to the first that does:
    pypdf takes most of a second for a certificate's pages)."""
    return any(text in p.extract_text() for p in _pdf(pdf).pages)


@pytest.mark.slow
def test_draft_states_the_iso17025_content(stored: Path) -> None:
    c = certificate_content(stored)
    html = certificate_html(c)
    rec = read_recording(stored)
    env = next(d for d in rec.documents if d.get("kind") == "start")["metadata"]["environment"]
    assert env["source"] == "simulated room sensor" and 19 < env["temperature_c"] < 21
    for text in ("DRAFT", "Example Customer Ltd.", "sinecal demonstration laboratory", rec.transducer_id,
                 "CAL-DS-2026-014", "2027-06-30", "CAL-M-2026-003", "stepped sine", "crank", "Levenberg",
                 f"{env['temperature_c']:.1f} °C", "simulated room sensor", "relate only to the item calibrated",
                 "not approved", "model structure"):
        assert text in html, text
    names = [r["name"] for r in c["results"]]
    assert {"S", "k_f", "b_f", "natural_frequency_hz", "series_stiffness"} <= set(names)


def _pdf_cuts_nothing(c: dict[str, Any], text: str) -> None:
    """The PDF's text holds every budget row whole on one line (all its cells in order, "combined"
    last), every result with its uncertainties and unit, the coverage statement and the statement."""
    flat = re.sub(r"\s+", " ", text)
    assert "combined unit" in flat
    lines = text.splitlines()
    for row in c["budget"]["rows"]:
        want = " ".join([row["name"], *row["cells"], row["combined"], row["unit"]])
        assert want in lines, (want, [ln for ln in lines if ln.startswith(row["name"] + " ")])
    for r in c["results"]:
        assert f"{r['text']} {r['u_text']} {r['k_text']} {r['U_text']} {r['unit_text']}".strip() in flat, r["name"]
    assert "coverage factor k = 2" in flat and "95.45 %" in flat
    for s in c["statement"]:
        assert re.sub(r"\s+", " ", s) in flat


@pytest.mark.slow
def test_issue_needs_a_second_person_who_may_approve_and_is_immutable(stored: Path, tmp_path: Path) -> None:
    rec = _copy(stored, tmp_path)
    with pytest.raises(CertificateError, match="may not approve"):
        issue(rec, prepared_by=APPROVER, approver=TECH)
    with pytest.raises(CertificateError, match="second person"):
        issue(rec, prepared_by=APPROVER, approver=APPROVER)
    with pytest.raises(CertificateError, match="not a known user"):
        issue(rec, prepared_by="Nobody", approver=APPROVER)
    when = datetime(2026, 11, 24, 12, tzinfo=UTC)
    first = issue(rec, prepared_by=TECH, approver=APPROVER, now=when)
    assert first.number == "SC-2026-0001"
    # the PDF is the HTML and cuts nothing (WeasyPrint, about 2 s a PDF: the issued one is read back)
    text = _pdf_text(first.path("pdf").read_bytes())
    _pdf_cuts_nothing(first.record["content"], text)
    assert "SC-2026-0001" in text and "A. Approver (approver)" in text and "DRAFT" not in text
    assert read_issued(first.folder, first.number).record["sha256"] == first.record["sha256"]
    assert b"<dcc:uniqueIdentifier>SC-2026-0001</dcc:uniqueIdentifier>" in first.path("xml").read_bytes()
    _, html = draft(rec, TECH)
    assert "DRAFT" in html  # drafts stay drafts whatever was issued
    # a correction is a new certificate that says what it replaces; the old one stays as issued
    with pytest.raises(CertificateError, match="reason"):
        issue(rec, prepared_by=TECH, approver=APPROVER, replaces=first.number, now=when)
    second = issue(rec, prepared_by=TECH, approver=APPROVER, replaces=first.number, reason="customer address",
                   now=when)
    assert second.number == "SC-2026-0002"
    assert "replaces" in second.path("html").read_text() and first.number in second.path("html").read_text()
    with pytest.raises(CertificateError, match="replaced already"):
        issue(rec, prepared_by=TECH, approver=APPROVER, replaces=first.number, reason="again", now=when)
    listed = list_issued(first.folder, read_recording(rec).transducer_id)
    assert [(x["number"], x["replaced_by"]) for x in listed] == [("SC-2026-0001", "SC-2026-0002"),
                                                                 ("SC-2026-0002", None)]
    assert list_issued(first.folder, "OTHER") == []
    # altered after issue: refused when read
    p = first.path("html")
    p.write_text(p.read_text().replace("A. Approver", "B. Approver"))
    with pytest.raises(CertificateError, match="altered"):
        read_issued(first.folder, first.number)


@pytest.mark.slow
def test_api_drafts_issues_lists_and_serves_certificates(tmp_path: Path) -> None:
    """The daemon's app in process on a seeded store: draft, refused and accepted approval, the
    register per transducer, the issued forms."""
    import asyncio

    from tests.station_support import CAPPED_SPEEDUP, PASSWORDS, Seed, app_in_process, daemon_config, login, seed_runs

    rec = tmp_path / "recordings"
    [rid] = seed_runs(daemon_config(rec), [Seed()])

    async def go() -> None:
        async with app_in_process(rec, max_speedup=CAPPED_SPEEDUP) as (_, c):
            r = await c.get(f"/runs/{rid}/certificate.html")
            assert r.status_code == 200 and "DRAFT" in r.text and r.headers["content-type"].startswith("text/html")
            x = await c.get(f"/runs/{rid}/certificate.xml")  # a draft DCC, marked as such
            assert x.status_code == 200 and "<dcc:uniqueIdentifier>DRAFT-" in x.text and "DRAFT: not issued" in x.text
            assert (await c.get(f"/runs/{rid}/certificate.doc")).status_code == 422
            # the approver is who authenticates, never a name in the body; an admin may not approve
            assert (await c.post(f"/runs/{rid}/certificate", json={"prepared_by": TECH})).status_code == 403
            app = c._transport.app  # type: ignore[attr-defined]
            user = {"role": "approver", "password": PASSWORDS["anton"]}
            assert (await c.put("/users/anton", json=user)).status_code == 200
            assert (await c.put("/users/tina", json={"role": "technician"})).status_code == 200
            anton = await login(app, "anton")
            assert (await anton.post(f"/runs/{rid}/certificate", json={"approver": "x"})).status_code == 422
            bad = await anton.post(f"/runs/{rid}/certificate", json={"prepared_by": "anton"})
            assert bad.status_code in (403, 409) and "second person" in bad.json()["detail"]
            bad = await anton.post(f"/runs/{rid}/certificate", json={"prepared_by": TECH})  # free text
            assert bad.status_code == 409 and "not an enabled user of the lab" in bad.json()["detail"]
            ok = await anton.post(f"/runs/{rid}/certificate", json={"prepared_by": "tina"})
            assert ok.status_code == 201, ok.text
            number = ok.json()["number"]
            html = (await c.get(f"/runs/{rid}/certificate.html")).text
            assert number in html and "DRAFT" not in html and "anton (approver)" in html
            audit = (await c.get("/audit")).json()
            assert "certificate" in str(audit)
            pdf = await c.get(ok.json()["pdf"])
            assert pdf.headers["content-type"] == "application/pdf" and _pdf_says(pdf.content, number)
            xml = await c.get(f"/runs/{rid}/certificate.xml")
            assert xml.status_code == 200 and f"<dcc:uniqueIdentifier>{number}<".encode() in xml.content
            listed = (await c.get("/certificates", params={"transducer": "TX5K-0001"})).json()["certificates"]
            assert [x["number"] for x in listed] == [number]
            assert (await c.get("/certificates", params={"transducer": "OTHER"})).json()["certificates"] == []
            assert (await c.get("/certificates/SC-1999-0001.html")).status_code == 404
            rp = await c.get(f"/runs/{rid}/report.pdf")
            assert rp.headers["content-type"] == "application/pdf" and _pdf_says(rp.content, "Uncertainty statement")
    asyncio.run(go())


@pytest.mark.slow
def test_cli_writes_the_three_forms_and_refuses_to_issue(stored: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """`station certificate` in process: issuing is refused (exit 1, the station named on stderr);
    a certificate issued as the station's worker issues it is written in its three forms and listed."""
    import json

    from station.cli import main

    rec = _copy(stored, tmp_path)
    assert main(["certificate", str(rec), "--issue"]) == 2  # bad input
    assert "issued through the station" in capsys.readouterr().err
    # issued as the test above issues its first one: the same page, its PDF laid out once per process
    number = issue(rec, prepared_by=TECH, approver=APPROVER, now=datetime(2026, 11, 24, 12, tzinfo=UTC)).number
    out = tmp_path / "out"
    out.mkdir()
    assert main(["certificate", str(rec), "--html", str(out / "c.html"), "--pdf", str(out / "c.pdf"),
                 "--xml", str(out / "c.xml")]) == 0
    assert number in (out / "c.html").read_text() and _pdf_says((out / "c.pdf").read_bytes(), number)
    assert f"<dcc:uniqueIdentifier>{number}</dcc:uniqueIdentifier>" in (out / "c.xml").read_text()
    capsys.readouterr()
    assert main(["certificate", str(rec), "--list", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["certificates"]
    assert [c["number"] for c in listed] == [number]
