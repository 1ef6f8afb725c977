"""The files the commands write (``simulate -o``, ``plot -o``, ``flight -o``, ``colmap
--report``): missing folders are made; a path that cannot be written is refused before any work
with exit 2 and one line naming the option, never a traceback after the work."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_cli import main
from hmcc_cli.outputs import OutputPathError, prepare_output
from tests.hmcc_colmap.dbs import db_from_pairs, digest, pose_file, sim_pair
from tests.support.flights import small_flight


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str], option: str, reason: str) -> None:
    """Exit 2 and one line ``error: <option>: <path>: <reason>``."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"error: {option}: ") and reason in err, err


def _unwritable(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    """``folder`` reads as not writable (tests run as root too, where chmod would not do)."""
    real = os.access

    def access(path: str | os.PathLike[str], mode: int, **kw: object) -> bool:
        if Path(path).resolve() == folder.resolve() and mode & os.W_OK:
            return False
        return real(path, mode, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "access", access)


# -- the shared helper --------------------------------------------------------------------------


def test_missing_folders_are_made(tmp_path: Path) -> None:
    path = prepare_output(tmp_path / "a" / "b" / "out.json", "--output")
    assert path.parent.is_dir() and not path.exists()


def test_an_existing_file_is_writable(tmp_path: Path) -> None:
    (tmp_path / "out.json").write_text("old")
    assert prepare_output(str(tmp_path / "out.json"), "-o") == tmp_path / "out.json"


def test_a_folder_a_path_below_a_file_and_an_unwritable_folder_are_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(OutputPathError, match=r"^--output: .*: is a folder"):
        prepare_output(tmp_path, "--output")
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputPathError, match=r"file is a file, not a folder$") as e:
        prepare_output(tmp_path / "file" / "sub" / "out.json", "--report")
    assert e.value.option == "--report"
    assert not (tmp_path / "file" / "sub").exists()
    _unwritable(monkeypatch, tmp_path)
    with pytest.raises(OutputPathError, match="is not writable"):
        prepare_output(tmp_path / "new" / "out.json", "-o")
    assert not (tmp_path / "new").exists()


# -- each command -------------------------------------------------------------------------------


def test_simulate_count_into_a_missing_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The README's ``hmcc simulate --count 10 -o sims/pair.json``, from a fresh folder."""
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--count", "3", "--n-inliers", "40", "-o", "sims/pair.json"]) == 0
    assert sorted(p.name for p in (tmp_path / "sims").iterdir()) == [
        "pair_0000.json",
        "pair_0001.json",
        "pair_0002.json",
    ]
    assert main(["simulate", "--n-inliers", "40", "-o", "one/more/pair.json"]) == 0
    assert json.loads((tmp_path / "one/more/pair.json").read_text())["matches"]


def test_simulate_refuses_a_folder_or_a_file_as_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _refused(["simulate", "-o", str(tmp_path)], capsys, "--output", "is a folder")
    (tmp_path / "sims").write_text("")
    argv = ["simulate", "--count", "2", "-o", str(tmp_path / "sims" / "pair.json")]
    _refused(argv, capsys, "--output", "is a file, not a folder")


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    doc = simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.5), 3)
    path = tmp_path_factory.mktemp("outputs") / "pair.json"
    path.write_text(json.dumps(doc))
    return path


def test_plot_into_a_missing_folder(pair_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "figures" / "motions.png"
    assert main(["plot", str(pair_file), "-o", str(out)]) == 0
    assert out.read_bytes().startswith(b"\x89PNG")


def test_plot_refuses_an_unwritable_folder_before_verifying(
    pair_file: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import hmcc_cli

    def never(*_: object, **__: object) -> None:
        raise AssertionError("verified before the output was checked")

    monkeypatch.setattr(hmcc_cli, "_run_pair", never)
    _unwritable(monkeypatch, tmp_path)
    _refused(["plot", str(pair_file), "-o", str(tmp_path / "x.png")], capsys, "--output", "not")
    _refused(["plot", str(pair_file), "-o", str(tmp_path)], capsys, "--output", "is a folder")


def test_flight_refuses_its_output_before_reading_the_flight(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "taken").write_text("")
    argv = ["flight", str(tmp_path / "no-such-flight.json"), "-o", str(tmp_path / "taken/x")]
    _refused(argv, capsys, "--output", "is a file, not a folder")


@pytest.mark.procs  # the command starts its child processes
def test_flight_into_a_missing_folder_counts_one_pair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flight = small_flight(1)
    flight.pop("truth")
    path = tmp_path / "flight.json"
    path.write_text(json.dumps(flight))
    out = tmp_path / "results" / "today" / "out.jsonl"
    assert main(["flight", str(path), "--processes", "1", "-o", str(out)]) == 0
    assert [json.loads(line)["status"] for line in out.read_text().splitlines()] == ["finished"]
    assert "1 pair in " in capsys.readouterr().err


@pytest.fixture
def matched(tmp_path: Path) -> tuple[Path, Path]:
    """A COLMAP database of one matched pair, and its pose file."""
    pair = sim_pair(1)
    db = tmp_path / "db.db"
    db_from_pairs(db, [pair])
    return db, pose_file(tmp_path / "poses.json", [pair])


def _colmap(db: Path, poses: Path, report: Path) -> list[str]:
    return ["colmap", str(db), "--poses", str(poses), "--processes", "0", "--report", str(report)]


def test_colmap_report_into_a_missing_folder(
    matched: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "reports" / "run1" / "report.json"
    assert main(_colmap(*matched, report)) == 0
    assert json.loads(report.read_text())["totals"]["verified"] == 1
    assert "verified 1 pair (" in capsys.readouterr().out


def test_colmap_refuses_its_report_before_writing_the_database(
    matched: tuple[Path, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    db, poses = matched
    before = digest(db)
    (tmp_path / "notes").write_text("")
    _refused(_colmap(db, poses, tmp_path / "notes" / "r.json"), capsys, "--report", "is a file")
    _refused(_colmap(db, poses, tmp_path), capsys, "--report", "is a folder")
    _unwritable(monkeypatch, tmp_path / "locked")
    (tmp_path / "locked").mkdir()
    _refused(_colmap(db, poses, tmp_path / "locked" / "r.json"), capsys, "--report", "writable")
    assert digest(db) == before
