"""Measurement scripts run by hand (``python -m benchmarks.<name>``); never imported by the product."""
