"""The one atomic writer: concurrent savers never collide, readers never see part of a file, failures leave no trace."""

from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path

import pytest

from cell.data.atomic import atomic_path, save_atomic, write_atomic

pytestmark = pytest.mark.timeout(60)


def _doc(writer: int, i: int) -> str:
    # Large enough that a write takes several system calls: a torn file would show.
    return json.dumps({"writer": writer, "i": i, "payload": [writer * 1000 + i] * 20_000})


def test_two_threads_saving_the_same_file_never_fail_and_it_is_always_complete(tmp_path: Path) -> None:
    target = tmp_path / "model.json"
    write_atomic(target, _doc(0, 0))
    errors: list[BaseException] = []
    seen: list[tuple[int, int]] = []
    done = threading.Event()

    def save(writer: int) -> None:
        try:
            for i in range(50):
                write_atomic(target, _doc(writer, i))
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    def read() -> None:
        while not done.is_set():
            try:
                doc = json.loads(target.read_text())
                assert doc["payload"] == [doc["writer"] * 1000 + doc["i"]] * 20_000
                seen.append((doc["writer"], doc["i"]))
            except BaseException as exc:  # noqa: BLE001 - reported by the test
                errors.append(exc)
                return

    savers = [threading.Thread(target=save, args=(w,)) for w in (1, 2)]
    reader = threading.Thread(target=read)
    reader.start()
    for t in savers:
        t.start()
    for t in savers:
        t.join()
    done.set()
    reader.join()
    assert not errors, errors[:3]
    final = json.loads(target.read_text())
    assert (final["writer"], final["i"]) in {(1, 49), (2, 49)}
    assert len(seen) > 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.json"]  # no temporary file left behind


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path: Path) -> None:
    target = tmp_path / "calibration.json"
    write_atomic(target, "old")

    def broken(path: Path) -> None:
        path.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        save_atomic(target, broken)
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.json"]


def test_the_temporary_file_is_hidden_unique_and_keeps_the_extension(tmp_path: Path) -> None:
    target = tmp_path / "booster_j1.ubj"
    with atomic_path(target) as a, atomic_path(target, durable=False) as b:
        assert a != b and a.parent == b.parent == tmp_path
        assert a.name.startswith(".") and a.suffix == ".ubj"
        a.write_bytes(b"a")
        b.write_bytes(b"b")
    assert target.read_bytes() == b"a"  # the last to finish wins, whole


def test_the_file_gets_the_permissions_a_plain_write_would(tmp_path: Path) -> None:
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    target = write_atomic(tmp_path / "atomic.txt", "x")
    assert stat.S_IMODE(os.stat(target).st_mode) == stat.S_IMODE(os.stat(plain).st_mode)
