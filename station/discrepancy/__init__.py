"""Model-gap (discrepancy) workflow: where simulation and measurement disagree, which
catalogue effect is missing, how much the gap shrinks when it is added, and what is left.

Modules: ``decompose`` (per-step LS decomposition, noise floor), ``spectrum`` (line searches),
``data`` (stacked arrays), ``model`` (the rig in the harmonic domain with every catalogue effect),
``catalogue`` (parameters, starts), ``fit`` (weighted LM fits, gap), ``search`` (candidates),
``locate`` (where the gap is), ``workflow`` (selection, report), ``report`` (JSON), ``plot`` (PNG),
``scenarios`` (recordings with effects drawn at random, for tests and the bench).
"""

from station.discrepancy.result import DiscrepancyResult
from station.discrepancy.workflow import analyse_recording

__all__ = ["DiscrepancyResult", "analyse_recording"]
