"""Certificates: a run's certificate (the issued one, else its draft) as HTML, PDF and DCC XML,
issuing it, and the register of issued certificates per transducer (docs/certificate.md)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Query, Response

from station.api.deps import ArtifactsDep, Reader, RunDep, Writer
from station.api.routes.runs import BODY_ERRORS, E401, E404, E409, E422, E503, NON_JSON_ERRORS
from station.api.schemas import CertificateIssueIn, CertificateList, CertificateOut
from station.certificate.register import MEDIA

router = APIRouter(tags=["certificates"])
Ext = Literal["html", "pdf", "xml"]
DOCS: dict[int | str, dict[str, Any]] = {200: {"content": {m.split(";")[0]: {"schema": {"type": "string"}}
                                                         for m in MEDIA.values()},
                                               "description": "the certificate in the asked form"}}


def _out(c: dict[str, Any]) -> CertificateOut:
    base = f"/certificates/{c['number']}"
    return CertificateOut(**c, html=f"{base}.html", pdf=f"{base}.pdf", xml=f"{base}.xml")


@router.get("/runs/{run_id}/certificate.{ext}", response_class=Response, dependencies=[Reader],
            responses={**DOCS, **NON_JSON_ERRORS}, summary="The run's certificate (issued, else the draft)")
async def run_certificate(run: RunDep, artifacts: ArtifactsDep, ext: Ext) -> Response:
    """The latest issued certificate of the run that has not been replaced; before it is issued, the
    draft (marked DRAFT; HTML and PDF only)."""
    return Response(await artifacts.certificate(run.id, ext), media_type=MEDIA[ext])


@router.post("/runs/{run_id}/certificate", response_model=CertificateOut, status_code=201, dependencies=[Writer],
             responses={**E401, **E404, **E409, **E422, **E503, **BODY_ERRORS},
             summary="Issue the run's certificate (approval by a second person)")
async def issue_certificate(run: RunDep, artifacts: ArtifactsDep, body: CertificateIssueIn) -> CertificateOut:
    """Numbers the run's certificate and stores it, immutable, with its hashes; 409 when the approver
    may not approve, approves their own work, a standard was overdue, or `replaces` cannot be replaced."""
    return _out(await artifacts.issue_certificate(run.id, body.prepared_by, body.approver, body.replaces,
                                                  body.reason))


@router.get("/certificates", response_model=CertificateList, dependencies=[Reader], responses={**E401, **E422},
            summary="Issued certificates, optionally of one transducer")
async def list_certificates(artifacts: ArtifactsDep,
                            transducer: Annotated[str | None, Query(max_length=64)] = None) -> CertificateList:
    return CertificateList(certificates=[_out(c) for c in await artifacts.certificates(transducer)])


@router.get("/certificates/{number}.{ext}", response_class=Response, dependencies=[Reader],
            responses={**DOCS, **NON_JSON_ERRORS}, summary="An issued certificate as issued")
async def issued_certificate(artifacts: ArtifactsDep, ext: Ext,
                             number: Annotated[str, Path(pattern=r"^[A-Za-z0-9\-]{1,40}$")]) -> Response:
    return Response(await artifacts.issued_certificate(number, ext), media_type=MEDIA[ext])
