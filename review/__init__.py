"""Curator review: queues, quality labels, decisions, audit, agreement reports.

Empty until the review feature lands; see ``annotation/__init__.py`` for why it exists now.
"""
