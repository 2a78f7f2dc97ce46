"""Release formats, one module each, behind one interface (:mod:`.base`) in one registry (:mod:`.registry`).

``keystonedepth`` (KeystoneDepth's folders), ``parquet`` (Hugging Face shards), ``webdataset``
(tar shards), ``views`` (the five GD images per card) and ``stereo`` (viewing files per card).
docs/ARCHITECTURE.md, "How to add ... an export format", shows how to add one.
"""

from .base import FormatWriter, NoOptions, PlanTally, Problems, ReleaseFormat, WriteContext
from .registry import (
    chosen_formats,
    default_format_names,
    format_encodings,
    format_names,
    get_format,
    parse_formats,
    register_format,
    registered_formats,
    release_format,
)

__all__ = [
    "FormatWriter",
    "NoOptions",
    "PlanTally",
    "Problems",
    "ReleaseFormat",
    "WriteContext",
    "chosen_formats",
    "default_format_names",
    "format_encodings",
    "format_names",
    "get_format",
    "parse_formats",
    "register_format",
    "registered_formats",
    "release_format",
]
