"""Write ``docs/paper-reproduction.md`` and its figures (``docs/figures/*.png``) from the
benchmarks' JSON: ``benchmarks/results/paper.json`` (``bench_paper``) and, when present,
``core.json`` (``bench_core``). Nothing is measured here; rerun the benchmarks first.

Usage::

    .venv/bin/python -m benchmarks.paper_report [--results DIR] [--docs DIR]
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .common import DEFAULT_OUT, REPO, fmt, mean, median

DOCS = REPO / "docs"
COLMAP_REPORT = REPO / "benchmarks" / "results" / "colmap.md"

#: The paper's numbers (Jiang & Jiang, section 4), quoted where the report compares.
PAPER_STAGE1 = {"V-V": (46, 12.0), "V-F": (21, 15.7), "B-F": (22, 32.4), "L-F": (28, 28.9)}
PAPER_RECALL = {"V-V": "> 0.90", "V-F": "~ 0.80", "B-F": "> 0.90", "L-F": "~ 0.65"}
PAPER_TABLE3 = {  # seconds: LO, GC filter, GC verif, GC sum, HMCC filter, HMCC verif, HMCC sum
    "V-V": (0.011, 0.031, 0.016, 0.047, 0.002, 0.006, 0.008),
    "V-F": (0.273, 0.007, 0.044, 0.051, 0.002, 0.033, 0.035),
    "B-F": (1.424, 0.002, 0.047, 0.049, 0.002, 0.008, 0.010),
    "L-F": (0.677, 0.004, 0.109, 0.113, 0.002, 0.047, 0.049),
}
PAPER_TABLE4 = {  # seconds over 4130 pairs: LO, GC, RANSAC after GC, HMCC, RANSAC after HMCC
    "Max": (19.423, 6.207, 0.996, 0.013, 0.635),
    "Mean": (0.180, 0.118, 0.038, 0.001, 0.039),
    "Stddev": (0.487, 0.495, 0.068, 0.001, 0.063),
    "Sum": (743.697, 492.537, 155.531, 4.395, 162.327),
}
PAPER_TABLE6 = {  # seconds: LO-RANSAC, GC-RANSAC, HMCC-RANSAC per dataset
    "dataset 1 (1 camera, 25/-15 deg)": (126.0, 1445.0, 128.1),
    "dataset 2 (2 cameras)": (198.5, 2359.4, 120.1),
    "dataset 3 (penta-view, 45 deg)": (2604.2, 1247.2, 437.2),
}
PAIRS = ("V-V", "V-F", "B-F", "L-F")
LOW = "paper, 0.25 px noise"  # bench_paper's low-noise protocol


def _table(headers: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out + [""]


def _ms(value: float) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.2f}" if value < 100 else f"{value:.0f}"


# --------------------------------------------------------------------------- figures


def motion_figures(paper: dict[str, Any], figures: Path) -> list[tuple[str, str]]:
    """One PNG per paper pair (hmcc-ransac), and hmcc-plus on L-F; (name, file) pairs."""
    from hmcc_cli.plot import draw_motions

    made = []
    for record in paper["stages"]:
        figure = record.get("figure")
        if figure is None:
            continue
        name = record["pair"]
        for method in ("hmcc-ransac", "hmcc-plus"):
            if method == "hmcc-plus" and name != "L-F":
                continue
            path = figures / f"motions-{name}-{method}.png"
            draw_motions(figure["doc"], figure["results"][method], path)
            made.append((f"{name} {method}", path.name))
    real = paper.get("real_figure")
    if real is not None:
        path = figures / "motions-real-hmcc-ransac.png"
        draw_motions(real["doc"], real["result"], path)
        made.append((f"real {real['pair']} (its own candidate matches) hmcc-ransac", path.name))
    return made


def robustness_figure(cells: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    groups = [*PAIRS, "real"]
    colours = dict(
        zip(groups, ["#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#444444"], strict=True)
    )
    for ax, key, title in (
        (axes[0], "paper_precision", "precision, the paper's definition (Fig. 13)"),
        (axes[1], "paper_recall", "recall, the paper's definition (Fig. 14)"),
        (axes[2], "recall", "recall against the truth"),
    ):
        for group in groups:
            for protocol, style in (("paper", "-"), ("ours", ":"), (LOW, "--")):
                rows = sorted(
                    (c for c in cells if c["pair"] == group and c["protocol"] == protocol),
                    key=lambda c: c["ratio"],
                )
                if rows:
                    ax.plot(
                        [c["ratio"] for c in rows],
                        [c[key] for c in rows],
                        style,
                        marker="o",
                        ms=3,
                        color=colours[group],
                        label=f"{group} ({protocol} outliers)",
                    )
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("outlier ratio")
        ax.set_ylim(0, 1.05)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def methods_figure(records: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 4))
    x = np.arange(len(PAIRS))
    for ax, key, methods, title, unit in (
        (axes[0], "filter_ms", ("gc-ransac", "hmcc-ransac"), "(Fig. 15a) filter time", "ms"),
        (axes[1], "filter_kept", ("gc-ransac", "hmcc-ransac"), "(Fig. 15b) kept by the filter", ""),
        (
            axes[2],
            "ransac_ms",
            ("lo-ransac", "gc-ransac", "hmcc-ransac"),
            "(Fig. 16a) verification time",
            "ms",
        ),
        (
            axes[3],
            "final_kept",
            ("lo-ransac", "gc-ransac", "hmcc-ransac"),
            "(Fig. 16b) final inliers",
            "",
        ),
    ):
        width = 0.8 / len(methods)
        for k, method in enumerate(methods):
            values = [
                median(r["methods"][method][key] for r in records if r["pair"] == p) for p in PAIRS
            ]
            ax.bar(x + k * width, values, width, label=method)
        ax.set_xticks(x + 0.4 - width / 2, PAIRS)
        ax.set_title(title, fontsize=10)
        ax.set_ylabel(unit)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def flight_figure(records: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = flight_columns(records)
    fig, axes = plt.subplots(1, 5, figsize=(18, 3.6), sharey=False)
    for ax, (name, values) in zip(axes, columns.items(), strict=True):
        ax.plot(np.arange(len(values)), values, ".", ms=3)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("pair")
        ax.set_ylabel("ms")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def flight_columns(records: list[dict[str, Any]]) -> dict[str, list[float]]:
    """Per-pair ms of Table 4's five columns."""
    return {
        "(a) LO-RANSAC": [r["methods"]["lo-ransac"]["total_ms"] for r in records],
        "(b) GC filter": [r["methods"]["gc-ransac"]["filter_ms"] for r in records],
        "(c) RANSAC after GC": [r["methods"]["gc-ransac"]["ransac_ms"] for r in records],
        "(d) HMCC filter": [r["methods"]["hmcc-ransac"]["filter_ms"] for r in records],
        "(e) RANSAC after HMCC": [r["methods"]["hmcc-ransac"]["ransac_ms"] for r in records],
    }


# --------------------------------------------------------------------------- sections


def stages_section(paper: dict[str, Any]) -> list[str]:
    lines = [
        "## Sections 4.2-4.3: motions and the three stages (Figs. 7-12)",
        "",
        "**What we ran.** The four pairs of Table 2, simulated like the paper's site (see "
        "*Pairs*), each with the paper's number of initial matches and inlier ratio; the "
        "outliers are mismatched true features (SIFT's kind of error). `hmcc-ransac` with "
        f"`params.return_motions`, {len({r['seed'] for r in paper['stages']})} pairs (seeds) "
        "per geometry; counts are means over them. The figures are seed 0, drawn by "
        "`hmcc plot`'s code.",
        "",
    ]
    rows = []
    for name in PAIRS:
        recs = [r for r in paper["stages"] if r["pair"] == name]
        if not recs:
            continue

        def removed(stage: str, kind: str, recs: list[dict[str, Any]] = recs) -> float:
            return mean(next(s[kind] for s in r["stages"] if s["name"] == stage) for r in recs)

        stage1 = removed("direction", "removed_false") + removed("direction", "removed_true")
        paper1, share1 = PAPER_STAGE1[name]
        rows.append(
            [
                name,
                f"{mean(r['matches'] for r in recs):.0f}",
                f"{mean(r['true'] / r['matches'] for r in recs):.1%}",
                f"{paper1} ({share1:.1f} %)",
                f"{stage1:.1f} ({stage1 / mean(r['matches'] for r in recs):.1%}; "
                f"{removed('direction', 'removed_true'):.1f} true)",
                f"{removed('direction_change', 'removed_false'):.1f} / "
                f"{removed('direction_change', 'removed_true'):.1f}",
                f"{removed('length', 'removed_false'):.1f} / "
                f"{removed('length', 'removed_true'):.1f}",
                f"{mean(r['hmcc']['precision'] for r in recs):.2f} / "
                f"{mean(r['hmcc']['recall'] for r in recs):.2f}",
                f"{mean(r['final']['precision'] for r in recs):.2f} / "
                f"{mean(r['final']['recall'] for r in recs):.2f}",
            ]
        )
    lines += _table(
        [
            "pair",
            "matches",
            "inlier ratio",
            "paper: removed by the direction vote",
            "ours: removed by the direction vote",
            "direction change: false / true removed",
            "length: false / true removed",
            "after HMCC P / R (truth)",
            "hmcc-ransac P / R (truth)",
        ],
        rows,
    )
    z0 = [r["z0_m"] for r in paper["stages"] if r.get("z0_m") is not None]
    lines += [
        "The paper's pairs have 383, 134, 68 and 97 matches with 52.5, 32.8, 26.5 and 27.8 % "
        "inliers (section 4.2); ours are drawn to the same numbers. Our plane lies at "
        f"{min(z0):.1f} to {max(z0):.1f} m (the paper's: -100 m).",
        "",
        "**Where we differ, and why.** (1) Our direction vote removes far more matches than the "
        "paper's (on V-V about half of them, against its 12 %): the simulator's outliers pair "
        "random true features, so their motions point anywhere, while the paper's SIFT "
        "mismatches were mostly caught later, i.e. many of them moved like the true ones "
        "(repeated texture, nearby features). (2) Our direction-change vote also removes true "
        "matches (on V-V about an eighth of them): near buildings and with 15 m of relief, "
        "neighbouring "
        "true motions differ by more than its 3 deg bin (the paper's Fig. 11 shows nearly all "
        "changes within 3 deg). (3) The final RANSAC then drops another part of the true "
        "matches: with 0.5 px keypoint noise the larger of two point-to-line distances of a "
        "true match often exceeds 1 px (see section 4.4's low-noise run). (4) The length "
        "stage removes almost nothing, as in the paper (one motion over its four pairs).",
        "",
    ]
    return lines


def robustness_section(paper: dict[str, Any]) -> list[str]:
    cells = paper["robustness"]["cells"]
    lines = [
        "## Section 4.4: robustness to outliers (Figs. 13-14)",
        "",
        "**What we ran.** The paper's total inliers per pair (204, 44, 15, 20), simulated, plus "
        "random point pairs (uniform in both images) at outlier ratios 0.1-0.9; and the 14 "
        "Brighton Beach fixtures reduced to their reference inliers. Two outlier protocols: "
        '*paper* keeps every random pair, as section 4.4 does ("adding random point pairs"), '
        "so a few land within a pixel of their epipolar line and count as inliers of any good "
        "F; *ours* (the core benchmark's) redraws a pair within 3 px of its true epipolar line; "
        "and the paper's protocol once more with 0.25 px keypoint noise instead of the "
        "simulator's 0.5 px. "
        "Metrics of `hmcc-ransac`: the paper's (precision = RANSAC inliers / HMCC survivors, "
        "recall = RANSAC inliers / total inliers: counts, not checked against any truth) and "
        "the truth's.",
        "",
        "![precision and recall](figures/robustness.png)",
        "",
    ]
    rows = []
    for group in [*PAIRS, "real"]:
        for ratio in (0.1, 0.5, 0.7, 0.8, 0.9):
            get = {
                c["protocol"]: c
                for c in cells
                if c["pair"] == group and abs(c["ratio"] - ratio) < 1e-9
            }
            if "paper" not in get:
                continue
            p, o, q = get["paper"], get.get("ours", {}), get.get(LOW, {})
            rows.append(
                [
                    group,
                    f"{ratio:.1f}",
                    f"{fmt(p['paper_precision'])} / {fmt(p['paper_recall'])}",
                    f"{fmt(p['precision'])} / {fmt(p['recall'])}",
                    f"{fmt(o.get('paper_precision'))} / {fmt(o.get('paper_recall'))}",
                    f"{fmt(o.get('precision'))} / {fmt(o.get('recall'))}",
                    f"{fmt(q.get('paper_precision'))} / {fmt(q.get('paper_recall'))}",
                    PAPER_RECALL.get(group, "-") if ratio == 0.5 else "",
                ]
            )
    lines += _table(
        [
            "pair",
            "ratio",
            "paper outliers: paper P / R",
            "paper outliers: truth P / R",
            "our outliers: paper P / R",
            "our outliers: truth P / R",
            "paper outliers, 0.25 px noise: paper P / R",
            "paper's mean recall (text)",
        ],
        rows,
    )
    lines += [
        "The paper reports high precision below 0.8 for all four pairs, better for the first two "
        'at 0.9, and a recall "scarcely affected by outlier ratios": a mean above 0.9 for '
        "pairs 1 and 3, near 0.8 for pair 2 and about 0.65 for pair 4 (it gives figures, no "
        "table). Its precision can exceed the truth's, since a RANSAC inlier that is an injected "
        "outlier near its epipolar line counts as correct; its recall can exceed 1 for the same "
        "reason.",
        "",
        "**Where we differ, and why** (figures of this run). Our recall by the paper's "
        "definition stays flat up to "
        "0.7-0.8, as the paper's does, but lower: about 0.6 on V-V (paper: above 0.9), 0.7 on "
        "V-F (about 0.8), 0.8 on B-F (above 0.9) and 0.7 on L-F (about 0.65). Two causes, "
        "measured: the direction-change vote's loss on V-V (above), and the final RANSAC at "
        "1 px on 0.5 px keypoint noise; with 0.25 px noise the recall rises to about 0.7, 0.8, "
        "0.9 and 0.85. The paper's precision is RANSAC inliers over HMCC survivors, so below "
        "0.8 it is mostly the final RANSAC's recall among the survivors (0.69-0.87 in this run, "
        "0.84-0.93 with 0.25 px noise, while "
        "the truth's precision is 1.00), not outliers let through. At 0.9 B-F and L-F fail "
        "(truth precision about 0.25 and 0.6; the paper also reports its last two pairs "
        "weaker at 0.9): the direction peak is often the outliers'. The two outlier protocols "
        "give nearly the same numbers: few random pairs land within 3 px of their epipolar "
        "line in 7360 px images.",
        "",
    ]
    return lines


def methods_section(paper: dict[str, Any]) -> list[str]:
    records = paper["methods"]
    lines = [
        "## Section 4.5.1: the three methods on the four pairs (Figs. 15-16, Table 3)",
        "",
        "**What we ran.** LO-RANSAC (OpenCV's USAC with uniform sampling and inner local "
        "optimisation), GC-RANSAC (Lu et al.'s quadratic vote, then our seven-point RANSAC) "
        "and HMCC-RANSAC on the pairs of sections 4.2-4.3; median wall times over repeats "
        "and seeds. Paper: seconds on an i7-4770 (C++); ours: milliseconds on a shared 2-core "
        "machine (Python around OpenCV and numba).",
        "",
        "![filter and verification](figures/methods.png)",
        "",
    ]
    rows = []
    for name in PAIRS:
        recs = [r for r in records if r["pair"] == name]
        if not recs:
            continue

        def med(method: str, key: str, recs: list[dict[str, Any]] = recs) -> float:
            return median(r["methods"][method][key] for r in recs)

        p = PAPER_TABLE3[name]
        rows.append(
            [
                name,
                f"{p[0] * 1e3:.0f} / {_ms(med('lo-ransac', 'total_ms'))}",
                f"{p[1] * 1e3:.0f} / {_ms(med('gc-ransac', 'filter_ms'))}",
                f"{p[2] * 1e3:.0f} / {_ms(med('gc-ransac', 'ransac_ms'))}",
                f"{p[3] * 1e3:.0f} / {_ms(med('gc-ransac', 'total_ms'))}",
                f"{p[4] * 1e3:.0f} / {_ms(med('hmcc-ransac', 'filter_ms'))}",
                f"{p[5] * 1e3:.0f} / {_ms(med('hmcc-ransac', 'ransac_ms'))}",
                f"{p[6] * 1e3:.0f} / {_ms(med('hmcc-ransac', 'total_ms'))}",
                f"x{p[0] / p[6]:.1f} / "
                f"x{med('lo-ransac', 'total_ms') / med('hmcc-ransac', 'total_ms'):.1f}",
                f"{med('gc-ransac', 'filter_kept'):.0f} / {med('hmcc-ransac', 'filter_kept'):.0f}",
                " / ".join(
                    f"{med(m, 'precision'):.2f}-{med(m, 'recall'):.2f}"
                    for m in ("lo-ransac", "gc-ransac", "hmcc-ransac")
                ),
            ]
        )
    lines += _table(
        [
            "pair",
            "LO (paper ms / ours)",
            "GC filter",
            "GC verif",
            "GC sum",
            "HMCC filter",
            "HMCC verif",
            "HMCC sum",
            "LO / HMCC sum",
            "kept GC / HMCC",
            "P-R LO / GC / HMCC (truth)",
        ],
        rows,
    )
    lines += [
        "Paper: HMCC's filter takes a constant 2 ms, GC's grows with the matches; GC keeps more "
        "matches than HMCC; HMCC-RANSAC is about three times faster than GC-RANSAC on pairs 1, "
        "3 and 4 and as fast on pair 2; LO-RANSAC is 1.4-140 times slower than HMCC-RANSAC.",
        "",
        "**Where we differ, and why.** The shapes agree: HMCC's filter takes a near-constant "
        "fraction of a millisecond, GC's grows with the matches (quadratic) and is the "
        "largest share of GC-RANSAC, and HMCC-RANSAC is the fastest of the three on every "
        "pair. GC keeps about as many matches as HMCC on V-F and more on the others, as in the "
        "paper. The LO-RANSAC / HMCC-RANSAC ratios differ in size: OpenCV's USAC LO-RANSAC "
        "is fast where the inlier ratio is high (V-V) and fails rather than runs long on B-F "
        "(18 true matches of 68: its precision and recall fall), where the paper's took "
        "1.4 s. Absolute times are not comparable (C++ on an i7-4770 against Python around "
        "compiled code on a shared machine).",
        "",
    ]
    return lines


def flight_section(paper: dict[str, Any], core: dict[str, Any] | None) -> list[str]:
    flight = paper["flight"]
    records = flight["records"]
    columns = flight_columns(records)
    o = flight["options"]
    lines = [
        "## Section 4.5.2: a flight (Fig. 17, Tables 4 and 6)",
        "",
        f"**What we ran.** A simulated penta-view flight (the paper's dataset-3 rig: nadir and "
        f"four 45 deg obliques at {o['altitude_m']:.0f} m; {flight['images']} images, "
        f"{flight['pairs']} pairs, outlier ratio {o['outlier_ratio']}), {flight['sample']} "
        "pairs drawn at random, each verified once by every method. The paper verified 4 130 "
        "pairs of its site (Table 4) and 5 169 / 5 842 / 18 283 pairs of three more datasets "
        "(Table 6); we cannot run those images, so we compare shapes and ratios, not seconds.",
        "",
        "![per-pair times](figures/flight.png)",
        "",
    ]
    rows = []
    for stat in ("Max", "Mean", "Stddev", "Sum"):
        ours = []
        for values in columns.values():
            arr = np.asarray([v for v in values if v is not None and math.isfinite(v)])
            ours.append(
                {"Max": arr.max(), "Mean": arr.mean(), "Stddev": arr.std(), "Sum": arr.sum()}[stat]
                if arr.size
                else math.nan
            )
        rows.append(
            [stat]
            + [f"{PAPER_TABLE4[stat][i] * 1e3:.0f} / {_ms(ours[i])}" for i in range(len(ours))]
        )
    lines += _table(["(ms: paper / ours)", *columns.keys()], rows)
    lo = sum(columns["(a) LO-RANSAC"])
    gc = sum(columns["(b) GC filter"]) + sum(columns["(c) RANSAC after GC"])
    hm = sum(columns["(d) HMCC filter"]) + sum(columns["(e) RANSAC after HMCC"])
    pr = {
        m: (
            mean(r["methods"][m]["precision"] for r in records),
            mean(r["methods"][m]["recall"] for r in records),
        )
        for m in ("lo-ransac", "gc-ransac", "hmcc-ransac")
    }
    lines += [
        f"Sums over our sample: LO-RANSAC {lo:.0f} ms, GC-RANSAC {gc:.0f} ms, HMCC-RANSAC "
        f"{hm:.0f} ms: LO / HMCC = x{lo / hm:.2f}, GC / HMCC = x{gc / hm:.2f}. Mean precision / "
        "recall against the truth: "
        + ", ".join(f"{m} {p:.2f} / {r:.2f}" for m, (p, r) in pr.items())
        + ".",
        "",
        "**Table 6 (speed-up of HMCC-RANSAC, like with like).** The paper's x6 is LO-RANSAC's "
        "time over HMCC-RANSAC's on dataset 3:",
        "",
    ]
    rows = [
        [
            name,
            f"{lo_s:.1f}",
            f"{gc_s:.1f}",
            f"{h_s:.1f}",
            f"x{lo_s / h_s:.2f}",
            f"x{gc_s / h_s:.2f}",
        ]
        for name, (lo_s, gc_s, h_s) in PAPER_TABLE6.items()
    ]
    t4 = PAPER_TABLE4["Sum"]
    rows.append(
        [
            "the site of Table 4 (4 130 pairs)",
            f"{t4[0]:.1f}",
            f"{t4[1] + t4[2]:.1f}",
            f"{t4[3] + t4[4]:.1f}",
            f"x{t4[0] / (t4[3] + t4[4]):.2f}",
            f"x{(t4[1] + t4[2]) / (t4[3] + t4[4]):.2f}",
        ]
    )
    rows.append(
        [
            f"ours: {flight['sample']} simulated flight pairs",
            f"{lo / 1e3:.2f}",
            f"{gc / 1e3:.2f}",
            f"{hm / 1e3:.2f}",
            f"x{lo / hm:.2f}",
            f"x{gc / hm:.2f}",
        ]
    )
    lines += _table(
        ["dataset", "LO-RANSAC s", "GC-RANSAC s", "HMCC-RANSAC s", "LO / HMCC", "GC / HMCC"], rows
    )
    lines += [
        f"**Where we differ, and why.** Our LO / HMCC ratio on the flight sample (x{lo / hm:.1f}) "
        "is of the paper's order for oblique data (x6 on dataset 3, x4.5 on Table 4's site); "
        "the core benchmark below shows how it depends on the outlier ratio: below about 0.4 "
        "LO-RANSAC is as fast or faster (the paper's datasets 1-2: x1.0-1.65), at 0.9 in "
        "simulation HMCC's survivors are mostly outliers and its final RANSAC runs long. Our "
        "GC-RANSAC is slower relative to HMCC than the paper's (x2.9-19.7 there): its "
        "quadratic vote (compiled, about 70 ns per pair of matches) meets large flight pairs "
        f"({median(r['matches'] for r in records):.0f} matches median, millions of match "
        "pairs each). Recall against the truth is the price of HMCC-RANSAC's speed (see 4.4).",
        "",
    ]
    if core is not None:
        lines += core_speedups(core)
    return lines


def core_speedups(core: dict[str, Any]) -> list[str]:
    """LO-RANSAC / hmcc-ransac in the core benchmark, per set and ratio (median per pair)."""
    cells = core["robustness"]["cells"]
    ratios = sorted({r for per in cells.values() for r in per}, key=float)
    rows = []
    for set_name, per_ratio in cells.items():
        rows.append(
            [set_name]
            + [
                f"x{per_ratio[r]['methods']['lo-ransac']['speedup_wall']:.2f}"
                if r in per_ratio
                else "-"
                for r in ratios
            ]
        )
    return [
        "In the core benchmark (`benchmarks/results/core.md`, pairs of 200 true matches with "
        "uniform outliers), LO-RANSAC's time over hmcc-ransac's, median per pair:",
        "",
        *_table(["set", *ratios], rows),
    ]


def colmap_section() -> list[str]:
    link = (
        "[the COLMAP benchmark](../benchmarks/results/colmap.md)"
        if COLMAP_REPORT.is_file()
        else "the COLMAP benchmark (`benchmarks/results/colmap.md`, issue 14; not in this "
        "branch yet)"
    )
    return [
        "## Table 5: reconstruction after each verification method",
        "",
        "The paper oriented its 157 images after each method (LO-RANSAC 86 110 points, RMSE "
        "0.552 px; GC-RANSAC 85 491, 0.542 px; HMCC-RANSAC 82 472, 0.545 px: about 5 % fewer "
        f"points at the same accuracy). Our equivalent runs COLMAP on the verified matches: see "
        f"{link}.",
        "",
        *_colmap_table(),
    ]


def _colmap_table() -> list[str]:
    """The COLMAP benchmark's rows that were mapped (its JSON), if it has run."""
    path = COLMAP_REPORT.with_suffix(".json")
    if not path.is_file():
        return []
    doc = json.loads(path.read_text())
    mapped = [r for r in doc["rows"] if r.get("registered") is not None]
    base = next((r for r in mapped if r["row"] == "colmap"), None)
    if base is None:
        return []
    base_err = base["reprojection_error_px"]
    rows = [
        [
            r["row"],
            f"{r['stage_s']:.3f}",
            str(r["registered"]),
            f"{r['points3d']:,}".replace(",", " "),
            f"{r['reprojection_error_px']:.3f}",
            f"{r['track_length']:.2f}",
        ]
        for r in mapped
    ]
    return [
        "The 18 Brighton Beach images (COLMAP's SIFT, exhaustive matching), each method's "
        "verification written into the database, then `pycolmap.incremental_mapping`:",
        "",
        *_table(
            ["verification", "stage s", "registered", "3-D points", "reproj. px", "track"], rows
        ),
        "The paper's HMCC-RANSAC kept about 5 % fewer points than LO-RANSAC at the same "
        "accuracy. Here, against COLMAP's own verification: "
        + "; ".join(
            f"{r['row']} {100 * (r['points3d'] / base['points3d'] - 1):+.1f} % points, "
            f"reprojection error {100 * (r['reprojection_error_px'] / base_err - 1):+.1f} %"
            for r in mapped
            if r is not base
        )
        + ". hmcc-ransac's final seven-point RANSAC at 1 px drops true matches (section 4.4), "
        "hence fewer points with a lower error; the paper's pairs do not show it this strongly.",
        *_against_lo(mapped),
        "",
    ]


def _against_lo(mapped: list[dict[str, Any]]) -> list[str]:
    """The paper's own comparison, against LO-RANSAC, when that row ran."""
    lo = next((r for r in mapped if r["row"] == "lo-ransac"), None)
    if lo is None:
        return []
    others = [r for r in mapped if r["row"] in ("gc-ransac", "hmcc-ransac", "hmcc-plus")]
    return [
        "",
        "Against LO-RANSAC, as the paper compares (its HMCC-RANSAC: -4.2 % points, RMSE -1.3 %): "
        + "; ".join(
            f"{r['row']} {100 * (r['points3d'] / lo['points3d'] - 1):+.1f} % points, "
            f"reprojection error "
            f"{100 * (r['reprojection_error_px'] / lo['reprojection_error_px'] - 1):+.1f} %"
            for r in others
        )
        + ".",
    ]


INTRO = """\
# The paper, reproduced: what we ran beside Jiang & Jiang's section 4

Generated by `python -m benchmarks.paper_report` from `benchmarks/results/paper.json`
(`python -m benchmarks.bench_paper`, {paper_s:.0f} s at commit {commit}) and, for the speed-ups
by outlier ratio, `benchmarks/results/core.json` (`python -m benchmarks.bench_core`). Do not
edit by hand: rerun the two commands.

**Timings come from a shared, noisy 2-core machine** (other benchmarks and test suites ran at
the same time); single timings move by tens of percent between runs, so read ratios within one
run. The paper's are C++ on an i7-4770.

**Pairs.** We do not have the paper's images. Its four pairs (Table 2) are simulated like its
site (section 4.1, Table 1): a site near 0 m flown at 300 m, 7360 x 4912 px, f = 7175 px (35 mm
on 35.9 mm), 64 % forward overlap, nadir and 45 deg obliques, the simulator's urban scene
(15 m relief, buildings 5-30 m on 20 % of the ground), rough POS with GNSS 1.5/3 m and IMU
2/1/1 deg noise, 0.5 px keypoint noise. The real pairs are the 14 Brighton Beach fixtures
(nadir, another site), reduced to their automatic reference inliers (MAGSAC++, not manual).

**The method as run.** `hmcc-ransac` is the paper's three stages with its parameters, then the
paper's classic seven-point RANSAC at 1 px (our own: OpenCV's FM_RANSAC runs LMedS below 15
matches). Two choices are ours, named in the README: the plane and the direction-change
"absolute subtraction" taken on the circle. **The plane**: the paper gives one instance, a
plane at -100 m for a site near 0 m flown at 300 m "to decrease the influence of terrain
relief" (section 4.2), and says in section 5 that its planes were approximated by the sites'
average altitudes. Our rule generalises the instance: Z0 = ground - 1/3 x (flying height above
the ground), which gives the paper's -100 m here; for other flights it is our extrapolation.
**GC-RANSAC** is Lu et al. (2016) as the paper times it: every pair of matches votes
(quadratic), unweighted, k-NN candidate lists through their first candidates
(`worker/hmcc/gc_filter.py` names each choice the papers leave open).
"""


def where_we_differ() -> list[str]:
    return [
        "## Where we differ, and why",
        "",
        "- **Data.** Simulated pairs sized like the paper's, not its images; the simulator's "
        "outliers and its rough-POS noise are models (see `hmcc.simulate`). The real fixtures "
        "are another site, nadir only, with an automatic reference.",
        "- **Outlier injection.** The core benchmark redraws injected outliers that land "
        "within 3 px of their epipolar line so that its truth is exact; the paper does not. "
        "This report runs both; the paper's precision counts such lucky outliers as inliers.",
        "- **Metrics.** The paper's precision and recall are ratios of inlier counts (RANSAC "
        "after HMCC, over HMCC survivors / over total inliers), not checked against a truth; we "
        "report them beside precision and recall against the known true matches.",
        "- **Timings.** Python around OpenCV (C++) and numba on a shared 2-core machine against "
        "the paper's C++ on an i7-4770: absolute times differ, ratios within one run are what "
        "compare. Our LO-RANSAC is OpenCV's USAC (uniform sampling, inner LO), not the paper's "
        "own code; our seven-point RANSAC and GC vote are compiled with numba.",
        "- **Speed-up.** The paper's x6 is LO-RANSAC over HMCC-RANSAC on its dataset 3 (and "
        "x1.0 and x1.65 on datasets 1-2, x4.5 on Table 4's site). Compare our LO / HMCC "
        "ratios above with those, not plain RANSAC's.",
        "- **The plane rule** extrapolates the paper's single instance (see above).",
        "",
    ]


def build(results: Path, docs: Path) -> Path:
    paper = json.loads((results / "paper.json").read_text())
    core_path = results / "core.json"
    core = json.loads(core_path.read_text()) if core_path.is_file() else None
    figures = docs / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    made = motion_figures(paper, figures)
    robustness_figure(paper["robustness"]["cells"], figures / "robustness.png")
    methods_figure(paper["methods"], figures / "methods.png")
    flight_figure(paper["flight"]["records"], figures / "flight.png")
    env = paper["meta"]["environment"]
    lines = [
        INTRO.format(paper_s=paper["meta"]["run_wall_s"], commit=env.get("git_commit")),
        "## Contents",
        "",
        "- Sections 4.2-4.3 (Figs. 7-12), 4.4 (Figs. 13-14), 4.5.1 (Figs. 15-16, Table 3), "
        "4.5.2 (Fig. 17, Tables 4 and 6), Table 5 (COLMAP), where we differ.",
        "",
    ]
    lines += stages_section(paper)
    for name, file in made:
        lines += [
            f"**{name}** (Figs. 7-12: (a) Figs. 7/8/10 in one, (b) Fig. 9, (c) Fig. 11, "
            "(f) Fig. 12):",
            "",
            f"![{name}](figures/{file})",
            "",
        ]
    lines += robustness_section(paper)
    lines += methods_section(paper)
    lines += flight_section(paper, core)
    lines += colmap_section()
    lines += where_we_differ()
    out = docs / "paper-reproduction.md"
    out.write_text("\n".join(lines))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--docs", type=Path, default=DOCS)
    args = parser.parse_args(None if argv is None else [str(a) for a in argv])
    print(f"wrote {build(args.results, args.docs)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
