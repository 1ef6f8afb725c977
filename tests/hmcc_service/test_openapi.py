"""The committed ``openapi/openapi.json`` is the app's document, and the document keeps its
promises: every /v1 operation has an operationId, documents 422 and requires X-API-Key, and
its request schemas state the rules across fields the API applies (a body the schema accepts
is not refused for them, nor the other way round)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema_rs
import orjson
import pytest
from pydantic import ValidationError

from hmcc import InputError
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_batch, parse_pair
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
    [
        ("POST /v1/verifications", "PairRequest"),
        ("POST /v1/batches", "BatchRequest"),
        ("POST /v1/pairs", "PairsRequest"),
    ],
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


# -- rules across fields: the schema and the parser agree ------------------------------------

IDENTITY = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
CAMERA = {"width": 6000, "height": 4000}
#: (case, the pair's top-level fields replaced, valid)
CROSS_FIELD: list[tuple[str, dict[str, Any], bool]] = [
    ("fx-fy", {}, True),
    ("focal", {"camera": {**CAMERA, "focal": 4000.0}}, True),
    ("focal-null-fx", {"camera": {**CAMERA, "focal": 4000.0, "fx": None}}, True),
    ("focal-and-fx", {"camera": {**CAMERA, "focal": 4000.0, "fx": 4000.0}}, False),
    ("fx-only", {"camera": {**CAMERA, "fx": 4000.0}}, False),
    ("fx-null-fy", {"camera": {**CAMERA, "fx": 4000.0, "fy": None}}, False),
    ("no-focal", {"camera": CAMERA}, False),
    ("plane-auto", {"plane": {"z": "auto"}}, True),
    ("plane-empty", {"plane": {}}, True),
    ("plane-z-null-ground", {"plane": {"z": 40.0, "ground_z": None}}, True),
    ("plane-ground", {"plane": {"ground_z": 40.0}}, True),
    ("plane-z-and-ground", {"plane": {"z": 40.0, "ground_z": 47.0}}, False),
    ("plane-auto-and-ground", {"plane": {"z": "auto", "ground_z": 47.0}}, False),
    ("mounting-yaw-pitch-roll", {"mounting": {"pitch": 10.0}}, True),
    (
        "mounting-omega-phi-kappa",
        {"attitude": {"omega": 0.0, "phi": 0.0, "kappa": 0.0}, "mounting": {"pitch": 10.0}},
        False,
    ),
    ("mounting-matrix", {"attitude": {"matrix": IDENTITY}, "mounting": {"yaw": 1.0}}, False),
    ("null-mounting-matrix", {"attitude": {"matrix": IDENTITY}, "mounting": None}, True),
    ("keypoints-4-wide", {}, True),
    ("keypoints-2-wide", {"keypoints": 2}, True),
    ("keypoints-3-wide", {"keypoints": 3}, False),
    ("keypoints-2-and-4-wide", {"keypoints": "mixed"}, False),
    ("method-known", {"method": "ransac"}, True),
    ("method-unknown", {"method": "magic"}, False),
]


@pytest.fixture(scope="module")
def valid_pair() -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=20), seed=1)
    pair.pop("ground_truth")
    return pair


def _edited(pair: dict[str, Any], edits: dict[str, Any]) -> dict[str, Any]:
    """``pair`` with image1's camera/attitude/mounting, the plane, the method or the width of
    keypoints1's rows replaced."""
    body = json.loads(json.dumps(pair))
    image = body["image1"]
    for key, value in edits.items():
        if key == "camera":
            image["camera"] = value
        elif key in ("attitude", "mounting"):
            image["pose"][key] = value
        elif key == "keypoints":
            rows = body["keypoints1"]
            width = {2: [2] * len(rows), 3: [3] * len(rows), "mixed": [2, 4] * len(rows)}[value]
            body["keypoints1"] = [row[:w] for row, w in zip(rows, width, strict=False)]
        else:
            body[key] = value
    return body


def _schema(document: dict[str, Any], name: str) -> Any:
    return jsonschema_rs.Draft202012Validator(
        {"$ref": f"#/components/schemas/{name}", "components": document["components"]}
    )


def _accepted(parse: Any, body: dict[str, Any]) -> bool:
    try:
        parse(orjson.dumps(body))
    except (ValidationError, InputError):
        return False
    return True


@pytest.mark.parametrize(
    ("edits", "valid"), [c[1:] for c in CROSS_FIELD], ids=[c[0] for c in CROSS_FIELD]
)
def test_schema_and_parser_agree_on_rules_across_fields(
    document: dict[str, Any], valid_pair: dict[str, Any], edits: dict[str, Any], valid: bool
) -> None:
    """Each rule across fields, both ways, for a pair and for the same pair in a batch (its
    images by id): the document's schema and the API's parser give the same verdict."""
    pair = _edited(valid_pair, edits)
    assert _schema(document, "PairRequest").is_valid(pair) is valid
    assert _accepted(parse_pair, pair) is valid

    images = {"a": pair["image1"], "b": pair["image2"]}
    fields = {k: pair[k] for k in ("keypoints1", "keypoints2", "matches")}
    batch = {
        "images": images,
        "pairs": [{"image1": "a", "image2": "b", **fields}],
        **{k: pair[k] for k in ("plane", "method") if k in pair},
    }
    assert _schema(document, "BatchRequest").is_valid(batch) is valid
    assert _accepted(lambda raw: parse_batch(raw, 10), batch) is valid
