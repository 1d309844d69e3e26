"""A transducer's history as a lab reads it: control charts of each dynamic parameter (Shewhart with
t-limits, EWMA), their run lengths, calibration intervals from the history (NCSLI RP-1 method A3 and
S2, the variables method of NASA-HDBK-8739.19-5) and the risk of being out of tolerance at the next
due date from a drift model fitted with its uncertainty (``docs/batch.md``).

Pure functions of the values: no files, no database; ``station.lab.history`` and the batch feed them.
"""
