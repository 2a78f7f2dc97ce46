"""An operator's word for a whole collection: ``keystone orientation set`` and ``show``.

An operator who knows a collection (prints, never negatives; scanned in eye order) says so once
for all its cards, flag by flag. Each card's orientation then takes the word for those flags
over the crowd's and the step's, and a curator's override on one card still wins over it
(:mod:`pipeline.decided_orientation`). The orientation step is given the word as ``known_flags`` and decides
the other flags itself where it can; the word is part of the step's inputs, so the next
``keystone run`` reruns the step on the collection's cards.

The word (``core.models.CollectionOrientation``) and an audit event (entity ``orientation``, no
card; before and after the word) are committed together.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sqlalchemy import func, or_, select
from sqlalchemy.exc import IntegrityError

from core.audit import record_event
from core.db import db, utcnow
from core.models import Card, Collection, CollectionOrientation, Person
from pipeline.decided_orientation import FLAGS, word_phrase

from .models import OrientationOverride
from .tasks import MAX_NOTE_CHARS, ReviewError

__all__ = ["collection_words", "set_collection_orientation"]


def _collection(name: str) -> Collection:
    collection = db.session.scalar(select(Collection).where(Collection.name == name))
    if collection is None:
        known = list(db.session.scalars(select(Collection.name).order_by(Collection.name).limit(20)))
        raise ReviewError(
            f"There is no collection {name!r}; collections: {', '.join(known) if known else 'none (ingest one first)'}", 404
        )
    return collection


def _word_flags(row: CollectionOrientation | None) -> dict[str, bool | None]:
    return {flag: None if row is None else getattr(row, flag) for flag in FLAGS}


def word_document(row: CollectionOrientation) -> dict[str, Any]:
    """One word in force as ``keystone orientation show --json`` lists it: the flags (null: not
    said), the word in words, who said it and when, the note, how many cards it covers and on
    how many of them a curator's override replaces some of it."""
    said = [getattr(OrientationOverride, flag).is_not(None) for flag in FLAGS if getattr(row, flag) is not None]
    cards = db.session.scalar(select(func.count(Card.id)).where(Card.collection_id == row.collection_id)) or 0
    overridden = (
        db.session.scalar(
            select(func.count(OrientationOverride.id))
            .join(Card, Card.id == OrientationOverride.card_id)
            .where(Card.collection_id == row.collection_id, or_(*said))
        )
        if said
        else 0
    )
    return {
        "collection": row.collection_name,
        **_word_flags(row),
        "says": word_phrase(row),
        "set_by": row.set_by_name,
        "set_by_account": row.set_by.username if row.set_by is not None else None,
        "set_at": row.set_at.isoformat(),
        "note": row.note,
        "cards": cards,
        "overridden_on_cards": overridden,
    }


def collection_words(collection_name: str | None = None) -> list[dict[str, Any]]:
    """The words in force (of one collection when named), by collection name."""
    query = select(CollectionOrientation).join(Collection).order_by(Collection.name)
    if collection_name is not None:
        query = query.where(CollectionOrientation.collection_id == _collection(collection_name).id)
    return [word_document(row) for row in db.session.scalars(query)]


def set_collection_orientation(
    collection_name: str,
    flags: Mapping[str, bool | None],
    *,
    by: Person | None,
    by_name: str,
    note: str | None = None,
) -> dict[str, Any]:
    """Set (true / false) or clear (None) the operator's word on each flag named in ``flags``
    for every card of the collection; flags not named keep their word. ``by`` is the operator's
    account when one was named, ``by_name`` the name shown (the account's username, or the OS
    user). ``note`` replaces the word's note; without one, a change of flags empties it (the
    old reason may not hold for the new word) and a command that changes nothing keeps it.

    Returns ``{"collection", "changed", "word"}``: ``word`` is the word now in force (as
    :func:`word_document`), or None when every flag is clear (the row is removed). A command
    that changes nothing writes nothing."""
    unknown = sorted(set(flags) - set(FLAGS))
    if unknown:
        raise ReviewError(f"Unknown orientation flag(s) {', '.join(unknown)}; expected {', '.join(FLAGS)}")
    if not flags:
        raise ReviewError("Say at least one flag: --upside-down, --inverted or --swapped (yes, no or clear)")
    bad = {flag: value for flag, value in flags.items() if value is not None and not isinstance(value, bool)}
    if bad:
        raise ReviewError(f"Expected each flag to be true, false or None (clear), got {bad!r}")
    note_text = None if note is None else note.strip()
    if note_text is not None and len(note_text) > MAX_NOTE_CHARS:
        raise ReviewError(f"Expected a note of at most {MAX_NOTE_CHARS} characters, got {len(note_text)}")
    collection = _collection(collection_name)
    row = db.session.scalar(select(CollectionOrientation).where(CollectionOrientation.collection_id == collection.id))
    before = _word_flags(row)
    after = {**before, **flags}
    flags_changed = after != before
    cleared = all(value is None for value in after.values())
    # A new note matters only on a word that stays in force.
    note_changed = not cleared and note_text is not None and note_text != (row.note if row is not None else "")
    if not flags_changed and not note_changed:
        return {"collection": collection.name, "changed": False, "word": word_document(row) if row is not None else None}
    before_doc = {"collection": collection.name, **before, "note": row.note if row is not None else None}
    if row is None:
        row = CollectionOrientation(collection_id=collection.id, collection=collection)
        db.session.add(row)
    for flag, value in after.items():
        setattr(row, flag, value)
    row.set_by_id, row.set_by, row.set_by_name = (by.id if by is not None else None), by, by_name
    row.note = note_text or ""  # a word's note is the one said with its latest change
    row.set_at = utcnow()
    try:
        db.session.flush()
        word_id = row.id
        if cleared:
            db.session.delete(row)
        record_event(
            entity="orientation",
            action="collection_word_cleared" if cleared else "collection_word",
            entity_id=word_id,
            actor=by,
            actor_label=f"{by_name} (keystone orientation set)",
            before=before_doc,
            after={"collection": collection.name, **after, "note": None if cleared else row.note},
            why=row.note,
        )
        db.session.commit()
    except IntegrityError as exc:
        # Two operators saying a first word for one collection at once: the second insert loses.
        db.session.rollback()
        raise ReviewError(
            f"Another word for collection {collection.name!r} was saved at the same time; run the command again", 409
        ) from exc
    return {"collection": collection.name, "changed": True, "word": None if cleared else word_document(row)}
