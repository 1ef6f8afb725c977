"""``hmcc loadtest`` through the real command line parser: loopback only, bounds, a tiny run
against a real ``hmcc serve`` (embedded queue), and the exit code when requests fail."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from hmcc_cli import main as hmcc_main
from hmcc_service.loadtest import is_loopback_url, percentile
from tests.support.procs import free_port, running, service_env, start_api


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    api, url = start_api(service_env())
    with running(api):
        yield url


@pytest.mark.parametrize(
    "url",
    [
        "http://example.com:8000",
        "http://10.0.0.1:8000",
        "http://192.168.1.5",
        "http://127.0.0.1.nip.io:8000",
        "http://localhost.example.com",
        "http://[2001:db8::1]:8000",
        "ftp://127.0.0.1",
        "127.0.0.1:8000",
        "http://127.0.0.1:99999",
    ],
)
def test_refuses_non_loopback_urls(url: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert hmcc_main(["loadtest", "--url", url, "--count", "1"]) == 2
    err = capsys.readouterr().err
    assert "error: --url" in err and "127.0.0.0/8" in err


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:8000",
        "http://127.3.4.5",
        "http://localhost:1",
        "https://LOCALHOST/",
        "http://[::1]:8000",
        "http://[::ffff:127.0.0.1]:80",
    ],
)
def test_loopback_urls_are_accepted(url: str) -> None:
    assert is_loopback_url(url)


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--concurrency", "0"], "--concurrency"),
        (["--concurrency", "65"], "--concurrency"),
        (["--count", "0"], "--count"),
        (["--count", "100001"], "--count"),
        (["--duration", "601"], "--duration"),
        (["--duration", "0"], "--duration"),
        (["--outlier-ratio", "1"], "--outlier-ratio"),
        (["--method", "nope"], "--method"),
    ],
)
def test_bounds(flags: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens: bounds are checked first
    assert hmcc_main(["loadtest", "--url", url, *flags]) == 2
    assert f"error: {message}" in capsys.readouterr().err


@pytest.mark.procs
def test_tiny_run_prints_figures(server: str, capsys: pytest.CaptureFixture[str]) -> None:
    code = hmcc_main(
        [
            "loadtest",
            "--url",
            server,
            "--count",
            "10",
            "--concurrency",
            "2",
            "--matches",
            "300",
            "--pairs",
            "2",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "requests      10 in" in out
    assert "pairs/s" in out
    for label in ("p50", "p95", "p99", "overhead ms"):
        assert label in out
    assert "finished 10  failed 0  unfinished 0  HTTP errors: none" in out


@pytest.mark.procs
def test_tiny_run_json(server: str, capsys: pytest.CaptureFixture[str]) -> None:
    code = hmcc_main(
        [
            "loadtest",
            "--url",
            server,
            "--count",
            "10",
            "--concurrency",
            "3",
            "--matches",
            "200",
            "--json",
        ]
    )
    doc = json.loads(capsys.readouterr().out)
    assert code == 0
    assert doc["requests"] == doc["finished"] == 10
    assert doc["errors"] == 0 and doc["http_errors"] == {}
    assert doc["throughput_pairs_s"] > 0
    lat = doc["latency_ms"]
    assert 0 < lat["p50"] <= lat["p95"] <= lat["p99"] <= lat["max"]
    assert doc["overhead_ms"]["p50"] < lat["p50"]
    assert doc["compute_ms"]["p50"] > 0


@pytest.mark.procs
def test_duration_stops_before_count(server: str, capsys: pytest.CaptureFixture[str]) -> None:
    code = hmcc_main(
        [
            "loadtest",
            "--url",
            server,
            "--count",
            "100000",
            "--duration",
            "0.3",
            "--concurrency",
            "1",
            "--matches",
            "100",
            "--json",
        ]
    )
    doc = json.loads(capsys.readouterr().out)
    assert code == 0
    assert 1 <= doc["requests"] < 1000 and doc["elapsed_s"] < 5


@pytest.mark.procs
def test_http_errors_are_counted_and_exit_1(
    server: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # A method the service does not know is refused with 422 by every request (the local
    # check is bypassed to get there).
    import hmcc_service.loadtest as lt

    monkeypatch.setattr(lt, "_check_args", lambda args: [])
    code = hmcc_main(
        [
            "loadtest",
            "--url",
            server,
            "--count",
            "4",
            "--matches",
            "50",
            "--method",
            "no-such-method",
            "--json",
        ]
    )
    doc = json.loads(capsys.readouterr().out)
    assert code == 1
    assert doc["http_errors"] == {"422": 4} and doc["finished"] == 0 and doc["errors"] == 4


def test_unreachable_service_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    assert hmcc_main(["loadtest", "--url", url, "--count", "2", "--matches", "50"]) == 1
    assert "does not answer /healthz" in capsys.readouterr().err


def test_percentile() -> None:
    assert percentile([], 50) is None
    assert percentile([5.0], 99) == 5.0
    assert percentile([1.0, 2.0, 3.0, 4.0], 50) == 2.5
    assert percentile([4.0, 1.0, 3.0, 2.0], 100) == 4.0
