"""Certificates: a run's certificate (the issued one, else its draft) as HTML, PDF and DCC XML,
issuing it, and the register of issued certificates per transducer (docs/certificate.md)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Path, Query, Response

from station.api.deps import Approver, ArtifactsDep, ManagerDep, Reader, RunDep
from station.api.routes import api_router
from station.api.routes.runs import BINARY, BODY_ERRORS, E401, E403, E404, E409, E422, E503, NON_JSON_ERRORS
from station.api.schemas import (
    CertificateIssueIn,
    CertificateList,
    CertificateOut,
    CertificateWithdrawIn,
    ErrorOut,
    SigningKeyOut,
)
from station.lab.issued import MEDIA

router = api_router(tags=["certificates"])
Ext = Literal["html", "pdf", "xml"]
DOCS: dict[int | str, dict[str, Any]] = {200: {"content": {m.split(";")[0]: {"schema": BINARY if "pdf" in m
                                                                    else {"type": "string"}}
                                                         for m in MEDIA.values()},
                                               "description": "the certificate in the asked form"}}


def _out(c: dict[str, Any]) -> CertificateOut:
    base = f"/certificates/{c['number']}"
    return CertificateOut(**{k: v for k, v in c.items() if k != "files"}, html=f"{base}.html", pdf=f"{base}.pdf",
                          xml=f"{base}.xml")


@router.get("/runs/{run_id}/certificate.{ext}", response_class=Response, dependencies=[Reader],
            responses={**DOCS, **NON_JSON_ERRORS}, summary="The run's certificate (issued, else the draft)")
async def run_certificate(run: RunDep, artifacts: ArtifactsDep, ext: Ext) -> Response:
    """The latest issued certificate of the run that has not been replaced; before it is issued, the
    draft (marked DRAFT; its DCC with the identifier DRAFT-<run id> and a draft statement)."""
    return Response(await artifacts.certificate(run.id, ext), media_type=MEDIA[ext])


@router.post("/runs/{run_id}/certificate", response_model=CertificateOut, status_code=201,
             responses={**E401, **E403, **E404, **E409, **E422, **E503, **BODY_ERRORS},
             summary="Issue the run's certificate (approval by a second person)")
async def issue_certificate(run: RunDep, manager: ManagerDep, who: Approver,
                            body: CertificateIssueIn) -> CertificateOut:
    """The authenticated approver issues the run's certificate: the audit chain intact, the preparer
    an enabled user of the lab (the run's operator by default), the approver neither the preparer nor
    the operator, no other certificate of the run in force unless this one `replaces` it with a
    `reason`, the run's files as the audit trail vouches for them.  It is numbered from the lab's
    sequence, stored immutable, and its issue entry names the number and each file's SHA-256.  A
    refusal (403, 409) writes one `certificate.refused` entry and nothing else."""
    return _out(await manager.issue_certificate(run.id, who.user, body.prepared_by, body.replaces, body.reason))


@router.post("/certificates/{number}/withdraw", response_model=CertificateOut,
             responses={**E401, **E403, **E404, **E409, **E422, **BODY_ERRORS},
             summary="Withdraw an issued certificate (an approver, with the reason)")
async def withdraw_certificate(manager: ManagerDep, who: Approver, body: CertificateWithdrawIn,
                               number: Annotated[str, Path(pattern=r"^[A-Za-z0-9\-]{1,40}$")]) -> CertificateOut:
    """The certificate stays as issued; the audit trail records who withdrew it and why, and the
    register shows it no longer in force."""
    return _out(await manager.withdraw_certificate(who.user, number, body.reason))


@router.get("/signing-key", response_model=SigningKeyOut, responses={409: {"model": ErrorOut}},
            summary="The lab's public key that verifies its certificates (no login needed)")
async def signing_key(manager: ManagerDep) -> SigningKeyOut:
    """What a customer needs to check a certificate off-line (`station verify CERTIFICATE --key
    FILE`): the Ed25519 public key (PEM) and its fingerprint, as printed on each certificate."""
    return SigningKeyOut(**manager.public_key())


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
