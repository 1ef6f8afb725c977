"""The benchmark pages (``benchmarks/pages.py``): the committed ``docs/benchmarks/*.md`` are what
the generator writes from the committed results, and a page says stale when the code changed."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.common import REPO, _code, code_files, code_hash, with_code_hash

from benchmarks import pages


def test_the_committed_pages_are_what_the_generator_writes(tmp_path: Path) -> None:
    """A number edited by hand, a results file rerun without regenerating, or code changed
    since the pages were written (their status line): run ``python -m benchmarks.pages``."""
    written = pages.write_pages(tmp_path)
    assert written
    for path in written:
        committed = pages.PAGES / path.name
        assert committed.is_file(), f"{committed} missing: run python -m benchmarks.pages"
        assert committed.read_text() == path.read_text(), (
            f"{committed.relative_to(REPO)} differs from what benchmarks/results gives: "
            "run python -m benchmarks.pages (and do not edit the pages by hand)"
        )


def test_every_results_file_has_a_page() -> None:
    stems = {path.stem for path in pages.RESULTS.glob("*.json")}
    assert stems <= set(pages.BENCHMARKS), stems - set(pages.BENCHMARKS)


def test_a_page_is_stale_when_the_code_hash_differs() -> None:
    bench = pages.BENCHMARKS["parse"]
    doc = json.loads((pages.RESULTS / "parse.json").read_text())
    today = code_hash(REPO / "benchmarks" / "bench_parse.py")
    current, status = pages.render_page("parse", bench, {**doc, "code_hash": today})
    assert status == "current" and "Status: current" in current
    stale, status = pages.render_page("parse", bench, {**doc, "code_hash": "0" * 16})
    assert status == "stale" and "**stale**" in stale
    unknown, status = pages.render_page(
        "parse", bench, {k: v for k, v in doc.items() if k != "code_hash"}
    )
    assert status == "unknown" and "code hash unknown" in unknown


def _files(script: str) -> set[str]:
    return {path.relative_to(REPO).as_posix() for path in code_files(REPO / "benchmarks" / script)}


def test_the_code_hash_covers_the_script_and_the_modules_it_imports() -> None:
    files = _files("bench_hard.py")
    assert {"benchmarks/bench_hard.py", "benchmarks/common.py"} <= files
    assert "benchmarks/bench_parse.py" not in files
    # imported directly (hmcc.plus), through another (hmcc.ransac from hmcc.plus), by the
    # core's lazy names (hmcc.lean, imported by computed name in hmcc/__init__.py)
    assert {"worker/hmcc/plus.py", "worker/hmcc/ransac.py", "worker/hmcc/lean.py"} <= files
    # bench_hard runs nothing of the service, the client or the flight command
    assert not any(f.startswith(("client/", "service/", "worker/hmcc_worker/")) for f in files)
    doc = with_code_hash({"x": 1}, REPO / "benchmarks" / "bench_hard.py")
    assert doc["code_hash"] == code_hash(REPO / "benchmarks" / "bench_hard.py")
    assert len(doc["code_hash"]) == 16


def test_the_code_hash_follows_imports_inside_functions_and_modules_named_in_strings() -> None:
    # bench_real imports hmcc_colmap inside a function; the compute pool names the fork
    # server's preload module in a string
    assert "service/hmcc_colmap/capture.py" in _files("bench_real.py")
    assert "worker/hmcc_worker/forkserver.py" in _files("bench_guards.py")


def test_a_benchmark_that_starts_the_projects_processes_covers_all_of_its_code() -> None:
    everything = {
        path.relative_to(REPO).as_posix()
        for root in ("worker", "service", "client")
        for path in (REPO / root).rglob("*.py")
        if "__pycache__" not in path.parts and ".egg-info" not in path.as_posix()
    }
    for script in ("bench_flight.py", "bench_service.py", "bench_soak.py", "bench_match.py"):
        assert everything <= _files(script), script


def test_comments_and_docstrings_leave_the_code_hash_and_code_changes_it(tmp_path: Path) -> None:
    path = tmp_path / "m.py"
    path.write_text('"""A module."""\n\ndef f(x):\n    """Twice."""\n    return 2 * x\n')
    before = _code(path)
    path.write_text(
        '"""Other words."""\n# a comment\ndef f(x):  # here\n    """Two x."""\n\n    return 2 * x\n'
    )
    assert _code(path) == before
    path.write_text('"""A module."""\n\ndef f(x):\n    """Twice."""\n    return 3 * x\n')
    assert _code(path) != before
    path.write_text('def f(x):\n    return 2 * x\n\nX = "a string, not a docstring"\n')
    assert _code(path) != before
    path.write_text("def f(:\n")  # does not parse: its bytes
    assert _code(path) == b"def f(:\n"


def test_the_paper_reproduction_is_what_its_generator_writes(tmp_path: Path) -> None:
    """docs/paper-reproduction.md says "do not edit by hand": it must be what
    ``python -m benchmarks.paper_report`` writes from the committed results."""
    from benchmarks import paper_report

    out = paper_report.build(REPO / "benchmarks" / "results", tmp_path)
    committed = REPO / "docs" / "paper-reproduction.md"
    assert out.read_text() == committed.read_text(), "run python -m benchmarks.paper_report"
