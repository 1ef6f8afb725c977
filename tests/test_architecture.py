"""The packages' import rules (ARCHITECTURE.md): each may import only those below it, and the
core nothing of ours nor any service library. The rules are read from the source (``ast``),
so a lazy import inside a function counts too."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: package -> where it lives, the project packages it may import, other libraries it may import
RULES: dict[str, tuple[str, set[str], set[str] | None]] = {
    "hmcc": ("worker", set(), {"numpy", "scipy", "cv2", "numba", "pymap3d", "annotated_types"}),
    # the client installs on its own (client/pyproject.toml): HTTP and body encoding only;
    # orjson only where it is installed (a faster reader; json otherwise)
    "hmcc_client": ("client", set(), {"httpx", "msgpack", "numpy", "orjson"}),
    "hmcc_schema": ("worker", {"hmcc"}, None),
    "hmcc_worker": ("worker", {"hmcc", "hmcc_schema"}, None),
    "hmcc_service": ("service", {"hmcc", "hmcc_schema", "hmcc_worker", "hmcc_client"}, None),
    "hmcc_colmap": (
        "service",
        {"hmcc", "hmcc_schema", "hmcc_worker", "hmcc_client", "hmcc_service"},
        None,
    ),
    "hmcc_cli": (
        "service",
        {"hmcc", "hmcc_schema", "hmcc_worker", "hmcc_client", "hmcc_service", "hmcc_colmap"},
        None,
    ),
}
OURS = set(RULES)


def imported_modules(source: str) -> set[str]:
    """Top-level names of the absolute imports in ``source``."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names |= {alias.name.partition(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.partition(".")[0])
    return names


def violations(package: str, source: str) -> set[str]:
    """What ``source`` (a module of ``package``) imports against the rules."""
    _, allowed_ours, allowed_libraries = RULES[package]
    found = imported_modules(source) - {package} - set(sys.stdlib_module_names)
    bad = {name for name in found & OURS if name not in allowed_ours}
    if allowed_libraries is not None:
        bad |= found - OURS - allowed_libraries
    return bad


@pytest.mark.parametrize("package", sorted(RULES))
def test_each_package_imports_only_what_is_below_it(package: str) -> None:
    folder = ROOT / RULES[package][0] / package
    files = sorted(folder.rglob("*.py"))
    assert files, folder
    broken = {
        str(path.relative_to(ROOT)): sorted(bad)
        for path in files
        if (bad := violations(package, path.read_text()))
    }
    assert not broken, broken


def test_the_rules_catch_a_violation() -> None:
    assert violations("hmcc", "import pydantic\nfrom hmcc_service import app") == {
        "pydantic",
        "hmcc_service",
    }
    assert violations("hmcc_worker", "def f():\n    from hmcc_cli import main") == {"hmcc_cli"}
    assert violations("hmcc_schema", "import pydantic, orjson\nfrom hmcc import verify") == set()
    assert violations("hmcc_service", "from hmcc_colmap import ColmapRun") == {"hmcc_colmap"}
    client = "import httpx, msgpack, numpy, json\nimport pydantic\nfrom hmcc_schema import parse"
    assert violations("hmcc_client", client) == {"pydantic", "hmcc_schema"}
    assert violations("hmcc_worker", "from hmcc_client import HmccClient") == {"hmcc_client"}


def test_pycolmap_is_imported_by_hmcc_colmap_only() -> None:
    """pycolmap is an optional extra: the other packages stay importable without it."""
    users = {
        str(path.relative_to(ROOT))
        for package, (where, _, _) in RULES.items()
        if package != "hmcc_colmap"
        for path in (ROOT / where / package).rglob("*.py")
        if "pycolmap" in imported_modules(path.read_text())
    }
    assert not users, users
