"""What a release format is: the one interface every format implements, and what it is handed.

A release streams its cards once; each chosen format's writer is handed every card's
:class:`~exports.writers.CardPayload` (the card's bytes and arrays, read once and shared) and
writes its files through the :class:`~exports.writers.FileLedger`, which records each file's
sha256 for ``SHA256SUMS`` and ``croissant.json``. After the last card a writer's summary (what it
wrote, and why some cards have no files of it) goes into the release report, and the format
turns it into its lines of the CHANGELOG and the dataset card and its Croissant record sets.
``keystone verify`` asks every registered format to check the files of its own it finds.

Nothing here touches the database, and nothing may read the clock: the same inputs must give
byte-identical releases.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, ClassVar, Protocol

from ..records import ReleaseCard
from ..writers import CardPayload, FileLedger


@dataclass(frozen=True)
class WriteContext:
    """What a writer may use besides the cards: where files go, a scratch file, the release's date."""

    ledger: FileLedger  # write every file through it (``write_bytes`` or ``record_file``)
    scratch: Path  # a file name an encoder that needs a real file may write and remove (EXR)
    date: datetime  # the release's date (the newest review decision), for in-file times: never the clock


class FormatWriter(Protocol):
    """Writes one release's files of one format, a card at a time."""

    def add(self, payload: CardPayload) -> None:
        """Write (or buffer) one card's files; a card this format cannot make is counted, not raised."""

    def close(self) -> None:
        """Flush what is buffered and record the last files; called once, after the last card."""

    def summary(self) -> dict[str, Any] | None:
        """JSON-safe facts for the release report (``None``: nothing to say)."""


class PlanTally(Protocol):
    """Counts, during the dry run, what a format would say of the cards (same shape as its summary)."""

    def add(self, card: ReleaseCard) -> None: ...

    def as_json(self) -> dict[str, Any]: ...


class Problems(Protocol):
    """Where ``verify`` checks report a problem (:class:`exports.verify.VerifyReport`)."""

    def problem(self, path: str, problem: str) -> None: ...


@dataclass(frozen=True)
class NoOptions:
    """A format without tunables."""


class ReleaseFormat(ABC):
    """One release format. Subclass, fill in the class attributes, implement :meth:`writer`, and
    decorate the class with :func:`exports.formats.release_format` in a module of
    ``exports/formats/``; the other methods have defaults for a format with nothing to add there.
    """

    name: ClassVar[str]  # as given to ``--format``; lowercase, no comma
    description: ClassVar[str]  # one line: ``--format``'s help and the releases page
    order: ClassVar[int]  # place in every listing (writers, CHANGELOG, README, Croissant, verify)
    default: ClassVar[bool] = False  # part of a release when no format is named
    # Whether the cards must be streamed with their views artifacts (a card's manifest entry then
    # carries its views digest): only for a format that releases the views stage's outputs.
    with_views: ClassVar[bool] = False
    # File suffix -> MIME type of the files it writes that croissant.json's common table lacks.
    encodings: ClassVar[Mapping[str, str]] = {}
    # Whether the release report (``keystone export --json``) carries its summary under its name
    # (which must then differ from the report's own keys: version, cards, ...).
    reports: ClassVar[bool] = False

    def __init__(self, options: Any = None) -> None:
        # A frozen dataclass of the format's tunables; the defaults are what releases use.
        self.options: Any = options if options is not None else self.default_options()

    def default_options(self) -> Any:
        return NoOptions()

    @abstractmethod
    def writer(self, context: WriteContext) -> FormatWriter:
        """A fresh writer for one release."""

    def plan_tally(self) -> PlanTally | None:
        """What the dry run counts for this format, or ``None``."""
        return None

    def readme_header(self) -> list[str]:
        """Lines of the dataset card's YAML header (e.g. the Hugging Face ``configs``)."""
        return []

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        """The dataset card's "Dataset Structure" items for the files it wrote."""
        return []

    def changelog(self, summary: dict[str, Any] | None) -> list[str]:
        """The CHANGELOG's section for this format (lines, from its blank line on), or none."""
        return []

    def record_sets(self, summary: dict[str, Any] | None, card_count: int) -> list[dict[str, Any]]:
        """Croissant ``cr:RecordSet`` documents describing its files (their file objects are listed
        by ``croissant.json`` whatever the format)."""
        return []

    def verify(self, root: Path, listed: dict[str, str], problems: Problems) -> None:
        """Check this format's files in a release (``listed``: path -> sha256 from ``SHA256SUMS``,
        each already checked to exist with that hash). Must return quietly when the release holds
        none of its files: every registered format checks every release."""
        return None
