"""Benchmarks and measurement scripts: they check the project's speed, memory and accuracy targets.

Never imported by the product (``app``, ``annotation``, ``review``, ``pipeline``, ``exports``):
``keystone bench NAME`` loads a benchmark's command from here only when it is run.
"""
