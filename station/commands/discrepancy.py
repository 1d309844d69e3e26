"""``station discrepancy RECORDING``: the model-gap workflow on a recording."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from station.discrepancy.result import DiscrepancyResult
    from station.ident.result import Estimate


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("discrepancy", help="find, name and remove the model gap of a recording")
    p.add_argument("recording", type=Path, help="recording (.h5), own or imported")
    p.add_argument("--json", action="store_true", help="print the JSON result (stable contract)")
    p.add_argument("--max-effects", type=int, default=4, help="most effects to add (default 4)")
    p.add_argument("--plot", type=Path, default=None,
                   help="PNG of the gap per step and stage (default: RECORDING.discrepancy.png)")
    p.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    p.add_argument("--save", action="store_true", help="store the result beside the recording "
                   "(<run>.results/results.discrepancy.h5)")
    p.add_argument("--config", type=Path, default=None,
                   help="the rig's station configuration (YAML): its limits bound a proposed follow-up run "
                        "(default: the limits the recording states)")
    p.set_defaults(handler=run)


def _est(e: Estimate) -> str:
    if not e.identifiable:
        return f"not identifiable ({e.reason})"
    return f"{e.value:.6g} ± {e.std:.2g} {e.unit}"


def text_report(rep: DiscrepancyResult) -> str:
    """Human-readable summary: gaps, named effects with parameters, before/after, what is left."""
    from station.discrepancy.workflow import gap_table

    lines = [f"recording {rep.recording}",
             f"noise floor {rep.noise_floor_V:.4g} V; gap {rep.base_gap:.4g} V -> {rep.final_gap:.4g} V"]
    if rep.base_findings:
        lines.append("where the base model disagrees:")
        lines += [f"  - {t}" for t in rep.base_findings]
    lines.append("force fundamental, measured vs model (gain %, phase mrad, z), base -> final:")
    for b, a in zip(rep.base_fundamental, rep.final_fundamental, strict=True):
        lines.append(f"  {b[0]:8.4g} Hz: {b[1]:+9.4f} % {b[2]:+9.4f} mrad z {b[3]:8.3g}  ->  "
                     f"{a[1]:+9.4f} % {a[2]:+9.4f} mrad z {a[3]:6.3g}")
    lines.append("gap per step (V): " + "  ".join(f"{f:.4g} Hz" for f in rep.f_hz))
    for stage, g in gap_table(rep):
        lines.append(f"  {stage:<28s}" + "  ".join(f"{x:.3e}" for x in g))
    for e in rep.effects:
        lines.append(f"named: {e.name}: " + "; ".join(f"{k} = {_est(v)}" for k, v in e.params.items()))
        lines.append(f"  evidence: {e.evidence}")
    if not rep.effects:
        lines.append("named: nothing (no catalogue effect improves the fit significantly)")
    lines.append("transducer before -> after:")
    for k, v in rep.parameters_before.items():
        after = rep.parameters_after.get(k)
        lines.append(f"  {k}: {_est(v)} -> {_est(after) if after else '-'}")
    for k, v in rep.parameters_after.items():
        if k not in rep.parameters_before:
            lines.append(f"  {k}: - -> {_est(v)}")
    lines.append("unexplained: " + ("nothing significant" if not rep.unexplained else ""))
    lines += [f"  - {t}" for t in rep.unexplained]
    lines += [f"note: {n}" for n in rep.notes]
    if rep.proposal is None and rep.proposal_note:
        lines.append(f"proposal: {rep.proposal_note}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from station.discrepancy import analyse_recording
    from station.discrepancy.plot import plot_report
    from station.recording import write_result

    station = None
    if args.config is not None:
        from station.config import load_config

        station = load_config(args.config)
    rep = analyse_recording(args.recording, max_effects=args.max_effects, station=station)
    if not args.no_plot:
        png = args.plot or args.recording.with_name(args.recording.name + ".discrepancy.png")
        plot_report(rep, png)
    if args.save:
        write_result(args.recording, "discrepancy", {**rep.to_dict(), "max_effects": args.max_effects})
    if args.json:
        print(json.dumps(rep.to_json(), indent=2))
    else:
        print(text_report(rep))
    return 0
