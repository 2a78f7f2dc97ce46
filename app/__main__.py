"""``python -m app`` is the ``keystone`` command."""

from app.cli import main

main()
