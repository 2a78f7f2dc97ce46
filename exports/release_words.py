"""What a release changes, in words, for the releases pages (issue 33.8).

A release that only adds a format read "a patch release after 1.0.0: 0 added, 0 removed, 0
changed", which says nothing. These functions say what it is ("format-only release: adds
webdataset; same cards as 1.0.0") and why it has the version it has, by the release rules of
docs/RELEASES.md: a patch has the same data written again, a minor only adds cards, a major
removes or changes cards. A new format writes the same cards' data in another form, so a
format-only release is a patch. Pure: they read the ``changes`` document a plan or a Release row
carries (:meth:`exports.records.Changes.as_json`) and the two releases' formats and lowest grades.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

# Why a release of each kind got its version, after docs/RELEASES.md ("Versions are semantic").
VERSION_RULES = {
    "first": "the first release is 1.0.0",
    "patch": "a patch: the same cards with the same data (docs/RELEASES.md: a patch has the same data written again)",
    "minor": "a minor release: it only adds cards (docs/RELEASES.md: a minor only adds cards)",
    "major": "a major release: it removes or changes cards (docs/RELEASES.md: a major removes or changes cards)",
}


def _names(names: Sequence[str]) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _cards(count: int) -> str:
    return f"{count} card{'' if count == 1 else 's'}"


def release_summary(
    changes: dict[str, Any],
    formats: Sequence[str],
    previous_formats: Sequence[str] | None = None,
    min_grade: str | None = None,
    previous_min_grade: str | None = None,
) -> str:
    """One sentence saying what this release is against the previous one: which formats it adds
    or drops, and which cards it adds, removes or changes (or that it holds the same cards)."""
    previous = changes.get("previous_version")
    added, removed, changed = changes.get("added") or [], changes.get("removed") or [], changes.get("changed") or []
    if previous is None:
        return f"First release: {_cards(len(added))} in {_names(formats) if formats else 'no format'}."
    before = list(previous_formats or [])
    new_formats = [name for name in formats if name not in before]
    dropped_formats = [name for name in before if name not in formats]
    format_parts = ([f"adds {_names(new_formats)}"] if new_formats else []) + (
        [f"drops {_names(dropped_formats)}"] if dropped_formats else []
    )
    card_parts = (
        ([f"adds {_cards(len(added))}"] if added else [])
        + ([f"removes {_cards(len(removed))}"] if removed else [])
        + ([f"changes {_cards(len(changed))}"] if changed else [])
    )
    grade_note = (
        f" (lowest grade {previous_min_grade} → {min_grade})"
        if min_grade and previous_min_grade and min_grade != previous_min_grade
        else ""
    )
    if not card_parts:
        if format_parts:
            return f"Format-only release: {'; '.join(format_parts)}; same cards as {previous}{grade_note}."
        return f"Same cards and formats as {previous}{grade_note}: the same data written again."
    return (
        f"Against {previous}: {', '.join(card_parts)}"
        + (f"; {'; '.join(format_parts)}" if format_parts else "")
        + f"{grade_note}."
    )


def version_reason(changes: dict[str, Any], formats: Sequence[str], previous_formats: Sequence[str] | None = None) -> str:
    """Why the release has its version, in the words of the release rules; a format-only patch
    says that a new format is the same data in another form."""
    kind = str(changes.get("kind") or "patch")
    reason = VERSION_RULES.get(kind, kind)
    format_change = set(formats) != set(previous_formats or formats)
    if kind == "patch" and format_change:
        reason += "; a format added or dropped writes the same cards' data in another form, so it is a patch"
    return reason[0].upper() + reason[1:] + "."
