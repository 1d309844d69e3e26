"""The frequency-domain estimator (method ``fd``) on a recording.

``core`` (start values, the weighted fit of the structurally identifiable parameters, the fit
summary), ``budget`` (the GUM uncertainty budget by sensitivity coefficients) and ``identify``
(``identify_fd``: inputs, gate, fit, model structure, budget and the result).
"""
