"""Request and response schemas of ``POST /campaigns`` (multi-mass joint identification).

The response mirrors ``station.ident.campaign.result.CampaignResult.to_dict`` (the CLI's JSON)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

from station.api.deps import RUN_ID_PATTERN
from station.api.schemas import (
    BudgetOut,
    CheckOut,
    CovarianceOut,
    EstimateOut,
    MassAssumptionOut,
    MeasurementChainOut,
    MethodName,
    ModelName,
    OutModel,
    RunMassOut,
)

RunIdStr = Annotated[str, StringConstraints(pattern=RUN_ID_PATTERN)]


class CampaignRequest(BaseModel):
    """Completed runs of one transducer with different top masses, to be identified jointly."""

    model_config = ConfigDict(extra="forbid")

    runs: list[RunIdStr] = Field(min_length=1, max_length=32,
                                 description="run ids (each once); at least two distinct top masses separate "
                                             "S from the end mass m_e")
    store: bool = Field(default=False, description="also store the result beside every run's "
                                                   "recording (its report then shows it); needs the bearer token")


class MassOut(OutModel):
    value: float | None = Field(description="kg")
    std: float | None = Field(description="kg")


class OwnValueOut(OutModel):
    value: float | None
    std: float | None
    unit: str


class OwnFitOut(OutModel):
    S: OwnValueOut
    k_f: OwnValueOut


class CampaignRecordingOut(OutModel):
    run_id: str
    path: str = Field(description="recording file name")
    load_mass_kg: MassOut = Field(description="top mass + adaption as weighed")
    load_mass_fitted_kg: MassOut = Field(description="as fitted (the weighed value is its prior)")
    steps_used: list[int]
    f_range_hz: list[float]
    chi2: float | None = Field(description="this recording's share of the joint chi^2")
    n_real: int = Field(description="real numbers it contributes (2 per step)")
    own_fit: OwnFitOut = Field(description="its own Eq. 9 fit with m_e held at the campaign's (consistency check)")


class CampaignFitOut(OutModel):
    chi2: float | None
    dof: int
    chi2_per_dof: float | None
    inflated: bool = Field(description="uncertainties scaled by sqrt(chi2/dof)")


class CampaignAssumptionsOut(BaseModel):
    """What the joint result rests on: the model, the masses, the measurement chain, the structure."""

    model_config = ConfigDict(extra="allow")

    model: str
    end_mass_kg: MassAssumptionOut | None
    load_mass_kg: list[RunMassOut] = Field(description="each run's weighed load mass (its prior)")
    measurement_chain: MeasurementChainOut
    structure: dict[str, Any] | None = None


class CampaignOut(OutModel):
    """Joint identification of S, m_e, k_f, b_f (Eq. 9) from runs with different top masses."""

    kind: Literal["campaign"]
    method: MethodName
    model: ModelName
    status: Literal["separated", "conditional", "refused"] = Field(
        description="separated: S and m_e determined by the data; conditional: the top masses are too alike, "
                    "S, k_f, b_f given on the stated end mass; refused: see checks and determined")
    transducer_id: str
    runs: list[str]
    stored_as: str | None = Field(default=None, description="where the result was stored beside each recording, "
                                     "relative to the recordings folder")
    parameters: dict[str, EstimateOut]
    covariance: CovarianceOut
    recordings: list[CampaignRecordingOut]
    fit: CampaignFitOut
    checks: list[CheckOut]
    budget: dict[str, BudgetOut]
    assumptions: CampaignAssumptionsOut
    determined: dict[str, Any]
    notes: list[str]
