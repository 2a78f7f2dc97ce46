"""Pure pipeline stages over arrays, plus a thin runner and I/O.

Nothing in this package imports Flask or SQLAlchemy (a test checks it in a subprocess):
stages take arrays and a frozen parameter dataclass, return arrays or small dataclasses;
only :mod:`pipeline.io` touches disk and only :mod:`pipeline.runner` loops over cards.
"""

CODE_VERSION = "0.1.0"
