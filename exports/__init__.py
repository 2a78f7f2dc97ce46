"""Dataset releases: writers per format and release verification.

Empty until the releases feature lands; see ``annotation/__init__.py`` for why it exists now.
"""
