"""What is wrong with a request, for the caller: a field path into the body and a reason.

Every place that reports bad input (the API's 422, a failed job, the command line's
``error: <field>: <reason>`` lines) goes through :func:`validation_issues`, which also bounds
whatever it quotes of the input: a 10 MB method name or object key is not sent back whole.
"""

from __future__ import annotations

import re

from pydantic import BaseModel, ValidationError

from hmcc import InputError

__all__ = ["MAX_QUOTE", "FieldIssue", "clip", "validation_issues"]

#: Characters of the caller's input an error quotes at most (field paths and reasons alike).
MAX_QUOTE = 200

_UNION_TAGS = {"local", "geodetic", "yaw_pitch_roll", "omega_phi_kappa", "matrix"}
_BRANCH_LABELS = re.compile(r"^(float|int|str|bool|literal\[.*\]|function-.*)$")


class FieldIssue(BaseModel):
    """One problem with a request: a dotted field path and the reason."""

    field: str
    reason: str


def clip(text: str, limit: int = MAX_QUOTE) -> str:
    """``text`` cut to ``limit`` characters, with an ellipsis and the length it had."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text)} characters)"


def _field_path(loc: tuple[int | str, ...]) -> str:
    """``("matches", 3, 1)`` -> ``"matches[3][1]"``; union tags are dropped."""
    path = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            path += f"[{part}]"
        elif part in _UNION_TAGS and i > 0 and loc[i - 1] in ("position", "attitude"):
            continue
        elif _BRANCH_LABELS.match(part):
            continue
        else:
            part = clip(part)
            path += f".{part}" if path else part
    return path or "body"


def validation_issues(error: ValidationError | InputError) -> list[FieldIssue]:
    """What the caller must fix, one entry per problem, without internals."""
    if isinstance(error, InputError):
        return [FieldIssue(field=clip(error.field), reason=clip(error.reason, 2 * MAX_QUOTE))]
    # A dict keeps the first-seen order and dedupes in O(1): a body can carry ~10^5 errors.
    unique: dict[tuple[str, str], None] = {}
    for e in error.errors(include_url=False, include_input=False):
        reason = clip(str(e["msg"]).removeprefix("Value error, "), 2 * MAX_QUOTE)
        unique.setdefault((_field_path(tuple(e["loc"])), reason), None)
    return [FieldIssue(field=field, reason=reason) for field, reason in unique]
