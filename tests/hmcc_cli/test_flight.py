"""``hmcc flight``: a flight file verified here, one JSON line per pair; bad files exit 2."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from hmcc_cli import main
from hmcc_schema import parse_batch
from hmcc_schema.flight_columns import encode_flight_columns
from hmcc_schema.flight_file import encode_flight
from tests.support.flights import small_flight
from tests.support.procs import free_port, running, service_env, start_api

pytestmark = pytest.mark.procs  # the command starts its child processes


def _flight_file(tmp_path: Path, n: int, nowhere: int | None = None) -> tuple[dict[str, Any], Path]:
    """A flight of ``n`` pairs without its truth, written to a file; pair ``nowhere`` (if any)
    names an image the flight does not have."""
    flight = small_flight(n)
    flight.pop("truth")
    if nowhere is not None:
        flight["pairs"][nowhere]["image2"] = "nowhere"
    path = tmp_path / "flight.json"
    path.write_text(json.dumps(flight))
    return flight, path


def test_a_flight_is_verified_here_one_line_per_pair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flight, path = _flight_file(tmp_path, 5)
    out = tmp_path / "out.jsonl"
    assert main(["flight", str(path), "--processes", "2", "-o", str(out)]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted(line["index"] for line in lines) == list(range(5))
    local = parse_batch(flight, max_pairs=10)
    for line in lines:
        assert line["status"] == "finished" and line["id"] == f"p{line['index']}"
        assert line["result"]["inliers"] == local.verify(line["index"]).inliers.tolist()
    assert "5 pairs in" in capsys.readouterr().err


def test_a_bad_flight_exits_two_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, path = _flight_file(tmp_path, 2, nowhere=1)
    assert main(["flight", str(path), "--processes", "1"]) == 2
    assert "error: pairs[1].image2: no image 'nowhere' in images" in capsys.readouterr().err


def test_the_garbage_collector_is_paused_while_the_document_for_a_service_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # --url: the document is kept whole to the end, as a parsed flight is (an unreachable
    # service: the document is read all the same)
    import gc

    import hmcc_cli.flight as command

    _, path = _flight_file(tmp_path, 3)
    seen = []
    document = command._document

    def read(raw: bytes) -> Any:
        seen.append(gc.isenabled())
        return document(raw)

    monkeypatch.setattr(command, "_document", read)
    try:
        assert main(["flight", str(path), "--url", f"http://127.0.0.1:{free_port()}"]) == 1
        assert seen == [False]
        assert gc.isenabled() and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
        gc.enable()


def test_through_a_service_a_refused_flight_exits_two_naming_the_flights_pair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, path = _flight_file(tmp_path, 3, nowhere=2)
    api, url = start_api(service_env())
    with running(api):
        assert main(["flight", str(path), "--url", url]) == 2
    err = capsys.readouterr().err
    assert f"error: {url} answered 422 invalid_input" in err, err
    assert "error: pairs[2].image2: no image 'nowhere' in images" in err, err
    assert "Traceback" not in err


def test_an_unreachable_service_exits_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, path = _flight_file(tmp_path, 1)
    url = f"http://127.0.0.1:{free_port()}"
    assert main(["flight", str(path), "--url", url]) == 1
    assert f"error: {url}:" in capsys.readouterr().err


def test_a_binary_flight_file_through_the_pool_gives_the_json_files_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flight, path = _flight_file(tmp_path, 4)
    binary = tmp_path / "flight.msgpack"
    assert main(["convert-flight", str(path), str(binary)]) == 0
    assert binary.read_bytes()[:1] != b"{"
    out_json, out_bin = tmp_path / "json.jsonl", tmp_path / "bin.jsonl"
    pool = ["--processes", "2", "--in-process-max", "0"]
    assert main(["flight", str(path), *pool, "-o", str(out_json)]) == 0
    assert main(["flight", str(binary), *pool, "-o", str(out_bin)]) == 0
    by_index = [_untimed(out) for out in (out_json, out_bin)]
    assert by_index[0] == by_index[1] and len(by_index[0]) == 4
    local = parse_batch(flight, max_pairs=10)
    for line in by_index[1]:
        assert line["status"] == "finished" and line["id"] == f"p{line['index']}"
        assert line["result"]["inliers"] == local.verify(line["index"]).inliers.tolist()
    assert "s in child processes" in capsys.readouterr().err


def _retyped(m: dict[str, Any]) -> None:
    m.update(dtype="<i2", data=np.frombuffer(m["data"], m["dtype"]).astype("<i2").tobytes())


def _three_columns(m: dict[str, Any]) -> None:
    rows = len(m["data"]) // 12
    m.update(shape=[rows, 3], data=m["data"][: rows * 12])


def _beyond_the_image(m: dict[str, Any]) -> None:
    matches = np.frombuffer(m["data"], m["dtype"]).reshape(m["shape"]).copy()
    matches[7, 1] = 150_000  # below MAX_KEYPOINTS, beyond the image's keypoints
    m["data"] = matches.tobytes()


@pytest.mark.parametrize(
    ("change", "error"),
    [
        (_retyped, "error: pairs[1].matches: Input should be a valid list"),
        (_three_columns, "error: pairs[1].matches[0]: List should have at most 2 items"),
        (_beyond_the_image, "error: pairs[1].matches: matches[7][1] = 150000 is out of range"),
        (None, "error: body: Input should be a valid dictionary"),  # the file cut short
    ],
)
def test_a_bad_binary_flight_exits_two_naming_the_field_before_any_pair_is_verified(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    change: Callable[[dict[str, Any]], None] | None,
    error: str,
) -> None:
    """Read in place for the children (:class:`~hmcc_schema.flight_file.MappedFlightFile`),
    a bad file is refused as the whole file's parse refuses it, no pair verified."""
    flight, _ = _flight_file(tmp_path, 3)
    data = encode_flight(flight.pop("images"), flight.pop("pairs"), **flight)
    if change is None:
        data = data[:-100]
    else:
        doc = msgpack.unpackb(data)
        change(doc["pairs"][1]["matches"])
        data = msgpack.packb(doc)
    path, out = tmp_path / "bad.msgpack", tmp_path / "out.jsonl"
    path.write_bytes(data)
    pool = ["--processes", "2", "--in-process-max", "0"]
    assert main(["flight", str(path), *pool, "-o", str(out)]) == 2
    assert error in capsys.readouterr().err
    assert out.read_bytes() == b""


def test_a_small_flight_in_process_gives_the_pools_outcomes(tmp_path: Path) -> None:
    _, path = _flight_file(tmp_path, 3, nowhere=None)
    outs = []
    for limit in ("0", "100"):
        out = tmp_path / f"out-{limit}.jsonl"
        args = ["flight", str(path), "--processes", "2", "--in-process-max", limit]
        assert main([*args, "--result", "inliers", "-o", str(out)]) == 0
        outs.append(_untimed(out))
    assert outs[0] == outs[1] and len(outs[0]) == 3


def test_no_processes_verifies_in_this_process_whatever_the_flights_size(tmp_path: Path) -> None:
    """``--processes 0``: in this process, also above ``--in-process-max`` (it divided by the
    children's number)."""
    _, path = _flight_file(tmp_path, 3)
    out = tmp_path / "out.jsonl"
    args = ["flight", str(path), "--processes", "0", "--in-process-max", "0", "-o", str(out)]
    assert main(args) == 0
    assert [line["status"] for line in _untimed(out)] == ["finished"] * 3


def _untimed(out: Path) -> list[Any]:
    """The lines of ``out`` in pair order, without the times (they differ run to run)."""

    def strip(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items() if not k.startswith("tim")}
        if isinstance(value, list):
            return [strip(v) for v in value]
        return value

    lines = [json.loads(line) for line in out.read_text().splitlines()]
    return [strip(line) for line in sorted(lines, key=lambda line: line["index"])]


@pytest.mark.parametrize("nowhere", [None, 1])
def test_the_garbage_collector_is_paused_while_the_flight_is_parsed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, nowhere: int | None
) -> None:
    # the parse makes objects a pair that live until the end: no collection goes through them
    # again and again; they are frozen after it, and the collector runs again (a bad flight too)
    import gc

    import hmcc_cli.flight as command

    _, path = _flight_file(tmp_path, 3, nowhere=nowhere)
    seen = []

    def parse(*args: Any, **kwargs: Any) -> Any:
        seen.append(gc.isenabled())
        return parse_batch(*args, **kwargs)

    monkeypatch.setattr(command, "parse_batch", parse)
    try:
        code = main(["flight", str(path), "--processes", "0", "-o", str(tmp_path / "out.jsonl")])
        assert code == (0 if nowhere is None else 2)
        assert seen == [False]
        assert gc.isenabled() and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
        gc.enable()


@pytest.mark.parametrize("limit", ["0", "100"])  # on the children, and here
def test_a_flight_file_of_columns_gives_the_json_files_lines(tmp_path: Path, limit: str) -> None:
    _, path = _flight_file(tmp_path, 4)
    columns = tmp_path / "columns.msgpack"
    assert main(["convert-flight", "--columns", str(path), str(columns)]) == 0
    assert isinstance(msgpack.unpackb(columns.read_bytes())["pairs"], dict)
    out_json, out_columns = tmp_path / "json.jsonl", tmp_path / "columns.jsonl"
    pool = ["--processes", "2", "--in-process-max", limit]
    assert main(["flight", str(path), *pool, "-o", str(out_json)]) == 0
    assert main(["flight", str(columns), *pool, "-o", str(out_columns)]) == 0
    lines = [_untimed(out) for out in (out_json, out_columns)]
    assert lines[0] == lines[1] and len(lines[0]) == 4
    # and back: the columns as a JSON flight of rows
    back = tmp_path / "back.json"
    assert main(["convert-flight", str(columns), str(back)]) == 0
    assert [p["id"] for p in json.loads(back.read_text())["pairs"]] == ["p0", "p1", "p2", "p3"]


def test_a_bad_flight_file_of_columns_exits_two_before_any_pair_is_verified(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flight, _ = _flight_file(tmp_path, 3, nowhere=1)
    path, out = tmp_path / "bad.msgpack", tmp_path / "out.jsonl"
    path.write_bytes(encode_flight_columns(flight.pop("images"), flight.pop("pairs"), **flight))
    pool = ["--processes", "2", "--in-process-max", "0"]
    assert main(["flight", str(path), *pool, "-o", str(out)]) == 2
    assert "error: pairs[1].image2: no image 'nowhere' in images" in capsys.readouterr().err
    assert out.read_bytes() == b""
    doc = msgpack.unpackb(path.read_bytes())
    doc["pairs"]["counts"]["data"] = doc["pairs"]["counts"]["data"][:-8]
    path.write_bytes(msgpack.packb(doc))
    assert main(["flight", str(path), *pool, "-o", str(out)]) == 2
    assert "error: pairs.counts: its data does not hold its shape" in capsys.readouterr().err


def test_a_flight_whose_pairs_bring_keypoints_is_not_written_as_columns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flight, path = _flight_file(tmp_path, 2)
    flight["pairs"][1]["keypoints1"] = flight["images"]["a1"].pop("keypoints")
    path.write_text(json.dumps(flight))
    assert main(["convert-flight", "--columns", str(path), str(tmp_path / "c.msgpack")]) == 2
    assert "error: --columns: pairs[1] has ['keypoints1', 'matches']" in capsys.readouterr().err


def test_a_flight_file_of_columns_through_a_service_gives_the_lines_of_this_process(
    tmp_path: Path,
) -> None:
    flight, path = _flight_file(tmp_path, 3)
    columns = tmp_path / "columns.msgpack"
    assert main(["convert-flight", "--columns", str(path), str(columns)]) == 0
    here, there = tmp_path / "here.jsonl", tmp_path / "there.jsonl"
    assert main(["flight", str(columns), "--processes", "0", "-o", str(here)]) == 0
    api, url = start_api(service_env())
    with running(api):
        assert main(["flight", str(columns), "--url", url, "-o", str(there)]) == 0
    by_index = {line["index"]: line for line in _untimed(there)}
    for line in _untimed(here):
        assert by_index[line["index"]]["result"]["inliers"] == line["result"]["inliers"]


def test_a_flight_of_columns_reads_from_standard_input(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import io
    import types

    flight, _ = _flight_file(tmp_path, 3)
    data = encode_flight_columns(flight.pop("images"), flight.pop("pairs"), **flight)
    out = tmp_path / "out.jsonl"
    for limit in ("0", "100"):  # on the children (the columns written to the shared file), here
        stdin = types.SimpleNamespace(buffer=io.BytesIO(data))
        monkeypatch.setattr("sys.stdin", stdin)
        args = ["flight", "-", "--processes", "2", "--in-process-max", limit, "-o", str(out)]
        assert main(args) == 0
        assert [line["id"] for line in _untimed(out)] == ["p0", "p1", "p2"]
