"""``hmcc-lean`` with other ``LeanOptions`` on a real fixture's pairs, beside MAGSAC++ (issue 29).

For a comparison of variants, not the evaluation (``bench_real`` is that): the pairs, labels
and thresholds of ``bench_real`` (strict, and one relaxed set on the share ``--relaxed-every``
fixes by the names), each (pair, method) called once to warm it and once timed; precision and
recall pooled, time summed, pairs where MAGSAC++ ran counted. One markdown table to ``--out``.

Usage::

    .venv/bin/python -m benchmarks.lean_variants --fixture caliterra \\
        --variant '{}' --variant '{"yaw_from_field": true}' --out FILE
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any

from hmcc import verify
from hmcc.lean import LeanOptions

from . import bench_real as br
from . import real_reference as ref
from .common import environment, warm_up_opencv


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fixture", choices=sorted(br.FIXTURES), default="caliterra")
    p.add_argument("--variant", action="append", default=[], help="LeanOptions fields (JSON)")
    p.add_argument("--relaxed", default="ratio 0.9")
    p.add_argument("--relaxed-every", type=int, default=4)
    p.add_argument("--half", default="held-out")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "hmcc-match")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    fixture = br.FIXTURES[args.fixture]
    reference = ref.load_reference(fixture.reference)
    variants = [json.loads(v) for v in args.variant] or [{}]
    warm_up_opencv()
    rows: list[list[str]] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for matching in ref.MATCHING_SETS:
            if matching.name not in ("strict", args.relaxed):
                continue
            db, _ = ref.matched_database(fixture.images, args.cache, matching, fixture.max_size)
            pairs, _ = br.read_pairs(db, fixture.images, reference, Path(tmp), fixture)
            pairs = [q for q in pairs if q.half == args.half]
            if matching.name != "strict":
                pairs = [q for q in pairs if br.sampled(q.name1, q.name2, args.relaxed_every)]
            for threshold in br.THRESHOLDS_PX:
                runs: list[tuple[str, str, Any]] = [("magsac++", "magsac++", None)]
                runs += [("hmcc-lean", json.dumps(v), LeanOptions(**v)) for v in variants]
                for method, label, lean in runs:
                    options = br.options_at(threshold)
                    if lean is not None:
                        options = dataclasses.replace(options, lean=lean)
                    tp = kept = true = fallbacks = 0
                    ms = 0.0
                    for q in pairs:
                        verify(q.data, method, options)
                        start = time.perf_counter()
                        result = verify(q.data, method, options)
                        ms += (time.perf_counter() - start) * 1e3
                        labels = q.labels[ref.REFERENCE_THRESHOLD_PX]
                        tp += int(labels[result.inliers].sum())
                        kept += len(result.inliers)
                        true += int(labels.sum())
                        fallbacks += bool(result.statistics.get("fallback", {}).get("used"))
                    fb = f"{fallbacks}/{len(pairs)}" if lean is not None else "-"
                    rows.append(
                        [
                            matching.name,
                            f"{threshold:g}",
                            f"{method} {label if lean is not None else ''}".strip(),
                            f"{ms:.0f}",
                            f"{tp / max(kept, 1):.3f}",
                            f"{tp / max(true, 1):.3f}",
                            fb,
                        ]
                    )
                    print(" | ".join(rows[-1]), flush=True)
    env = environment()
    head = "| matching | threshold (px) | method | time (ms, sum) | precision | recall | fallback |"
    lines = [
        head,
        "|:---|:---|:---|---:|---:|---:|---:|",
        *("| " + " | ".join(r) + " |" for r in rows),
    ]
    meta = (
        f"{fixture.title}, {args.half} pairs, labels at {ref.REFERENCE_THRESHOLD_PX:g} px; "
        f"{args.relaxed} on the pairs with SHA-256('name1 name2')[1] % {args.relaxed_every} == 0. "
        f"Git {env['git_commit']}, {time.perf_counter() - t0:.0f} s on {env['cpu_count']} "
        "shared cores; one warm and one timed call a pair."
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join([meta, "", *lines, ""]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
