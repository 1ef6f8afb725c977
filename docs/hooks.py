"""MkDocs hook: a link from a page to a file of the repository outside ``docs/`` (a results
file, a source file) becomes its text, so ``mkdocs build --strict`` checks the links within the
site and the pages may still name the repository's files."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

_LINK = re.compile(r"(?<!!)\[([^\]]+)\]\(([^)\s#]+)(#[^)\s]*)?\)")


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    docs = Path(config["docs_dir"]).resolve()
    here = (docs / page.file.src_path).parent

    def unlink(match: re.Match[str]) -> str:
        target = match.group(2)
        if "://" in target or target.startswith("mailto:"):
            return match.group(0)
        resolved = (here / target).resolve()
        return match.group(0) if resolved.is_relative_to(docs) else match.group(1)

    return _LINK.sub(unlink, markdown)
