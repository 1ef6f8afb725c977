"""``hmcc flight``'s fork server started before the command's imports (``flight_args``): when it
is started, that the pool then forks from it, and that a flight verified here after all stops
it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hmcc_cli.flight_args import EARLY_MIN_BYTES, starts_early
from tests.support.flights import small_flight

pytestmark = pytest.mark.procs  # the commands start their child processes


@pytest.fixture
def big(tmp_path: Path) -> str:
    """A file of the size that starts the server early (its content is not read)."""
    path = tmp_path / "big.msgpack"
    with path.open("wb") as f:
        f.truncate(EARLY_MIN_BYTES)
    return str(path)


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["{big}"], True),
        (["{big}", "--processes", "2", "--timings"], True),
        (["-o", "out.jsonl", "--method", "hmcc-plus", "{big}"], True),  # options first
        (["{small}"], False),
        (["{small}", "--in-process-max", "0"], True),  # the pool, whatever the size
        (["{big}", "--url", "http://localhost:1"], False),  # verified by a service
        (["{big}", "--processes", "0"], False),  # verified here
        (["-"], False),  # standard input: no size to go by
        (["{tmp}/missing.json"], False),
        (["{big}", "--processes", "two"], False),  # the real parser says what is wrong
    ],
)
def test_the_server_starts_early_for_a_big_file_verified_on_children(
    tmp_path: Path, big: str, argv: list[str], expected: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    small = tmp_path / "small.json"
    small.write_text("{}")
    names = {"big": big, "small": str(small), "tmp": str(tmp_path)}
    assert starts_early([a.format(**names) for a in argv]) is expected
    assert capsys.readouterr() == ("", "")  # a guess says nothing


# As the ``hmcc`` console script is, a main module with a file: a pool's child runs it again
# with the command line (multiprocessing's spawn.prepare), and must not start a server there.
_MAIN = """
import os, sys
sys.argv = ["hmcc", "flight", os.environ["FLIGHT"], "--processes", "2"]
import hmcc_cli  # starts the server here, before its imports
from hmcc_worker import forking

early = forking.running_pid()

if __name__ == "__main__":
    from hmcc_worker.pool import ComputePool

    pool = ComputePool(2, forked=True)
    try:
        parents = {pool.call(os.getppid) for _ in range(4)}
    finally:
        pool.close()
    print(early, *sorted(parents))
"""


def test_the_pool_forks_its_children_from_the_server_started_early(
    tmp_path: Path, big: str
) -> None:
    script = tmp_path / "main.py"
    script.write_text(_MAIN)
    done = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        env={**os.environ, "FLIGHT": big},
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    early, *parents = done.stdout.split()
    assert early != "None"
    assert parents == [early]  # every child's parent: the server started first


def test_a_big_file_of_few_pairs_is_verified_here_after_all(tmp_path: Path) -> None:
    """A flight file big enough for the early start, with three pairs: verified in the
    command's process, the server stopped on the way (the command ends, its lines all
    there)."""
    flight = small_flight(3)
    flight.pop("truth")
    path, out = tmp_path / "flight.json", tmp_path / "out.jsonl"
    text = json.dumps(flight)
    path.write_text(text + " " * (EARLY_MIN_BYTES - len(text)))  # JSON's own whitespace
    done = subprocess.run(
        [sys.executable, "-m", "hmcc_cli", "flight", str(path), "--processes", "2"]
        + ["-o", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    statuses = [json.loads(line)["status"] for line in out.read_text().splitlines()]
    assert statuses == ["finished"] * 3


_STOP = """
import os
from hmcc_worker import forking

assert forking.start()
pid = forking.running_pid()
forking.stop()  # while it warms up
try:
    os.kill(pid, 0)
except ProcessLookupError:
    print("gone", forking.running_pid())
"""


def test_stopping_the_server_ends_it() -> None:
    done = subprocess.run(
        [sys.executable, "-c", _STOP], capture_output=True, text=True, timeout=120, check=True
    )
    assert done.stdout.split() == ["gone", "None"]


def test_the_server_is_not_started_for_other_commands(tmp_path: Path, big: str) -> None:
    probe = "import sys; sys.argv = sys.argv[1:]; import hmcc_cli; from hmcc_worker import forking"
    probe += "; print(forking.running_pid())"
    for argv in (["hmcc", "verify", big], ["hmcc", "flight", big, "--url", "http://x"]):
        done = subprocess.run(
            [sys.executable, "-c", probe, *argv],
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        )
        assert done.stdout.split() == ["None"], argv
