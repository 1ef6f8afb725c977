"""The committed ``openapi/openapi.json`` is the app's document, and the document keeps its
promises: every /v1 operation has an operationId, documents 422 and requires X-API-Key."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hmcc_service.openapi import DEFAULT_PATH, build_document, diff_paths, main, render

METHODS = {"get", "put", "post", "delete", "patch", "head", "options", "trace"}


@pytest.fixture(scope="module")
def document() -> dict[str, Any]:
    return build_document()


def operations(document: dict[str, Any], prefix: str = "/") -> Iterator[tuple[str, dict]]:
    """``("POST /v1/batches", operation)`` for every operation under ``prefix``."""
    for path, item in document["paths"].items():
        if path.startswith(prefix):
            for method, operation in item.items():
                if method in METHODS:
                    yield f"{method.upper()} {path}", operation


def refs(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        if isinstance(node.get("$ref"), str):
            yield node["$ref"]
        for value in node.values():
            yield from refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from refs(value)


def test_committed_document_is_current(document: dict[str, Any]) -> None:
    """Regenerate with ``python -m hmcc_service.openapi`` when the API changes."""
    assert DEFAULT_PATH.is_file(), f"{DEFAULT_PATH} is missing"
    committed = DEFAULT_PATH.read_text(encoding="utf-8")
    drift = diff_paths(json.loads(committed), document)
    assert not drift, "openapi/openapi.json is out of date: " + ", ".join(drift[:10])
    assert committed == render(document), "openapi/openapi.json is not in canonical form"


def test_check_mode(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--check`` passes on a fresh file and fails (naming the path) on a drifted one."""
    out = tmp_path / "openapi.json"
    assert main(["--check", "--output", str(out)]) == 1  # missing
    assert main(["--output", str(out)]) == 0
    assert main(["--check", "--output", str(out)]) == 0
    drifted = json.loads(out.read_text())
    drifted["info"]["version"] = "0.0.0-drift"
    out.write_text(render(drifted))
    capsys.readouterr()
    assert main(["--check", "--output", str(out)]) == 1
    assert "~ /info/version" in capsys.readouterr().err
    out.write_text(json.dumps(build_document()))  # same content, not canonical
    assert main(["--check", "--output", str(out)]) == 1


def test_rendering_is_canonical(document: dict[str, Any]) -> None:
    text = render(document)
    assert text.endswith("}\n") and not text.endswith("\n\n")
    assert text == json.dumps(json.loads(text), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def test_every_v1_operation_has_an_id_and_documents_422(document: dict[str, Any]) -> None:
    ops = dict(operations(document, "/v1/"))
    assert ops, "no /v1 operations in the document"
    missing_id = [name for name, op in ops.items() if not op.get("operationId")]
    takes_input = {
        name: op for name, op in ops.items() if op.get("parameters") or op.get("requestBody")
    }
    assert len(takes_input) == len(ops) - 1  # all but GET /v1/limits
    missing_422 = [name for name, op in takes_input.items() if "422" not in op.get("responses", {})]
    assert not missing_id, f"no operationId: {missing_id}"
    assert not missing_422, f"422 not documented: {missing_422}"
    ids = [op["operationId"] for _, op in operations(document)]
    assert len(ids) == len(set(ids)), f"duplicate operationIds: {ids}"


def test_api_key_scheme_guards_every_v1_operation(document: dict[str, Any]) -> None:
    schemes = document["components"]["securitySchemes"]
    names = [
        name
        for name, s in schemes.items()
        if s.get("type") == "apiKey" and s.get("in") == "header" and s.get("name") == "X-API-Key"
    ]
    assert names, f"no X-API-Key header scheme in {schemes}"
    for name, op in operations(document, "/v1/"):
        required = {scheme for req in op.get("security", []) for scheme in req}
        assert required & set(names), f"{name} does not declare the X-API-Key scheme"


@pytest.mark.parametrize(
    ("operation", "model"),
    [("POST /v1/verifications", "PairRequest"), ("POST /v1/batches", "BatchRequest")],
)
def test_raw_body_routes_document_their_request(
    document: dict[str, Any], operation: str, model: str
) -> None:
    """The routes parse their body themselves; the document still names the model."""
    body = dict(operations(document))[operation]["requestBody"]
    assert body["required"] is True
    assert body["content"]["application/json"]["schema"] == {
        "$ref": f"#/components/schemas/{model}"
    }


def test_every_ref_resolves(document: dict[str, Any]) -> None:
    schemas = document["components"]["schemas"]
    prefix = "#/components/schemas/"
    dangling = sorted({r for r in refs(document) if r.removeprefix(prefix) not in schemas})
    assert not dangling, f"unresolved $refs: {dangling}"
