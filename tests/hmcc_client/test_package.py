"""The client as its own distribution: importing it loads none of the core, and in a fresh
virtualenv holding only ``pip install ./client`` it verifies a flight against a real
``hmcc serve``."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from tests.support.flights import small_flight
from tests.support.procs import ROOT, running, service_env, start_api

#: What a front end that only talks HTTP must not have to install (orjson is not among them:
#: the client reads answers with it where it is installed, and with ``json`` where it is not,
#: which ``test_the_client_alone_installs_and_verifies_a_flight`` shows).
CORE_MODULES = ("cv2", "numba", "scipy", "pydantic", "hmcc", "hmcc_schema")

#: pip's words for an index it could not reach or that lacks a dependency: the test is then
#: skipped (anything else pip says is the client's fault, and fails it).
_UNREACHABLE = (
    "No matching distribution found",
    "Could not find a version",
    "NewConnectionError",
    "Temporary failure in name resolution",
    "Network is unreachable",
    "ProxyError",
    "ConnectTimeout",
    "ReadTimeoutError",
)

#: Run by the fresh virtualenv's python: a flight (keypoints as float32 ndarrays, so the
#: MessagePack bodies carry raw buffers) through ``verify_flight``; one JSON line per item.
_FLIGHT_SCRIPT = """
import json, sys
import numpy as np
from hmcc_client import HmccClient
url, path = sys.argv[1:]
flight = json.loads(open(path).read())
for image in flight["images"].values():
    image["keypoints"] = np.asarray(image["keypoints"], dtype=np.float32)
with HmccClient(url, timeout=30) as client:
    for item in client.verify_flight(
        flight["images"], flight["pairs"], plane=flight["plane"], max_batch_pairs=2, timeout=60
    ):
        inliers = None if item.result is None else item.result.inliers.tolist()
        print(json.dumps({"index": item.index, "id": item.id, "status": item.status,
                          "inliers": inliers}))
"""


def test_importing_the_client_loads_none_of_the_core() -> None:
    code = (
        f"import sys, hmcc_client; print(sorted(m for m in {CORE_MODULES!r} if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]"


def _install_client(tmp_path: Path) -> Path:
    """A fresh virtualenv with ``pip install ./client`` (from a copy, so no build files land
    in the checkout); its python. Skips when pip cannot reach an index for the client's
    dependencies."""
    source = tmp_path / "client"
    shutil.copytree(
        ROOT / "client",
        source,
        ignore=shutil.ignore_patterns("*.egg-info", "build", "__pycache__"),
    )
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    python = env_dir / "bin" / "python"
    pip = subprocess.run(
        [str(python), "-m", "pip", "install", "--quiet", str(source)],
        capture_output=True,
        text=True,
        timeout=240,
    )
    if pip.returncode != 0:
        said = pip.stdout + pip.stderr
        if any(words in said for words in _UNREACHABLE):
            pytest.skip(f"pip could not fetch the client's dependencies: {said.strip()[-300:]}")
        raise AssertionError(f"pip install ./client failed:\n{said}")
    return python


@pytest.mark.procs
def test_the_client_alone_installs_and_verifies_a_flight(tmp_path: Path) -> None:
    api, url = start_api(service_env())
    with running(api):
        python = _install_client(tmp_path)

        def run(*args: str) -> str:
            done = subprocess.run(
                [str(python), *args], capture_output=True, text=True, timeout=90, cwd=tmp_path
            )
            assert done.returncode == 0, done.stderr
            return done.stdout

        run("-c", "import hmcc_client")
        probe = (
            "import importlib.util as u; "
            f"print([m for m in {CORE_MODULES!r} if u.find_spec(m) is not None])"
        )
        assert run("-c", probe).strip() == "[]", "the fresh environment holds the core"
        typed = "import hmcc_client as c, pathlib; print(pathlib.Path(c.__file__).parent)"
        installed = Path(run("-c", typed).strip())
        assert installed.parent.name == "site-packages", installed  # not the checkout's
        assert (installed / "py.typed").is_file(), "no py.typed (PEP 561) installed"

        flight = small_flight(5, seed=7)
        truth = flight.pop("truth")
        (tmp_path / "flight.json").write_text(json.dumps(flight))
        (tmp_path / "flight.py").write_text(_FLIGHT_SCRIPT)
        lines = run("flight.py", url, str(tmp_path / "flight.json")).splitlines()

    items = [json.loads(line) for line in lines]
    assert sorted(i["index"] for i in items) == list(range(5))
    for item in items:
        assert item["status"] == "finished" and item["id"] == f"p{item['index']}"
        found = set(item["inliers"])
        assert len(found & set(truth[item["id"]])) > len(found) / 2, item
