"""``python -m app`` is the ``keystone`` command."""

from .cli import main

main()
