"""Counts in the commands' messages: ``1 pair``, ``2 pairs``."""

from __future__ import annotations

__all__ = ["counted"]


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``"1 pair"``, ``"0 pairs"``, ``"3 pairs"``; ``plural`` where it is not ``noun + "s"``."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"
