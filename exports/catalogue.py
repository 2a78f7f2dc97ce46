"""The database side of a release: which cards go in, streamed as :class:`ReleaseCard`.

A card goes in when its curator review is ``accepted`` or ``changed`` with a final grade at
or above the chosen minimum, and it has a finished rectification and disparity whose files
are on disk. Cards are read in id order, ``CHUNK`` at a time, and the session is cleared
after each chunk, so memory does not grow with the catalogue.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import selectinload

from core.db import db
from core.models import Card
from review.models import CardReview
from runs.card_state import card_states

from .models import Release
from .records import RELEASED_DECISIONS, VIEW_ARTIFACTS, ReleaseCard, grades_at_or_above

CHUNK = 200
# The date a release carries when no review has a decision time (never, in practice).
EPOCH = datetime(2000, 1, 1, tzinfo=UTC)


@dataclass(frozen=True)
class Exclusion:
    card_id: int
    reason: str


def eligible_query(min_grade: str):  # type: ignore[no-untyped-def]
    return (
        select(CardReview.card_id)
        .where(CardReview.decision.in_(RELEASED_DECISIONS), CardReview.grade.in_(grades_at_or_above(min_grade)))
        .order_by(CardReview.card_id)
    )


def eligible_card_ids(min_grade: str) -> list[int]:
    """Ids of the curator-accepted cards at or above ``min_grade``, ascending."""
    return list(db.session.scalars(eligible_query(min_grade)))


def inputs_date(card_ids: list[int]) -> datetime:
    """The newest decision time among ``card_ids``: the release's date, so the same inputs
    give the same files whenever they are written. Truncated to whole seconds, UTC."""
    newest: datetime | None = None
    for start in range(0, len(card_ids), 1000):
        chunk = card_ids[start : start + 1000]
        value = db.session.scalar(
            select(func.max(func.coalesce(CardReview.decided_at, CardReview.updated_at))).where(CardReview.card_id.in_(chunk))
        )
        if value is not None and (newest is None or _utc(value) > newest):
            newest = _utc(value)
    return (newest or EPOCH).replace(microsecond=0)


def _utc(value: datetime) -> datetime:
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def latest_release() -> Release | None:
    return db.session.scalar(select(Release).order_by(Release.id.desc()).limit(1))


def stream_release_cards(
    card_ids: list[int], data_dir: Path, exclusions: list[Exclusion] | None = None, with_views: bool = False
) -> Iterator[ReleaseCard]:
    """Yield a :class:`ReleaseCard` per id (ascending); a card that cannot be released (no
    finished rectification or disparity, a missing file) is skipped and noted in ``exclusions``.
    ``with_views``: also collect each card's views (see :func:`card_views`)."""
    from annotation.models import Aggregate
    from runs.specs import available_stages

    specs = available_stages()  # once per release: the stale check builds each stage's inputs
    for start in range(0, len(card_ids), CHUNK):
        chunk = card_ids[start : start + CHUNK]
        cards = db.session.scalars(
            select(Card)
            .where(Card.id.in_(chunk))
            .order_by(Card.id)
            .options(selectinload(Card.stage_results), selectinload(Card.collection))
        ).all()
        reviews = {row.card_id: row for row in db.session.scalars(select(CardReview).where(CardReview.card_id.in_(chunk)))}
        crowd: dict[int, dict[str, dict[str, Any]]] = {}
        for row in db.session.scalars(
            select(Aggregate).where(Aggregate.card_id.in_(chunk), Aggregate.state == "approved").order_by(Aggregate.id)
        ):
            crowd.setdefault(row.card_id, {})[row.kind] = {"batch": row.batch_id, "answers": row.answers}
        # The flow rule, as the review gate asks it: an undecided orientation, an open crowd
        # dispute, a stale result, a ruling "not a stereo pair", or an acceptance given other
        # results than the card has now keeps an accepted card out of the release.
        states = card_states(cards, specs=specs)
        ready: list[ReleaseCard] = []
        for card in cards:
            blockers = states[card.id].release_blockers
            if blockers:
                if exclusions is not None:
                    exclusions.append(Exclusion(card.id, "; ".join(blockers)))
                continue
            try:
                ready.append(
                    release_card(
                        card,
                        reviews[card.id],
                        crowd.get(card.id, {}),
                        data_dir,
                        with_views,
                        states[card.id].inputs_now,
                        (states[card.id].stale or {}).get("views"),
                        states[card.id].orientation,
                    )
                )
            except ReleaseInputError as exc:
                if exclusions is not None:
                    exclusions.append(Exclusion(card.id, str(exc)))
        # Only plain data leaves this function; drop the ORM objects before the next chunk.
        db.session.expunge_all()
        yield from ready


class ReleaseInputError(ValueError):
    """A card the curator accepted but whose pipeline outputs are incomplete."""


def card_views(result: Any, data_dir: Path) -> tuple[dict[str, Path], str]:
    """A card's views (artifact name -> absolute path) and ``"done"``, or no views and why not.

    Views are optional: a card whose latest ``views`` result is not ``done`` (not run, skipped
    because it was graded failure, failed) or whose files are gone is released without them."""
    if result is None:
        return {}, "views not run"
    if result.status != "done":
        return {}, f"views {result.status}" + (f": {result.reason}" if result.reason else "")
    found: dict[str, Path] = {}
    for name in VIEW_ARTIFACTS:
        relative = result.artifacts.get(name)
        if not relative or not (data_dir / relative).is_file():
            return {}, f"views artifact {name!r} is missing on disk"
        found[name] = data_dir / relative
    return found, "done"


def release_card(
    card: Card,
    review: CardReview,
    crowd: dict[str, dict[str, Any]],
    data_dir: Path,
    with_views: bool = False,
    inputs_now: dict[str, str] | None = None,
    stale_views: str | None = None,
    orientation_now: dict[str, Any] | None = None,
) -> ReleaseCard:
    """One accepted card as released. ``inputs_now``: the inputs digest each stage would be given
    from people's decisions at release time (:attr:`runs.card_state.CardState.inputs_now`),
    recorded beside the digest each released result was computed from, with the acceptance, so
    ``keystone verify`` can tell from the release alone that nothing in it was stale.
    ``stale_views``: why the card's views are out of date; the card is then released without
    them (views are optional), and its record says why."""
    latest = card.latest_results()
    rectify, disparity, grade = latest.get("rectify"), latest.get("disparity"), latest.get("grade")
    if rectify is None or rectify.status not in ("done", "skipped"):
        raise ReleaseInputError("no finished rectification")
    if disparity is None or disparity.status != "done":
        raise ReleaseInputError("no finished disparity")

    def path(result: Any, name: str) -> Path:
        relative = result.artifacts.get(name)
        if not relative:
            raise ReleaseInputError(f"the {result.stage} result has no {name!r} artifact")
        target = data_dir / relative
        if not target.is_file():
            raise ReleaseInputError(f"{result.stage} artifact {name!r} is missing on disk ({relative})")
        return target

    rectification_file = path(rectify, "rectification")
    try:
        rectification = json.loads(rectification_file.read_text())
    except (OSError, ValueError) as exc:
        raise ReleaseInputError(f"rectification.json unreadable: {exc}") from exc
    if "left_box" not in rectification or "right_box" not in rectification:
        raise ReleaseInputError("rectification.json has no crop boxes")
    original = data_dir / card.stored_path
    if not original.is_file():
        raise ReleaseInputError(f"the original scan is missing on disk ({card.stored_path})")
    stages = {
        result.stage: {
            "param_hash": result.param_hash,
            "code_version": result.code_version,
            "status": result.status,
            "inputs_digest": result.metrics.get("inputs_digest"),
            "computed_at": None if result.started_at is None else _utc(result.started_at).isoformat(),
        }
        for result in (rectify, disparity, grade)
        if result is not None
    }
    views: dict[str, Path] = {}
    views_note: str | None = None
    if with_views and stale_views is not None:
        views, views_note = {}, f"views out of date ({stale_views}): left out until they are recomputed"
    elif with_views:
        views, views_note = card_views(latest.get("views"), data_dir)
        if views:
            result = latest["views"]
            stages["views"] = {
                "param_hash": result.param_hash,
                "code_version": result.code_version,
                "status": result.status,
                "inputs_digest": result.metrics.get("inputs_digest"),
            }
    orientation = rectify.metrics.get("orientation") or {}
    metadata = dict(card.source_metadata or {})
    return ReleaseCard(
        card_id=card.id,
        accession=card.accession,
        collection=card.collection.name,
        source_name=card.source_name,
        content_hash=card.content_hash,
        original=original,
        width=card.width,
        height=card.height,
        metadata=metadata,
        museum_url=metadata.get("url") or None,
        grade=review.grade or "",
        decision=review.decision,
        auto_grade=review.auto_grade,
        orientation=list(orientation.get("applied") or []),
        rectification=rectification,
        rectified_left=path(rectify, "left"),
        rectified_right=path(rectify, "right"),
        disparity_left=path(disparity, "disparity_left"),
        disparity_right=path(disparity, "disparity_right"),
        depth_512=path(disparity, "depth_512"),
        stages=stages,
        crowd=crowd,
        views=views,
        views_note=views_note,
        stereo_source=card.stereo_source,
        iiif_source=card.iiif_source,
        annotation_facts={
            "scanned_boxes": rectify.metrics.get("scanned_boxes"),
            "orientation_used": rectify.metrics.get("orientation_used"),
            # Who decided the orientation rectify used: nothing stale is released, so the card's
            # orientation now (runs.card_state) is the one its results were computed with.
            "orientation_decided_by": (orientation_now or {}).get("decided_by"),
            "orientation_source": (orientation_now or {}).get("source") or orientation.get("source"),
            "grade_reasons": list((grade.metrics.get("reasons") if grade is not None else None) or []),
            "box_source": rectify.metrics.get("box_source"),
        },
        acceptance={
            "decided_at": None if review.decided_at is None else _utc(review.decided_at).isoformat(),
            "accepted_results": review.accepted_results,
            "inputs_now": {stage: digest for stage, digest in (inputs_now or {}).items() if stage in stages},
        },
    )
