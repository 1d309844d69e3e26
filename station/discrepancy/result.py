"""Frozen result types of the model-gap workflow and their JSON form (the ``--json`` contract); a
candidate effect tried in a round is ``search.Candidate``.

``DiscrepancyResult`` is what ``analyse_recording`` returns and what is stored beside a recording as
result ``discrepancy``; its parameters are ``station.ident.result.Estimate`` (the one estimate type of
the station).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TypedDict

from station.discrepancy.drive import DriveCheck, DriveJson
from station.discrepancy.estimates import EstimateJson
from station.discrepancy.propose import Proposal, ProposalJson
from station.discrepancy.search import Candidate
from station.discrepancy.structure import Structure, StructureJson
from station.discrepancy.ties import Tie, TieJson
from station.ident.result import Estimate


class EffectJson(TypedDict):
    """An added effect in the ``--json`` contract: its parameters' estimates, the RMS force gap after
    it (V), the evidence sentence, the other candidates of its round that fit as well."""

    name: str
    params: dict[str, EstimateJson]
    gap_after: float
    evidence: str
    tied_with: list[str]


class DiscrepancyJson(TypedDict):
    """``DiscrepancyResult.to_json``: the stable ``--json`` contract (gaps in V, parameters as estimates
    with their units, the sub-results' own JSON forms or None)."""

    base_gap: float
    effects: list[EffectJson]
    final_gap: float
    parameters_before: dict[str, EstimateJson]
    parameters_after: dict[str, EstimateJson]
    unexplained: list[str]
    ties: list[TieJson]
    notes: list[str]
    drive: DriveJson | None
    proposal: ProposalJson | None
    proposal_note: str | None
    structure: StructureJson | None


class CandidateJson(TypedDict):
    """A candidate of a round (``search.Candidate``): chi^2 decrease, added parameters, p-value, Delta BIC,
    gap after (V)."""

    name: str
    delta_chi2: float
    added_params: int
    p_value: float
    delta_bic: float
    gap_V: float


class DiscrepancyDict(DiscrepancyJson):
    """``DiscrepancyResult.to_dict``: the contract plus the details stored beside the recording: the noise
    floor (V), per step the recording's index, the frequency (Hz) and the gaps (V), the force
    fundamental's rows (``fundamental_columns``: Hz, %, mrad, z), the rounds' and the last round's
    rejected candidates."""

    recording: str
    noise_floor_V: float
    steps: list[int]
    f_hz: list[float]
    base_gap_steps: list[float]
    final_gap_steps: list[float]
    effect_gap_steps: dict[str, list[float]]
    base_findings: list[str]
    mains_search: str
    fundamental_columns: list[str]
    base_fundamental: list[list[float]]
    final_fundamental: list[list[float]]
    rounds: list[list[CandidateJson]]
    rejected: list[CandidateJson]


def candidate_json(c: Candidate) -> CandidateJson:
    return CandidateJson(name=c.name, delta_chi2=c.delta_chi2, added_params=c.added_params, p_value=c.p_value,
                         delta_bic=c.delta_bic, gap_V=c.gap_V)


@dataclass(frozen=True)
class AddedEffect:
    """An effect the workflow named: parameters with uncertainties, gap after it (V), overall and
    per step (n,), the evidence sentence, and the candidates of its round."""

    name: str
    params: dict[str, Estimate]
    gap_after: float
    gap_steps_after: tuple[float, ...]
    evidence: str
    candidates: tuple[Candidate, ...]
    parameters: dict[str, Estimate]
    tied: tuple[str, ...] = ()  # the candidates of its round that fit as well (itself included)

    def to_dict(self) -> EffectJson:
        return {"name": self.name, "params": {k: v.to_dict() for k, v in self.params.items()},
                "gap_after": float(self.gap_after), "evidence": self.evidence,
                "tied_with": [t for t in self.tied if t != self.name]}


@dataclass(frozen=True)
class DiscrepancyResult:
    """Result of ``analyse_recording``.

    base_gap / final_gap: RMS force residual (V) of the base and the final model over all record
    windows; noise_floor_V: RMS of the force noise measured from the data (the gap cannot go below);
    steps / f_hz / base_gap_steps / final_gap_steps: per step (recording index, Hz, V);
    base_findings: where the base model disagrees; unexplained: what no catalogue effect explains;
    rejected: the last round's candidates that were not significant; base_fundamental /
    final_fundamental: per step (f Hz, gain error %, phase error mrad, z) of the force fundamental.
    """

    recording: str
    base_gap: float
    final_gap: float
    noise_floor_V: float
    effects: tuple[AddedEffect, ...]
    parameters_before: dict[str, Estimate]
    parameters_after: dict[str, Estimate]
    unexplained: tuple[str, ...]
    base_findings: tuple[str, ...]
    steps: tuple[int, ...]
    f_hz: tuple[float, ...]
    base_gap_steps: tuple[float, ...]
    final_gap_steps: tuple[float, ...]
    rejected: tuple[Candidate, ...] = ()
    base_fundamental: tuple[tuple[float, float, float, float], ...] = ()
    final_fundamental: tuple[tuple[float, float, float, float], ...] = ()
    mains_search: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    wall_s: float = 0.0
    proposal: Proposal | None = None  # the next run that settles a tie
    proposal_note: str = ""  # why there is no proposal ('' when there is one)
    structure: Structure | None = None  # the model parameters_after rests on, and what a coupling changes
    ties: tuple[Tie, ...] = ()  # models the data do not decide between
    drive: DriveCheck | None = None  # the recorded frame motion against the slider crank

    def to_json(self) -> DiscrepancyJson:
        """The stable ``--json`` contract."""
        return {"base_gap": float(self.base_gap), "effects": [e.to_dict() for e in self.effects],
                "final_gap": float(self.final_gap),
                "parameters_before": {k: v.to_dict() for k, v in self.parameters_before.items()},
                "parameters_after": {k: v.to_dict() for k, v in self.parameters_after.items()},
                "unexplained": list(self.unexplained), "ties": [t.to_json() for t in self.ties],
                "notes": list(self.notes), "drive": None if self.drive is None else self.drive.to_json(),
                "proposal": None if self.proposal is None else self.proposal.to_json(),
                "proposal_note": self.proposal_note or None,
                "structure": None if self.structure is None else self.structure.to_json()}

    def to_dict(self) -> DiscrepancyDict:
        """Everything (the contract plus details), e.g. to store with the recording's results."""
        return DiscrepancyDict(
            **self.to_json(),
            recording=self.recording, noise_floor_V=self.noise_floor_V,
            steps=list(self.steps), f_hz=list(self.f_hz),
            base_gap_steps=list(self.base_gap_steps), final_gap_steps=list(self.final_gap_steps),
            effect_gap_steps={e.name: list(e.gap_steps_after) for e in self.effects},
            base_findings=list(self.base_findings), mains_search=self.mains_search,
            fundamental_columns=["f_hz", "gain_error_percent", "phase_error_mrad", "z"],
            base_fundamental=[list(r) for r in self.base_fundamental],
            final_fundamental=[list(r) for r in self.final_fundamental],
            rounds=[[candidate_json(c) for c in e.candidates] for e in self.effects],
            rejected=[candidate_json(c) for c in self.rejected])
