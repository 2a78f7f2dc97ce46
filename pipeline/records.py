"""Small, picklable records that cross the process boundary between driver and workers.

Workers return :class:`StageRecord`; the driver (``runs.loop``) writes them to the database in
batches. Keeping these plain dataclasses means a distributed executor can ship them cheaply.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

StageStatus = Literal["done", "skipped", "failed"]


def param_hash(params: Any) -> str:
    """Stable 16-hex-digit hash of a frozen parameters dataclass (its fields as sorted JSON).

    Outputs are keyed by (card content hash, stage, param hash), so a rerun with the same
    parameters skips finished work and a changed threshold reruns the stage.
    """
    payload = json.dumps(asdict(params), sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def inputs_digest(inputs: dict[str, Any]) -> str:
    """Stable 16-hex-digit hash of a stage's inputs (sorted JSON), stored with each result: a
    finished card runs again when the inputs its builder gives now hash otherwise."""
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]


def card_work_dir(data_dir: Path, content_hash: str, stage: str, phash: str) -> Path:
    """Artifacts are keyed by card content and stage parameters, never by database id."""
    return data_dir / "derived" / content_hash[:2] / content_hash / stage / phash


@dataclass(frozen=True)
class CardTask:
    """One card's work order for a stage.

    ``image_path`` is the absolute path of the stored original (read-only);
    ``work_dir`` is an absolute folder the stage may write its artifacts into;
    ``data_dir`` is the root that artifact paths in the record are made relative to;
    ``inputs`` carries what earlier stages decided that this one needs (e.g. the filter's
    split boxes for rectification), as plain JSON values.
    """

    card_id: int
    content_hash: str
    image_path: str
    work_dir: str
    data_dir: str
    inputs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class StageRecord:
    """What a worker reports for one card and one stage.

    ``status`` is ``done``, ``skipped`` (``reason`` says what the card did not need) or
    ``failed`` (``reason`` is a typed reason, ``"<code>: <words>"``). ``outcome`` is a
    stage's own verdict where it has one (the filter's ``pass`` / ``review`` / ``culled``).
    ``artifacts`` maps a name to a path relative to the data dir.
    """

    card_id: int
    stage: str
    param_hash: str
    status: StageStatus
    outcome: str | None = None
    reason: str | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    artifacts: dict[str, str] = field(default_factory=dict)
    started_at: float = 0.0  # unix seconds
    seconds: float = 0.0  # wall time spent on this card in this stage
    code_version: str = ""
