"""Options' types and bounds, declared once on their fields and checked when they are built.

Every stage's options are a frozen dataclass whose numeric bounds are ``annotated_types``
markers on the field types::

    threshold_px: Annotated[float, Interval(gt=0, le=100)] = 1.5

:func:`check_fields` enforces them (and the plain types, and ``Literal`` choices) in the
dataclass's ``__post_init__``, so a library caller gets ``ValueError("threshold_px: must be in
(0, 100]")``. Where options travel in a request, pydantic reads the same markers (and the
class attribute ``__pydantic_config__``), so the service refuses the same values with a 422
and its OpenAPI document shows the bounds. Rules that combine fields stay in ``__post_init__``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
from typing import Annotated, Any, Literal, Union, get_args, get_origin, get_type_hints

import annotated_types as at

__all__ = ["PYDANTIC_CONFIG", "check_fields"]

#: What pydantic applies to option dataclasses inside a request: unknown keys and non-finite
#: numbers are refused, as everywhere in the request.
PYDANTIC_CONFIG: dict[str, Any] = {"extra": "forbid", "allow_inf_nan": False}


def check_fields(obj: Any) -> None:
    """Check every field of the dataclass ``obj`` against its annotation; lists given for tuple
    fields are stored as tuples. Raises ``ValueError("<field>: <reason>, got <value>")`` for
    the first bad field."""
    cls: Any = type(obj)
    for name, hint in _hints(cls):
        value = getattr(obj, name)
        if isinstance(value, list) and get_origin(_strip(hint)) is tuple:
            value = tuple(value)
            object.__setattr__(obj, name, value)
        reason = _reason(value, hint)
        if reason is not None:
            raise ValueError(f"{name}: {reason}, got {value!r}")


@functools.cache
def _hints(cls: Any) -> tuple[tuple[str, Any], ...]:
    hints = get_type_hints(cls, include_extras=True)
    return tuple((f.name, hints[f.name]) for f in dataclasses.fields(cls))


def _strip(hint: Any) -> Any:
    """The type inside ``Annotated[...]`` and ``X | None``."""
    if get_origin(hint) is Annotated:
        hint = get_args(hint)[0]
    if get_origin(hint) in (Union, types.UnionType):
        (hint,) = [o for o in get_args(hint) if o is not type(None)]
    return hint


def _reason(value: Any, hint: Any) -> str | None:
    """Why ``value`` does not fit ``hint``, or None."""
    metadata: tuple[Any, ...] = ()
    if get_origin(hint) is Annotated:
        hint, *rest = get_args(hint)
        metadata = tuple(rest)
    if get_origin(hint) in (Union, types.UnionType):
        members = get_args(hint)
        if value is None:
            return None if type(None) in members else "must not be null"
        (hint,) = [m for m in members if m is not type(None)]
        if (reason := _reason(value, hint)) is not None:
            return reason
        hint = _strip(hint)
    origin = get_origin(hint)
    if origin is Literal:
        choices = get_args(hint)
        return None if value in choices else f"must be one of {list(choices)}"
    if origin is tuple:
        items = get_args(hint)
        if not isinstance(value, tuple):
            return "must be a list"
        if items[-1] is not Ellipsis and len(value) != len(items):
            return f"must be a sequence of {len(items)} values"
        per_item = items if items[-1] is not Ellipsis else (items[0],) * len(value)
        for v, item in zip(value, per_item, strict=True):
            if (reason := _reason(v, item)) is not None:
                return f"each item {reason}"
    elif hint is bool:
        if not isinstance(value, bool):
            return "must be true or false"
    elif hint is int:
        if not isinstance(value, int) or isinstance(value, bool):
            return "must be an integer"
    elif hint is float:
        if not isinstance(value, int | float) or isinstance(value, bool):
            return "must be a number"
        if not math.isfinite(value):
            return "must be finite"
    elif hint is str:
        if not isinstance(value, str):
            return "must be a string"
    elif isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if not isinstance(value, hint):
            return f"must be a {hint.__name__}"
    for marker in metadata:
        for bound in marker if isinstance(marker, at.Interval) else (marker,):
            if (reason := _bound(value, bound)) is not None:
                return reason
    return None


def _bound(value: Any, marker: Any) -> str | None:
    """Why ``value`` breaks one ``annotated_types`` ``marker``, or None."""
    if isinstance(marker, at.Gt) and not value > marker.gt:
        return f"must be > {marker.gt!r}"
    if isinstance(marker, at.Ge) and not value >= marker.ge:
        return f"must be >= {marker.ge!r}"
    if isinstance(marker, at.Lt) and not value < marker.lt:
        return f"must be < {marker.lt!r}"
    if isinstance(marker, at.Le) and not value <= marker.le:
        return f"must be <= {marker.le!r}"
    if isinstance(marker, at.MaxLen) and len(value) > marker.max_length:
        return f"must have at most {marker.max_length} items"
    if isinstance(marker, at.MinLen) and len(value) < marker.min_length:
        return f"must have at least {marker.min_length} items"
    return None
