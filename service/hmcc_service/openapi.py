"""The committed OpenAPI document: ``python -m hmcc_service.openapi [--check] [--output PATH]``.

Writes the app's document (built with the default settings, never the environment's) to
``openapi/openapi.json``: sorted keys, two-space indent, trailing newline, so a change to the
API shows up as a reviewable diff. ``--check`` writes nothing and exits 1 when the file is
missing or differs, naming the first paths that differ.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from .app import create_app
from .settings import Settings

__all__ = ["DEFAULT_PATH", "build_document", "diff_paths", "main", "render"]

#: ``openapi/openapi.json`` at the root of the checkout.
DEFAULT_PATH = Path(__file__).resolve().parents[2] / "openapi" / "openapi.json"


def build_document() -> dict[str, Any]:
    """The app's OpenAPI document under the field defaults of :class:`Settings` (no env)."""
    return create_app(Settings.model_construct()).openapi()


def render(document: dict[str, Any]) -> str:
    """The canonical text of a document: sorted keys, indent 2, trailing newline."""
    return json.dumps(document, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def diff_paths(old: Any, new: Any, path: str = "") -> list[str]:
    """JSON-pointer-like paths where ``old`` and ``new`` differ (``+`` added, ``-`` removed,
    ``~`` changed), depth first in key order."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        for key in sorted(old.keys() | new.keys()):
            where = f"{path}/{key}"
            if key not in old:
                out.append(f"+ {where}")
            elif key not in new:
                out.append(f"- {where}")
            else:
                out.extend(diff_paths(old[key], new[key], where))
        return out
    if old != new:
        return [f"~ {path or '/'}"]
    return []


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m hmcc_service.openapi", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--check", action="store_true", help="fail if the file is out of date")
    parser.add_argument("--output", type=Path, default=DEFAULT_PATH, help="default: %(default)s")
    args = parser.parse_args(argv)
    document = build_document()
    text = render(document)
    path: Path = args.output
    if not args.check:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")
        return 0
    if not path.is_file():
        print(f"{path} is missing; run python -m hmcc_service.openapi", file=sys.stderr)
        return 1
    current = path.read_text(encoding="utf-8")
    if current == text:
        return 0
    try:
        changes = diff_paths(json.loads(current), document)
    except json.JSONDecodeError:
        changes = ["~ / (the file is not valid JSON)"]
    changes = changes or ["~ formatting only (keys, indent or trailing newline)"]
    print(f"{path} is out of date ({len(changes)} difference(s)):", file=sys.stderr)
    for line in changes[:20]:
        print(f"  {line}", file=sys.stderr)
    if len(changes) > 20:
        print(f"  ... and {len(changes) - 20} more", file=sys.stderr)
    print("regenerate it with: python -m hmcc_service.openapi", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
