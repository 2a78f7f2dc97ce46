"""Crowd annotation: judge and crop tasks, assignment, providers, aggregation, worker quality.

Empty until the crowd-annotation feature lands; the package exists so the layout that users
and the later features rely on (``app/``, ``annotation/``, ``review/``, ``pipeline/``,
``exports/``) is fixed from the start.
"""
