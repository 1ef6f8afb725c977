"""The binary API -> worker payload: same verification as JSON, and foreign bytes refused."""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np
import pytest

from hmcc.schema import BatchRequest, PairRequest
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_worker.jobs import run_chunk, run_pair
from hmcc_worker.payload import MAGIC, decode, encode


def _pair(seed: int = 0) -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=80, outlier_ratio=0.4), seed)
    pair.pop("ground_truth")
    return pair


def test_a_pair_verifies_the_same_from_json_and_from_its_payload() -> None:
    pair = _pair()
    blob = encode(PairRequest.model_validate(pair))
    assert blob.startswith(MAGIC)
    assert run_pair(blob)["result"]["inliers"] == run_pair(json.dumps(pair))["result"]["inliers"]


def test_a_chunk_keeps_its_pairs_ids_and_order() -> None:
    pairs = [_pair(seed) for seed in range(3)]
    chunk = BatchRequest.model_validate({
        "images": {"a": pairs[0]["image1"], "b": pairs[0]["image2"]},
        "plane": pairs[0]["plane"],
        "pairs": [{"id": f"p{k}", "image1": "a", "image2": "b", "keypoints1": p["keypoints1"],
                   "keypoints2": p["keypoints2"], "matches": p["matches"]}
                  for k, p in enumerate(pairs)],
    })
    decoded = decode(encode(chunk))
    assert isinstance(decoded, BatchRequest)
    assert [p.id for p in decoded.pairs] == ["p0", "p1", "p2"]
    from_blob = [o["result"]["inliers"] for o in run_chunk(encode(chunk))]
    assert from_blob == [o["result"]["inliers"] for o in run_chunk(chunk)]


def _tampered(pair: dict[str, Any], array: int, value: float) -> bytes:
    """The payload of ``pair`` with the first number of array ``array`` overwritten."""
    blob = bytearray(encode(PairRequest.model_validate(pair)))
    (size,) = struct.unpack_from("<I", blob, len(MAGIC))
    offset = len(MAGIC) + 4 + size
    shapes = json.loads(blob[len(MAGIC) + 4:offset])["arrays"]
    offset += sum(int(np.prod(s)) * 8 for s in shapes[:array])
    fmt = "<q" if array == 2 else "<d"
    struct.pack_into(fmt, blob, offset, int(value) if array == 2 else value)
    return bytes(blob)


@pytest.mark.parametrize(
    ("blob", "message"),
    [
        (b"not ours", "not an hmcc binary payload"),
        (lambda p: encode(PairRequest.model_validate(p))[:-8], "do not match"),
        (lambda p: _tampered(p, 0, float("nan")), "finite"),
        (lambda p: _tampered(p, 2, 10**9), "out of range"),
        (lambda p: _tampered(p, 2, -1), "out of range"),
    ],
)
def test_foreign_or_damaged_bytes_are_refused(blob: Any, message: str) -> None:
    data = blob(_pair()) if callable(blob) else blob
    with pytest.raises(ValueError, match=message):
        decode(data)
