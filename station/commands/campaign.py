"""``station identify REC1 REC2 ...``: several recordings of one transducer with different top masses,
identified jointly (S, m_e, k_f, b_f; ``station.ident.campaign.identify``)."""

from __future__ import annotations

import json
from pathlib import Path

from station.errors import BadInputError
from station.ident.campaign.identify import RESULT_NAME, CampaignRefused, identify_campaign
from station.ident.campaign.result import CampaignResult
from station.recording import read_recording, write_result


def format_text(res: CampaignResult) -> str:
    """Human-readable campaign result: status, checks, parameters with budget, recordings, fit."""
    lines = [f"campaign of {len(res.recordings)} recordings of {res.transducer_id}: {res.status}"]
    lines += [f"  check {c.severity}: {c.name}: {c.message}" for c in res.checks]
    for name, p in res.parameters.items():
        if p.identifiable:
            flag = p.flag
            lines.append(f"  {name:4s} = {p.value:.7g} {p.unit}  (std {p.std:.2g})" + (f"  [{flag}]" if flag else ""))
            b = res.budget.get(name)
            if b:
                lines.append("       budget: " + ", ".join(f"{k} {v:.2g}" for k, v in b.stds.items()
                                                           if v is not None) + f"; combined {b.combined:.2g}")
        else:
            lines.append(f"  {name:4s}   not given: {p.reason}")
    for r in res.recordings:
        lines.append(f"  {Path(r.path).name}: m_l {r.load_mass_kg:.6g} kg (std {r.load_mass_std_kg:.2g}), "
                     f"{len(r.steps_used)} steps {r.f_range_hz[0]:.4g}-{r.f_range_hz[1]:.4g} Hz, "
                     f"chi2 {r.chi2:.3g} on {2 * len(r.steps_used)}")
    lines.append(f"  fit: chi2/dof {res.chi2_per_dof:.3g} ({res.chi2:.4g} on {res.dof})")
    from station.report.quantities import structure_sentence

    lines.append(f"  structure: {structure_sentence(res.assumptions.structure.to_dict())}")
    lines += [f"  note: {n}" for n in res.notes]
    return "\n".join(lines)


def run_campaign(paths: list[Path], *, as_json: bool, write: bool, end_mass_kg: float | None = None,
                 end_mass_std_kg: float | None = None) -> int:
    """Identify the recordings jointly, print the result, store it in each of them unless told not to."""
    for p in paths:
        if not p.exists():
            raise BadInputError(f"{p}: no such recording")
    recs = [read_recording(p) for p in paths]
    try:
        res = identify_campaign(recs, assumed_end_mass_kg=end_mass_kg, assumed_end_mass_std_kg=end_mass_std_kg)
    except CampaignRefused as exc:
        if not as_json:
            raise
        print(json.dumps({"refused": True, "message": str(exc), "checks": [c.to_dict() for c in exc.checks]},
                         indent=2))
        return exc.exit_code
    payload = res.to_dict()
    if write:
        payload["stored_as"] = [str(write_result(p, RESULT_NAME, payload).relative_to(p.parent)) for p in paths]
    print(json.dumps(payload, indent=2) if as_json else format_text(res))
    return 0
