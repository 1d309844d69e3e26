"""The measured frequency response H(f) of a recording and the weighted fit of a model to it.

``sinefit`` (IEEE 1057 sine fits per step and channel), ``gate`` (the plausibility gate: named
checks per step and per run, refusals), ``checked`` (``checked_response``: H(f) of the steps the
gate kept, with their signals) and ``frf`` (H(f) with its covariance per step, the linear start
and the weighted Levenberg-Marquardt fit of a model).
"""
