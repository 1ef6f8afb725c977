"""The JSON pair format: every bad input names its field; equivalent pose forms agree."""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from hmcc.errors import InputError
from hmcc_schema import (
    PairRequest,
    parse_batch,
    parse_pair,
    reference_to_pair,
    validation_issues,
)
from hmcc_schema import parse as parse_module
from hmcc_schema.parse import JSON, MSGPACK
from tests.support.shared_data import BRIGHTON

FIXTURE = BRIGHTON / "pair_DJI_0030_DJI_0031.json"


def raw_fixture() -> dict[str, Any]:
    return json.loads(FIXTURE.read_text())


def fixture_pair() -> dict[str, Any]:
    return reference_to_pair(raw_fixture())


def issues_of(body: dict[str, Any]) -> list[tuple[str, str]]:
    try:
        parse_pair(body).verify(0)
    except (ValidationError, InputError) as e:
        return [(i.field, i.reason) for i in validation_issues(e)]
    raise AssertionError("accepted")


def edit(path: str, value: Any) -> dict[str, Any]:
    """A copy of the fixture pair with the dotted ``path`` set to ``value``."""
    body = copy.deepcopy(fixture_pair())
    node = body
    keys = path.split(".")
    for key in keys[:-1]:
        node = node[int(key)] if isinstance(node, list) else node[key]
    last = keys[-1]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return body


@pytest.mark.parametrize(
    ("path", "value", "field", "reason"),
    [
        ("matches.3", [0, 10_000], "matches", "matches[3][1] = 10000 is out of range"),
        ("matches.0", [-1, 0], "matches[0][0]", "greater than or equal to 0"),
        ("matches.0", [1, 2, 3], "matches[0]", "at most 2"),
        ("matches", [], "matches", "at least 1"),
        ("keypoints1.0", [math.nan, 1.0, 2.0, 3.0], "keypoints1[0][0]", "finite"),
        ("keypoints2.1", [1.0, math.inf, 2.0, 3.0], "keypoints2[1][1]", "finite"),
        ("keypoints1.0", [1.0, 2.0], "keypoints1", "every keypoint"),
        ("keypoints1.0", ["a", 2.0], "keypoints1[0][0]", "valid number"),
        ("method", "magic", "method", "unknown method"),
        ("image1.camera.width", 0, "image1.camera.width", "greater than 0"),
        ("image1.camera.fx", -5.0, "image1.camera.fx", "greater than 0"),
        ("image2.pose.position.x", "far", "image2.pose.position.x", "valid number"),
        (
            "image1.pose.attitude.matrix",
            [[1, 0, 0], [0, 1, 0], [0, 0, 2]],
            "image1.pose.attitude.matrix",
            "not a rotation",
        ),
        (
            "image1.pose.attitude.matrix",
            [[1, 0, 0], [0, 1, 0], [0, 0, -1]],
            "image1.pose.attitude.matrix",
            "not a rotation",
        ),
        ("image1.pose.attitude", {"yaw": 1, "pitch": 2}, "image1.pose.attitude.roll", "required"),
        ("plane.z", "sea level", "plane.z", "valid number"),
        ("plane.z", math.nan, "plane.z", "finite"),
        ("params", {"direction": {"bin_deg": 7}}, "params.direction", "bin_deg"),
        ("params", {"ransac": {"estimator": "gpu"}}, "params.ransac.estimator", "'magsac++'"),
        ("params", {"seed": 1, "bogus": 2}, "params.bogus", "Unexpected"),
        ("surprise", 1, "surprise", "Extra inputs"),
        (
            "image2.camera.distortion",
            [0.0, 0.0, 1e300, 1e300],
            "image2.camera.distortion",
            "do not undistort to finite values",
        ),
        (
            "keypoints2.0",
            [4001.0, 2.0, 2.0, 3.0],
            "keypoints2",
            "keypoint 0 at (4001, 2) lies outside the 2000 x 1125 px frame of image2",
        ),
    ],
)
def test_bad_input_names_the_field_and_the_reason(path, value, field, reason) -> None:
    issues = issues_of(edit(path, value))
    assert any(f == field and reason in r for f, r in issues), issues


def test_the_core_checks_name_their_fields_too() -> None:
    few = fixture_pair()
    few["matches"] = few["matches"][:5]
    assert issues_of(few) == [("matches", "5 matches; a fundamental model needs 8")]
    above = edit("plane", {"z": 1000.0})
    assert issues_of(above)[0][0] == "plane.z"
    mixed = edit("image1.pose.position", {"lat": 46.84, "lon": -91.99, "alt": 200.0})
    assert issues_of(mixed)[0][0] == "image2.pose.position"
    gc_needs_angles = fixture_pair()
    gc_needs_angles["keypoints1"] = [k[:2] for k in gc_needs_angles["keypoints1"]]
    gc_needs_angles["method"] = "gc-ransac"
    assert issues_of(gc_needs_angles)[0][0] == "keypoints1"


def test_mounting_needs_a_platform_attitude() -> None:
    body = edit("image1.pose.mounting", {"pitch": 45})
    assert any("mounting applies" in r for _, r in issues_of(body))


def test_camera_needs_one_focal() -> None:
    body = fixture_pair()
    cam = body["image1"]["camera"]
    del cam["fx"]
    assert any("give fx and fy, or focal" in r for _, r in issues_of(body))
    cam["focal"] = cam["fy"]
    del cam["fy"]
    parse_pair(body).verify(0)


def result_of(body: dict[str, Any]) -> dict[str, Any]:
    return parse_pair(body).verify(0).to_dict()


def test_yaw_pitch_roll_form_gives_the_same_result_as_the_matrix() -> None:
    raw = raw_fixture()
    body = fixture_pair()
    for key in ("image1", "image2"):
        img = raw[key]
        assert img["pixel_rotation_after_capture_deg"] == 0
        body[key]["pose"]["attitude"] = {
            "yaw": img["flight_yaw"],
            "pitch": img["flight_roll"],
            "roll": -img["flight_pitch"],
        }
    assert result_of(body)["inliers"] == result_of(fixture_pair())["inliers"]


def test_geodetic_positions_give_the_same_motions_as_local_ones() -> None:
    raw = raw_fixture()
    body = fixture_pair()
    for key in ("image1", "image2"):
        img = raw[key]
        body[key]["pose"]["position"] = {
            "lat": img["lat"],
            "lon": img["lon"],
            "alt": img["absolute_altitude"],
        }
    geo = parse_pair(body).pair_data(0)
    local = parse_pair(fixture_pair()).pair_data(0)
    # Same frame up to the origin: the baseline between the cameras agrees to a centimetre.
    np.testing.assert_allclose(
        geo.pose2.center - geo.pose1.center, local.pose2.center - local.pose1.center, atol=0.01
    )
    # The frames differ by millimetres (another ENU origin), so the sampled model can differ
    # at rounding level and flip a match that sits on the threshold; no more than that.
    geo_inliers, local_inliers = result_of(body)["inliers"], result_of(fixture_pair())["inliers"]
    assert len(set(geo_inliers) ^ set(local_inliers)) <= 2
    assert len(geo_inliers) > 400


def test_omega_phi_kappa_form_is_accepted() -> None:
    body = fixture_pair()
    for key in ("image1", "image2"):
        body[key]["pose"]["attitude"] = {"omega": 0.0, "phi": 0.0, "kappa": -45.0}
    assert result_of(body)["statistics"]["matches"] == len(body["matches"])


def test_mounting_and_lever_arm_are_accepted_with_yaw_pitch_roll() -> None:
    body = fixture_pair()
    body["image1"]["pose"]["attitude"] = {"yaw": 45.0, "pitch": 0.0, "roll": 0.0}
    body["image1"]["pose"]["mounting"] = {"pitch": 0.0, "lever_arm": [0.1, 0.0, 0.2]}
    assert result_of(body)["statistics"]["matches"] == len(body["matches"])


def test_distortion_is_applied_before_projection() -> None:
    plain = parse_pair(fixture_pair()).pair_data(0)
    body = fixture_pair()
    body["image1"]["camera"]["distortion"] = [-0.1, 0.01, 0.0, 0.0]
    distorted = parse_pair(body).pair_data(0)
    assert distorted.camera1.distortion == (-0.1, 0.01, 0.0, 0.0, 0.0)
    corner = np.array([[0.0, 0.0]])
    assert not np.allclose(distorted.camera1.normalize(corner), plain.camera1.normalize(corner))


def test_ground_truth_is_ignored_and_params_are_echoed_resolved() -> None:
    body = fixture_pair()
    body["params"] = {"seed": 4, "direction": {"window_bins": 4}}
    out = result_of(body)
    assert out["params"]["seed"] == 4
    assert out["params"]["direction"] == {"bin_deg": 10.0, "window_bins": 4, "min_vote_ratio": 0.2}
    assert out["params"]["direction_change"]["k_neighbors"] == 7
    assert out["params"]["ransac"]["threshold_px"] == 1.0


def test_plane_is_z_or_ground_z_not_both() -> None:
    issues = issues_of(edit("plane", {"z": 150.0, "ground_z": 160.0}))
    assert issues == [("plane", "give either z or ground_z, not both")]


def test_ground_z_puts_the_plane_a_third_of_the_flying_height_below_it() -> None:
    out = result_of(fixture_pair())
    proj = out["stages"][0]["stats"]
    raw = raw_fixture()
    height = (raw["image1"]["C_enu"][2] + raw["image2"]["C_enu"][2]) / 2 - raw["Z0"]
    assert proj["z0_source"] == "ground_z" and proj["ground_z_m"] == raw["Z0"]
    assert proj["z0_m"] == pytest.approx(raw["Z0"] - height / 3)


def test_plane_defaults_to_auto() -> None:
    body = fixture_pair()
    del body["plane"]
    out = result_of(body)
    assert out["stages"][0]["stats"]["z0_source"] == "auto"


def test_the_request_schema_documents_the_contract() -> None:
    schema = PairRequest.model_json_schema()
    assert {"image1", "image2", "keypoints1", "keypoints2", "matches"} <= set(schema["required"])
    assert schema["additionalProperties"] is False


# --------------------------------------------------------------------------- encodings


def _flights_equal(a: Any, b: Any) -> None:
    assert (a.method, a.options, a.plane_z, a.ground_z) == (
        b.method,
        b.options,
        b.plane_z,
        b.ground_z,
    )
    for x, y in zip(a.pairs, b.pairs, strict=True):
        for name in ("matches", "keypoints1", "keypoints2"):
            u, v = getattr(x, name), getattr(y, name)
            assert (u is None) == (v is None)
            if u is not None:
                np.testing.assert_array_equal(u, v)


def test_json_messagepack_and_objects_give_the_same_flight() -> None:
    import msgpack

    from hmcc_schema.parse import MSGPACK

    body = fixture_pair()
    from_json = parse_pair(json.dumps(body))
    from_object = parse_pair(body)
    kp1 = np.asarray(body["keypoints1"], dtype="<f8")
    buffers = dict(
        body,
        keypoints1={"dtype": "<f8", "shape": list(kp1.shape), "data": kp1.tobytes()},
        matches={
            "dtype": "<i4",
            "shape": [len(body["matches"]), 2],
            "data": np.asarray(body["matches"], dtype="<i4").tobytes(),
        },
    )
    from_msgpack = parse_pair(msgpack.packb(buffers), MSGPACK)
    for other in (from_object, from_msgpack):
        _flights_equal(from_json, other)
    assert from_msgpack.verify(0).inliers.tolist() == from_json.verify(0).inliers.tolist()


def test_messagepack_buffers_of_the_wrong_size_are_refused_with_the_field() -> None:
    import msgpack

    from hmcc_schema.parse import MSGPACK

    body = fixture_pair()
    body["matches"] = {"dtype": "<i4", "shape": [10, 2], "data": b"\0" * 12}
    with pytest.raises(ValidationError) as e:
        parse_pair(msgpack.packb(body), MSGPACK)
    assert validation_issues(e.value)[0].field == "matches"


def test_rows_that_flatten_to_a_plausible_count_are_still_refused() -> None:
    body = fixture_pair()
    body["keypoints1"][:3] = [[1.0, 2.0, 3.0, 4.0], [5.0, 6.0], [7.0, 8.0, 9.0, 10.0, 11.0, 12.0]]
    assert issues_of(body)[0][0].startswith("keypoints1")


def test_numbers_as_strings_are_read_as_the_model_reads_them() -> None:
    body = fixture_pair()
    strings = copy.deepcopy(body)
    strings["keypoints2"] = [[str(v) for v in row] for row in body["keypoints2"]]
    strings["matches"] = [[float(i), float(j)] for i, j in body["matches"]]  # 3.0 is an index
    _flights_equal(parse_pair(json.dumps(strings)), parse_pair(json.dumps(body)))


@pytest.mark.parametrize("seed", range(40))
def test_what_the_fast_path_accepts_the_model_accepts(seed: int) -> None:
    """Random edits of a valid body: the fast path never accepts what the full pydantic model
    refuses (so its speed cannot widen the contract)."""
    from hmcc_schema.parse import _fast_pair, _load, _pair_arrays

    rng = np.random.default_rng(seed)
    body = fixture_pair()
    values: list[Any] = [True, -1, 0, 1.5, 1e300, "7", None, [], [1.0], [[1.0, 2.0]], {}]
    for _ in range(int(rng.integers(1, 4))):
        target = rng.choice(["keypoints1", "keypoints2", "matches"])
        rows = body[target]
        i = int(rng.integers(len(rows)))
        row = list(rows[i])
        row[int(rng.integers(len(row)))] = values[int(rng.integers(len(values)))]
        rows[i] = row
    text = json.dumps(body)
    doc = _load(text, "application/json", _pair_arrays)
    try:
        fast = _fast_pair(doc)
    except InputError:  # refused by a check across fields (a keypoint outside the frame)
        fast = None
    try:
        PairRequest.model_validate_json(text)
        accepted = True
    except ValidationError:
        accepted = False
    assert fast is None or accepted


def _no_full_model(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: Any) -> Any:
        raise AssertionError("the full model read a body the fast path should have")

    monkeypatch.setattr("hmcc_schema.parse._full", refuse)


def test_a_valid_json_pair_is_read_as_arrays_not_by_the_model(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    body = fixture_pair()
    slow = parse_pair(json.dumps(body))
    _no_full_model(monkeypatch)
    _flights_equal(parse_pair(json.dumps(body)), slow)


def test_a_valid_json_batch_is_read_as_arrays_not_by_the_model(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pair = fixture_pair()
    body = {
        "images": {
            "a": {**pair["image1"], "keypoints": pair["keypoints1"]},
            "b": {**pair["image2"], "keypoints": pair["keypoints2"]},
        },
        "pairs": [{"image1": "a", "image2": "b", "matches": pair["matches"]}] * 2,
    }
    _no_full_model(monkeypatch)
    flight = parse_batch(json.dumps(body), max_pairs=10)
    assert len(flight.pairs) == 2
    assert np.array_equal(flight.images["a"].keypoints, np.asarray(pair["keypoints1"]))


def test_a_key_given_twice_counts_once_as_for_the_model() -> None:
    """The fast path looks keys up (first value); the model keeps the last one."""
    body = fixture_pair()
    text = json.dumps(body)
    twice = text[:-1] + ', "matches": [[0, 100000]]}'
    assert issues_of_text(twice) == issues_of_model(twice)


def issues_of_text(text: str) -> list[tuple[str, str]]:
    try:
        parse_pair(text).verify(0)
    except (ValidationError, InputError) as e:
        return [(i.field, i.reason) for i in validation_issues(e)]
    return []


def issues_of_model(text: str) -> list[tuple[str, str]]:
    try:
        PairRequest.model_validate_json(text)
    except ValidationError as e:
        return [(i.field, i.reason) for i in validation_issues(e)]
    return []


# --------------------------------------------------------------------------- nesting depth


def nested(levels: int) -> Any:
    """``levels`` lists, one inside the other, around a number."""
    value: Any = 1
    for _ in range(levels):
        value = [value]
    return value


def encoded(body: Any, media_type: str) -> bytes:
    import msgpack

    from hmcc_schema.parse import JSON

    if media_type == JSON:
        return json.dumps(body).encode()  # nested() stays below json's own recursion
    return bytes(msgpack.packb(body))


def reasons_of(body: bytes | dict[str, Any], media_type: str) -> list[tuple[str, str]]:
    try:
        parse_pair(body, media_type)
    except (ValidationError, InputError) as e:
        return [(i.field, i.reason) for i in validation_issues(e)]
    return []


@pytest.mark.parametrize("media_type", ["application/json", "application/vnd.hmcc+msgpack"])
def test_json_and_messagepack_refuse_the_same_nesting_depth(media_type: str) -> None:
    """A valid pair whose ``ground_truth`` makes the body exactly MAX_DEPTH deep (the body, the
    ground_truth object, then lists) is read; one level more is refused as too deep, naming
    the body, in either encoding."""
    from hmcc_schema.parse import MAX_DEPTH

    kind = "JSON" if media_type == "application/json" else "MessagePack"
    at_limit = {**fixture_pair(), "ground_truth": {"x": nested(MAX_DEPTH - 2)}}
    assert reasons_of(encoded(at_limit, media_type), media_type) == []
    beyond = {**fixture_pair(), "ground_truth": {"x": nested(MAX_DEPTH - 1)}}
    [(field, reason)] = reasons_of(encoded(beyond, media_type), media_type)
    assert field == "body"
    assert reason.startswith(f"Invalid {kind}: recursion limit exceeded")


@pytest.mark.parametrize("levels", [480, 10_000])
def test_deep_messagepack_is_refused_as_too_deep_not_walked(levels: int) -> None:
    """About 480 levels once overflowed the recursion of the model's fallback (a 500 in the
    service); past the unpacker's own stack (1024) the answer is the same."""
    body = b"\x81\xa6image1" + b"\x91" * levels + b"\x01"  # {"image1": [[...[1]...]]}
    for parse in (parse_pair, lambda b, m: parse_batch(b, 10, m)):
        with pytest.raises(InputError) as e:
            parse(body, "application/vnd.hmcc+msgpack")
        assert e.value.field == "body"
        assert e.value.reason.startswith("Invalid MessagePack: recursion limit exceeded")


def test_a_deep_object_body_is_refused_too() -> None:
    with pytest.raises(InputError, match="recursion limit exceeded"):
        parse_pair({**fixture_pair(), "ground_truth": {"x": nested(300)}})


# --------------------------------------------------------------------------- strict numbers

ENCODINGS = ["application/json", "application/vnd.hmcc+msgpack", "object"]


def parsed_issues(parse: Any, body: dict[str, Any], encoding: str) -> list[tuple[str, str]]:
    import msgpack

    raw: Any = body
    if encoding == "application/json":
        raw = json.dumps(body)
    elif encoding != "object":
        raw = bytes(msgpack.packb(body))
    try:
        parse(raw, encoding if encoding != "object" else "application/json")
    except (ValidationError, InputError) as e:
        return [(i.field, i.reason) for i in validation_issues(e)]
    raise AssertionError("accepted")


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize(
    ("path", "field"),
    [
        ("image1.camera.fx", "image1.camera.fx"),
        ("image1.camera.width", "image1.camera.width"),
        ("image1.camera.cx", "image1.camera.cx"),
        ("image2.pose.position.z", "image2.pose.position.z"),
        ("image1.pose.attitude.matrix.0.0", "image1.pose.attitude.matrix[0][0]"),
        ("plane.ground_z", "plane.ground_z"),
        ("keypoints1.0.0", "keypoints1[0][0]"),
        ("keypoints2.3.1", "keypoints2[3][1]"),
        ("matches.0.0", "matches[0][0]"),
        ("matches.5.1", "matches[5][1]"),
        ("params.seed", "params.seed"),
        ("params.ransac.threshold_px", "params.ransac.threshold_px"),
        ("params.ransac.max_iters", "params.ransac.max_iters"),
        ("params.gc.max_partners", "params.gc.max_partners"),
        ("params.plus.lo_schedule.0", "params.plus.lo_schedule[0]"),
    ],
)
@pytest.mark.parametrize("flag", [True, False])
def test_a_boolean_is_not_a_number_of_a_pair(
    path: str, field: str, flag: bool, encoding: str
) -> None:
    """``"fx": true`` was read as fx = 1 (pydantic's lax mode; numpy for MessagePack rows)."""
    body = fixture_pair()
    body["params"] = {"ransac": {}, "gc": {}, "plus": {"lo_schedule": [2.0, 1.0, 1.0]}}
    node: Any = body
    *parents, last = path.split(".")
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    if isinstance(node, list):
        node[int(last)] = flag
    else:
        node[last] = flag
    issues = parsed_issues(parse_pair, body, encoding)
    assert (field, "Input should be a number, not a boolean") in issues


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize(
    ("edit_batch", "field"),
    [
        (lambda b: b["images"]["a"]["camera"].update(fy=True), "images.a.camera.fy"),
        (
            lambda b: b["images"]["b"]["keypoints"][2].__setitem__(0, True),
            "images.b.keypoints[2][0]",
        ),
        (lambda b: b["pairs"][0]["matches"][1].__setitem__(1, False), "pairs[0].matches[1][1]"),
        (lambda b: b.update(params={"direction": {"bin_deg": True}}), "params.direction.bin_deg"),
    ],
)
def test_a_boolean_is_not_a_number_of_a_batch(edit_batch: Any, field: str, encoding: str) -> None:
    pair = fixture_pair()
    body = {
        "images": {
            "a": {**pair["image1"], "keypoints": pair["keypoints1"]},
            "b": {**pair["image2"], "keypoints": pair["keypoints2"]},
        },
        "pairs": [{"image1": "a", "image2": "b", "matches": pair["matches"]}],
    }
    edit_batch(body)
    issues = parsed_issues(lambda raw, kind: parse_batch(raw, 10, kind), body, encoding)
    assert (field, "Input should be a number, not a boolean") in issues


def test_booleans_still_read_where_the_contract_has_booleans() -> None:
    body = {**fixture_pair(), "params": {"return_motions": True, "plus": {"gate": False}}}
    flight = parse_pair(json.dumps(body))
    assert flight.options.return_motions is True
    assert flight.options.plus.gate is False


def _two_image_batch(n_pairs: int) -> dict[str, Any]:
    pair = fixture_pair()
    return {
        "images": {
            "a": {**pair["image1"], "keypoints": pair["keypoints1"]},
            "b": {**pair["image2"], "keypoints": pair["keypoints2"]},
        },
        "pairs": [
            {"id": f"p{k}", "image1": "a", "image2": "b", "matches": pair["matches"]}
            for k in range(n_pairs)
        ],
    }


def _msgpack_with_buffers(body: dict[str, Any], dtype: str) -> bytes:
    import msgpack

    def buffer(rows: Any, kind: str) -> dict[str, Any]:
        a = np.asarray(rows, dtype=dtype if kind == "matches" else "<f8")
        return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}

    doc = copy.deepcopy(body)
    for image in doc["images"].values():
        image["keypoints"] = buffer(image["keypoints"], "keypoints")
    for pair in doc["pairs"]:
        pair["matches"] = buffer(pair["matches"], "matches")
    return bytes(msgpack.packb(doc))


@pytest.mark.parametrize("views", [False, True])
@pytest.mark.parametrize("dtype", ["<u2", "<i4", "<i8"])
def test_a_batch_index_beyond_its_image_keypoints_names_the_pair_and_the_index(
    dtype: str, views: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pairs' indices are checked all at once (with ``views``, in chunks of a few rows
    here, each pair's rows across several); the error still names the first pair out of
    range, the row and the column, in every encoding and buffer dtype."""
    monkeypatch.setattr(parse_module, "_CHUNK_ROWS", 40)
    body = _two_image_batch(6)
    n = len(body["images"]["b"]["keypoints"])
    for k in (4, 2):  # two bad pairs: the first is named
        body["pairs"][k]["matches"] = [list(m) for m in body["pairs"][k]["matches"]]
        body["pairs"][k]["matches"][7][1] = n
    for raw, media_type in (
        (json.dumps(body), JSON),
        (_msgpack_with_buffers(body, dtype), MSGPACK),
    ):
        with pytest.raises(InputError) as e:
            parse_batch(raw, max_pairs=10, media_type=media_type, views=views)
        assert e.value.field == "pairs[2].matches"
        assert f"matches[7][1] = {n} is out of range: images.b has {n} keypoints" in str(e.value)


@pytest.mark.parametrize("chunk_rows", [1, 7, 40, 10**6])
@pytest.mark.parametrize("pair", [0, 3, 5])
def test_a_negative_index_in_any_chunk_is_named_by_the_model(
    chunk_rows: int, pair: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(parse_module, "_CHUNK_ROWS", chunk_rows)
    body = _two_image_batch(6)
    body["pairs"][pair]["matches"] = [list(m) for m in body["pairs"][pair]["matches"]]
    body["pairs"][pair]["matches"][-1][0] = -1
    with pytest.raises(ValidationError) as e:
        parse_batch(_msgpack_with_buffers(body, "<i4"), 10, MSGPACK, views=True)
    row = len(body["pairs"][pair]["matches"]) - 1
    assert f"pairs[{pair}].matches[{row}][0]" in [i.field for i in validation_issues(e.value)]


def test_the_chunked_check_finds_each_arrays_largest_indices() -> None:
    rng = np.random.default_rng(0)
    arrays = [
        rng.integers(0, 1000, size=(int(n), 2)).astype(dtype)
        for n, dtype in zip(
            rng.integers(1, 300, size=200),
            rng.choice(["<u2", "<u4", "<i4", "<i8"], 200),
            strict=True,
        )
    ]
    expected = np.array([a.max(axis=0) for a in arrays], dtype=np.int64)
    maxima = parse_module._chunked_maxima(arrays)
    assert maxima is not None and maxima.dtype == np.int64
    np.testing.assert_array_equal(maxima, expected)
    # beyond int64 (and any image): made the largest count; with signed ones: the model's
    huge = np.array([[2**63 + 5, 3]], dtype=np.uint64)
    largest = parse_module.MAX_KEYPOINTS
    np.testing.assert_array_equal(parse_module._chunked_maxima([huge]), [[largest, 3]])
    assert parse_module._chunked_maxima([huge, arrays[0].astype(np.int64)]) is None


@pytest.mark.parametrize("dtype", ["<u2", "<i4"])
def test_a_batch_reads_every_pair_its_own_matches(dtype: str) -> None:
    """Pairs of different lengths keep their own matches, as int64, from one conversion."""
    body = _two_image_batch(5)
    for k, pair in enumerate(body["pairs"]):
        pair["matches"] = pair["matches"][: 10 + 7 * k]
    flight = parse_batch(_msgpack_with_buffers(body, dtype), max_pairs=10, media_type=MSGPACK)
    for pair, given in zip(flight.pairs, body["pairs"], strict=True):
        assert pair.matches.dtype == np.int64
        np.testing.assert_array_equal(pair.matches, np.asarray(given["matches"]))


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda p: p.update(image1=5), "pairs[1].image1"),
        (lambda p: p.update(id="x" * 201), "pairs[1].id"),
        (lambda p: p.update(image2=""), "pairs[1].image2"),
        (lambda p: p.update(match=None), "pairs[1].match"),
        (lambda p: p.update(extra=1), "pairs[1].extra"),
    ],
)
def test_a_pair_field_the_fast_check_does_not_take_is_named_by_the_model(
    edit: Any, field: str
) -> None:
    body = _two_image_batch(3)
    edit(body["pairs"][1])
    with pytest.raises(ValidationError) as e:
        parse_batch(_msgpack_with_buffers(body, "<u2"), max_pairs=10, media_type=MSGPACK)
    assert field in [i.field for i in validation_issues(e.value)]
