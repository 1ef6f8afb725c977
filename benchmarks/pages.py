"""Write the documentation's benchmark pages, ``docs/benchmarks/*.md``, from the committed
results, ``benchmarks/results/*.json``. Nothing is measured here, and no page is written by hand.

Each page states the commit its results measured (the run's ``git_commit``) and the hash of the
code it measured (the results' ``code_hash``, :func:`benchmarks.common.code_hash`), and compares
that hash with today's tree: a page whose code changed since is marked **stale** (rerun its
benchmark), one whose results predate the hash says "code hash unknown". The key tables are
the benchmark's own Markdown writer where it has one that reads the JSON (``markdown(doc)``),
else tables of the JSON's summaries.

Usage (from the checkout's root; ``tests/benchmarks/test_pages.py`` fails when a committed page
differs from what this writes)::

    .venv/bin/python -m benchmarks.pages             # rewrite docs/benchmarks/
    .venv/bin/python -m benchmarks.pages --check     # exit 1 when a page is out of date
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .common import REPO, code_hash

__all__ = ["BENCHMARKS", "Benchmark", "render_pages", "write_pages"]

RESULTS = REPO / "benchmarks" / "results"
PAGES = REPO / "docs" / "benchmarks"
MAX_ROWS = 80


@dataclass(frozen=True)
class Benchmark:
    """One results file: the script that writes it and what of it the page shows."""

    script: str  # module of benchmarks/ that writes the JSON
    title: str
    command: str
    tables: tuple[str, ...] = ()  # keys of the JSON shown as tables (lists or dicts of records)
    writer: str | None = None  # the script's own ``markdown(doc)``, when it reads only the JSON
    extra: Callable[[dict[str, Any]], list[str]] | None = None  # a table the keys do not give


def _default_cells(doc: dict[str, Any]) -> list[str]:
    """bench_default's cells: per set and outlier ratio, each method's precision, recall, ms."""
    rows = []
    for set_name, ratios in doc.get("cells", {}).items():
        for ratio, cell in ratios.items():
            row: dict[str, Any] = {"set": set_name, "outliers": ratio, "pairs": cell.get("pairs")}
            for method, figures in cell.get("methods", {}).items():
                row[f"{method} P / R / ms"] = (
                    f"{_cell(figures.get('precision'))} / {_cell(figures.get('recall'))} / "
                    f"{_cell(figures.get('wall_ms'))}"
                )
            rows.append(row)
    return ["### cells (precision / recall / ms a pair through verify())", "", *_table(rows), ""]


def _flight_rows(doc: dict[str, Any]) -> list[str]:
    """bench_flight's rows, the columns a reader compares (every figure is in the JSON)."""
    rows = []
    for r in doc.get("records", []):
        share = r.get("serial_share")
        amdahl = r.get("amdahl_speedup") or {}
        row: dict[str, Any] = {"path": r["path"]}
        if "run" in r:
            row["run"] = r["run"]
        row |= {
            "processes": r["processes"],
            "seconds": r["seconds"],
            "x core 1 process": r["vs_core_1"],
            "pairs run": r["pairs_run"],
            "precision": r["precision"],
            "recall": r["recall"],
            "serial %": None if share is None else round(100 * share, 1),
            "CPU / pair x core 1": r.get("cpu_per_pair_vs_core_1"),
            "Amdahl x16": amdahl.get("x16"),
            "API peak RSS MiB": (
                None if r.get("api_peak_rss") is None else round(r["api_peak_rss"] / 2**20)
            ),
        }
        rows.append(row)
    note = [doc["note"], ""] if doc.get("note") else []
    return ["### rows (seconds: the whole flight)", "", *note, *_table(rows), ""]


BENCHMARKS: dict[str, Benchmark] = {
    "core": Benchmark(
        "bench_core",
        "Core: filter scaling, methods, robustness",
        "python -m benchmarks.bench_core",
        ("summary", "stage_losses"),
    ),
    "default": Benchmark(
        "bench_default",
        "The default method against the baselines",
        "OPENBLAS_NUM_THREADS=1 python -m benchmarks.bench_default",
        ("summary",),
        extra=_default_cells,
    ),
    "hard": Benchmark(
        "bench_hard",
        "hmcc-plus pair by pair (hard pairs)",
        "OPENBLAS_NUM_THREADS=1 python -m benchmarks.bench_hard "
        "--before benchmarks/results/hard_before.json",
        ("sets",),
    ),
    "hard_before": Benchmark(
        "bench_hard",
        "hmcc-plus pair by pair, before the check (the comparison run)",
        "python -m benchmarks.bench_hard --name hard_before",
        ("sets",),
    ),
    "lean": Benchmark(
        "bench_lean",
        "hmcc-lean on held-out simulated seeds",
        "python -m benchmarks.bench_lean",
        ("summary",),
    ),
    "real": Benchmark(
        "bench_real",
        "Real pairs labelled by COLMAP's model",
        "python -m benchmarks.bench_real",
        writer="markdown",
    ),
    "paper": Benchmark(
        "bench_paper",
        "The paper's experiments (data of the paper reproduction)",
        "python -m benchmarks.bench_paper",
        ("methods",),
    ),
    "service": Benchmark(
        "bench_service",
        "The service against in-process verification",
        "python -m benchmarks.bench_service",
        ("targets", "modes"),
    ),
    "flight": Benchmark(
        "bench_flight",
        "A whole flight through every path",
        "python -m benchmarks.bench_flight --cutover 100,300,1000,2000,3000",
        ("flight", "targets"),
        extra=_flight_rows,
    ),
    "flight16": Benchmark(
        "bench_flight",
        "A whole flight on 16 cores",
        "OUT=... benchmarks/scale_device.sh (on a 16-core machine)",
        ("flight",),
        extra=_flight_rows,
    ),
    "parse": Benchmark(
        "bench_parse", "Reading bodies", "python -m benchmarks.bench_parse", writer="markdown"
    ),
    "soak": Benchmark(
        "bench_soak",
        "Soak: memory over repeated load",
        "python -m benchmarks.bench_soak",
        ("checks",),
    ),
    "guards": Benchmark(
        "bench_guards",
        "Guards: every method on the limits",
        "python -m benchmarks.bench_guards",
        writer="markdown",
    ),
    "colmap": Benchmark(
        "bench_colmap",
        "A COLMAP project's verification stage",
        "python -m benchmarks.bench_colmap",
        writer="markdown",
    ),
    "colmap_caliterra": Benchmark(
        "bench_colmap",
        "A GPS-only flight end to end (Caliterra)",
        "python -m benchmarks.bench_colmap --fixture caliterra",
        writer="markdown",
    ),
    "relaxed-brighton": Benchmark(
        "bench_relaxed",
        "Relaxed matching, verified and mapped: Brighton",
        "python -m benchmarks.bench_relaxed --fixture brighton",
        writer="markdown",
    ),
    "relaxed-caliterra": Benchmark(
        "bench_relaxed",
        "Relaxed matching, verified and mapped: Caliterra",
        "python -m benchmarks.bench_relaxed --fixture caliterra",
        writer="markdown",
    ),
    "pairs": Benchmark(
        "bench_pairs",
        "Choosing the pairs to match",
        "python -m benchmarks.bench_pairs",
        writer="markdown",
    ),
    "match": Benchmark(
        "bench_match",
        "Guided matching",
        "python -m benchmarks.bench_match --repeats 3",
        writer="markdown",
    ),
    "match-caliterra": Benchmark(
        "bench_match",
        "Guided matching: Caliterra",
        "python -m benchmarks.bench_match --fixture caliterra",
        writer="markdown",
    ),
}


def _find(doc: Any, key: str) -> Any:
    """The first value of ``key`` anywhere in ``doc`` (depth first), or None."""
    if isinstance(doc, dict):
        if key in doc:
            return doc[key]
        for value in doc.values():
            found = _find(value, key)
            if found is not None:
                return found
    return None


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        text = ", ".join(_cell(v) for v in value[:8]) + (", ..." if len(value) > 8 else "")
        return text
    return str(value).replace("|", "\\|").replace("\n", " ")


def _flatten(record: dict[str, Any], prefix: str = "", depth: int = 2) -> dict[str, Any]:
    """Scalar leaves of a record, nested keys joined by '.', at most ``depth`` levels."""
    flat: dict[str, Any] = {}
    for key, value in record.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            if depth > 1:
                flat.update(_flatten(value, f"{name}.", depth - 1))
        elif not (isinstance(value, list) and value and isinstance(value[0], dict | list)):
            flat[name] = value
    return flat


def _table(rows: list[dict[str, Any]]) -> list[str]:
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows[:MAX_ROWS]:
        lines.append("| " + " | ".join(_cell(row.get(c)) for c in columns) + " |")
    if len(rows) > MAX_ROWS:
        lines.append("")
        lines.append(f"(the first {MAX_ROWS} of {len(rows)} rows; every row is in the JSON)")
    return lines


def _key_table(name: str, value: Any) -> list[str]:
    """``value`` as a Markdown table: a list of records, records by name, or one record."""
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        rows = [_flatten(v) for v in value]
    elif isinstance(value, dict) and value and all(isinstance(v, dict) for v in value.values()):
        rows = [{"": key, **_flatten(v)} for key, v in value.items()]
    elif isinstance(value, dict):
        rows = [{"field": key, "value": v} for key, v in _flatten(value).items()]
    else:
        return []
    return [f"### {name}", "", *_table(rows), ""]


def _status(doc: dict[str, Any], today: str) -> tuple[str, str]:
    """('current' | 'stale' | 'unknown', a sentence saying so)."""
    recorded = doc.get("code_hash")
    if recorded is None:
        return "unknown", (
            "**code hash unknown**: these results predate the code hash; whether the code "
            "changed since cannot be told. Rerun the benchmark to record it."
        )
    if recorded != today:
        return "stale", (
            f"**stale**: the code these results measured hashed `{recorded}`, today's tree "
            f"hashes `{today}`. Rerun the benchmark for current numbers."
        )
    return "current", f"current: today's tree hashes the same (`{today}`)."


def render_page(stem: str, bench: Benchmark, doc: dict[str, Any]) -> tuple[str, str]:
    """The page of one results file and its status."""
    today = code_hash(REPO / "benchmarks" / f"{bench.script}.py")
    status, sentence = _status(doc, today)
    commit = _find(doc, "git_commit") or "unknown"
    lines = [
        f"# {bench.title}",
        "",
        "<!-- generated by `python -m benchmarks.pages` from "
        f"benchmarks/results/{stem}.json: do not edit -->",
        "",
        f"- Results: `benchmarks/results/{stem}.json`, written by `{bench.command}`.",
        f"- Commit measured: `{commit}`; code hash recorded: `{doc.get('code_hash', 'unknown')}`.",
        f"- Status: {sentence}",
        "",
    ]
    if bench.writer is not None:
        module = importlib.import_module(f"benchmarks.{bench.script}")
        writer: Callable[[dict[str, Any]], str] = getattr(module, bench.writer)
        text = writer(doc).strip().splitlines()
        if text and text[0].startswith("# "):
            text = text[1:]
        # the writer's headings under the page's title
        lines.extend("#" + line if line.startswith("#") else line for line in text)
        lines.append("")
    for key in bench.tables:
        lines.extend(_key_table(key, doc.get(key)))
    if bench.extra is not None:
        lines.extend(bench.extra(doc))
    return "\n".join(lines).rstrip() + "\n", status


def render_pages(results: Path = RESULTS) -> dict[str, str]:
    """Every page by file name (``index.md`` and one per results file), from ``results``."""
    pages: dict[str, str] = {}
    index = [
        "# Benchmarks",
        "",
        "<!-- generated by `python -m benchmarks.pages`: do not edit -->",
        "",
        "Every page here is generated from a results file of `benchmarks/results/`; the numbers "
        "the other pages quote come from these. A page is *stale* when the code it measured "
        "differs from today's: its benchmark's scripts and the modules of `worker/`, "
        "`service/` and `client/` they import, directly or through others (all of them for a "
        "benchmark that starts the service, its workers or the `hmcc` command), their code "
        "hashed (comments and docstrings aside). "
        "Rerun its benchmark. How to run them: [Running the benchmarks](running.md).",
        "",
        "| page | results | commit measured | status |",
        "|---|---|---|---|",
    ]
    for stem, bench in BENCHMARKS.items():
        path = results / f"{stem}.json"
        if not path.is_file():
            continue
        doc = json.loads(path.read_text())
        pages[f"{stem}.md"], status = render_page(stem, bench, doc)
        commit = _find(doc, "git_commit") or "unknown"
        index.append(f"| [{bench.title}]({stem}.md) | `{stem}.json` | `{commit}` | {status} |")
    pages["index.md"] = "\n".join(index) + "\n"
    return pages


def write_pages(out: Path = PAGES, results: Path = RESULTS) -> list[Path]:
    """Write every page into ``out``; the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in render_pages(results).items():
        path = out / name
        path.write_text(text)
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=PAGES)
    parser.add_argument("--check", action="store_true", help="compare, write nothing")
    args = parser.parse_args(argv)
    if args.check:
        stale = [
            name
            for name, text in render_pages().items()
            if not (args.out / name).is_file() or (args.out / name).read_text() != text
        ]
        for name in stale:
            print(f"{args.out / name}: differs from the results; run python -m benchmarks.pages")
        return 1 if stale else 0
    for path in write_pages(args.out):
        print(f"wrote {path.relative_to(REPO) if path.is_relative_to(REPO) else path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
