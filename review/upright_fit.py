"""A collection teaches the orientation step's learned heads: ``keystone orientation fit``.

The orientation step stores, for every card it reads, the learned heads' inputs (the network's
feature differences of both photos, :mod:`pipeline.upright`; the stage artifact
``upright_differences``). Once people have decided a few thousand cards of a collection, those
decisions label them: a refit of the linear heads on them (pulled towards the head in force, so a
few hundred cards cannot undo what it knew) fits the collection's own printers, mounts and
subjects. Labels come from cards whose orientation was decided by people (the crowd, a curator)
or by the step itself with a wide margin (its most probable combination at
:data:`WIDE_MARGIN` or more); a flag an operator fixed for the collection counts as decided.

The refit is versioned like the grade thresholds (:class:`review.models.UprightHeadFit`, newest
per collection in force, a collection without its own falling back to a fit on all collections,
then to the shipped head); the head reaches the orientation step through its inputs
(:func:`upright_head_inputs`), so it changes decisions only on the next run, and that run lists
the cards whose decision changed. The fit itself reports held-out accuracy before and after
(grouped by card) and previews which decisions would change.
"""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from flask import current_app
from sqlalchemy import func, select

from core.audit import record_event
from core.db import db
from core.models import Card, Collection

from .models import UprightHeadFit

WIDE_MARGIN = 0.99  # an automatic decision this sure labels its card
MIN_CARDS = 10
L2_CHOICES = (1.0, 3.0, 10.0, 30.0)
CHUNK = 500


class UprightFitError(Exception):
    """The refit cannot be made (no such collection, too few decided cards); the message says why."""


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:40] or "collection"


def heads_in_force() -> dict[int | None, UprightHeadFit]:
    """The newest fit per collection (key None: the fit on every collection)."""
    newest = select(UprightHeadFit.collection_id, func.max(UprightHeadFit.id).label("id")).group_by(UprightHeadFit.collection_id)
    ids = [row.id for row in db.session.execute(newest)]
    return {fit.collection_id: fit for fit in db.session.scalars(select(UprightHeadFit).where(UprightHeadFit.id.in_(ids)))}


def head_file(fit: UprightHeadFit) -> Path:
    """The fit's head as a JSON file in the data dir (workers read it by path), written once."""
    path = Path(current_app.config["KEYSTONE_DATA_DIR"]) / "heads" / f"upright-{fit.version}.json"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(fit.head))
        tmp.replace(path)
    return path


def upright_head_inputs(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """The head in force per card, for the orientation step's inputs:
    ``{card: {"upright_head": {"path": relative to the data dir, "version": ...}}}``; cards on
    the shipped head are left out (their inputs, and so their inputs digest, do not change)."""
    fits = heads_in_force()
    if not fits or not card_ids:
        return {}
    data_dir = Path(current_app.config["KEYSTONE_DATA_DIR"])
    entries = {key: {"path": str(head_file(fit).relative_to(data_dir)), "version": fit.version} for key, fit in fits.items()}
    found: dict[int, dict[str, Any]] = {}
    for start in range(0, len(card_ids), CHUNK):
        rows = db.session.execute(select(Card.id, Card.collection_id).where(Card.id.in_(card_ids[start : start + CHUNK])))
        for card_id, collection_id in rows:
            entry = entries.get(collection_id) or entries.get(None)
            if entry is not None:
                found[card_id] = {"upright_head": entry}
    return found


def _current_head(collection_id: int | None) -> tuple[Any, str]:
    from pipeline.upright import UprightHead, shipped_head

    fits = heads_in_force()
    fit = fits.get(collection_id) if collection_id is not None else None
    fit = fit or fits.get(None)
    if fit is None:
        head = shipped_head()
        return head, head.version
    return UprightHead.from_dict(fit.head), fit.version


def labelled_cards(collection_id: int | None) -> list[dict[str, Any]]:
    """Cards whose orientation is decided by people or by the step with a wide margin, and whose
    step stored the network's readings: ``{"card", "orientation", "step", "differences"}``."""
    from core.hooks import approved_decisions
    from pipeline.decided_orientation import card_orientation
    from pipeline.upright import read_learned_differences

    data_dir = Path(current_app.config["KEYSTONE_DATA_DIR"])
    query = select(Card).where(Card.state.in_(("pass", "review"))).order_by(Card.id)
    if collection_id is not None:
        query = query.where(Card.collection_id == collection_id)
    cards = list(db.session.scalars(query))
    found = []
    for start in range(0, len(cards), CHUNK):
        chunk = cards[start : start + CHUNK]
        approved = approved_decisions([card.id for card in chunk])
        for card in chunk:
            step = card.latest_results().get("orientation")
            if step is None or step.status != "done" or "upright_differences" not in (step.artifacts or {}):
                continue
            orientation = card_orientation(card, approved.get(card.id, {}))
            by = orientation.get("decided_by")
            sure = float(step.metrics.get("combination_probability") or 0.0) >= WIDE_MARGIN
            if by is None or (by in ("auto", "operator") and not sure):
                continue
            path = data_dir / step.artifacts["upright_differences"]
            try:
                differences = read_learned_differences(path)
            except (OSError, ValueError, KeyError):
                continue  # a missing or damaged artifact: that card teaches nothing
            found.append({"card": card.id, "orientation": orientation, "step": step, "differences": differences})
    return found


def signed_rows(card: dict[str, Any]) -> dict[str, np.ndarray]:
    """The card's differences signed so each row's right answer is +1: the turn head's on the
    tone the card really has (the photos read as a positive), the tone head's as scanned."""
    orientation, differences = card["orientation"], card["differences"]
    rows: dict[str, np.ndarray] = {}
    turn = differences.get("turn_negative" if orientation["inverted"] else "turn")
    if turn is not None:
        rows["turn"] = -turn if orientation["upside_down"] else turn
    if "tone" in differences:
        rows["tone"] = -differences["tone"] if orientation["inverted"] else differences["tone"]
    return rows


def _folds(n: int, folds: int, seed: int) -> np.ndarray:
    order = np.random.default_rng(seed).permutation(n)
    assignment = np.empty(n, int)
    assignment[order] = np.arange(n) % folds
    return assignment


def cross_validate(cards: list[dict[str, Any]], head: Any, kind: str, l2: float, folds: int, seed: int) -> dict[str, Any]:
    """Held-out margins (grouped by card) of the head in force and of a refit pulled towards it."""
    from pipeline.upright import fit_linear_head, margin_summary

    rows = [signed_rows(card).get(kind) for card in cards]
    keep = [k for k, r in enumerate(rows) if r is not None]
    if len(keep) < 2:
        return {"cards": len(keep)}
    fold_of = _folds(len(keep), min(folds, len(keep)), seed)
    before, after = [], []
    prior = np.asarray(getattr(head, kind), np.float64)
    for fold in range(int(fold_of.max()) + 1):
        train = np.concatenate([rows[keep[k]] for k in range(len(keep)) if fold_of[k] != fold])
        held = np.concatenate([rows[keep[k]] for k in range(len(keep)) if fold_of[k] == fold])
        w = fit_linear_head(train, l2, prior)
        before.append(held @ prior)
        after.append(held @ w)
    return {
        "cards": len(keep),
        "before": margin_summary(np.concatenate(before)),
        "after": margin_summary(np.concatenate(after)),
    }


def _preview_changes(cards: list[dict[str, Any]], new_head: Any) -> list[dict[str, Any]]:
    """Cards whose step decision would change with the new head, from the cue values the step
    stored and the new head's reading of the stored differences (the next run recomputes)."""
    from pipeline.orientation import OrientationParams, decided_combination

    params = OrientationParams()
    weights = params.weights()
    limit = params.learned_max_log_odds

    def mean(differences: dict[str, np.ndarray], kind: str, key: str) -> float | None:
        if key not in differences:
            return None
        return float(np.clip(np.mean(new_head.margins(kind, differences[key])), -limit, limit))

    changes = []
    for card in cards:
        step = card["step"]
        values = dict(step.metrics.get("cue_values") or {})
        if not values:
            continue
        differences = card["differences"]
        upright, inverse = mean(differences, "turn", "turn"), mean(differences, "turn", "turn_negative")
        tone = mean(differences, "tone", "tone")
        values["learned_upright"] = upright if upright is not None else (inverse or 0.0)
        values["learned_upright_inverse"] = inverse if inverse is not None else (upright or 0.0)
        values["learned_tone"] = tone or 0.0
        known = step.metrics.get("known_flags") or None
        chosen, _ = decided_combination(values, weights, params.auto_probability, known)
        now = step.metrics.get("proposed") if step.outcome == "auto" else None
        new = None if chosen is None else dict(zip(("upside_down", "inverted", "swapped"), chosen))
        if new != now:
            changes.append({"card": card["card"], "before": now, "after": new})
    return changes


def fit_collection(
    collection: str | None, *, folds: int = 5, seed: int = 0, save: bool = True, actor: Any = None
) -> dict[str, Any]:
    """Refit the heads on ``collection``'s decided cards (every collection when None); report
    held-out accuracy before and after, the decisions that would change, and save unless told
    not to. Raises :class:`UprightFitError` when it cannot."""
    from pipeline.upright import UprightHead, fit_linear_head, weights_digest

    collection_id = None
    if collection is not None:
        row = db.session.scalar(select(Collection).where(Collection.name == collection))
        if row is None:
            names = ", ".join(db.session.scalars(select(Collection.name).order_by(Collection.name))) or "none yet"
            raise UprightFitError(f"There is no collection {collection!r} (collections: {names})")
        collection_id = row.id
    cards = labelled_cards(collection_id)
    if len(cards) < MIN_CARDS:
        raise UprightFitError(
            f"Refitting needs at least {MIN_CARDS} cards whose orientation people decided (or the step with P >= "
            f"{WIDE_MARGIN}) and whose orientation step stored the network's readings; found {len(cards)}"
        )
    head, version_before = _current_head(collection_id)
    report: dict[str, Any] = {"collection": collection, "cards": len(cards), "head_before": version_before, "heads": {}}
    weights: dict[str, tuple[float, ...]] = {}
    for kind in ("turn", "tone"):
        sweep = {l2: cross_validate(cards, head, kind, l2, folds, seed) for l2 in L2_CHOICES}
        usable = {l2: v for l2, v in sweep.items() if "after" in v}
        if not usable:
            weights[kind] = tuple(getattr(head, kind))
            report["heads"][kind] = {"kept": "too few cards with this reading", "cards": sweep[L2_CHOICES[0]].get("cards", 0)}
            continue
        l2 = min(usable, key=lambda value: (usable[value]["after"]["log_loss"], -value))
        rows = np.concatenate([r[kind] for r in (signed_rows(card) for card in cards) if kind in r])
        weights[kind] = tuple(float(v) for v in fit_linear_head(rows, l2, np.asarray(getattr(head, kind))))
        report["heads"][kind] = {"l2": l2, **usable[l2]}
    digest = weights_digest(weights["turn"], weights["tone"])
    stamp = datetime.now(UTC).strftime("%Y%m%d%H%M%S")
    version = f"{_slug(collection) if collection else 'all'}-{stamp}-{digest}"
    new_head = UprightHead(version=version, input_side=head.input_side, turn=weights["turn"], tone=weights["tone"])
    report["head_after"] = version
    report["would_change"] = _preview_changes(cards, new_head)
    report["saved"] = False
    if save:
        fit = UprightHeadFit(
            collection_id=collection_id,
            version=version,
            head=new_head.as_dict(),
            fitted_on=len(cards),
            evaluation={kind: report["heads"][kind] for kind in report["heads"]},
            created_by=getattr(actor, "id", None),
        )
        db.session.add(fit)
        db.session.flush()
        record_event(
            entity="upright_head",
            entity_id=fit.id,
            action="fit",
            actor=actor,
            actor_label=None if actor else "keystone orientation fit",
            before={"head": version_before},
            after={"head": version, "would_change": len(report["would_change"])},
            why=f"refitted on {len(cards)} decided cards of {collection or 'every collection'}",
        )
        db.session.commit()
        head_file(fit)
        report["saved"] = True
    return report
