"""The one error of bad input to ``hmcc colmap``."""

from __future__ import annotations

__all__ = ["ColmapInputError"]


class ColmapInputError(Exception):
    """Input the run cannot use (a missing or old database, no matches, images or a pose file
    that do not fit it): one line saying what, raised before anything is written."""
