"""``hmcc flight``'s parent only reads the flight and hands its pairs to its children: it does
not load numba, SciPy or OpenCV (0.8 CPU-s of a run's serial share), the children do; nor
httpx, which only ``--url`` and ``hmcc loadtest`` use (0.1 s of every command's start)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.flights import small_flight

pytestmark = pytest.mark.procs  # the command starts its child processes

HEAVY = ("numba", "scipy", "cv2")
#: What the parent must not load either way.
WATCHED = (*HEAVY, "httpx")

_PARENT = """
import sys
from hmcc_cli import main
code = main(["flight", sys.argv[1], "--processes", "1", "--in-process-max", sys.argv[2],
             "-o", sys.argv[3]])
print(" ".join(m for m in {watched!r} if m in sys.modules))
sys.exit(code)
"""


def _parent_modules(tmp_path: Path, in_process_max: int) -> tuple[set[str], list[str], float]:
    """Run ``hmcc flight`` on a 3-pair flight in a fresh interpreter: the heavy modules its
    process holds at the end, the status of each pair's line, and the CPU seconds it reports
    for its child processes."""
    flight = small_flight(3)
    flight.pop("truth")
    path, out = tmp_path / "flight.json", tmp_path / "out.jsonl"
    path.write_text(json.dumps(flight))
    script = _PARENT.format(watched=WATCHED)
    done = subprocess.run(
        [sys.executable, "-c", script, str(path), str(in_process_max), str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    statuses = [json.loads(line)["status"] for line in out.read_text().splitlines()]
    children = re.search(r"([\d.]+) s in child processes", done.stderr)
    assert children is not None, done.stderr
    return set(done.stdout.split()), statuses, float(children[1])


def test_the_parent_hands_pairs_to_children_without_loading_the_kernels(tmp_path: Path) -> None:
    loaded, statuses, children_cpu = _parent_modules(tmp_path, in_process_max=0)
    assert statuses == ["finished"] * 3  # the children loaded them and verified every pair
    assert loaded == set()
    # the children, forked from the fork server, are its own: their CPU time is still counted
    assert children_cpu > 0.5


def test_a_flight_verified_in_process_loads_them(tmp_path: Path) -> None:
    loaded, statuses, _ = _parent_modules(tmp_path, in_process_max=100)
    assert statuses == ["finished"] * 3
    assert loaded == set(HEAVY)  # the check above can see them


_BLAS = """
import os, sys
sys.argv = ["hmcc", *sys.argv[1:]]
import hmcc_cli
from threadpoolctl import threadpool_info
blas = [p["num_threads"] for p in threadpool_info() if p["internal_api"] == "openblas"]
print(os.environ.get("OPENBLAS_NUM_THREADS"), *blas)
"""


@pytest.mark.parametrize(
    ("argv", "env", "expected"),
    [
        (["flight", "f.json"], None, "1"),  # its process only moves bytes: one BLAS thread
        (["flight", "f.json"], "3", "3"),  # the user's setting wins
        (["verify", "p.json"], None, None),  # other commands keep OpenBLAS's own choice
    ],
)
def test_hmcc_flight_starts_one_blas_thread(
    argv: list[str], env: str | None, expected: str | None
) -> None:
    environ = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if env is not None:
        environ["OPENBLAS_NUM_THREADS"] = env
    done = subprocess.run(
        [sys.executable, "-c", _BLAS, *argv],
        capture_output=True,
        text=True,
        env=environ,
        timeout=60,
        check=True,
    )
    setting, *threads = done.stdout.split()
    assert setting == str(expected)
    if expected == "1":  # numpy's OpenBLAS started one thread
        assert threads and all(t == "1" for t in threads)
