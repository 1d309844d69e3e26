"""Identification of force-transducer models from sine-mechanism calibration data.

Entry point: ``identify.identify_recording`` (every method and model; ``names`` lists them).
Shared by every estimator: ``models`` (paper Eq. 8-11 and the maps between digital coefficients
and physical parameters), ``inputs`` (masses and measurement chain), ``result`` (the frozen result
types), ``identifiability``, ``structure`` (the model structure a result rests on), ``crb``
(Cramér-Rao bounds) and ``synthetic`` (exact stepped-sine data for tests and benchmarks).
Families: ``response`` (H(f) through the plausibility gate), ``fd`` (the frequency-domain
estimator), ``oe`` (time-domain output error), ``paper`` (PSO, PSO+, RLS as published) and
``campaign`` (several top masses jointly).
"""
