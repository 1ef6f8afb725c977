"""The one error the core raises for bad input, naming the offending field."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Input the caller must fix: ``field`` is a dotted path into the pair format
    (``"image1.pose.attitude.matrix"``, ``"plane.z"``), ``reason`` says what is wrong."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason
