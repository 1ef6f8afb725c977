"""The RQ job and its callbacks: what they refuse, how they classify failures."""

from __future__ import annotations

import importlib

import pytest

from hmcc_worker import jobs, rq_compat
from hmcc_worker.protocol import JOB_FUNCTION, ON_FAILURE, ON_SUCCESS


def test_the_allow_list_names_importable_functions() -> None:
    assert set(jobs.JOB_FUNCTIONS) == {JOB_FUNCTION, ON_FAILURE, ON_SUCCESS}
    for name, func in jobs.JOB_FUNCTIONS.items():
        module, _, attr = name.rpartition(".")
        assert getattr(importlib.import_module(module), attr) is func


def test_the_job_refuses_to_run_outside_a_worker() -> None:
    with pytest.raises(RuntimeError, match="outside an RQ worker"):
        jobs.verify_job()


@pytest.mark.parametrize(
    ("exc_type", "code"),
    [
        (jobs.PayloadExpired, "payload_expired"),
        (rq_compat.AbandonedJobError, "worker_lost"),
        (rq_compat.JobTimeoutException, "timeout"),
        (ValueError, "internal_error"),
        (None, "internal_error"),
    ],
)
def test_failures_are_classified_by_exception_type(exc_type: type | None, code: str) -> None:
    error = jobs.classify_failure(exc_type)
    assert error["code"] == code and error["message"]
