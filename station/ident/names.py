"""The identification methods and models by name, in a module importing nothing heavy so that the CLI's
parser can offer them as choices without loading the estimators.

``station.vocabulary.METHOD_REGISTRY`` is the one list of the methods (name, description, swarm or
not, models, in the report's order of preference); these are its views. ``identify.py`` dispatches
each name to its estimator.

The names themselves are ``station.vocabulary.Method`` and ``Model``."""

from station.vocabulary import METHOD_REGISTRY, Method, Model

METHODS: tuple[str, ...] = tuple(m.value for m in Method)  # the CLI's and the API's order
METHOD_PREFERENCE: tuple[str, ...] = tuple(m.name for m in METHOD_REGISTRY)  # the report shows the first stored
SWARM_METHODS: tuple[str, ...] = tuple(m.name for m in METHOD_REGISTRY if m.swarm)
METHOD_DESCRIPTIONS: dict[str, str] = {m.name: m.description for m in METHOD_REGISTRY}
MODELS: tuple[str, ...] = tuple(m.value for m in Model)
