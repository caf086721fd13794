"""worker.durable: whole files and whole directories, or nothing."""

from pathlib import Path

import numpy as np
import pytest

from worker.durable import npy_bytes, replace_dir_atomic, write_file_atomic, write_new_file


def test_write_file_atomic_replaces_and_leaves_no_temp(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "a.json"
    write_file_atomic(target, b"old")
    write_file_atomic(target, b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in target.parent.iterdir()) == ["a.json"]


def test_write_new_file_refuses_to_overwrite(tmp_path: Path) -> None:
    write_new_file(tmp_path / "x.bin", b"1")
    with pytest.raises(FileExistsError):
        write_new_file(tmp_path / "x.bin", b"2")
    assert (tmp_path / "x.bin").read_bytes() == b"1"


def test_npy_bytes_round_trip(tmp_path: Path) -> None:
    array = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_new_file(tmp_path / "a.npy", npy_bytes(array))
    np.testing.assert_array_equal(np.load(tmp_path / "a.npy"), array)


def test_replace_dir_atomic_swaps_in_a_complete_directory(tmp_path: Path) -> None:
    target = tmp_path / "model"
    replace_dir_atomic(target, lambda tmp: write_new_file(tmp / "v1.txt", b"1"))
    replace_dir_atomic(target, lambda tmp: write_new_file(tmp / "deep" / "v2.txt", b"2"))
    assert sorted(str(p.relative_to(target)) for p in target.rglob("*.txt")) == ["deep/v2.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["model"]


def test_replace_dir_atomic_keeps_the_old_directory_when_filling_fails(tmp_path: Path) -> None:
    target = tmp_path / "model"
    replace_dir_atomic(target, lambda tmp: write_new_file(tmp / "good.txt", b"ok"))

    def half_then_fail(tmp: Path) -> None:
        write_new_file(tmp / "partial.txt", b"half")
        raise RuntimeError("disk pulled out")

    with pytest.raises(RuntimeError, match="disk pulled out"):
        replace_dir_atomic(target, half_then_fail)
    assert [p.name for p in target.iterdir()] == ["good.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["model"]
