"""A flight shared through a file: tasks pickle small, children read the same arrays, and a
crashing pair still costs that pair only."""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from hmcc_schema import parse_batch
from hmcc_schema.flight_columns import read_flight_columns, write_flight_columns
from hmcc_schema.flight_file import MappedFlightFile, read_flight_file, write_flight_file
from hmcc_worker.outcomes import (
    FAULT_CRASH_PAIR_ID,
    flight_line,
    unpack,
    verify_flight_lean,
    verify_flight_lines,
)
from hmcc_worker.pool import ComputePool
from hmcc_worker.shared_flight import SharedFlight, shared_flight
from tests.support.flights import small_flight


def _flight(n: int, crash: int | None = None):  # type: ignore[no-untyped-def]
    doc = small_flight(n)
    doc.pop("truth")
    if crash is not None:
        doc["pairs"][crash]["id"] = "boom"
    return parse_batch(json.loads(json.dumps(doc, default=lambda a: a.tolist())), 100)


def test_a_shared_flight_pickles_as_its_indices_and_reads_the_same_arrays() -> None:
    flight = _flight(4)
    with shared_flight(flight) as shared:
        part = shared.subset([3, 1])
        assert isinstance(part, SharedFlight) and part.indices == (3, 1)
        data = pickle.dumps(part)
        assert len(data) < 300
        read = pickle.loads(data)
        # in a child: the pairs' arrays read from the file, their places in the flight kept
        assert isinstance(read, SharedFlight) and read.indices == (3, 1)
        assert len(pickle.dumps(read)) < 300
        assert [p.id for p in read.pairs] == ["p3", "p1"]
        assert set(read.images) == {"a3", "b3", "a1", "b1"}
        for mine, theirs in zip([flight.pairs[3], flight.pairs[1]], read.pairs, strict=True):
            np.testing.assert_array_equal(mine.matches, theirs.matches)
            image = read.images[theirs.image1]
            assert image.keypoints is not None
            original = flight.images[mine.image1].keypoints
            np.testing.assert_array_equal(image.keypoints, original)
        np.testing.assert_array_equal(read.verify(0).inliers, flight.verify(3).inliers)


@pytest.fixture(scope="module")
def pool() -> Iterator[ComputePool]:
    os.environ[FAULT_CRASH_PAIR_ID] = "boom"  # read by the children, which start below
    pool = ComputePool(2, timeout_s=30)
    try:
        pool.start()
        yield pool
    finally:
        pool.close(wait=False)
        del os.environ[FAULT_CRASH_PAIR_ID]


@pytest.mark.procs
def test_a_crashing_pair_of_a_shared_flight_costs_that_pair_only(pool: ComputePool) -> None:
    flight = _flight(6, crash=4)
    with shared_flight(flight) as shared:
        got = dict(pool.map_flight(shared, chunk_pairs=3, fn=verify_flight_lean))
    assert sorted(got) == list(range(6))
    for i, outcome in got.items():
        status, body = unpack(outcome.pack())
        if i == 4:
            assert json.loads(body)["code"] == "worker_crashed"
        else:
            assert status.value == "finished"
            inliers = json.loads(body)["inliers"]
            assert inliers == flight.verify(i).inliers.tolist()


def test_a_shared_flight_keeps_descriptors_and_the_pairs_to_match() -> None:
    from tests.support.matching import matching_batch

    body, _ = matching_batch(0, n_inliers=60)
    body["matching"] = {"max_ratio": 0.7}
    flight = parse_batch(body, 10)
    with shared_flight(flight) as shared:
        read = pickle.loads(pickle.dumps(shared.subset([0])))
    assert read.pairs[0].match and read.match_options.max_ratio == 0.7
    for name, image in read.images.items():
        assert image.descriptors is not None
        np.testing.assert_array_equal(image.descriptors, flight.images[name].descriptors)
        assert image.descriptors.dtype == np.uint8
    assert read.verify(0).to_dict()["matches"] == flight.verify(0).to_dict()["matches"]


def test_a_flight_read_in_place_is_shared_from_its_own_file(tmp_path: Path) -> None:
    """A flight read from a mapped binary file: nothing written but where its arrays lie in
    that file; a child reads them from it, as the whole file's parse gives them (int64
    matches, aligned, writeable), and verifies its pairs alike."""
    doc = small_flight(3)
    doc.pop("truth")
    path = tmp_path / "flight.msgpack"
    write_flight_file(path, doc.pop("images"), doc.pop("pairs"), **doc)
    mapped = MappedFlightFile.open(path)
    assert mapped is not None
    flight, whole = mapped.flight(), read_flight_file(path)
    assert flight is not None
    with shared_flight(flight, mapped) as shared:
        assert (Path(shared.folder) / "arrays.bin").stat().st_size == 0
        read = pickle.loads(pickle.dumps(shared.subset([2, 0])))
    for i, theirs in zip([2, 0], read.pairs, strict=True):
        assert theirs.matches.dtype == np.int64 and theirs.matches.flags.aligned
        np.testing.assert_array_equal(theirs.matches, whole.pairs[i].matches)
        assert theirs.matches.flags.writeable
        image = read.images[theirs.image1].keypoints
        assert image is not None and image.flags.aligned and image.flags.writeable
        np.testing.assert_array_equal(image, whole.images[theirs.image1].keypoints)
        mine = read.verify([2, 0].index(i)).inliers
        np.testing.assert_array_equal(mine, whole.verify(i).inliers)


def _lost_line(single, outcome):  # type: ignore[no-untyped-def]
    return flight_line(single.indices[0], single.pairs[0].id, outcome)


@pytest.mark.procs
def test_children_encode_the_lines_with_the_flights_indices(pool: ComputePool) -> None:
    # each child writes its pairs' whole lines (their indices in the whole flight); the pair
    # that kills its child gets its line from the parent, in the same form
    flight = _flight(6, crash=4)
    with shared_flight(flight) as shared:
        tasks = list(pool.map_tasks(shared, 3, fn=verify_flight_lines, lost=_lost_line))
    lines = {}
    for indices, outcomes in tasks:  # a task's lines in order, in runs of one status
        docs = [
            (o.status.value, json.loads(line)) for o in outcomes for line in o.body.splitlines()
        ]
        assert all(o.body.endswith(b"\n") for o in outcomes)
        assert [doc["index"] for _, doc in docs] == indices
        lines |= {doc["index"]: (status, doc) for status, doc in docs}
    assert sorted(lines) == list(range(6))
    for i, (status, doc) in lines.items():
        assert doc["index"] == i and doc["id"] == flight.pairs[i].id and doc["status"] == status
        if i == 4:
            assert status == "failed" and doc["error"]["code"] == "worker_crashed"
        else:
            assert doc["result"]["inliers"] == flight.verify(i).inliers.tolist()


def test_a_flight_of_more_arrays_than_one_write_takes_reads_the_same_arrays(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 350 pairs' matches and 700 images' keypoints (and padding between them): more buffers
    # than one writev takes (_IOV_MAX), and each write cut short, as a system call may: every
    # array still lands where its slot says
    from hmcc_worker import shared_flight as module

    real = os.writev
    calls = []

    def short(fd: int, buffers: list[bytes]) -> int:
        calls.append(len(buffers))
        return real(fd, buffers[: max(1, len(buffers) // 2)])

    monkeypatch.setattr(module.os, "writev", short)
    doc = small_flight(350, n_inliers=20)
    doc.pop("truth")
    flight = parse_batch(json.loads(json.dumps(doc, default=lambda a: a.tolist())), 350)
    with shared_flight(flight) as shared:
        read = pickle.loads(pickle.dumps(shared.subset(range(350))))
    assert len(calls) > 1 and max(calls) <= module._IOV_MAX
    for mine, theirs in zip(flight.pairs, read.pairs, strict=True):
        np.testing.assert_array_equal(mine.matches, theirs.matches)
        for name in (mine.image1, mine.image2):
            np.testing.assert_array_equal(
                flight.images[name].keypoints, read.images[name].keypoints
            )


def test_pairs_of_several_dtypes_and_their_own_keypoints_read_back_as_given() -> None:
    """The pairs' columns (:class:`_PairTable`) hold each pair's own dtype, image ids, id,
    and keypoints of its own: matches in uint16, int32 and int64 (as a batch parsed with
    ``views`` keeps them) read back as the int64 the core takes, each at its own place."""
    flight = _flight(4)
    kinds = ("<u2", "<i4", "<i8", "<u4")
    pairs = [
        dataclasses.replace(p, matches=p.matches.astype(kind), id=f"x{k}")
        for k, (p, kind) in enumerate(zip(flight.pairs, kinds, strict=True))
    ]
    own = flight.images[pairs[2].image1].keypoints
    assert own is not None
    pairs[2] = dataclasses.replace(pairs[2], keypoints1=own[:, ::-1].copy())
    flight = dataclasses.replace(flight, pairs=pairs)
    with shared_flight(flight) as shared:
        read = pickle.loads(pickle.dumps(shared.subset([3, 2, 0, 1])))
    for i, theirs in zip([3, 2, 0, 1], read.pairs, strict=True):
        mine = flight.pairs[i]
        assert (theirs.id, theirs.image1, theirs.image2) == (mine.id, mine.image1, mine.image2)
        assert theirs.matches.dtype == np.int64
        np.testing.assert_array_equal(theirs.matches, mine.matches)
        assert (theirs.keypoints1 is None) == (mine.keypoints1 is None)
    np.testing.assert_array_equal(read.pairs[1].keypoints1, pairs[2].keypoints1)


def test_a_flight_of_columns_is_shared_from_its_own_file(tmp_path: Path) -> None:
    """Pairs as columns (:mod:`hmcc_schema.flight_columns`): nothing written but where each
    pair's rows lie in the flight file; a child reads them as the rows' parse gives them and
    verifies alike, a selection of a selection too."""
    doc = small_flight(4)
    doc.pop("truth")
    path = tmp_path / "flight.msgpack"
    write_flight_columns(path, doc["images"], doc["pairs"], plane=doc["plane"])
    mapped = MappedFlightFile.open(path)
    assert mapped is not None
    flight = read_flight_columns(mapped)
    whole = parse_batch({**doc, "pairs": doc["pairs"]}, 100)
    with shared_flight(flight, mapped) as shared:
        assert (Path(shared.folder) / "arrays.bin").stat().st_size == 0
        part = shared.subset([3, 0, 2]).subset([2, 0])
        assert part.indices == (2, 3) and len(pickle.dumps(part)) < 300
        read = pickle.loads(pickle.dumps(part))
    assert [p.id for p in read.pairs] == ["p2", "p3"]
    for k, (i, theirs) in enumerate(zip([2, 3], read.pairs, strict=True)):
        assert theirs.matches.dtype == np.int64 and theirs.matches.flags.writeable
        np.testing.assert_array_equal(theirs.matches, whole.pairs[i].matches)
        np.testing.assert_array_equal(read.verify(k).inliers, whole.verify(i).inliers)
