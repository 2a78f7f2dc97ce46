"""Typed errors a stage can raise. Each carries a short machine code used in recorded reasons."""

from __future__ import annotations


class PipelineError(Exception):
    """Base class: ``code`` is a stable identifier, the message is for people."""

    code = "pipeline_error"

    def reason(self) -> str:
        return f"{self.code}: {self}"


class ImageReadError(PipelineError):
    """The file is missing, unreadable, truncated, not an image, or too large to decode."""

    code = "unreadable_image"


class ImageTooLargeError(ImageReadError):
    code = "image_too_large"


class InvalidInputError(PipelineError):
    """An array that breaks a stage's contract (wrong shape, dtype, NaN, too small)."""

    code = "invalid_input"
