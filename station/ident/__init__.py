"""Identification of force-transducer models from sine-mechanism calibration data.

Modules: ``models`` (paper Eq. 8-11 and the maps between digital coefficients and physical
parameters), ``pso``/``rls`` (the paper's estimators, Eq. 12-17), ``sinefit``/``frf``/``oe`` (the
expert estimators), ``crb`` (Cramér-Rao bounds), ``identifiability`` and ``api``.
"""
