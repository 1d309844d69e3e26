"""``station certificate``: a recording's certificate (draft or issued) as HTML, PDF or DCC XML and
the certificates issued in its folder.  Issuing is the station's (``POST /runs/{id}/certificate`` or
the page): an authenticated approver, the lab's users, the database's number sequence and the audit
trail; ``--issue`` here says so."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("certificate", help="a recording's calibration certificate: draft, issue, list")
    p.add_argument("recording", type=Path, metavar="RECORDING", help="the run's .h5 recording")
    p.add_argument("--html", type=Path, metavar="FILE", help="write the certificate as HTML")
    p.add_argument("--pdf", type=Path, metavar="FILE", help="write the certificate as PDF")
    p.add_argument("--xml", type=Path, metavar="FILE", help="write the DCC (a draft one marked as a draft)")
    p.add_argument("--issue", action="store_true", help="refused: certificates are issued through the station")
    p.add_argument("--list", action="store_true", help="list the issued certificates of this transducer")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from station.certificate.issue import folder_of, run_document
    from station.errors import BadInputError
    from station.lab.issued import list_issued
    from station.recording import read_recording

    out: dict[str, object] = {}
    if args.issue:
        raise BadInputError("certificates are issued through the station by an authenticated approver (POST "
                            "/runs/{id}/certificate, or the page): the lab's users, its number sequence and its "
                            "audit trail; this command writes drafts and issued certificates as they are")
    for ext in ("html", "pdf", "xml"):
        target = getattr(args, ext)
        if target is not None:
            target.write_bytes(run_document(args.recording, ext))
            out[ext] = str(target)
    if args.list:
        out["certificates"] = list_issued(folder_of(args.recording), read_recording(args.recording).transducer_id)
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k, v in out.items():
            if k == "certificates" and isinstance(v, list):
                for c in v:
                    print(f"{c['number']}  {c['issued_at']}  run {c['run_id']}  approved by {c['approved_by']}"
                          + (f"  replaces {c['replaces']}" if c["replaces"] else "")
                          + (f"  REPLACED by {c['replaced_by']}" if c["replaced_by"] else ""))
            else:
                print(f"{k}: {v}")
    return 0
