"""Parsing and validating request bodies: ms per 1 000 matches, per encoding, in one run.

* a single pair as JSON (its keypoints in the body), through ``hmcc_schema.parse_pair``;
* a batch whose images carry their keypoints once, as JSON and as MessagePack with raw
  array buffers, through ``parse_batch``: per pair only its matches;
* the same bodies through pydantic alone (``PairRequest`` / ``BatchRequest``
  ``model_validate_json``): how every number was validated before.

Target (issue #13): parsing + validation at most 0.5 ms per 1 000 matches.
Results: ``benchmarks/results/parse.{json,md}``. Run: ``python -m benchmarks.bench_parse``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import orjson

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import BatchRequest, PairRequest, parse_batch, parse_pair
from hmcc_schema.parse import MSGPACK

from .common import DEFAULT_OUT, environment, verdict, with_code_hash

TARGET_MS_PER_1000 = 0.5


def _best_ms(call: Callable[[], Any], repeats: int) -> float:
    call()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return min(times) * 1e3


def _bodies(n_pairs: int, n_matches: int) -> dict[str, Any]:
    """One simulated pair (n_matches matches), and a batch of n_pairs pairs between images that
    carry their keypoints (as a flight would)."""
    doc = simulate_pair(SimulationOptions(n_inliers=n_matches // 2, outlier_ratio=0.5), 0)
    doc.pop("ground_truth")
    for key in ("keypoints1", "keypoints2"):
        doc[key] = np.round(np.asarray(doc[key]), 2).tolist()
    images = {
        "a": {**doc["image1"], "keypoints": doc["keypoints1"]},
        "b": {**doc["image2"], "keypoints": doc["keypoints2"]},
    }
    pairs = [
        {"id": str(k), "image1": "a", "image2": "b", "matches": doc["matches"]}
        for k in range(n_pairs)
    ]
    batch = {"images": images, "pairs": pairs, "plane": doc["plane"]}
    matches = np.asarray(doc["matches"], dtype="<i4")
    buffer = {"dtype": "<i4", "shape": list(matches.shape), "data": matches.tobytes()}
    binary_images = {
        name: {**image, "keypoints": _buffer(np.asarray(image["keypoints"], dtype="<f8"))}
        for name, image in images.items()
    }
    binary = {
        **batch,
        "images": binary_images,
        "pairs": [{**p, "matches": buffer} for p in pairs],
    }
    return {
        "pair": orjson.dumps(doc),
        "batch": orjson.dumps(batch),
        "batch_msgpack": msgpack.packb(binary),
        "matches": len(doc["matches"]),
    }


def _buffer(array: np.ndarray) -> dict[str, Any]:
    return {"dtype": array.dtype.str, "shape": list(array.shape), "data": array.tobytes()}


def run(n_pairs: int, n_matches: int, repeats: int) -> dict[str, Any]:
    bodies = _bodies(n_pairs, n_matches)
    m = bodies["matches"]
    rows = []

    def row(name: str, body: bytes, matches: int, call: Callable[[], Any]) -> None:
        ms = _best_ms(call, repeats)
        rows.append(
            {
                "path": name,
                "bytes": len(body),
                "matches": matches,
                "ms": ms,
                "ms_per_1000_matches": ms / matches * 1000,
            }
        )

    row("pair, JSON: parse_pair", bodies["pair"], m, lambda: parse_pair(bodies["pair"]))
    row(
        "pair, JSON: pydantic only (before)",
        bodies["pair"],
        m,
        lambda: PairRequest.model_validate_json(bodies["pair"]),
    )
    total = m * n_pairs
    row(
        "batch, JSON, images once: parse_batch",
        bodies["batch"],
        total,
        lambda: parse_batch(bodies["batch"], 10_000),
    )
    row(
        "batch, MessagePack buffers: parse_batch",
        bodies["batch_msgpack"],
        total,
        lambda: parse_batch(bodies["batch_msgpack"], 10_000, MSGPACK),
    )
    row(
        "batch, JSON: pydantic only (before)",
        bodies["batch"],
        total,
        lambda: BatchRequest.model_validate_json(bodies["batch"]),
    )
    return {
        "environment": environment(),
        "pairs": n_pairs,
        "matches_per_pair": m,
        "target_ms_per_1000": TARGET_MS_PER_1000,
        "rows": rows,
    }


def markdown(doc: dict[str, Any]) -> str:
    lines = [
        "# Parsing and validating request bodies",
        "",
        f"- {doc['pairs']} pairs of {doc['matches_per_pair']} matches in the batches; best of "
        f"the repeats; target: at most {doc['target_ms_per_1000']} ms per 1 000 matches",
        f"- {doc['environment']['platform']}, commit {doc['environment']['git_commit']}, load "
        f"average {doc['environment']['load_average_at_start']}",
        "",
        "| path | body bytes | ms | ms / 1000 matches | target |",
        "|:---|---:|---:|---:|:---|",
    ]
    for r in doc["rows"]:
        ok = (
            "before"
            if "before" in r["path"]
            else verdict(r["ms_per_1000_matches"] <= doc["target_ms_per_1000"])
        )
        lines.append(
            f"| {r['path']} | {r['bytes']:,} | {r['ms']:.2f} | "
            f"{r['ms_per_1000_matches']:.3f} | {ok} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--matches", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    doc = run(args.pairs, args.matches, args.repeats)
    text = markdown(doc)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "parse.json").write_text(json.dumps(with_code_hash(doc, __file__), indent=2) + "\n")
    (args.out / "parse.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
