"""docs/getting-started.md runs as written: every ``sh`` block not marked ``<!-- not run``
runs, in order and in one shell, in an empty folder holding a copy of ``examples/``, with this
environment's ``hmcc`` on the PATH and the service on a free port; the text of each
``<!-- expect: TEXT -->`` after a block must be in that block's output."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.support.procs import BIN, ROOT, free_port, service_env

pytestmark = pytest.mark.procs  # hmcc serve and the compute pool's children

PAGE = ROOT / "docs" / "getting-started.md"
_BLOCK = re.compile(r"```sh\n(.*?)```\n(?:\n<!-- (not run.*?|expect: (.*?)) -->)?", re.DOTALL)


@dataclass(frozen=True)
class Block:
    script: str
    expect: str | None


def runnable_blocks(text: str) -> list[Block]:
    """The page's ``sh`` blocks that run, each with the text its output must hold."""
    return [
        Block(match.group(1), match.group(3))
        for match in _BLOCK.finditer(text)
        if match.group(2) is None or not match.group(2).startswith("not run")
    ]


def test_the_page_has_runnable_blocks_with_expectations() -> None:
    blocks = runnable_blocks(PAGE.read_text())
    assert len(blocks) >= 4
    assert all(block.expect for block in blocks)


def test_getting_started_runs_as_written(tmp_path: Path) -> None:
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    port = free_port()
    env = service_env(HMCC_PORT=str(port), PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}")
    env["HMCC_EMBEDDED_WORKERS"] = "1"
    blocks = runnable_blocks(PAGE.read_text())
    marker = "@@hmcc-docs-block@@"
    script = "set -euo pipefail\n" + "".join(
        block.script.replace("127.0.0.1:8000", f"127.0.0.1:{port}") + f"echo {marker}\n"
        for block in blocks
    )
    shell = subprocess.Popen(
        ["bash", "-c", script],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        output, _ = shell.communicate(timeout=120)
    finally:
        try:
            os.killpg(shell.pid, signal.SIGTERM)  # the service the page started
        except ProcessLookupError:
            pass
    outputs = output.split(marker)
    assert shell.returncode == 0, f"a block failed:\n{output}"
    assert len(outputs) == len(blocks) + 1
    for block, out in zip(blocks, outputs, strict=False):
        assert block.expect is not None and block.expect in out, (
            f"{block.script}\nprinted:\n{out}\nwithout {block.expect!r}"
        )
