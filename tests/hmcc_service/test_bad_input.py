"""Bad input through the real app (in-process, embedded queue): every refusal is the expected
4xx in the error envelope, names the offending field and leaks nothing internal. Also the
API key (401 on every /v1 route, probes stay open) and CORS (off unless configured)."""

from __future__ import annotations

import copy
import json
import math
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

import httpx
import pytest

from hmcc.method_names import F_ONLY_METHODS
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import MAX_MATCHES, clip
from hmcc_service.app import create_app
from hmcc_service.errors import MAX_ISSUES
from hmcc_service.models import ErrorResponse
from hmcc_service.settings import Settings

# the app's lifespan starts its compute children
pytestmark = [pytest.mark.anyio, pytest.mark.procs, pytest.mark.usefixtures("hermetic_env")]

Path = tuple[str | int, ...]
#: Marks a key to delete in :class:`Case` edits.
DELETE = object()
#: Substrings that would mean internals leaked into a message.
LEAKS = ("Traceback", "/work/", ".py", "site-packages", "pydantic.dev", "errors.pydantic")
#: Where the batch keeps what a single pair has at its top level.
BATCH_IMAGE_IDS = {"image1": "a", "image2": "b"}
PAIR_FIELDS = ("keypoints1", "keypoints2", "matches")
ROUTES = {"pair": "/v1/verifications", "batch": "/v1/batches"}
IDENTITY = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
JSON = {"content-type": "application/json"}
#: A submission answers 202, or 200 when the (tiny) job already ended in the embedded queue.
ACCEPTED = (200, 202)


# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@asynccontextmanager
async def serve(**overrides: Any) -> AsyncIterator[httpx.AsyncClient]:
    """A client of a fresh app built with ``Settings(**overrides)``."""
    app = create_app(Settings(**overrides))
    transport = httpx.ASGITransport(app=app)
    try:
        async with httpx.AsyncClient(transport=transport, base_url="http://hmcc.test") as client:
            yield client
    finally:
        await app.state.queue.close()


@pytest.fixture
async def client() -> AsyncIterator[httpx.AsyncClient]:
    async with serve() as c:
        yield c


@pytest.fixture(scope="module")
def bodies() -> dict[str, dict[str, Any]]:
    """A valid body of each POST route: a small simulated pair, the same as a batch, and its
    two images as a pairs request."""
    pair = simulate_pair(SimulationOptions(n_inliers=20), seed=1)
    del pair["ground_truth"]
    batch = {
        "images": {BATCH_IMAGE_IDS[k]: pair[k] for k in BATCH_IMAGE_IDS},
        "pairs": [
            {
                "id": "p0",
                **{k: BATCH_IMAGE_IDS[k] for k in BATCH_IMAGE_IDS},
                **{k: pair[k] for k in PAIR_FIELDS},
            }
        ],
        "plane": pair["plane"],
    }
    pairs = {
        "images": {
            BATCH_IMAGE_IDS[k]: {"camera": pair[k]["camera"], "pose": pair[k]["pose"]}
            for k in BATCH_IMAGE_IDS
        },
        "ground_z": 0.0,
    }
    return {"pair": pair, "batch": batch, "pairs": pairs}


# --------------------------------------------------------------------------- helpers


def dotted(path: Path) -> str:
    """``("matches", 0, 1)`` -> ``"matches[0][1]"``: the API's field notation."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


def in_batch(path: Path) -> Path:
    """A pair-format path as it is in the batch body (images by id, pair fields in pairs[0])."""
    head, *rest = path
    if head in PAIR_FIELDS:
        return ("pairs", 0, head, *rest)
    if head in BATCH_IMAGE_IDS:
        return ("images", BATCH_IMAGE_IDS[str(head)], *rest)
    return path


def put(body: Any, path: Path, value: Any) -> None:
    """Set (or with :data:`DELETE`, remove) ``body[path]``."""
    *parents, last = path
    for part in parents:
        body = body[part]
    if value is DELETE:
        del body[last]
    else:
        body[last] = value


def assert_error(
    response: httpx.Response, status: int, code: str | None = None, field: str | None = None
) -> dict[str, Any]:
    """The envelope ``{"error": {code, message, issues?}}`` with that status, ``field`` among
    the issues when given, and no internals in any text."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    payload = response.json()
    assert set(payload) == {"error"}, payload
    assert set(payload["error"]) <= {"code", "message", "issues"}, payload
    error = ErrorResponse.model_validate(payload).error
    assert error.code and error.message
    if code is not None:
        assert error.code == code, payload
    if field is not None:
        fields = [i.field for i in error.issues or []]
        assert field in fields, f"no issue names {field!r}: {payload}"
    for leak in LEAKS:
        assert leak not in response.text, f"{leak!r} leaked: {response.text}"
    return payload


# --------------------------------------------------------------------------- bodies -> 422


@dataclass(frozen=True)
class Case:
    """One bad body: ``edits`` applied to a valid pair (pair-format paths, translated for
    the batch), or ``raw`` bytes instead; the issue must name ``field`` (a pair-format path,
    or a literal string used as is)."""

    name: str
    field: Path | str
    edits: tuple[tuple[Path, Any], ...] = ()
    raw: bytes | None = None
    routes: tuple[str, ...] = ("pair", "batch")
    #: A known bug outside the files this suite may fix: strict xfail until it is fixed.
    bug: str | None = None

    def body(self, route: str, valid: dict[str, Any]) -> bytes:
        if self.raw is not None:
            return self.raw
        body = copy.deepcopy(valid)
        for path, value in self.edits:
            put(body, in_batch(path) if route == "batch" else path, value)
        return json.dumps(body, allow_nan=True).encode()

    def expected_field(self, route: str) -> str:
        if isinstance(self.field, str):
            return self.field
        return dotted(in_batch(self.field) if route == "batch" else self.field)


def edit(name: str, path: Path, value: Any, field: Path | None = None, **kw: Any) -> Case:
    """A one-edit case whose issue names ``field`` (default: the edited path)."""
    return Case(name, path if field is None else field, ((path, value),), **kw)


ATTITUDE = ("image1", "pose", "attitude")
CASES: list[Case] = [
    # wrong types
    edit("keypoints-not-a-list", ("keypoints1",), "abc"),
    edit("width-a-string", ("image1", "camera", "width"), "wide"),
    edit("index-a-string", ("matches", 0, 0), "zero"),
    edit("index-a-fraction", ("matches", 0, 1), 1.5),
    edit("keypoint-coordinate-a-bool-list", ("keypoints2", 0, 0), [True]),
    edit("method-a-number", ("method",), 7),
    edit("params-a-string", ("params",), "fast"),
    Case("body-an-array", "body", raw=b"[]"),
    Case("body-a-string", "body", raw=b'"pair"'),
    # NaN / Infinity literals (json.dumps writes them as NaN, Infinity, -Infinity)
    edit("nan-keypoint", ("keypoints1", 0, 0), math.nan),
    edit("infinity-position", ("image1", "pose", "position", "x"), math.inf),
    edit("minus-infinity-focal", ("image2", "camera", "fx"), -math.inf),
    edit("nan-yaw", ("image2", "pose", "attitude", "yaw"), math.nan),
    edit("nan-plane", ("plane",), {"z": math.nan}, field=("plane", "z")),
    # match indices
    edit("negative-index", ("matches", 0, 0), -1),
    edit("index-past-keypoints", ("matches", 3, 1), 199_999, field=("matches",)),
    edit("index-beyond-int64", ("matches", 0, 0), 2**70),
    # shapes that disagree
    edit("keypoint-rows-2-and-4-wide", ("keypoints1", 0), [1.0, 2.0], field=("keypoints1",)),
    edit("keypoint-row-3-wide", ("keypoints1", 0), [1.0, 2.0, 3.0], field=("keypoints1",)),
    edit("keypoint-row-5-wide", ("keypoints2", 0), [1.0, 2.0, 3.0, 4.0, 5.0]),
    edit("keypoint-row-1-wide", ("keypoints2", 1), [1.0]),
    edit("match-with-3-indices", ("matches", 0), [0, 1, 2]),
    edit("match-with-1-index", ("matches", 2), [0]),
    edit("matrix-2x3", ATTITUDE, {"matrix": IDENTITY[:2]}, field=(*ATTITUDE, "matrix")),
    edit(
        "matrix-3x2",
        ATTITUDE,
        {"matrix": [r[:2] for r in IDENTITY]},
        field=(*ATTITUDE, "matrix", 0),
    ),
    # empty and too many
    edit("empty-keypoints", ("keypoints1",), []),
    edit("empty-matches", ("matches",), []),
    edit("too-many-matches", ("matches",), [[0, 0]] * (MAX_MATCHES + 1)),
    # unknown method, unknown / missing fields
    edit("unknown-method", ("method",), "magic"),
    edit("unknown-field", ("colour",), "red"),
    edit("missing-keypoints", ("keypoints2",), DELETE),
    edit("missing-camera", ("image2", "camera"), DELETE),
    edit(
        "unknown-ransac-model",
        ("params",),
        {"ransac": {"model": "affine"}},
        field=("params", "ransac", "model"),
    ),
    edit("negative-seed", ("params",), {"seed": -1}, field=("params", "seed")),
    edit(
        "bin-not-dividing-360",
        ("params",),
        {"direction": {"bin_deg": 7.0}},
        field=("params", "direction"),
    ),
    # bounds declared on the options' fields: the issue names the field itself
    edit(
        "zero-bin",
        ("params",),
        {"direction_change": {"bin_deg": 0.0}},
        field=("params", "direction_change", "bin_deg"),
    ),
    edit(
        "subnormal-bin",
        ("params",),
        {"direction": {"bin_deg": 2.2e-311}},
        field=("params", "direction", "bin_deg"),
    ),
    # degenerate cameras and poses
    edit(
        "matrix-not-orthonormal",
        ATTITUDE,
        {"matrix": [[2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]},
        field=(*ATTITUDE, "matrix"),
    ),
    edit(
        "matrix-huge-entries",
        ATTITUDE,
        {"matrix": [[1e200, 1e200, 0], [-1e200, 1e200, 0], [0, 0, 1.0]]},
        field=(*ATTITUDE, "matrix"),
    ),
    edit(
        "matrix-a-reflection",
        ATTITUDE,
        {"matrix": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]]},
        field=(*ATTITUDE, "matrix"),
    ),
    edit("focal-and-fx", ("image1", "camera", "focal"), 1000.0, field=("image1", "camera")),
    edit("no-focal", ("image1", "camera", "fy"), DELETE, field=("image1", "camera")),
    edit("zero-focal", ("image1", "camera", "fx"), 0.0),
    edit("zero-width", ("image2", "camera", "width"), 0),
    edit("short-distortion", ("image1", "camera", "distortion"), [0.1]),
    # checks across fields: no coordinate that is not finite may reach OpenCV
    edit("distortion-to-infinity", ("image1", "camera", "distortion"), [0.0, 0.0, 1e300, 1e300]),
    edit(
        "keypoint-outside-the-frame",
        ("keypoints1", 0),
        [1e5, 10.0, 2.0, 3.0],
        field=("keypoints1",),
    ),
    Case(
        "mounting-with-matrix",
        ("image1", "pose"),
        ((ATTITUDE, {"matrix": IDENTITY}), (("image1", "pose", "mounting"), {"pitch": 45.0})),
    ),
    edit("attitude-not-an-object", ATTITUDE, True),
    edit("position-not-an-object", ("image2", "pose", "position"), 3),
    edit(
        "latitude-91",
        ("image1", "pose", "position"),
        {"lat": 91.0, "lon": 0.0, "alt": 1.0},
        field=("image1", "pose", "position", "lat"),
    ),
    edit("plane-z-and-ground-z", ("plane",), {"z": 1.0, "ground_z": 2.0}),
    # not JSON at all
    Case("invalid-json", "body", raw=b'{"image1": '),
    Case("empty-body", "body", raw=b""),
    Case("binary-garbage", "body", raw=bytes(range(256)) * 4),
    Case("json-then-garbage", "body", raw=b"{}\x00\xff"),
    # batch only
    edit("unknown-image-id", ("pairs", 0, "image1"), "nope", routes=("batch",)),
    edit("empty-image-id", ("pairs", 0, "image2"), "", routes=("batch",)),
    edit("no-images", ("images",), {}, routes=("batch",)),
    edit("no-pairs", ("pairs",), [], routes=("batch",)),
    edit("pair-with-method", ("pairs", 0, "method"), "hmcc", routes=("batch",)),
]


@pytest.mark.parametrize(
    ("route", "case"),
    [
        pytest.param(
            r,
            c,
            id=f"{r}-{c.name}",
            marks=[pytest.mark.xfail(strict=True, reason=c.bug)] if c.bug else [],
        )
        for c in CASES
        for r in c.routes
    ],
)
@pytest.mark.filterwarnings("error::RuntimeWarning")  # no numpy overflow on the way
async def test_bad_body_is_422_naming_the_field(
    client: httpx.AsyncClient, bodies: dict[str, dict[str, Any]], route: str, case: Case
) -> None:
    """Each bad body: 422 ``invalid_input`` with an issue on the offending field."""
    response = await client.post(
        ROUTES[route], content=case.body(route, bodies[route]), headers=JSON
    )
    assert_error(response, 422, "invalid_input", case.expected_field(route))


async def test_valid_bodies_are_accepted(
    client: httpx.AsyncClient, bodies: dict[str, dict[str, Any]]
) -> None:
    """The baseline the cases edit is itself valid (so each case fails for its own edit)."""
    for route, path in ROUTES.items():
        response = await client.post(path, content=json.dumps(bodies[route]), headers=JSON)
        assert response.status_code in ACCEPTED, response.text


async def test_many_issues_are_answered_quickly(client: httpx.AsyncClient) -> None:
    """10^4 distinct issues (one per bad match index) take well under a second to list; the
    deduplication was quadratic (tens of seconds here, hours at MAX_MATCHES)."""
    body = {"matches": [[i, -1] for i in range(5_000)]}
    started = time.monotonic()
    response = await client.post(ROUTES["pair"], content=json.dumps(body), headers=JSON)
    elapsed = time.monotonic() - started
    payload = assert_error(response, 422, "invalid_input", "matches[0][1]")
    assert len(payload["error"]["issues"]) == MAX_ISSUES  # capped; the message says how many
    assert "more" in payload["error"]["message"]
    assert elapsed < 5.0, f"{elapsed:.1f} s"


async def test_too_many_batch_pairs_names_pairs(bodies: dict[str, dict[str, Any]]) -> None:
    """Over ``max_batch_pairs`` (a setting, checked after the schema): 422 naming ``pairs``."""
    body = copy.deepcopy(bodies["batch"])
    body["pairs"] *= 2
    async with serve(max_batch_pairs=1) as client:
        response = await client.post(ROUTES["batch"], content=json.dumps(body), headers=JSON)
    assert_error(response, 422, "invalid_input", "pairs")


#: A 10 MB string: an error answer must not send it back.
HUGE = "a" * 10_000_000


@pytest.mark.parametrize(
    ("route", "path", "value", "field"),
    [
        ("pair", ("method",), HUGE, "method"),
        ("batch", ("method",), HUGE, "method"),
        ("pair", (HUGE,), 1, clip(HUGE)),
        ("pair", ("image1", "camera", HUGE), 1.0, "image1.camera." + clip(HUGE)),
        ("pair", ("params",), {HUGE: {}}, "params." + clip(HUGE)),
        ("pair", ("params",), {"ransac": {"model": HUGE}}, "params.ransac.model"),
        ("pair", ("plane",), {"z": HUGE}, "plane.z"),
        ("batch", ("pairs", 0, "id"), HUGE, "pairs[0].id"),
        ("batch", ("pairs", 0, "image1"), HUGE, "pairs[0].image1"),
    ],
    ids=[
        "method",
        "batch-method",
        "unknown-key",
        "unknown-nested-key",
        "unknown-option",
        "option-value",
        "plane",
        "pair-id",
        "image-id",
    ],
)
async def test_error_answers_quote_input_briefly(
    client: httpx.AsyncClient,
    bodies: dict[str, dict[str, Any]],
    route: str,
    path: Path,
    value: Any,
    field: str,
) -> None:
    """A 10 MB value or key is a small 422 naming the field (quoted input is clipped)."""
    body = copy.deepcopy(bodies[route])
    put(body, path, value)
    response = await client.post(ROUTES[route], content=json.dumps(body), headers=JSON)
    assert_error(response, 422, "invalid_input", field)
    assert len(response.content) < 10_000, len(response.content)


@pytest.mark.parametrize("route", ["pair", "batch"])
@pytest.mark.parametrize("method", sorted(F_ONLY_METHODS))
@pytest.mark.parametrize("model", ["essential", "homography"])
async def test_a_model_the_method_does_not_fit_is_refused_at_once(
    client: httpx.AsyncClient,
    bodies: dict[str, dict[str, Any]],
    route: str,
    method: str,
    model: str,
) -> None:
    """A method that fits F alone with another model: 422 naming ``params.ransac.model`` when
    the body is read (it was accepted, and each pair then failed with ``invalid_input``)."""
    body = {
        **copy.deepcopy(bodies[route]),
        "method": method,
        "params": {"ransac": {"model": model}},
    }
    response = await client.post(ROUTES[route], content=json.dumps(body), headers=JSON)
    payload = assert_error(response, 422, "invalid_input", "params.ransac.model")
    assert method in payload["error"]["message"]
    body["method"] = "hmcc-ransac"  # fits any model: accepted
    response = await client.post(ROUTES[route], content=json.dumps(body), headers=JSON)
    assert response.status_code in (200, 202), response.text


# --------------------------------------------------------------------------- query/path -> 422


@pytest.mark.parametrize(
    ("method", "url", "field"),
    [
        ("POST", "/v1/verifications?wait=-1", "query.wait"),
        ("POST", "/v1/verifications?wait=1000", "query.wait"),
        ("POST", "/v1/verifications?wait=soon", "query.wait"),
        ("POST", "/v1/verifications?wait=nan", "query.wait"),
        ("POST", "/v1/verifications?wait=inf", "query.wait"),
        ("GET", "/v1/verifications/nope?wait=-1", "query.wait"),
        ("GET", "/v1/verifications/nope?wait=1000", "query.wait"),
        ("GET", "/v1/batches/nope?offset=-1", "query.offset"),
        ("GET", "/v1/batches/nope?limit=1001", "query.limit"),
        ("GET", "/v1/batches/nope?limit=ten", "query.limit"),
        ("GET", f"/v1/batches/nope?offset={10**30}", "query.offset"),
        ("GET", f"/v1/batches/nope?offset={2**63}", "query.offset"),
        ("GET", f"/v1/batches/nope?limit={10**30}", "query.limit"),
        ("GET", f"/v1/batches/nope?limit=-{10**30}", "query.limit"),
        ("GET", "/v1/verifications/" + "x" * 101, "path.job_id"),
        ("DELETE", "/v1/verifications/" + "x" * 101, "path.job_id"),
        ("GET", "/v1/batches/" + "x" * 101, "path.batch_id"),
    ],
)
async def test_bad_parameter_is_422(
    client: httpx.AsyncClient,
    bodies: dict[str, dict[str, Any]],
    method: str,
    url: str,
    field: str,
) -> None:
    """Out-of-range or mistyped query/path parameters: 422 naming ``query.X``/``path.X``
    (checked before the body, and before looking the id up)."""
    content = json.dumps(bodies["pair"]) if method == "POST" else None
    response = await client.request(method, url, content=content, headers=JSON)
    assert_error(response, 422, "invalid_input", field)


async def test_unknown_ids_are_404(client: httpx.AsyncClient) -> None:
    for method, url in (
        ("GET", "/v1/verifications/nope"),
        ("DELETE", "/v1/verifications/nope"),
        ("GET", "/v1/batches/nope"),
    ):
        assert_error(await client.request(method, url), 404, "not_found")


# --------------------------------------------------------------------------- methods


@pytest.mark.parametrize(
    ("path", "allowed"),
    [
        ("/v1/verifications", {"POST"}),
        ("/v1/verifications/nope", {"GET", "DELETE"}),
        ("/v1/batches", {"POST"}),
        ("/v1/batches/nope", {"GET"}),
        ("/v1/limits", {"GET"}),
        ("/healthz", {"GET"}),
        ("/readyz", {"GET"}),
        ("/metrics", {"GET"}),
    ],
)
async def test_options_and_other_methods_name_every_allowed_method(
    client: httpx.AsyncClient, path: str, allowed: set[str]
) -> None:
    """OPTIONS answers 204 with ``Allow`` (every method of every route of the path); a method
    the path does not take is 405 with the same ``Allow``."""

    def methods(response: httpx.Response) -> set[str]:
        return {m.strip() for m in response.headers["allow"].split(",")}

    options = await client.options(path)
    assert options.status_code == 204, options.text
    assert methods(options) == allowed | {"OPTIONS"}
    assert options.content == b""
    refused = await client.put(path)
    assert_error(refused, 405, "method_not_allowed")
    assert methods(refused) == allowed | {"OPTIONS"}


# --------------------------------------------------------------------------- size -> 413


def chunks(data: bytes, size: int = 300) -> AsyncIterator[bytes]:
    """``data`` as a streamed body (httpx sends it chunked, without Content-Length)."""

    async def gen() -> AsyncIterator[bytes]:
        for i in range(0, len(data), size):
            yield data[i : i + size]

    return gen()


LIMIT = 1024  # the smallest max_body_bytes the settings allow


@pytest.mark.parametrize("route", sorted(ROUTES))
@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
@pytest.mark.parametrize(("size", "status"), [(LIMIT, 422), (LIMIT + 1, 413), (50 * LIMIT, 413)])
async def test_body_size_limit(route: str, chunked: bool, size: int, status: int) -> None:
    """Up to the limit the body reaches the route (here: 422, it is not JSON); one byte over
    is 413 ``body_too_large``, whether the length is declared or the body is chunked."""
    data = b"x" * size
    async with serve(max_body_bytes=LIMIT) as client:
        response = await client.post(
            ROUTES[route], content=chunks(data) if chunked else data, headers=JSON
        )
    assert ("content-length" in response.request.headers) is not chunked
    assert_error(response, status, "body_too_large" if status == 413 else "invalid_input")


async def test_content_length_not_a_number_is_400(client: httpx.AsyncClient) -> None:
    response = await client.post(
        ROUTES["pair"], content=b"{}", headers={**JSON, "content-length": "two"}
    )
    assert_error(response, 400, "bad_request")


# --------------------------------------------------------------------------- API key

KEY = "s3cret"
#: Every /v1 operation: a request for it and its statuses once the key is right.
V1_OPERATIONS: dict[tuple[str, str], tuple[str, str | None, tuple[int, ...]]] = {
    ("POST", "/v1/verifications"): ("/v1/verifications", "pair", ACCEPTED),
    ("GET", "/v1/verifications/{job_id}"): ("/v1/verifications/nope", None, (404,)),
    ("DELETE", "/v1/verifications/{job_id}"): ("/v1/verifications/nope", None, (404,)),
    ("POST", "/v1/batches"): ("/v1/batches", "batch", (202,)),
    ("GET", "/v1/batches/{batch_id}"): ("/v1/batches/nope", None, (404,)),
    ("GET", "/v1/limits"): ("/v1/limits", None, (200,)),
    ("POST", "/v1/pairs"): ("/v1/pairs", "pairs", (200,)),
}


@pytest.fixture
async def keyed() -> AsyncIterator[httpx.AsyncClient]:
    async with serve(api_key=KEY) as c:
        yield c


def test_every_v1_operation_is_in_the_key_table() -> None:
    """A new /v1 route must join :data:`V1_OPERATIONS` (and so the 401 tests)."""
    paths = create_app(Settings()).openapi()["paths"]
    documented = {
        (method.upper(), path)
        for path, ops in paths.items()
        if path.startswith("/v1/")
        for method in ops
    }
    assert documented == set(V1_OPERATIONS)


@pytest.mark.parametrize("operation", list(V1_OPERATIONS), ids=" ".join)
@pytest.mark.parametrize("key", [None, "", "wrong", KEY.upper(), KEY + " "])
async def test_v1_without_the_right_key_is_401(
    keyed: httpx.AsyncClient,
    bodies: dict[str, dict[str, Any]],
    operation: tuple[str, str],
    key: str | None,
) -> None:
    url, body, _ = V1_OPERATIONS[operation]
    headers = {**JSON, **({} if key is None else {"X-API-Key": key})}
    content = None if body is None else json.dumps(bodies[body])
    response = await keyed.request(operation[0], url, content=content, headers=headers)
    assert_error(response, 401, "unauthorized")
    assert response.headers["www-authenticate"] == "X-API-Key"


@pytest.mark.parametrize("operation", list(V1_OPERATIONS), ids=" ".join)
async def test_v1_with_the_right_key_works(
    keyed: httpx.AsyncClient, bodies: dict[str, dict[str, Any]], operation: tuple[str, str]
) -> None:
    url, body, statuses = V1_OPERATIONS[operation]
    content = None if body is None else json.dumps(bodies[body])
    response = await keyed.request(
        operation[0], url, content=content, headers={**JSON, "X-API-Key": KEY}
    )
    assert response.status_code in statuses, response.text


async def test_401_comes_before_body_validation(keyed: httpx.AsyncClient) -> None:
    """Without the key a bad body is still 401: nothing about the input is revealed."""
    assert_error(await keyed.post(ROUTES["pair"], content=b"garbage"), 401, "unauthorized")


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/metrics"])
async def test_probes_are_open(keyed: httpx.AsyncClient, path: str) -> None:
    assert (await keyed.get(path)).status_code == 200


# --------------------------------------------------------------------------- CORS

ALLOWED = "https://app.example"


def preflight(origin: str) -> dict[str, str]:
    return {
        "Origin": origin,
        "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "content-type,x-api-key",
    }


def cors_settings(configured: bool) -> dict[str, Any]:
    return {"cors_origins": [ALLOWED]} if configured else {}


@pytest.mark.parametrize(
    ("configured", "origin", "allowed"),
    [
        (False, ALLOWED, False),
        (True, ALLOWED, True),
        (True, "https://evil.example", False),
        (True, "http://app.example", False),
    ],
    ids=["default", "configured-origin", "other-origin", "other-scheme"],
)
@pytest.mark.parametrize(
    ("method", "path", "headers"),
    [
        ("OPTIONS", "/v1/verifications", preflight),
        ("GET", "/healthz", lambda origin: {"Origin": origin}),
        ("GET", "/v1/verifications/nope", lambda origin: {"Origin": origin}),
    ],
    ids=["preflight", "simple-get", "error-response"],
)
async def test_cors(
    configured: bool,
    origin: str,
    allowed: bool,
    method: str,
    path: str,
    headers: Any,
) -> None:
    """Access-Control-Allow-Origin only with ``cors_origins`` set, and only for those."""
    async with serve(**cors_settings(configured)) as client:
        response = await client.request(method, path, headers=headers(origin))
    if allowed:
        assert response.headers.get("access-control-allow-origin") == origin
        assert response.status_code < 500
    else:
        assert "access-control-allow-origin" not in response.headers


async def test_413_is_readable_cross_origin() -> None:
    async with serve(cors_origins=[ALLOWED], max_body_bytes=LIMIT) as client:
        response = await client.post(
            ROUTES["pair"], content=b"x" * (LIMIT + 1), headers={"Origin": ALLOWED}
        )
    assert_error(response, 413, "body_too_large")
    assert response.headers.get("access-control-allow-origin") == ALLOWED


# --------------------------------------------------------------------------- 500


async def test_unexpected_error_is_a_bare_500() -> None:
    """An exception nobody mapped: 500 ``internal_error``, nothing of the exception sent."""
    app = create_app(Settings())

    async def boom() -> None:
        raise RuntimeError("secret detail in /work/main/service/x.py")

    app.add_api_route("/boom", boom)
    transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
    async with httpx.AsyncClient(transport=transport, base_url="http://hmcc.test") as client:
        response = await client.get("/boom")
    await app.state.queue.close()
    payload = assert_error(response, 500, "internal_error")
    assert "secret" not in response.text and "issues" not in payload["error"]


def test_leak_markers_catch_a_traceback() -> None:
    """The leak check itself: a message with a file path fails it."""
    response = httpx.Response(
        422, json={"error": {"code": "invalid_input", "message": 'File "/work/x.py"'}}
    )
    with pytest.raises(AssertionError, match="leaked"):
        assert_error(response, 422)
