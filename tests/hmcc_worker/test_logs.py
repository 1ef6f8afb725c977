"""Structured logs: one JSON object per line on stderr, with the job id (given, or the RQ job
being run), the known extra fields, and the traceback of errors."""

from __future__ import annotations

import json
import logging
import sys
import types
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from hmcc_worker.logs import configure_logging

ROUTED = ("rq.worker", "uvicorn", "uvicorn.error")


@contextmanager
def _configured(level: str = "INFO") -> Iterator[logging.Formatter]:
    """``configure_logging(level)`` for the block, then the loggers as they were; yields the
    JSON formatter it installed."""
    root = logging.getLogger()
    saved_root = (root.handlers[:], root.level)
    saved = {
        name: (logging.getLogger(name).handlers[:], logging.getLogger(name).propagate)
        for name in ROUTED
    }
    try:
        configure_logging(level)
        formatter = root.handlers[0].formatter
        assert formatter is not None
        yield formatter
    finally:
        root.handlers[:], level_before = saved_root
        root.setLevel(level_before)
        for name, (handlers, propagate) in saved.items():
            logging.getLogger(name).handlers[:] = handlers
            logging.getLogger(name).propagate = propagate


@pytest.fixture
def no_rq(monkeypatch: pytest.MonkeyPatch) -> None:
    """No RQ job is running (RQ not even imported)."""
    monkeypatch.delitem(sys.modules, "rq", raising=False)


def _lines(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line]


def _record(**fields: Any) -> logging.LogRecord:
    base: dict[str, Any] = {
        "name": "hmcc.test",
        "levelno": logging.INFO,
        "levelname": "INFO",
        "msg": "verified %d pairs",
        "args": (3,),
    }
    return logging.makeLogRecord({**base, **fields})


def test_every_logger_goes_through_one_json_handler_on_stderr() -> None:
    uvicorn = logging.getLogger("uvicorn")
    uvicorn.addHandler(logging.NullHandler())
    uvicorn.propagate = False
    try:
        with _configured("debug"):
            root = logging.getLogger()
            assert len(root.handlers) == 1
            (handler,) = root.handlers
            assert isinstance(handler, logging.StreamHandler)
            assert handler.stream is sys.stderr
            assert root.level == logging.DEBUG  # the level's name in any case
            for name in ROUTED:
                assert logging.getLogger(name).handlers == []
                assert logging.getLogger(name).propagate
    finally:
        uvicorn.handlers[:] = []
        uvicorn.propagate = True


@pytest.mark.usefixtures("no_rq")
def test_a_log_line_is_one_json_object_with_the_basic_fields(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with _configured("INFO"):
        logging.getLogger("hmcc.test").info("verified %d pairs", 3)
        logging.getLogger("hmcc.test").debug("below the level")
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    (doc,) = _lines(err)
    assert set(doc) == {"ts", "level", "logger", "message"}  # no job: no job_id
    assert doc["level"] == "INFO"
    assert doc["logger"] == "hmcc.test"
    assert doc["message"] == "verified 3 pairs"


@pytest.mark.usefixtures("no_rq")
def test_the_timestamp_is_utc_iso_8601_with_milliseconds() -> None:
    with _configured() as formatter:
        record = _record(created=1700000000.0, msecs=7.9)
        doc = json.loads(formatter.format(record))
    assert doc["ts"] == "2023-11-14T22:13:20.007Z"


@pytest.mark.usefixtures("no_rq")
def test_the_job_id_given_as_extra_is_logged(capsys: pytest.CaptureFixture[str]) -> None:
    with _configured():
        logging.getLogger("hmcc.test").info("done", extra={"job_id": "job-42"})
    (doc,) = _lines(capsys.readouterr().err)
    assert doc["job_id"] == "job-42"


def test_the_job_id_of_the_running_rq_job_is_logged(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    rq = types.ModuleType("rq")
    rq.get_current_job = lambda: types.SimpleNamespace(id="rq-7")  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "rq", rq)
    with _configured():
        log = logging.getLogger("hmcc.test")
        log.info("inside a job")
        log.info("an id given wins", extra={"job_id": "job-42"})
    first, second = _lines(capsys.readouterr().err)
    assert first["job_id"] == "rq-7"
    assert second["job_id"] == "job-42"


def test_no_job_id_outside_an_rq_job(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    rq = types.ModuleType("rq")
    rq.get_current_job = lambda: None  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "rq", rq)
    with _configured():
        logging.getLogger("hmcc.test").info("between jobs")
    (doc,) = _lines(capsys.readouterr().err)
    assert "job_id" not in doc


@pytest.mark.usefixtures("no_rq")
def test_the_known_extra_fields_are_logged_and_others_not(
    capsys: pytest.CaptureFixture[str],
) -> None:
    extra = {
        "event": "request",
        "status": "finished",
        "duration_ms": 12.5,
        "path": "/v1/verifications",
        "method": "POST",
        "status_code": 201,
        "secret_input": "not logged",
    }
    with _configured():
        logging.getLogger("hmcc.test").info("answered", extra=extra)
        logging.getLogger("hmcc.test").info("none", extra={"event": None, "status_code": 0})
    doc, sparse = _lines(capsys.readouterr().err)
    extra.pop("secret_input")
    assert {k: doc[k] for k in extra} == extra
    assert "secret_input" not in doc
    assert "event" not in sparse  # None is left out, falsy values are kept
    assert sparse["status_code"] == 0


@pytest.mark.usefixtures("no_rq")
def test_errors_carry_their_traceback_and_lesser_levels_do_not(
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = logging.getLogger("hmcc.test")
    with _configured():
        try:
            raise RuntimeError("the core broke")
        except RuntimeError:
            log.exception("pair failed")
            log.warning("retrying", exc_info=True)
    error, warning = _lines(capsys.readouterr().err)
    assert error["level"] == "ERROR"
    assert error["message"] == "pair failed"
    assert error["exception"].startswith("Traceback (most recent call last)")
    assert "RuntimeError: the core broke" in error["exception"]
    assert warning["level"] == "WARNING"
    assert "exception" not in warning
