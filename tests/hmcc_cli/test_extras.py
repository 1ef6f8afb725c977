"""A command that needs an optional extra (``plot``: matplotlib, ``colmap``: pycolmap) says how
to install it with a command that exists: the checkout's ``scripts/bootstrap EXTRA`` (the
project is on no package index, so ``pip install 'hmcc-match[plot]'`` would fail)."""

from __future__ import annotations

import importlib.util
import os
import re
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from hmcc_cli import main

ROOT = Path(__file__).resolve().parents[2]
EXTRAS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]


def _without_matplotlib(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec

    def find_spec(name: str, *args: Any, **kw: Any) -> Any:
        return None if name == "matplotlib" else real(name, *args, **kw)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)


def _without_pycolmap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "hmcc_colmap", None)  # its import raises ImportError


def _hint(
    argv: list[str], extra: str, capsys: pytest.CaptureFixture[str], cwd: Path
) -> tuple[Path, str]:
    """Runs ``argv`` without the extra; the bootstrap script its one error line names (as a
    path from ``cwd``) and the line."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    assert "hmcc-match[" not in err, err
    found = re.search(rf"\brun (\S+) {extra}\b", err)
    assert found, err
    return cwd / found.group(1), err


@pytest.mark.parametrize(
    ("command", "extra"), [("plot", "plot"), ("colmap", "colmap"), ("match", "colmap")]
)
@pytest.mark.parametrize("where", ["checkout", "elsewhere"])
def test_the_missing_extra_message_names_a_command_that_exists(
    command: str,
    extra: str,
    where: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cwd = ROOT if where == "checkout" else tmp_path
    monkeypatch.chdir(cwd)
    if extra == "plot":
        _without_matplotlib(monkeypatch)
        argv = ["plot", "pair.json", "-o", str(tmp_path / "x.png")]
    else:
        _without_pycolmap(monkeypatch)
        argv = [command, "db.db"]
    script, err = _hint(argv, extra, capsys, cwd)
    assert script.resolve() == ROOT / "scripts" / "bootstrap"
    assert script.is_file() and os.access(script, os.X_OK)
    assert extra in EXTRAS  # what the script installs: pip install -e ".[EXTRA]"
    assert f"[{extra}]" in (ROOT / "scripts" / "bootstrap").read_text().replace(
        "${extras:+[$extras]}", f"[{extra}]"
    )
    if where == "checkout":
        assert f"run scripts/bootstrap {extra} (or pip install '.[{extra}]')" in err
