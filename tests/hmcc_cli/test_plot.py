"""``hmcc plot``: a PNG of a pair's motions by stage decision and its votes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    doc = simulate_pair(SimulationOptions(views=("L", "F"), n_inliers=80, outlier_ratio=0.5), 3)
    path = tmp_path_factory.mktemp("plot") / "pair.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("method", ["hmcc-ransac", "hmcc-plus"])
def test_plot_writes_a_png(pair_file: Path, tmp_path: Path, method: str) -> None:
    out = tmp_path / f"{method}.png"
    assert main(["plot", str(pair_file), "--method", method, "-o", str(out)]) == 0
    data = out.read_bytes()
    assert data.startswith(PNG_MAGIC)
    assert len(data) > 20_000  # six panels, not an empty canvas


def test_plot_refuses_bad_input_like_verify(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"matches": []}))
    assert main(["plot", str(bad), "-o", str(tmp_path / "x.png")]) == 2
    assert "error: " in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
