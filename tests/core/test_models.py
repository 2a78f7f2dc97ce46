"""Catalogue models on SQLite and PostgreSQL: constraints hold, JSON round-trips, roles work."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select, text
from sqlalchemy.exc import IntegrityError

from core.db import db
from core.models import Card, Collection, Person, StageResult

pytestmark = pytest.mark.both_databases


def _card(collection: Collection, content_hash: str = "a" * 64, **overrides) -> Card:
    values = dict(
        collection=collection,
        content_hash=content_hash,
        stored_path=f"originals/{content_hash[:2]}/{content_hash}.jpg",
        source_name="card.jpg",
        source_path="/scans/card.jpg",
        width=1400,
        height=700,
        image_format="JPEG",
        byte_size=12345,
        source_metadata={"Title": "Niagara", "Subjects": "Falls\nRivers", "extra column": "kept"},
    )
    values.update(overrides)
    return Card(**values)


def test_card_round_trip_with_metadata_and_results(app):
    with app.app_context():
        collection = Collection(name="keystone-mast")
        card = _card(collection)
        db.session.add(card)
        db.session.flush()
        db.session.add(
            StageResult(
                card_id=card.id,
                stage="filter",
                param_hash="0123456789abcdef",
                status="done",
                outcome="pass",
                reason="pass",
                metrics={"good_match_fraction": 0.25, "denominator": "keypoints_left"},
                artifacts={"left": "derived/x/left.jpg"},
                seconds=0.2,
                code_version="0.1.0",
            )
        )
        db.session.commit()
        db.session.expire_all()
        loaded = db.session.scalar(select(Card).where(Card.content_hash == "a" * 64))
        assert loaded.state == "ingested"
        assert loaded.source_metadata["Subjects"] == "Falls\nRivers"
        assert loaded.source_metadata["extra column"] == "kept"
        result = loaded.latest_results()["filter"]
        assert result.metrics["good_match_fraction"] == pytest.approx(0.25)
        assert result.as_status()["status"] == "done"


def test_content_hash_is_unique(app):
    with app.app_context():
        collection = Collection(name="c")
        db.session.add_all([_card(collection), _card(collection, source_name="copy.jpg")])
        with pytest.raises(IntegrityError):
            db.session.commit()
        db.session.rollback()


def test_one_result_per_card_stage_and_parameters(app):
    with app.app_context():
        card = _card(Collection(name="c"))
        db.session.add(card)
        db.session.flush()
        for _ in range(2):
            db.session.add(StageResult(card_id=card.id, stage="filter", param_hash="p", status="done"))
        with pytest.raises(IntegrityError):
            db.session.commit()
        db.session.rollback()


@pytest.mark.parametrize("column,value", [("status", "finished"), ("state", "lost")])
def test_check_constraints_refuse_unknown_values(app, column, value):
    with app.app_context():
        card = _card(Collection(name="c"))
        db.session.add(card)
        db.session.flush()
        if column == "state":
            card.state = value
        else:
            db.session.add(StageResult(card_id=card.id, stage="filter", param_hash="p", status=value))
        with pytest.raises(IntegrityError):
            db.session.commit()
        db.session.rollback()


def test_foreign_keys_are_enforced(app):
    with app.app_context():
        db.session.add(StageResult(card_id=999_999, stage="filter", param_hash="p", status="done"))
        with pytest.raises(IntegrityError):
            db.session.commit()
        db.session.rollback()


def test_deleting_a_card_deletes_its_results(app):
    with app.app_context():
        card = _card(Collection(name="c"))
        db.session.add(card)
        db.session.flush()
        db.session.add(StageResult(card_id=card.id, stage="filter", param_hash="p", status="done"))
        db.session.commit()
        db.session.delete(card)
        db.session.commit()
        assert db.session.scalar(select(func.count()).select_from(StageResult)) == 0


def test_people_roles_and_passwords(app):
    with app.app_context():
        person = Person(username="ada")
        person.set_password("correct horse")
        person.grant("curator")
        person.grant("curator")
        db.session.add(person)
        db.session.commit()
        db.session.expire_all()
        loaded = db.session.scalar(select(Person).where(Person.username == "ada"))
        assert loaded.roles == {"curator"}
        assert loaded.has_role("curator") and not loaded.has_role("exporter")
        assert loaded.check_password("correct horse") and not loaded.check_password("wrong")
        assert loaded.password_hash != "correct horse"
        with pytest.raises(ValueError, match="unknown role"):
            loaded.grant("owner")
        loaded.grant("admin")
        assert loaded.has_role("exporter")  # admins may do what any role may


def test_role_check_constraint_in_database(app):
    with app.app_context():
        person = Person(username="bob")
        db.session.add(person)
        db.session.flush()
        with pytest.raises(IntegrityError):
            db.session.execute(text("INSERT INTO person_roles (person_id, role) VALUES (:p, 'owner')"), {"p": person.id})
            db.session.commit()
        db.session.rollback()
