"""The closed sets of the station's results, defined once: ``Method`` and ``Model`` of an
identification, ``Severity`` of a finding, ``Flag`` of an estimate; and the registry of the methods
(``METHOD_REGISTRY``: name, description, order, models).  ``StrEnum``s without imports, so
that every layer can use them: the API's enumerations are these (``station.api.schemas``), and a
member is its string wherever a result compares or stores it (the stored JSON holds the strings).
``Estimate.flag`` is a ``Flag`` and ``Check.severity`` a ``Severity``; the identification result's
method and model are still plain strings holding these values."""

from enum import StrEnum
from typing import NamedTuple


class Method(StrEnum):
    """An identification method (the CLI's and the API's order)."""

    FD = "fd"
    OE = "oe"
    PSO = "pso"
    PSO_PLUS = "pso+"
    RLS = "rls"


class Model(StrEnum):
    """A transducer model: Eq. 9 (sdof), Eq. 8 (coupled), their discretisations H1 (Eq. 10), H2 (Eq. 11)."""

    SDOF = "sdof"
    COUPLED = "coupled"
    H1 = "h1"
    H2 = "h2"


class Severity(StrEnum):
    """A finding's severity: for information, a warning the result carries, or the result refused."""

    INFO = "info"
    WARNING = "warning"
    REFUSED = "refused"


class Flag(StrEnum):
    """An estimate's flag: none, poorly determined (relative uncertainty above the policy's), or
    conditional (on an assumed input)."""

    NONE = ""
    POORLY_DETERMINED = "poorly_determined"
    CONDITIONAL = "conditional"


class MethodEntry(NamedTuple):
    """A method in the registry: its name, its description (the report's and the certificate's
    words), whether it is a particle swarm (the report plots its convergence) and the models it is
    defined for, the first its default (``auto``: fd picks Eq. 9 or Eq. 8 from the data)."""

    name: Method
    description: str
    swarm: bool
    models: tuple[str, ...]


METHOD_REGISTRY: tuple[MethodEntry, ...] = (
    MethodEntry(Method.FD, "sine fits per step → H(f) → linear start on 1/H → weighted Levenberg–Marquardt "
                           "(frequency domain)", False, ("auto", Model.SDOF, Model.COUPLED)),
    MethodEntry(Method.OE, "output error: Levenberg–Marquardt on the raw force samples of every step (time "
                           "domain)", False, (Model.SDOF, Model.COUPLED)),
    MethodEntry(Method.PSO_PLUS, "the paper's particle swarm, PSO+ (Eq. 12–16), on one step cut as in Section 5.1",
                True, (Model.H2, Model.H1)),
    MethodEntry(Method.PSO, "the paper's particle swarm, PSO (Eq. 12–15), on one step cut as in Section 5.1", True,
                (Model.H2, Model.H1)),
    MethodEntry(Method.RLS, "the paper's recursive least squares (Eq. 17) on one step cut as in Section 5.1", False,
                (Model.H2,)),
)
"""The one list of the identification methods, in the report's order of preference
(``station.ident.identify`` dispatches each name to its estimator; the configuration's method
choice, the CLI's and the API's enumerations read it)."""
MODELS_OF_METHOD: dict[str, tuple[str, ...]] = {m.name: m.models for m in METHOD_REGISTRY}
