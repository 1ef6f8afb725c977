"""Numbers a document quotes by hand from a benchmark's results stay those of the results.

Most figures in the docs are generated (the benchmark pages, the paper reproduction); a few
paragraphs and tables quote a run in prose (the deployment guide's CPU per process, the
evaluation's relaxed-matching paragraphs). Each such passage is followed by a stamp naming the
results file it quotes and that file's run::

    <!-- quotes benchmarks/results/flight.json run 1234567890 -->

(an HTML comment: the site does not show it). When the benchmark is run again its results
change, this test fails, and whoever reran it rereads the passage, brings its numbers up to date
and writes the new run number the failure gives. The run number is a digest of the results
(their ``code_hash`` left out: the page machinery rewrites it without a new run), in decimal
digits so that it does not read as a commit hash (tests/docs/test_user_docs.py)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
from benchmarks.common import REPO

from .test_user_docs import DOCUMENTS

STAMP = re.compile(r"<!-- quotes (?P<path>\S+) run (?P<run>\d+) -->")


def run_number(path: Path) -> str:
    """The digest of a results file: of its JSON without ``code_hash`` (sorted keys), or of
    its bytes when it is not JSON; ten decimal digits."""
    data = path.read_bytes()
    if path.suffix == ".json":
        doc = json.loads(data)
        if isinstance(doc, dict):
            doc.pop("code_hash", None)
        data = json.dumps(doc, sort_keys=True).encode()
    return f"{int(hashlib.sha256(data).hexdigest(), 16) % 10**10:010d}"


STAMPS = [
    (document, number, match)
    for document in DOCUMENTS
    for number, line in enumerate(document.read_text().splitlines(), 1)
    for match in STAMP.finditer(line)
]


@pytest.mark.parametrize(
    ("document", "number", "match"),
    STAMPS,
    ids=[f"{d.relative_to(REPO).as_posix()}:{n}" for d, n, _ in STAMPS],
)
def test_a_quoted_run_is_the_committed_run(document: Path, number: int, match: re.Match[str]):
    results = REPO / match["path"]
    where = f"{document.relative_to(REPO)}:{number}"
    assert results.is_file(), f"{where} quotes {match['path']}, which does not exist"
    run = run_number(results)
    assert match["run"] == run, (
        f"{where} quotes a run of {match['path']} that is not the committed one: reread the "
        f"numbers it quotes, bring them up to date, then stamp it "
        f"<!-- quotes {match['path']} run {run} -->"
    )


def test_the_hand_quoted_documents_are_stamped() -> None:
    """The documents known to quote runs by hand carry their stamps (removing one is a
    decision, not an accident)."""
    stamped = {(d.relative_to(REPO).as_posix(), m["path"]) for d, _, m in STAMPS}
    assert {
        ("README.md", "benchmarks/results/flight16.json"),
        ("docs/service/deployment.md", "benchmarks/results/flight.json"),
        ("docs/service/deployment.md", "benchmarks/results/flight16.json"),
        ("docs/service/scaling.md", "benchmarks/results/flight.json"),
        ("docs/colmap.md", "benchmarks/results/pairs.json"),
        ("docs/design/evaluation.md", "benchmarks/results/relaxed-brighton.json"),
        ("docs/design/evaluation.md", "benchmarks/results/relaxed-caliterra.json"),
    } <= stamped


def test_a_changed_result_changes_its_run_number(tmp_path: Path) -> None:
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    first.write_text(json.dumps({"rows": [1.25], "code_hash": "x"}))
    second.write_text(json.dumps({"code_hash": "y", "rows": [1.25]}))
    assert run_number(first) == run_number(second)  # the code hash and key order do not count
    second.write_text(json.dumps({"rows": [1.26], "code_hash": "x"}))
    assert run_number(first) != run_number(second)
    assert re.fullmatch(r"\d{10}", run_number(first))
