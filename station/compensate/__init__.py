"""Dynamic compensation: inverse filters from a calibration, applied with an uncertainty at every sample
(docs/compensation.md)."""
