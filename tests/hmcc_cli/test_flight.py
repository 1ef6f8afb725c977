"""``hmcc flight``: a flight file verified here, one JSON line per pair; bad files exit 2."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from hmcc_cli import main
from hmcc_schema import parse_batch
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
