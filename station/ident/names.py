"""The identification methods and models by name, in a module without imports so that the CLI's
parser can offer them as choices without loading the estimators.

``METHOD_REGISTRY`` is the one list of the methods: name, description (the report's and the
certificate's words), whether it is a particle swarm (the report plots its convergence), in the
report's order of preference; ``identify.py`` dispatches each name to its estimator."""

from typing import NamedTuple


class MethodEntry(NamedTuple):
    name: str
    description: str
    swarm: bool


METHOD_REGISTRY: tuple[MethodEntry, ...] = (
    MethodEntry("fd", "sine fits per step → H(f) → linear start on 1/H → weighted Levenberg–Marquardt "
                      "(frequency domain)", False),
    MethodEntry("oe", "output error: Levenberg–Marquardt on the raw force samples of every step (time domain)",
                False),
    MethodEntry("pso+", "the paper's particle swarm, PSO+ (Eq. 12–16), on one step cut as in Section 5.1", True),
    MethodEntry("pso", "the paper's particle swarm, PSO (Eq. 12–15), on one step cut as in Section 5.1", True),
    MethodEntry("rls", "the paper's recursive least squares (Eq. 17) on one step cut as in Section 5.1", False),
)
METHODS: tuple[str, ...] = ("fd", "oe", "pso", "pso+", "rls")  # the CLI's and the API's order
METHOD_PREFERENCE: tuple[str, ...] = tuple(m.name for m in METHOD_REGISTRY)  # the report shows the first stored
SWARM_METHODS: tuple[str, ...] = tuple(m.name for m in METHOD_REGISTRY if m.swarm)
METHOD_DESCRIPTIONS: dict[str, str] = {m.name: m.description for m in METHOD_REGISTRY}
MODELS: tuple[str, ...] = ("sdof", "coupled", "h1", "h2")
