"""The ``hmcc`` command line: ``verify`` and ``simulate``, run in-process and once as a process.

Contract (cli.py / README): results as JSON on stdout (or a summary table), exit 0; bad input
exits 2 with one ``error: <field>: <reason>`` line per problem on stderr and no traceback.
"""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_cli import main
from hmcc_schema import parse_pair, reference_to_pair
from tests.support.shared_data import BRIGHTON

FIXTURE = BRIGHTON / "pair_DJI_0033_DJI_0034.json"
STAGES = ["projection", "direction", "direction_change", "length", "ransac"]
ERROR_LINE = re.compile(r"^error: [^:\s][^:]*: \S.*$")


def _strict_json(text: str) -> Any:
    """json.loads that rejects NaN/Infinity, which are not JSON."""

    def reject(constant: str) -> None:
        raise ValueError(f"non-JSON constant {constant}")

    return json.loads(text, parse_constant=reject)


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """hmcc.cli.main in-process: (exit code, stdout, stderr)."""
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def verify_json(argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    code, out, err = run(["verify", *argv], capsys)
    assert (code, err) == (0, "")
    return _strict_json(out)


@pytest.fixture(scope="module")
def fixture_doc() -> dict[str, Any]:
    return json.loads(FIXTURE.read_text())


def _errors(err: str) -> list[str]:
    """The stderr lines, each checked to be ``error: <field>: <reason>``, never a traceback."""
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines, "no error message"
    for line in lines:
        assert ERROR_LINE.match(line), line
    return lines


# --------------------------------------------------------------------------- verify


def test_verify_prints_the_result_json(
    fixture_doc: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """Inliers strictly ascending (so unique) indices into the matches; a 3x3 fundamental
    matrix; the five HMCC-RANSAC stages in order, each keeping at most its input and feeding
    the next; timings for every stage plus their total; counts that agree."""
    result = verify_json([str(FIXTURE), "--method", "hmcc-ransac"], capsys)
    n = len(fixture_doc["matches"])
    inliers = result["inliers"]
    assert result["method"] == "hmcc-ransac"
    assert all(isinstance(i, int) for i in inliers)
    assert all(a < b for a, b in zip(inliers, inliers[1:], strict=False))
    assert inliers and 0 <= inliers[0] and inliers[-1] < n
    assert result["model"]["type"] == "fundamental"
    matrix = result["model"]["matrix"]
    assert len(matrix) == 3 and all(len(row) == 3 for row in matrix)
    stages = result["stages"]
    assert [s["name"] for s in stages] == STAGES
    assert stages[0]["input"] == n
    for before, after in zip(stages, stages[1:], strict=False):
        assert 0 <= after["input"] == before["kept"] <= before["input"]
    assert stages[-1]["kept"] == len(inliers)
    timings = result["timings_ms"]
    assert list(timings) == [*STAGES, "total"]
    assert all(t >= 0.0 for t in timings.values())
    assert timings["total"] == pytest.approx(sum(timings[s] for s in STAGES))
    stats = result["statistics"]
    assert (stats["matches"], stats["inliers"]) == (n, len(inliers))
    assert stats["inlier_ratio"] == pytest.approx(len(inliers) / n)
    assert result["stages"][0]["stats"]["ground_z_m"] == pytest.approx(fixture_doc["Z0"])
    assert stats["z0_m"] < fixture_doc["Z0"] - 10.0  # the plane lies below the ground


def test_verify_equals_the_library_result(
    fixture_doc: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """The CLI reads a reference fixture as reference_to_pair does and returns exactly the
    library's inliers and model."""
    expected = parse_pair(reference_to_pair(fixture_doc)).verify(0)
    result = verify_json([str(FIXTURE)], capsys)
    assert result["inliers"] == expected.inliers.tolist()
    assert expected.model_matrix is not None
    assert result["model"]["matrix"] == expected.model_matrix.tolist()


def test_verify_reads_standard_input(
    fixture_doc: dict[str, Any], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``hmcc verify -`` reads the pair from stdin, with the same result as from the file."""
    from_file = verify_json([str(FIXTURE)], capsys)
    monkeypatch.setattr(sys, "stdin", io.StringIO(json.dumps(fixture_doc)))
    from_stdin = verify_json(["-"], capsys)
    assert from_stdin["inliers"] == from_file["inliers"]


def test_summary_prints_a_table_and_precision_recall(
    fixture_doc: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """--summary: a headline, the plane, one row per stage (in, kept as in the JSON) and the
    precision/recall of the inliers against the file's reference inliers."""
    result = verify_json([str(FIXTURE)], capsys)
    code, out, err = run(["verify", str(FIXTURE), "--summary"], capsys)
    assert (code, err) == (0, "")
    lines = out.splitlines()
    n, k = len(fixture_doc["matches"]), len(result["inliers"])
    assert lines[0].startswith(f"method hmcc-plus: {k} of {n} matches are inliers")
    assert lines[1].startswith("plane Z0 = ") and lines[1].endswith("m below the ground)")
    assert lines[2].split() == ["stage", "in", "kept", "ms"]
    n_stages = len(result["stages"])
    for line, stage in zip(lines[3 : 3 + n_stages], result["stages"], strict=True):
        name, n_in, kept, ms = line.split()
        assert (name, int(n_in), int(kept)) == (stage["name"], stage["input"], stage["kept"])
        assert float(ms) >= 0.0
    found, truth = set(result["inliers"]), set(fixture_doc["reference_inliers"])
    precision, recall = len(found & truth) / len(found), len(found & truth) / len(truth)
    last = 3 + n_stages
    assert lines[last] == f"vs ground truth: precision {precision:.3f}, recall {recall:.3f}"
    assert len(lines) == last + 1


def test_method_override_runs_the_bare_estimator(capsys: pytest.CaptureFixture[str]) -> None:
    """--method ransac: one ransac stage on all matches, echoed in method and params."""
    result = verify_json([str(FIXTURE), "--method", "ransac"], capsys)
    assert result["method"] == "ransac"
    assert [s["name"] for s in result["stages"]] == ["ransac"]
    assert result["stages"][0]["input"] == result["statistics"]["matches"]
    assert result["params"]["ransac"]["estimator"] == "ransac"
    assert list(result["timings_ms"]) == ["ransac", "total"]


def test_plane_override_auto_and_metres(
    fixture_doc: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """--plane-z auto estimates Z0 (within 1 m of the file's Z0_pair; measured 0.00 m for
    DJI_0033-0034); --plane-z 150.5 is used as given."""
    auto = verify_json([str(FIXTURE), "--plane-z", "auto"], capsys)
    projection = auto["stages"][0]
    assert projection["stats"]["z0_source"] == "auto"
    ground = auto["stages"][0]["stats"]["ground_z_m"]
    assert ground == pytest.approx(fixture_doc["Z0_pair"], abs=1.0)
    given = verify_json([str(FIXTURE), "--plane-z", "150.5"], capsys)
    assert given["stages"][0]["stats"]["z0_source"] == "given"
    assert given["statistics"]["z0_m"] == 150.5


def test_method_plane_and_seed_together(capsys: pytest.CaptureFixture[str]) -> None:
    """The README's example: --method ransac --plane-z auto --seed 3 runs the bare estimator
    (no projection, so no plane is estimated) with the seed echoed; the same seed gives the
    same result."""
    argv = [str(FIXTURE), "--method", "ransac", "--plane-z", "auto", "--seed", "3"]
    first, second = verify_json(argv, capsys), verify_json(argv, capsys)
    assert first["params"]["seed"] == 3
    assert first["method"] == "ransac" and "z0_m" not in first["statistics"]
    assert first["inliers"] == second["inliers"]
    assert first["model"] == second["model"]


def test_seed_reaches_the_random_estimator(capsys: pytest.CaptureFixture[str]) -> None:
    """--seed is passed to the estimator: lo-ransac (seeded through USAC) repeats its result
    for a seed, and different seeds give different inlier sets on this 630-match pair."""
    runs = [
        verify_json([str(FIXTURE), "--method", "lo-ransac", "--seed", str(seed)], capsys)
        for seed in (0, 0, 1, 2, 3)
    ]
    assert [r["params"]["seed"] for r in runs] == [0, 0, 1, 2, 3]
    assert runs[0]["inliers"] == runs[1]["inliers"]
    assert runs[0]["model"] == runs[1]["model"]
    assert len({tuple(r["inliers"]) for r in runs}) > 1


@pytest.mark.procs
def test_verify_as_a_process() -> None:
    """``python -m hmcc_cli verify <fixture> --summary`` exits 0 and prints the table; a bad
    file exits 2 with the error line and no traceback."""
    ok = subprocess.run(
        [sys.executable, "-m", "hmcc_cli", "verify", str(FIXTURE), "--summary"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("method hmcc-plus: ")  # the default method
    assert "vs ground truth: precision " in ok.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "hmcc_cli", "verify", "-"],
        input='{"image1": {}}',
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2
    assert bad.stdout == ""
    assert "error: matches: Field required" in _errors(bad.stderr)


# --------------------------------------------------------------------------- simulate


def test_simulate_writes_a_pair_that_verify_accepts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``hmcc simulate ... -o file`` writes exactly simulate_pair's pair for the options and
    seed; ``hmcc verify file --summary`` scores it against its ground truth."""
    path = tmp_path / "pair.json"
    argv = ["simulate", "--views", "V", "F", "--n-inliers", "150", "--outlier-ratio", "0.6"]
    code, out, err = run([*argv, "--seed", "4", "-o", str(path)], capsys)
    assert (code, out, err) == (0, "", "")
    written = json.loads(path.read_text())
    options = SimulationOptions(views=("V", "F"), n_inliers=150, outlier_ratio=0.6)
    assert written == json.loads(json.dumps(simulate_pair(options, 4)))
    assert len(written["ground_truth"]["inliers"]) == 150
    assert len(written["matches"]) == 375

    result = verify_json([str(path)], capsys)
    truth = set(written["ground_truth"]["inliers"])
    assert len(set(result["inliers"]) & truth) >= 0.95 * len(result["inliers"])
    code, out, err = run(["verify", str(path), "--summary"], capsys)
    assert (code, err) == (0, "")
    match = re.search(r"vs ground truth: precision (\d\.\d{3}), recall (\d\.\d{3})", out)
    assert match is not None
    assert float(match.group(1)) >= 0.95 and float(match.group(2)) > 0.0


def test_simulate_count_writes_numbered_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--count 3 with --seed 7 writes pair_0007/8/9.json, three different pairs, each the pair
    of its seed; nothing else."""
    argv = ["simulate", "--n-inliers", "50", "--count", "3", "--seed", "7"]
    code, out, err = run([*argv, "-o", str(tmp_path / "pair.json")], capsys)
    assert (code, out, err) == (0, "", "")
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["pair_0007.json", "pair_0008.json", "pair_0009.json"]
    docs = [json.loads((tmp_path / f).read_text()) for f in files]
    assert [d["ground_truth"]["seed"] for d in docs] == [7, 8, 9]
    assert len({json.dumps(d["keypoints1"]) for d in docs}) == 3


def test_simulate_to_stdout_prints_one_json_per_line(capsys: pytest.CaptureFixture[str]) -> None:
    """Without -o, each pair is one line of JSON on stdout."""
    code, out, err = run(["simulate", "--n-inliers", "20", "--count", "2"], capsys)
    assert (code, err) == (0, "")
    lines = out.splitlines()
    assert [json.loads(line)["ground_truth"]["seed"] for line in lines] == [0, 1]


def test_simulate_rejects_bad_options(capsys: pytest.CaptureFixture[str]) -> None:
    """An invalid simulation option exits 2 naming the option."""
    code, out, err = run(["simulate", "--outlier-ratio", "1.5"], capsys)
    assert (code, out) == (2, "")
    assert _errors(err) == ["error: outlier_ratio: must be < 1.0, got 1.5"]


# --------------------------------------------------------------------------- bad input


def _public(doc: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(reference_to_pair(doc)))


def _without(key: str) -> Any:
    def edit(doc: dict[str, Any]) -> str:
        pair = _public(doc)
        del pair[key]
        return json.dumps(pair)

    return edit


def _nan_keypoint(doc: dict[str, Any]) -> str:
    pair = _public(doc)
    pair["keypoints1"][3][0] = float("nan")
    return json.dumps(pair)  # writes the (non-JSON) NaN literal that Python reads back


def _match_out_of_range(doc: dict[str, Any]) -> str:
    pair = _public(doc)
    pair["matches"][5][1] = len(pair["keypoints2"])
    return json.dumps(pair)


def _unknown_method(doc: dict[str, Any]) -> str:
    pair = _public(doc)
    pair["method"] = "best-ransac"
    return json.dumps(pair)


def _not_a_rotation(doc: dict[str, Any]) -> str:
    pair = _public(doc)
    pair["image2"]["pose"]["attitude"]["matrix"][0][0] = 2.0
    return json.dumps(pair)


BAD_INPUTS = [
    pytest.param(lambda doc: "{not json", "", "", id="invalid-json"),
    pytest.param(_without("matches"), "matches", "Field required", id="missing-matches"),
    pytest.param(_without("image1"), "image1", "Field required", id="missing-image1"),
    pytest.param(
        _nan_keypoint, "keypoints1[3][0]", "Input should be a finite number", id="nan-keypoint"
    ),
    pytest.param(
        _match_out_of_range,
        "matches",
        "matches[5][1] = 630 is out of range: keypoints2 has 630 keypoints",
        id="match-index-out-of-range",
    ),
    pytest.param(_unknown_method, "method", "unknown method 'best-ransac'", id="unknown-method"),
    pytest.param(
        _not_a_rotation,
        "image2.pose.attitude.matrix",
        "not a rotation (must be orthonormal with determinant +1)",
        id="not-a-rotation",
    ),
    pytest.param(lambda doc: "[1, 2]", "body", "Input should be a valid dictionary", id="a-list"),
]


@pytest.mark.parametrize(("make", "field", "reason"), BAD_INPUTS)
def test_bad_input_exits_two_with_field_and_reason(
    make: Any,
    field: str,
    reason: str,
    fixture_doc: dict[str, Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Bad input: exit 2, nothing on stdout, ``error: <field>: <reason>`` on stderr (for a
    file that is not JSON, the field is the file name)."""
    path = tmp_path / "bad.json"
    path.write_text(make(fixture_doc))
    code, out, err = run(["verify", str(path)], capsys)
    assert (code, out) == (2, "")
    lines = _errors(err)
    if field:
        assert any(line.startswith(f"error: {field}: {reason}") for line in lines), lines
    else:
        assert lines[0].startswith(f"error: {path}: Expecting property name")


def test_missing_file_exits_two(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A file that does not exist is an error on that path, exit 2."""
    missing = tmp_path / "nope.json"
    code, out, err = run(["verify", str(missing)], capsys)
    assert (code, out) == (2, "")
    assert _errors(err)[0].startswith(f"error: {missing}: [Errno 2]")


def test_a_plane_no_ray_reaches_exits_two(capsys: pytest.CaptureFixture[str]) -> None:
    """--plane-z above the cameras (~198 m): an error on plane.z, exit 2."""
    code, out, err = run(["verify", str(FIXTURE), "--plane-z", "500"], capsys)
    assert (code, out) == (2, "")
    assert _errors(err) == ["error: plane.z: no ray of image1 reaches the plane Z0 = 500 m"]


def test_unknown_method_option_exits_two(capsys: pytest.CaptureFixture[str]) -> None:
    """--method with an unknown name is refused by the argument parser: exit 2, the option
    and the reason named on stderr."""
    with pytest.raises(SystemExit) as exit_info:
        main(["verify", str(FIXTURE), "--method", "best-ransac"])
    out, err = capsys.readouterr()
    assert (exit_info.value.code, out) == (2, "")
    assert "Traceback" not in err
    assert "error: argument --method: invalid choice: 'best-ransac'" in err


def _reference_without_matches(doc: dict[str, Any]) -> str:
    bad = dict(doc)
    del bad["matches"]
    return json.dumps(bad)


BAD_OPTIONS = [
    pytest.param(
        ["--plane-z", "abc"],
        None,
        "plane.z",
        id="plane-z-not-a-number",
    ),
    pytest.param(
        [],
        _reference_without_matches,
        "matches",
        id="reference-file-missing-matches",
    ),
    pytest.param(
        ["--seed", "-1"],
        None,
        "params.seed",
        id="negative-seed",
    ),
    pytest.param(
        ["--method", "lo-ransac", "--seed", str(2**31)],
        None,
        "params.seed",
        id="seed-beyond-c-int",
    ),
]


@pytest.mark.parametrize(("extra", "make", "field"), BAD_OPTIONS)
def test_bad_options_and_reference_files_exit_two(
    extra: list[str],
    make: Any,
    field: str,
    fixture_doc: dict[str, Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Bad options or a broken fixture file are bad input too: exit 2 and an error line
    naming the field, never a traceback."""
    path = FIXTURE
    if make is not None:
        path = tmp_path / "bad.json"
        path.write_text(make(fixture_doc))
    code, out, err = run(["verify", str(path), *extra], capsys)
    assert (code, out) == (2, "")
    assert any(line.startswith(f"error: {field}: ") for line in _errors(err))


def test_help_describes_the_commands_for_a_user(capsys: pytest.CaptureFixture[str]) -> None:
    """``hmcc --help`` tells what the command does and its commands, not the package's
    developer notes (the module docstring)."""
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "package graph" not in text and "imported when" not in text
    assert "Verify the candidate matches" in text
    for command in ("verify", "plot", "simulate", "flight", "colmap", "serve", "worker"):
        assert re.search(rf"^    {command} ", text, re.M), command
