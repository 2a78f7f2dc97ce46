"""The registry of release formats: every module of ``exports/formats/`` registers its format.

The modules are found with :mod:`pkgutil` the first time the registry is asked, so a new format
is one new module (decorated with :func:`release_format`) and nothing else: ``--format``, the
releases page, the writers of a release, its CHANGELOG, dataset card and Croissant record sets,
and ``keystone verify`` all read the registry.
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import TypeVar

from .base import ReleaseFormat

REGISTRY: dict[str, ReleaseFormat] = {}
NOT_FORMAT_MODULES = frozenset({"base", "registry"})
_discovered = False

F = TypeVar("F", bound=type[ReleaseFormat])


def release_format(cls: F) -> F:
    """Class decorator: register one instance of the format (with its default options)."""
    register_format(cls())
    return cls


def register_format(fmt: ReleaseFormat) -> None:
    """Add ``fmt``; a second format of the same name from another class is refused."""
    if not fmt.name or fmt.name != fmt.name.strip().lower() or "," in fmt.name:
        raise ValueError(f"Expected a lowercase format name without commas, got {fmt.name!r}")
    known = REGISTRY.get(fmt.name)
    if known is not None and type(known).__qualname__ != type(fmt).__qualname__:
        raise ValueError(f"Two release formats are named {fmt.name!r}: {type(known).__qualname__} and {type(fmt).__qualname__}")
    REGISTRY[fmt.name] = fmt


def _discover() -> None:
    global _discovered
    if _discovered:
        return
    package = importlib.import_module(__name__.rpartition(".")[0])
    for module in pkgutil.iter_modules(package.__path__):
        if module.name not in NOT_FORMAT_MODULES and not module.name.startswith("_"):
            importlib.import_module(f"{package.__name__}.{module.name}")
    _discovered = True


def registered_formats() -> tuple[ReleaseFormat, ...]:
    """Every format, in their canonical order (``order``, then name)."""
    _discover()
    return tuple(sorted(REGISTRY.values(), key=lambda fmt: (fmt.order, fmt.name)))


def format_names() -> tuple[str, ...]:
    return tuple(fmt.name for fmt in registered_formats())


def default_format_names() -> tuple[str, ...]:
    """The formats of a release when none is named."""
    return tuple(fmt.name for fmt in registered_formats() if fmt.default)


def get_format(name: str) -> ReleaseFormat:
    _discover()
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"Expected a format from {', '.join(format_names())}, got {name!r}") from None


def parse_formats(text: str | list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Comma-separated (or listed) format names, in the canonical order; unknown names raise."""
    names = [part.strip() for part in (text.split(",") if isinstance(text, str) else text) if part.strip()]
    known = format_names()
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise ValueError(f"Expected formats from {', '.join(known)}, got {', '.join(unknown) or 'none'}")
    return tuple(name for name in known if name in names)


def format_encodings() -> dict[str, str]:
    """File suffix -> MIME type declared by the formats (for ``croissant.json``), whichever were
    chosen: a suffix means the same in every release."""
    encodings: dict[str, str] = {}
    for fmt in registered_formats():
        for suffix, mime in fmt.encodings.items():
            if encodings.setdefault(suffix, mime) != mime:
                raise ValueError(f"Two release formats give {suffix} files different types: {encodings[suffix]} and {mime}")
    return encodings


def chosen_formats(names: str | list[str] | tuple[str, ...]) -> tuple[ReleaseFormat, ...]:
    """The formats named, in the canonical order (see :func:`parse_formats`)."""
    return tuple(get_format(name) for name in parse_formats(names))
