"""No body and no query parameter gets a 5xx from a real ``hmcc serve`` (embedded queue) over
HTTP on loopback: bodies nested too deep (MessagePack and JSON alike) are refused with 422
naming ``body``, an offset beyond any batch with 422 naming ``query.offset``, and bodies and
queries of any shape (hypothesis: any nesting, huge integers, NaN and infinities, booleans
where numbers go, valid pairs and batches with fields corrupted) never get a 5xx."""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from typing import Any

import httpx
import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema.parse import MAX_DEPTH
from tests.support.procs import service_env, start_api

pytestmark = pytest.mark.procs

JSON = "application/json"
MSGPACK = "application/vnd.hmcc+msgpack"
ROUTES = {"pair": "/v1/verifications", "batch": "/v1/batches"}
#: Stands in for a deeply nested value until the body is encoded (encoders recurse).
MARK = "\x00DEEP"
FUZZ = settings(
    max_examples=250,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _valid_bodies() -> dict[str, dict[str, Any]]:
    pair = simulate_pair(SimulationOptions(n_inliers=12, outlier_ratio=0.25), seed=3)
    pair.pop("ground_truth")
    batch = {
        "images": {
            "a": {**pair["image1"], "keypoints": pair["keypoints1"]},
            "b": {**pair["image2"], "keypoints": pair["keypoints2"]},
        },
        "plane": pair["plane"],
        "pairs": [{"id": "p", "image1": "a", "image2": "b", "matches": pair["matches"]}],
    }
    return {"pair": pair, "batch": batch}


VALID = _valid_bodies()


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every place of a body, containers and leaves."""
    if prefix:
        yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for i, value in enumerate(node[:3]):  # three rows stand for all
            yield from _paths(value, (*prefix, i))


PATHS = {route: sorted(_paths(body), key=str) for route, body in VALID.items()}


# --------------------------------------------------------------------------- encoding


def nested_json(levels: int, kind: str = "list") -> bytes:
    opening, closing = ("[", "]") if kind == "list" else ('{"a":', "}")
    return (opening * levels + "1" + closing * levels).encode()


def nested_msgpack(levels: int, kind: str = "list") -> bytes:
    opening = b"\x91" if kind == "list" else b"\x81\xa1a"  # [x] or {"a": x}
    return opening * levels + b"\x01"


def _fits(value: Any) -> Any:
    """Integers MessagePack cannot hold as floats."""
    if isinstance(value, dict):
        return {k: _fits(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_fits(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**64:
        return float(value)
    return value


def encode(body: Any, media_type: str, levels: int = 0, kind: str = "list") -> bytes:
    """``body`` in ``media_type``, where :data:`MARK` stands for ``levels`` nested lists (or
    objects) around a number."""
    if media_type == JSON:
        raw, mark, deep = json.dumps(body).encode(), json.dumps(MARK).encode(), nested_json
    else:
        raw, mark, deep = (
            bytes(msgpack.packb(_fits(body))),
            bytes(msgpack.packb(MARK)),
            nested_msgpack,
        )
    return raw.replace(mark, deep(levels, kind), 1) if mark in raw else raw


# --------------------------------------------------------------------------- strategies

_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.integers(min_value=-(10**40), max_value=10**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
_values = st.recursive(
    _scalars,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=16,
)
#: Around the limit, where recursion of the service once broke (about 480 and up), up to the
#: unpacker's own stack (1024) and beyond.
_depths = st.sampled_from(
    [MAX_DEPTH - 2, MAX_DEPTH - 1, MAX_DEPTH, MAX_DEPTH + 1, 480, 600, 800, 1000, 1020, 10_000]
) | st.integers(1, 3000)


def _set(body: Any, path: tuple[Any, ...], value: Any) -> None:
    node = body
    try:
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    except (KeyError, IndexError, TypeError):  # an earlier edit replaced the way there
        pass


@st.composite
def requests(draw: st.DrawFn) -> tuple[str, str, bytes]:
    """(route, media type, body): any value, raw bytes, or a valid body with up to three of
    its places replaced by any value (one of them perhaps by a deep nest)."""
    route = draw(st.sampled_from(sorted(ROUTES)))
    media_type = draw(st.sampled_from([JSON, MSGPACK]))
    shape = draw(st.sampled_from(["corrupted", "corrupted", "deep", "deep", "any", "bytes"]))
    if shape == "bytes":
        return route, media_type, draw(st.binary(max_size=300))
    if shape == "any":
        return route, media_type, encode(draw(_values), media_type)
    body = copy.deepcopy(VALID[route])
    for _ in range(draw(st.integers(1, 3))):
        _set(body, draw(st.sampled_from(PATHS[route])), draw(_values))
    if shape == "deep":
        _set(body, draw(st.sampled_from(PATHS[route])), MARK)
    levels, kind = draw(_depths), draw(st.sampled_from(["list", "object"]))
    return route, media_type, encode(body, media_type, levels, kind)


_query_values = st.one_of(
    st.integers(),
    st.integers(min_value=-(10**40), max_value=10**40),
    st.floats().map(repr),
    st.text(max_size=8),
).map(str)


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    api, base = start_api(service_env(HMCC_EMBEDDED_WORKERS="1"))
    try:
        yield base
    finally:
        api.stop()


@pytest.fixture(scope="module")
def client(url: str) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=url, timeout=30, trust_env=False) as c:
        yield c


@pytest.fixture(scope="module")
def batch_path(client: httpx.Client) -> str:
    """A batch of the service, so that a page of it is answered (not a 404 before the page)."""
    r = client.post(ROUTES["batch"], json=VALID["batch"])
    assert r.status_code == 202, r.text
    page = client.get(r.headers["Location"], params={"wait": 30}).json()
    assert page["status"] == "finished", page
    return str(r.headers["Location"])


def post(client: httpx.Client, route: str, body: bytes, media_type: str) -> httpx.Response:
    return client.post(ROUTES[route], content=body, headers={"content-type": media_type})


def refused(response: httpx.Response, field: str) -> str:
    """The reason of a 422 naming ``field``."""
    assert response.status_code == 422, response.text
    error = response.json()["error"]
    assert error["code"] == "invalid_input", error
    [reason] = [i["reason"] for i in error["issues"] if i["field"] == field]
    return str(reason)


# --------------------------------------------------------------------------- tests


@pytest.mark.parametrize("route", sorted(ROUTES))
@pytest.mark.parametrize("levels", [480, 10_000])
@pytest.mark.parametrize("kind", ["list", "object"])
def test_deep_messagepack_is_422_naming_the_body(
    client: httpx.Client, route: str, levels: int, kind: str
) -> None:
    """About 480 levels (a 500-byte body) overflowed the service's recursion: a 500."""
    body = encode({"image1": MARK}, MSGPACK, levels, kind)
    reason = refused(post(client, route, body, MSGPACK), "body")
    assert reason.startswith("Invalid MessagePack: recursion limit exceeded"), reason


@pytest.mark.parametrize("route", sorted(ROUTES))
@pytest.mark.parametrize("levels", [480, 10_000])
def test_deep_json_is_422_naming_the_body(client: httpx.Client, route: str, levels: int) -> None:
    body = encode({"image1": MARK}, JSON, levels)
    reason = refused(post(client, route, body, JSON), "body")
    assert reason.startswith("Invalid JSON: recursion limit exceeded"), reason


@pytest.mark.parametrize("media_type", [JSON, MSGPACK])
def test_json_and_messagepack_refuse_the_same_depth(client: httpx.Client, media_type: str) -> None:
    """A valid pair as deep as MAX_DEPTH (its ground_truth nested) is accepted, one level more
    is refused, in either encoding."""
    body = {**VALID["pair"], "ground_truth": {"x": MARK}}
    ok = post(client, "pair", encode(body, media_type, MAX_DEPTH - 2), media_type)
    assert ok.status_code in (200, 202), ok.text
    deep = post(client, "pair", encode(body, media_type, MAX_DEPTH - 1), media_type)
    assert "recursion limit exceeded" in refused(deep, "body")


@pytest.mark.parametrize("name", ["offset", "limit"])
@pytest.mark.parametrize("value", [10**30, 2**63, -(10**30)])
def test_page_parameters_beyond_their_bounds_are_422(
    client: httpx.Client, batch_path: str, name: str, value: int
) -> None:
    """``?offset=10**30`` of an existing batch was echoed in the page, which orjson could not
    encode: a 500."""
    refused(client.get(batch_path, params={name: value}), f"query.{name}")


def test_the_largest_offset_is_an_empty_page(client: httpx.Client, batch_path: str) -> None:
    from hmcc_service.routes.batches import MAX_OFFSET

    page = client.get(batch_path, params={"offset": MAX_OFFSET})
    assert page.status_code == 200, page.text
    assert page.json()["results"] == [] and page.json()["offset"] == MAX_OFFSET


@FUZZ
@given(request=requests())
def test_no_body_answers_5xx(client: httpx.Client, request: tuple[str, str, bytes]) -> None:
    route, media_type, body = request
    response = post(client, route, body, media_type)
    assert response.status_code < 500, (response.status_code, response.text, body[:300])
    if response.status_code >= 400:
        assert response.json()["error"]["code"], response.text


@settings(FUZZ, max_examples=120)
@given(
    which=st.sampled_from(["batch", "verification"]),
    params=st.dictionaries(st.sampled_from(["offset", "limit", "wait"]), _query_values),
)
def test_no_query_answers_5xx(
    client: httpx.Client, batch_path: str, which: str, params: dict[str, str]
) -> None:
    """Page parameters and long polls of any size or form (the batch has finished and the
    job does not exist, so no wait holds the answer)."""
    path = batch_path if which == "batch" else "/v1/verifications/nope"
    response = client.get(path, params=params)
    assert response.status_code < 500, (response.status_code, response.text, params)
