"""The closed sets of the station's results, defined once: ``Method`` and ``Model`` of an
identification, ``Severity`` of a finding, ``Flag`` of an estimate.  ``StrEnum``s without imports, so
that every layer can use them: the API's enumerations are these (``station.api.schemas``), and a
member is its string wherever a result compares or stores it (the stored JSON holds the strings).
``Estimate.flag`` is a ``Flag``; ``Check.severity`` and the identification result's method and model
are still plain strings holding these values."""

from enum import StrEnum


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
