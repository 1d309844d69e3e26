"""``station identify RECORDING``: identify the transducer and store the result in the recording."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from station.errors import BadInputError
from station.ident.names import METHODS, MODELS

if TYPE_CHECKING:
    from station.ident.result import IdentificationResult


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("identify", help="identify stiffness, damping and sensitivity from a recording")
    p.add_argument("recording", type=Path, nargs="?", default=None, help="HDF5 recording of a run")
    p.add_argument("more", type=Path, nargs="*", metavar="RECORDING",
                   help="further recordings of the same transducer with other top masses: all are identified "
                        "jointly (multi-mass campaign: S, m_e, k_f, b_f; method fd, model sdof)")
    p.add_argument("--method", choices=METHODS, default=None,
                   help="fd (default: sine fits + weighted LM), oe (time-domain output error), "
                        "pso, pso+, rls (the paper's, on one step)")
    p.add_argument("--model", choices=MODELS, default=None,
                   help="sdof (Eq. 9, default), coupled (Eq. 8), h2/h1 (the paper's digital Eq. 11/10)")
    p.add_argument("--seed", type=int, default=0, help="seed of the swarm (pso, pso+)")
    p.add_argument("--end-mass", type=float, default=None, metavar="KG",
                   help="end mass m_e to assume when the recording gives none (results conditional on it "
                        "unless --end-mass-std states its uncertainty)")
    p.add_argument("--end-mass-std", type=float, default=None, metavar="KG",
                   help="standard uncertainty of --end-mass, propagated into S, k_f, b_f")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--no-write", action="store_true", help="do not store the result in the recording")
    p.set_defaults(handler=run)


def format_text(res: IdentificationResult) -> str:
    """Human-readable result: checks, one line per parameter with its budget, the assumptions,
    what the data determine, then the fit and the notes."""
    lines = [f"method {res.method}, model {res.model}"]
    lines += [f"  check {c.severity}: {c.name}: {c.message}" for c in res.checks]
    for name, p in res.parameters.items():
        if p.identifiable:
            lines.append(f"  {name:4s} = {p.value:.7g} {p.unit}  (std {p.std:.2g})"
                         + (f"  [{p.flag}: {p.reason}]" if p.flag else ""))
            b = res.budget.get(name)
            if b:
                lines.append("       budget: " + ", ".join(
                    f"{k} {v:.2g}" if v is not None else f"{k} (conditional)"
                    for k, v in b.stds.items()) + f"; combined {b.combined:.2g}")
        else:
            lines.append(f"  {name:4s}   not identifiable: {p.reason}")
    em = res.assumptions.end_mass
    if em is not None:
        lines.append(f"  end mass m_e = {em.value:g} kg ({em.source}"
                     + (f", std {em.std:.2g} kg)" if em.std is not None else ", no uncertainty: "
                        "S, k_f, b_f are conditional on it)"))
    from station.report.quantities import range_text, structure_sentence

    st = res.assumptions.structure
    if st is not None:
        lines.append(f"  structure: {structure_sentence(st.to_dict())}")
    for k, d in res.determined.items():
        if d.range is not None:
            lines.append(f"  determined: {k} in {range_text(d.range)} {d.unit}, {d.conditional_on}")
        else:
            lines.append(f"  determined: {k} = {d.value:.7g} {d.unit} (std {d.combined:.2g})")
    rms = ", ".join(f"{v:.3g}" for v in res.fit.residual_rms_V)
    lines.append(f"  fit: MSE {res.fit.mse:.4g} V^2, residual RMS per step [{rms}] V")
    if res.identifiability is not None:
        lines.append(f"  condition number {res.identifiability.condition_number:.3g}")
    lines += [f"  note: {n}" for n in res.notes]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from station.ident.identify import identify_recording, store_result
    from station.ident.response.gate import IdentificationRefused
    from station.recording import read_recording

    if args.recording is None:
        raise BadInputError("name the recording to identify, e.g. `station identify recordings/<run id>.h5` "
                            "(the runs are in the configuration's station.recordings_dir)")
    if args.more:
        from station.commands.campaign import run_campaign

        if args.method not in (None, "fd") or args.model not in (None, "sdof", "h2"):
            raise BadInputError("a campaign of several recordings is identified with --method fd, --model sdof")
        if args.end_mass is None and args.end_mass_std is not None:
            raise BadInputError("--end-mass-std needs --end-mass")
        return run_campaign([args.recording, *args.more], as_json=args.json, write=not args.no_write,
                            end_mass_kg=args.end_mass, end_mass_std_kg=args.end_mass_std)

    if not args.recording.exists():
        raise BadInputError(f"{args.recording}: no such recording")
    rec = read_recording(args.recording)
    inputs = None
    if args.end_mass is not None or args.end_mass_std is not None:
        from station.ident.inputs import inputs_for

        if rec.end_mass_kg is not None:
            raise BadInputError(f"{args.recording}: the recording gives the end mass ({rec.end_mass_kg:g} kg); "
                                "--end-mass is only for recordings without one")
        if args.end_mass is None or args.end_mass <= 0 or (args.end_mass_std is not None and args.end_mass_std < 0):
            raise BadInputError(f"--end-mass > 0 kg (and --end-mass-std >= 0 kg) expected, got {args.end_mass!r}, "
                                f"{args.end_mass_std!r}")
        inputs = inputs_for(rec, assumed_end_mass_kg=args.end_mass, assumed_end_mass_std_kg=args.end_mass_std)
    try:
        res = identify_recording(rec, args.method, args.model, seed=args.seed, inputs=inputs)
    except IdentificationRefused as exc:
        if not args.json:
            raise
        print(json.dumps({"refused": True, "message": str(exc), "checks": [c.to_dict() for c in exc.checks]},
                         indent=2))
        return exc.exit_code
    payload = res.to_dict()
    if not args.no_write:
        payload["stored_as"] = store_result(args.recording, res)
    print(json.dumps(payload, indent=2) if args.json else format_text(res))
    return 0
