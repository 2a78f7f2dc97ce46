"""Release rows: one per published dataset release (the files themselves live on disk)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import DateTime, ForeignKey, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column, relationship

from core.db import JSONType, db, utcnow
from core.models import Person


class Release(db.Model):
    __tablename__ = "releases"

    id: Mapped[int] = mapped_column(primary_key=True)
    version: Mapped[str] = mapped_column(String(40), unique=True)  # semantic version, e.g. "1.2.0"
    path: Mapped[str] = mapped_column(Text)  # the release folder as written
    min_grade: Mapped[str] = mapped_column(String(10))
    formats: Mapped[list[str]] = mapped_column(JSONType, default=list)
    card_count: Mapped[int] = mapped_column(Integer, default=0)
    stats: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)  # grade counts, bytes, seconds
    changes: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)  # added/removed/changed vs previous
    notes: Mapped[str] = mapped_column(Text, default="")
    manifest_sha256: Mapped[str] = mapped_column(String(64))  # sha256 of the release's SHA256SUMS
    created_by: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    creator: Mapped[Person | None] = relationship()
