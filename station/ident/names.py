"""Names of the identification methods and models, in a module without imports so that the CLI's
parser can offer them as choices without loading the estimators."""

METHODS: tuple[str, ...] = ("fd", "oe", "pso", "pso+", "rls")
MODELS: tuple[str, ...] = ("sdof", "coupled", "h1", "h2")
