"""Certificates: a run's certificate (the issued one, else its draft) as HTML, PDF and DCC XML,
issuing it, and the register of issued certificates per transducer (docs/certificate.md)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Query, Response

from station.api.deps import Approver, ArtifactsDep, ManagerDep, Reader, RunDep
from station.api.routes.runs import BINARY, BODY_ERRORS, E401, E403, E404, E409, E422, E503, NON_JSON_ERRORS
from station.api.schemas import CertificateIssueIn, CertificateList, CertificateOut
from station.certificate.register import MEDIA, CertificateError

router = APIRouter(tags=["certificates"])
Ext = Literal["html", "pdf", "xml"]
DOCS: dict[int | str, dict[str, Any]] = {200: {"content": {m.split(";")[0]: {"schema": BINARY if "pdf" in m
                                                                    else {"type": "string"}}
                                                         for m in MEDIA.values()},
                                               "description": "the certificate in the asked form"}}


def _out(c: dict[str, Any]) -> CertificateOut:
    base = f"/certificates/{c['number']}"
    return CertificateOut(**c, html=f"{base}.html", pdf=f"{base}.pdf", xml=f"{base}.xml")


@router.get("/runs/{run_id}/certificate.{ext}", response_class=Response, dependencies=[Reader],
            responses={**DOCS, **NON_JSON_ERRORS}, summary="The run's certificate (issued, else the draft)")
async def run_certificate(run: RunDep, artifacts: ArtifactsDep, ext: Ext) -> Response:
    """The latest issued certificate of the run that has not been replaced; before it is issued, the
    draft (marked DRAFT; its DCC with the identifier DRAFT-<run id> and a draft statement)."""
    return Response(await artifacts.certificate(run.id, ext), media_type=MEDIA[ext])


@router.post("/runs/{run_id}/certificate", response_model=CertificateOut, status_code=201,
             responses={**E401, **E403, **E404, **E409, **E422, **E503, **BODY_ERRORS},
             summary="Issue the run's certificate (approval by a second person)")
async def issue_certificate(run: RunDep, artifacts: ArtifactsDep, manager: ManagerDep, who: Approver,
                            body: CertificateIssueIn) -> CertificateOut:
    """The authenticated approver approves the run (`POST /runs/{id}/approve`'s checks: an approver
    who did not run it, the recording's SHA-256 as stored at closing; audit trail) and issues its
    certificate: numbered, stored immutable with its hashes, with the register's transducer and
    standards as the run used them.  409 when a standard was overdue or `replaces` cannot be replaced."""
    prepared = body.prepared_by or run.operator
    if not prepared:
        raise CertificateError("the run has no recorded operator: say who prepared the certificate (prepared_by)")
    await manager.approve(run.id, who.user, body.note or f"certificate of run {run.id}")
    roles = {prepared: "operator", who.name: str(who.user.role)}
    return _out(await artifacts.issue_certificate(run.id, prepared, who.name, roles, body.replaces, body.reason))


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
