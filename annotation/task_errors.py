"""The error every crowd use case raises for something a worker (or an admin) can cause."""

from __future__ import annotations


class TaskError(Exception):
    """Something the worker (or an admin) did wrong: shown to them, status for the HTTP reply."""

    def __init__(self, message: str, status: int = 400, retry_after: int | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.status = status
        self.retry_after = retry_after  # seconds, sent as Retry-After (429 answers)
