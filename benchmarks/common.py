"""What the benchmark scripts share: timing loops, clean pairs with injected outliers, summary
statistics, Markdown tables and the run's environment.

Run the scripts as modules from the checkout's root (``python -m benchmarks.bench_core``), so
they import this module and the tests' process helpers (``tests.support.procs``) as packages.
"""

from __future__ import annotations

import ast
import gc
import hashlib
import json
import math
import os
import platform
import re
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import scipy

import hmcc
from hmcc import PairData, Verification, verify
from hmcc.projection import triangulate_midpoints, world_rays
from hmcc.ransac import sampson_distance
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair, reference_to_pair

T = TypeVar("T")


REPO = Path(__file__).resolve().parents[1]


DEFAULT_OUT = REPO / "benchmarks" / "results"


DEFAULT_FIXTURES = REPO.parent / "shared" / "fixtures" / "brighton-beach"


#: The paper's four pairs (Table 2): nadir-nadir, nadir-front, back-front, left-front.
SIM_GEOMETRIES: tuple[tuple[str, str], ...] = (("V", "V"), ("V", "F"), ("B", "F"), ("L", "F"))


OUTLIER_SIZE_PX = (2.0, 20.0)  # uniform keypoint size of an injected outlier (the simulator's)


OUTLIER_MIN_EPIPOLAR_PX = 3.0  # injected outliers closer than this to the true geometry: redrawn


MAX_REDRAW_ROUNDS = 50


@dataclass
class Timing:
    """Samples of one (pair, method): wall and stage-sum times (ms), per-stage times (ms)."""

    wall_ms: list[float] = field(default_factory=list)
    stage_sum_ms: list[float] = field(default_factory=list)
    stage_ms: dict[str, list[float]] = field(default_factory=dict)

    def add(self, wall_ms: float, result: Verification) -> None:
        """Record one call."""
        self.wall_ms.append(wall_ms)
        timings = result.timings_ms
        self.stage_sum_ms.append(timings["total"])
        for name, ms in timings.items():
            if name != "total":
                self.stage_ms.setdefault(name, []).append(ms)

    def summary(self) -> dict[str, Any]:
        """Medians and the number of samples."""
        return {
            "samples": len(self.wall_ms),
            "wall_ms": median(self.wall_ms),
            "stage_sum_ms": median(self.stage_sum_ms),
            "stage_ms": {name: median(v) for name, v in self.stage_ms.items()},
        }


def median(values: Iterable[float]) -> float:
    """Median of the finite values, NaN when there are none."""
    arr = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    return float(np.median(arr)) if arr.size else math.nan


def mean(values: Iterable[float]) -> float:
    """Mean of the finite values, NaN when there are none."""
    arr = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    return float(np.mean(arr)) if arr.size else math.nan


def time_calls(
    call: Callable[[], T], repeats: int, budget_s: float
) -> tuple[T, list[tuple[float, T]]]:
    """Warm up once, then time up to ``repeats`` calls of ``call()``: the warm-up's result and
    the (ms, result) of each timed call.

    Repeating stops early once the calls (warm-up included) have taken ``budget_s``; a call
    whose warm-up alone exceeds the budget is timed by that single call.
    """
    samples: list[tuple[float, T]] = []
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        t0 = time.perf_counter()
        result = call()
        first_ms = (time.perf_counter() - t0) * 1e3
        spent_s = first_ms / 1e3
        if spent_s >= budget_s:
            return result, [(first_ms, result)]
        while len(samples) < repeats and (not samples or spent_s < budget_s):
            t0 = time.perf_counter()
            again = call()
            ms = (time.perf_counter() - t0) * 1e3
            samples.append((ms, again))
            spent_s += ms / 1e3
    finally:
        if was_enabled:
            gc.enable()
    return result, samples


def time_verify(
    pair: PairData, method: str, repeats: int, budget_s: float
) -> tuple[Verification, Timing]:
    """:func:`time_calls` of ``verify(pair, method)``, with per-stage timings."""
    result, samples = time_calls(lambda: verify(pair, method), repeats, budget_s)
    timing = Timing()
    for ms, again in samples:
        timing.add(ms, again)
    return result, timing


def warm_up_opencv() -> None:
    """Run every method a few times on a small pair so that first-call costs are paid."""
    pair = parse_pair(
        simulate_pair(SimulationOptions(n_inliers=100, outlier_ratio=0.5), 12345)
    ).pair_data(0)
    for _ in range(3):
        for method in hmcc.METHODS:
            verify(pair, method)


@dataclass(frozen=True)
class BenchPair:
    """One contaminated pair of the robustness protocol."""

    set_name: str
    geometry: str
    source: str
    seed: int
    ratio: float
    data: PairData
    truth: np.ndarray  # sorted indices of the true matches

    @property
    def n_matches(self) -> int:
        return len(self.data.matches)


@dataclass(frozen=True)
class CleanPair:
    """A pair with only true matches, and the geometry that rejects consistent outliers."""

    set_name: str
    geometry: str
    source: str
    seed: int
    doc: dict[str, Any]  # public pair dict whose matches are all true
    fundamental: np.ndarray  # (3, 3), x2^T F x1 = 0 in pixels


def skew(t: np.ndarray) -> np.ndarray:
    """Cross-product matrix of a 3-vector."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def fundamental_from_true_poses(doc: dict[str, Any]) -> np.ndarray:
    """F of a simulated pair from its true poses (``x_cam = R (X - C)``) and intrinsics."""
    ks = []
    for key in ("image1", "image2"):
        cam = doc[key]["camera"]
        ks.append(np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0, 0, 1]]))
    p1, p2 = doc["ground_truth"]["true_poses"]
    r1, c1 = np.asarray(p1["R_world_to_cam"]), np.asarray(p1["center"])
    r2, c2 = np.asarray(p2["R_world_to_cam"]), np.asarray(p2["center"])
    essential = skew(r2 @ (c1 - c2)) @ r2 @ r1.T
    return np.linalg.inv(ks[1]).T @ essential @ np.linalg.inv(ks[0])


def epipolar_min_distance(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,) smaller of the two point-to-epipolar-line distances (px) of (N, 2) pixel pairs."""
    h1 = np.column_stack((p1, np.ones(len(p1))))
    h2 = np.column_stack((p2, np.ones(len(p2))))
    lines2 = h1 @ f.T
    lines1 = h2 @ f
    residual = np.abs(np.einsum("ij,ij->i", h2, lines2))
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = residual / np.hypot(lines2[:, 0], lines2[:, 1])
        d1 = residual / np.hypot(lines1[:, 0], lines1[:, 1])
    return np.fmin(d1, d2)


def simulated_clean_pair(views: tuple[str, str], n_inliers: int, seed: int) -> CleanPair:
    """A simulated pair without outliers (the simulator's defaults otherwise)."""
    options = SimulationOptions(views=views, n_inliers=n_inliers, outlier_ratio=0.0)  # type: ignore[arg-type]
    doc = simulate_pair(options, seed)
    geometry = "-".join(views)
    return CleanPair(
        f"sim {geometry}", geometry, f"seed {seed}", seed, doc, fundamental_from_true_poses(doc)
    )


def fixture_clean_pair(path: Path, index: int, audit: bool = False) -> CleanPair:
    """A real fixture reduced to its reference inliers (non-reference matches dropped). With
    ``audit``, also without :func:`impossible_matches`, and F refitted (8-point) on the rest
    when there were any: the reference F was fitted with them."""
    raw = json.loads(path.read_text())
    doc = reference_to_pair(raw)
    reference = np.asarray(sorted(doc["ground_truth"]["inliers"]), dtype=np.int64)
    f = np.asarray(raw["reference"]["F"], dtype=np.float64)
    if audit:
        data = parse_pair(doc).pair_data(0)
        reference, dropped = audited_reference(data, reference)
        if len(dropped):
            f = refitted_model(data, reference)
    doc["matches"] = [doc["matches"][i] for i in reference]
    doc["ground_truth"] = {"inliers": list(range(len(reference))), "pair": path.stem}
    return CleanPair("real", raw["pair_kind"], path.stem.removeprefix("pair_"), index, doc, f)


def impossible_matches(data: PairData, rows: np.ndarray) -> np.ndarray:
    """Of the matches ``rows``, those that cannot be true under the pair's rough POS: their two
    rays meet (closest approach) behind a camera or above both cameras.

    The fixtures' reference inliers are one MAGSAC++ draw at 1 px, with no POS. On the 14
    Brighton Beach pairs 15 of them (5 of DJI_0021-0023's 32) fit the reference F but meet
    above the drone or behind it, where the scene 40 m below cannot be; every one of the 15 is
    a visibly different patch in the two images (``benchmarks/results/reference_audit.jpg``).
    Attitude errors of a few degrees move the meeting point by metres at this range, not by the
    40+ m that would make them possible."""
    rows = np.asarray(rows, dtype=np.int64)
    px1, px2 = data.matched_pixels()
    d1 = world_rays(data.camera1, data.pose1, px1[rows])
    d2 = world_rays(data.camera2, data.pose2, px2[rows])
    points, in_front = triangulate_midpoints(data.pose1.center, d1, data.pose2.center, d2)
    bad = ~in_front | (points[:, 2] >= min(data.pose1.center[2], data.pose2.center[2]))
    return rows[bad]


def audited_reference(data: PairData, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(kept, dropped): a real pair's reference inliers without :func:`impossible_matches`."""
    dropped = impossible_matches(data, truth)
    return np.setdiff1d(truth, dropped), dropped


def refitted_model(data: PairData, truth: np.ndarray) -> np.ndarray:
    """F fitted (8-point) on the ``truth`` of a real pair: its reference's model once the
    audit dropped matches it was fitted with."""
    p1, p2 = (p[truth] for p in data.matched_pixels())
    fit = cv2.findFundamentalMat(p1, p2, cv2.FM_8POINT)[0]
    return np.asarray(fit[:3], dtype=np.float64)


def undecided_matches(
    data: PairData, truth: np.ndarray, f: np.ndarray, threshold_px: float
) -> np.ndarray:
    """Of a real pair's matches outside its (audited) reference ``truth``, those within
    ``threshold_px`` of the reference's model ``f`` (Sampson) whose rays meet where the scene
    can be (not :func:`impossible_matches`).

    The reference is one MAGSAC++ draw at 1 px; a method at 1.5 px (hmcc-plus) also keeps
    matches 1-1.5 px off that model, and the reference says nothing about them: of
    DJI_0024-0035's 23, the 12 looked at by eye are the same patch in both images. They are
    scored as neither true nor false (left out of every method's precision)."""
    px1, px2 = data.matched_pixels()
    outside = np.setdiff1d(np.arange(len(px1)), truth)
    near = outside[sampson_distance(f, px1[outside], px2[outside]) < threshold_px]
    return np.setdiff1d(near, impossible_matches(data, near))


def contaminate(
    clean: CleanPair, ratio: float, draw: int, redraw_near_epipolar: bool = True
) -> BenchPair:
    """Append uniform random outliers to reach ``ratio`` and shuffle the matches (seeded).

    An outlier is a new keypoint in each image, uniform inside the image with a random size
    (uniform 2-20 px) and angle. With ``redraw_near_epipolar`` (our protocol) one lying within
    3 px of its epipolar line under the true (or reference) geometry is redrawn, as the
    simulator does, so that no outlier is consistent; without it (the paper's section 4.4,
    "adding random point pairs") every random pair stays, and a few of them fit the geometry.
    """
    doc = clean.doc
    n_in = len(doc["matches"])
    n_out = int(round(n_in * ratio / (1.0 - ratio)))
    rng = np.random.default_rng([clean.seed, draw, int(round(ratio * 1000)), n_in])
    sizes = [(doc[k]["camera"]["width"], doc[k]["camera"]["height"]) for k in ("image1", "image2")]
    hi1 = (sizes[0][0] - 1.0, sizes[0][1] - 1.0)
    hi2 = (sizes[1][0] - 1.0, sizes[1][1] - 1.0)
    p1 = rng.uniform((0.0, 0.0), hi1, size=(n_out, 2))
    p2 = rng.uniform((0.0, 0.0), hi2, size=(n_out, 2))
    for _ in range(MAX_REDRAW_ROUNDS if redraw_near_epipolar else 0):
        bad = np.flatnonzero(
            epipolar_min_distance(clean.fundamental, p1, p2) < OUTLIER_MIN_EPIPOLAR_PX
        )
        if not len(bad):
            break
        p1[bad] = rng.uniform((0.0, 0.0), hi1, size=(len(bad), 2))
        p2[bad] = rng.uniform((0.0, 0.0), hi2, size=(len(bad), 2))
    kp1 = np.asarray(doc["keypoints1"], dtype=np.float64)
    kp2 = np.asarray(doc["keypoints2"], dtype=np.float64)
    new1 = np.column_stack(
        (p1, rng.uniform(*OUTLIER_SIZE_PX, n_out), rng.uniform(0.0, 360.0, n_out))
    )
    new2 = np.column_stack(
        (p2, rng.uniform(*OUTLIER_SIZE_PX, n_out), rng.uniform(0.0, 360.0, n_out))
    )
    outliers = np.column_stack((len(kp1) + np.arange(n_out), len(kp2) + np.arange(n_out))).astype(
        np.int64
    )
    matches = np.concatenate((np.asarray(doc["matches"], dtype=np.int64), outliers))
    order = rng.permutation(len(matches))
    contaminated = dict(doc)
    contaminated.update(
        {
            "keypoints1": np.concatenate((kp1, new1)).tolist(),
            "keypoints2": np.concatenate((kp2, new2)).tolist(),
            "matches": matches[order].tolist(),
            "ground_truth": None,
        }
    )
    truth = np.flatnonzero(order < n_in)
    data = parse_pair(contaminated).pair_data(0)
    return BenchPair(clean.set_name, clean.geometry, clean.source, draw, ratio, data, truth)


def precision_recall(
    found: np.ndarray, truth: np.ndarray, undecided: np.ndarray | None = None
) -> dict[str, Any]:
    """Precision (NaN for an empty output) and recall of ``found`` against ``truth``; the
    ``undecided`` matches (neither true nor false, see :func:`undecided_matches`) are left out
    of the precision (``kept`` counts them, ``undecided_kept`` says how many)."""
    tp = int(np.isin(found, truth).sum())
    out: dict[str, Any] = {"kept": len(found), "true_positives": tp}
    judged = len(found)
    if undecided is not None and len(undecided):
        out["undecided_kept"] = int(np.isin(found, undecided).sum())
        judged -= out["undecided_kept"]
    out["precision"] = tp / judged if judged else math.nan
    out["recall"] = tp / len(truth) if len(truth) else math.nan
    return out


def paper_precision_recall(final_kept: int, filter_kept: int, n_true: int) -> dict[str, float]:
    """The paper's section 4.4 metrics of a filter + RANSAC pipeline: precision = RANSAC
    inliers / filter survivors ("the ratio of the numbers of inliers, which are generated from
    the RANSAC method and the HMCC algorithm"), recall = RANSAC inliers / total inliers. They
    count inliers, not true ones (NaN when the filter kept nothing)."""
    return {
        "paper_precision": final_kept / filter_kept if filter_kept else math.nan,
        "paper_recall": final_kept / n_true if n_true else math.nan,
    }


def group_by(records: list[dict[str, Any]], *keys: str) -> dict[tuple[Any, ...], list[dict]]:
    """Records grouped by the values of ``keys``, in first-seen order."""
    groups: dict[tuple[Any, ...], list[dict]] = {}
    for r in records:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    return groups


def verdict(ok: bool | None) -> str:
    """met / not met / n/a."""
    return "n/a" if ok is None else ("met" if ok else "not met")


@dataclass
class Table:
    """A titled table that renders as fixed-width text and as markdown."""

    title: str
    headers: list[str]
    rows: list[list[str]]
    note: str = ""
    left: int = 0  # the first ``left`` columns are text, aligned left

    def text(self) -> str:
        widths = [max(len(h), *(len(r[i]) for r in self.rows)) for i, h in enumerate(self.headers)]

        def line(cells: Sequence[str]) -> str:
            return "  ".join(
                c.ljust(w) if i < self.left else c.rjust(w)
                for i, (c, w) in enumerate(zip(cells, widths, strict=True))
            ).rstrip()

        out = [self.title, line(self.headers), line(["-" * w for w in widths])]
        out += [line(r) for r in self.rows]
        if self.note:
            out.append(self.note)
        return "\n".join(out)

    def markdown(self) -> str:
        out = [f"**{self.title}**", "", "| " + " | ".join(self.headers) + " |"]
        out.append(
            "|"
            + "|".join(":---" if i < self.left else "---:" for i in range(len(self.headers)))
            + "|"
        )
        out += ["| " + " | ".join(r) + " |" for r in self.rows]
        if self.note:
            out += ["", self.note]
        return "\n".join(out)


def fmt(value: float | None, digits: int = 2) -> str:
    """Number or '-' for a missing value."""
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f}"


def fmt_ms(value: float) -> str:
    """Milliseconds with a precision that suits their size."""
    if not math.isfinite(value):
        return "-"
    return f"{value:.3f}" if value < 10 else (f"{value:.1f}" if value < 1000 else f"{value:.0f}")


def git_output(*args: str) -> str:
    """Output of a read-only git command in the repository, '' when git is unavailable."""
    try:
        return subprocess.run(
            ["git", "-C", str(REPO), *args],
            capture_output=True,
            text=True,
            check=False,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def package_fingerprint() -> str:
    """Short SHA-256 of the imported hmcc package's source files (identifies uncommitted code)."""
    digest = hashlib.sha256()
    for path in sorted(Path(hmcc.__file__).parent.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


# What a benchmark's numbers depend on: the project's modules its own files import, directly or
# through others (``_imported_modules``); and, for a benchmark that starts the project's own
# processes (``hmcc serve``, ``hmcc worker``, ``python -m hmcc_cli``: what runs there is not
# what its files import), every module of these roots (``benchmarks.pages`` compares the hash).
CODE_ROOTS = ("worker", "service", "client")
# How a benchmark's own files start the project's processes.
_STARTS_PROCESSES = re.compile(
    r"^\s*(from|import) tests\.support\.procs\b|[\"']-m[\"'],\s*[\"']hmcc_cli[\"']", re.M
)


def _imported_siblings(script: Path) -> list[Path]:
    """The modules of ``benchmarks/`` that ``script`` imports (``from .x import ...``)."""
    names: set[str] = set()
    for line in script.read_text().splitlines():
        if not line.startswith("from ."):
            continue
        module, _, imported = line[len("from .") :].partition(" import ")
        if module.strip():
            names.add(module.strip())
        else:
            names.update(part.split(" as ")[0].strip(" (),#") for part in imported.split(","))
    return [script.parent / f"{name}.py" for name in sorted(names) if name]


def _project_modules() -> dict[str, Path]:
    """Every module of the code roots by dotted name (a package by its ``__init__.py``)."""
    modules: dict[str, Path] = {}
    for root in CODE_ROOTS:
        base = REPO / root
        for path in base.rglob("*.py"):
            parts = path.relative_to(base).with_suffix("").parts
            if "__pycache__" in parts or not (base / parts[0] / "__init__.py").is_file():
                continue
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _named_modules(path: Path, package: str, modules: dict[str, Path]) -> set[str]:
    """The project's modules that the source file ``path`` (of ``package``) names: its imports
    (anywhere in the file, relative ones resolved; ``from x import y`` names ``x.y`` too when
    that is a module) and string constants that are a module's dotted name (a fork server's
    preload). A file that imports by computed name (``importlib.import_module``) names every
    module of its package."""
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, *([base] if base else [])])
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            names.add(node.value)
        elif isinstance(node, ast.Attribute) and node.attr in {"import_module", "__import__"}:
            names.update(m for m in modules if m.startswith(f"{package}."))
    found: set[str] = set()
    for name in names:
        parts = name.split(".")
        # the module and every package above it (importing one runs their __init__)
        found.update(".".join(parts[:k]) for k in range(1, len(parts) + 1))
    return found & modules.keys()


def _imported_modules(files: Iterable[Path]) -> set[Path]:
    """The project's source files that ``files`` import, directly or through one another."""
    modules = _project_modules()
    package_of = {
        path: name if path.name == "__init__.py" else name.rpartition(".")[0]
        for name, path in modules.items()
    }
    todo = [(path, "") for path in files]
    seen: set[Path] = set()
    while todo:
        path, package = todo.pop()
        for name in _named_modules(path, package, modules):
            if modules[name] not in seen:
                seen.add(modules[name])
                todo.append((modules[name], package_of[modules[name]]))
    return seen


def code_files(script: str | Path) -> list[Path]:
    """The source files a benchmark measures: the script, the ``benchmarks`` modules it imports
    and the project's modules these import, directly or through others; every ``.py`` of
    ``worker/``, ``service/`` and ``client/`` instead when they start the project's own
    processes. Sorted by path."""
    script = Path(script).resolve()
    own = [script, *(path for path in _imported_siblings(script) if path.is_file())]
    if any(_STARTS_PROCESSES.search(path.read_text()) for path in own):
        paths = set(_project_modules().values())
    else:
        paths = _imported_modules(own)
    paths.update(own)
    return sorted(paths, key=lambda path: path.relative_to(REPO).as_posix())


def code_hash(script: str | Path) -> str:
    """Short SHA-256 of :func:`code_files` (their paths relative to the checkout and their code,
    :func:`_code`), the same in every clone of the same tree: a results file records it as
    ``code_hash``, and ``python -m benchmarks.pages`` marks a page stale when today's tree
    hashes otherwise."""
    digest = hashlib.sha256()
    for path in code_files(script):
        digest.update(path.relative_to(REPO).as_posix().encode() + b"\0")
        digest.update(_code(path) + b"\0")
    return digest.hexdigest()[:16]


def _code(path: Path) -> bytes:
    """What of a source file can change a measurement: its syntax tree without docstrings
    (comments, docstrings and layout leave it as it is); a file that does not parse, its
    bytes."""
    source = path.read_bytes()
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        return source
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree).encode()


def with_code_hash(doc: dict[str, Any], script: str | Path) -> dict[str, Any]:
    """``doc`` with ``code_hash`` of the benchmark ``script`` (its ``__file__``) added: every
    benchmark writes its results JSON through this."""
    return {**doc, "code_hash": code_hash(script)}


def environment() -> dict[str, Any]:
    """Versions, threads and machine of this run, and the state of the package's source."""
    commit = git_output("rev-parse", "--short", "HEAD")
    dirty = git_output("status", "--porcelain", "--", "worker").splitlines()
    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "hmcc": hmcc.__version__,
        "git_commit": commit or None,
        "package_uncommitted": [line.split(maxsplit=1)[-1] for line in dirty],
        "package_source_sha256": package_fingerprint(),
        "load_average_at_start": list(os.getloadavg()),
        "timer": "time.perf_counter",
        "gc_during_timing": "disabled",
    }


def jsonable(value: Any) -> Any:
    """Numpy scalars/arrays to Python, NaN/inf to None, tuple keys to strings."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return float(f"{value:.6g}") if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def section(title: str, run: Callable[[], Any]) -> Any:
    """Run one section, printing its title and duration."""
    print(f"[{title}]", flush=True)
    t0 = time.perf_counter()
    value = run()
    print(f"  done in {time.perf_counter() - t0:.1f} s", flush=True)
    return value
