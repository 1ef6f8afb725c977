"""The API's answers in MessagePack, read back as their JSON form, for tests that compare the
two media types."""

from __future__ import annotations

from typing import Any

import httpx
import msgpack
import numpy as np

MSGPACK = "application/vnd.hmcc+msgpack"


def raw_arrays(doc: Any) -> list[np.ndarray]:
    """Every ``{"dtype", "shape", "data"}`` map in ``doc`` as the array it holds."""
    if isinstance(doc, dict) and set(doc) == {"dtype", "shape", "data"}:
        return [np.frombuffer(doc["data"], dtype=np.dtype(doc["dtype"])).reshape(doc["shape"])]
    children = doc.values() if isinstance(doc, dict) else doc if isinstance(doc, list) else []
    return [a for child in children for a in raw_arrays(child)]


def as_json(doc: Any) -> Any:
    """``doc`` with each raw array map a nested list, as JSON holds it."""
    if isinstance(doc, dict) and set(doc) == {"dtype", "shape", "data"}:
        return raw_arrays(doc)[0].tolist()
    if isinstance(doc, dict):
        return {k: as_json(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [as_json(v) for v in doc]
    return doc


def both(url: str, path: str, **kw: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """``GET path`` answered in JSON (the default) and in MessagePack (decoded as it came)."""
    plain = httpx.get(f"{url}{path}", timeout=40, **kw)
    packed = httpx.get(f"{url}{path}", headers={"Accept": MSGPACK}, timeout=40, **kw)
    assert plain.status_code == packed.status_code == 200, (plain.text, packed.content[:200])
    assert plain.headers["content-type"] == "application/json"
    assert packed.headers["content-type"] == MSGPACK
    assert plain.headers["vary"] == packed.headers["vary"] == "Accept"
    return plain.json(), msgpack.unpackb(packed.content)
