"""``station verify``: walk the station's audit chain and compare every recording, results file,
certificate and row of the lab's tables it vouches for (exit 0 when everything holds, 1 naming the
first broken link and every file or row that differs); ``--except ENTRY --reason TEXT`` records an
administrator's reviewed exception for a broken link (an audit entry: the break stays listed, it no
longer blocks issuing).
``station verify CERTIFICATE --key PUBLIC.pem`` checks one certificate file off-line, as a customer
does: no station, no database, the lab's public key alone.  ``station keys`` makes the lab's key.

    station verify
    station verify --except 412 --reason "entry 412 was restored from the backup of 3 May; reviewed by QM"
    station verify SC-2026-0007.pdf --key lab-public.pem
    station keys init          (station keys rotate, station keys show)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("verify", help="check the audit chain and every file it vouches for, or one certificate")
    p.add_argument("certificate", nargs="?", type=Path, default=None, metavar="CERTIFICATE",
                   help="an issued certificate file (HTML, PDF or DCC XML) to check against --key off-line")
    p.add_argument("--key", type=Path, default=None, metavar="PUBLIC.pem", help="the lab's public key (PEM)")
    p.add_argument("--signature", type=Path, default=None, metavar="FILE",
                   help="the signature file (default: <certificate>.sig beside it)")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--except", dest="exception", type=int, default=None, metavar="ENTRY",
                   help="record a reviewed exception for the broken link at this audit entry")
    p.add_argument("--reason", default="", help="what was reviewed (with --except)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=_run)

    k = sub.add_parser("keys", help="the lab's signing key: init, rotate, show")
    k.add_argument("action", choices=("init", "rotate", "show"))
    k.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    k.add_argument("--public", type=Path, default=None, metavar="FILE", help="also write the public key (PEM) here")
    k.set_defaults(handler=_keys)


def _keys(args: argparse.Namespace) -> int:
    from station.commands.lab import cli_user, open_store
    from station.lab import audit, signing

    store, settings = open_store(args)
    try:
        p = Path(settings.config.lab.signing_key).expanduser()
        path = p if p.is_absolute() else settings.database.parent / p
        if args.action == "show":
            key = signing.load_key(path)
        else:
            key, retired = signing.init_key(path, rotate=args.action == "rotate")
            fp = signing.fingerprint(key.public_key())
            audit.append(store, cli_user(), audit.KEY_CREATED, "signing-key",
                         {"fingerprint": fp, "path": str(path), "retired": str(retired) if retired else None})
            if retired:
                print(f"retired key kept as {retired} (its public key: {retired}.pub)")
    finally:
        store.close()
    pub = signing.public_pem(key.public_key())
    if args.public is not None:
        args.public.write_text(pub)
    print(f"{signing.ALGORITHM} key {path} (mode 0600)\nfingerprint {signing.fingerprint(key.public_key())}\n{pub}",
          end="")
    return 0


def _certificate(args: argparse.Namespace) -> int:
    from station.errors import BadInputError
    from station.lab import signing

    if args.key is None:
        raise BadInputError("station verify CERTIFICATE needs --key: the lab's public key (GET /signing-key)")
    try:
        st = signing.verify_file(args.certificate, signing.load_public(args.key.read_bytes()), args.signature)
    except signing.SigningError as exc:
        print(f"{args.certificate.name}: FAILED: {exc}")
        return 1
    if args.json:
        print(json.dumps(st, indent=1))
    else:
        print(f"{args.certificate.name}: OK: certificate {st['number']} as the lab signed it "
              f"(key {st['key_fingerprint']}, audit chain head {st['audit_chain_head']['id']})")
    return 0


def _run(args: argparse.Namespace) -> int:
    from station.commands.lab import cli_user, open_store
    from station.errors import BadInputError
    from station.lab import audit, chain, policy

    if args.certificate is not None:
        return _certificate(args)
    store, settings = open_store(args)
    try:
        if args.exception is not None:
            if len(args.reason.strip()) < 10:
                raise BadInputError("--except needs --reason saying what was reviewed (10 characters at least)")
            with store.reading() as db:
                state = chain.verify_chain(db)
            if not any(b.id == args.exception for b in state.breaks):
                raise BadInputError(f"the audit chain has no broken link at entry {args.exception} "
                                    f"({state.describe()})")
            audit.append(store, cli_user(), audit.AUDIT_EXCEPTION, "audit",
                         {"entry": args.exception, "reason": args.reason.strip()})
        with store.reading() as db:
            state, latest, records = chain.verify_chain(db), chain.latest_files(db), policy.record_mismatches(db)
        out = chain.integrity_report(state, latest, settings.recordings_dir, records)
    finally:
        store.close()
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        print(out["detail"].split("; ")[0])
        for b in out["breaks"]:
            print(f"  entry {b['id']}: {b['reason']}"
                  + (f" (reviewed: exception {b['excepted_by']})" if b["excepted_by"] else ""))
        for f in out["files"]:
            print(f"  file {f}")
        for r in out["records"]:
            print(f"  row {r}")
        print("OK" if out["ok"] else "FAILED")
    return 0 if out["ok"] else 1
