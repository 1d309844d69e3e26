"""Calibration runs: request and limits, procedure, acquisition, processing."""
